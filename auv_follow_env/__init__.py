"""auv_follow_env: delayed target following by an underwater robot, as Gymnasium envs.

The ids are registered without ``max_episode_steps``: the env truncates itself after
``episode_s`` (60 s = 1200 steps by default), so overriding ``episode_s`` or ``dt`` through
``gym.make`` can never be cut short by a registered TimeLimit that the env cannot see
(Gymnasium 1.x hides it from the env).

Importing this package registers

* ``AUVFollow-S1-v0`` ... ``AUVFollow-S4-v0`` (the paper's scenario presets, frozen) and
  ``AUVFollow-v0`` (``scenario=`` keyword);
* ``AUVFollow-Easy-v1``, ``-Medium-v1``, ``-Hard-v1`` and ``-Extreme-v1`` (the acoustic-link
  tiers of :mod:`auv_follow_env.tiers`, each with published test seeds) and ``AUVFollow-v1``
  (a scenario preset with the v1 link and observation; every link parameter a keyword);

and does nothing else.
"""

from gymnasium.envs.registration import register, registry

from auv_follow_env.params import SCENARIOS, make_config, make_task_spec
from auv_follow_env.tiers import ALL_TIERS, LEADER_TIERS, TIERS, check_training_seeds

__all__ = ["ENV_IDS", "ENV_IDS_V1", "ENV_IDS_LEADER", "TIERS", "LEADER_TIERS", "ALL_TIERS", "check_training_seeds",
           "make_config", "make_task_spec"]
__version__ = "0.1.0"

_ENTRY = "auv_follow_env.env:AUVFollowEnv"
_VECTOR_ENTRY = "auv_follow_env.vector_env:AUVFollowVectorEnv"

ENV_IDS: tuple[str, ...] = tuple(f"AUVFollow-{s}-v0" for s in SCENARIOS) + ("AUVFollow-v0",)
#: the Leader tiers' ids (targets with hidden manoeuvre modes and outlier fixes)
ENV_IDS_LEADER: tuple[str, ...] = tuple(t.env_id for t in LEADER_TIERS.values())
#: every v1 id (the v1 observation and link): the OU tiers, the Leader tiers and the custom AUVFollow-v1
ENV_IDS_V1: tuple[str, ...] = tuple(t.env_id for t in TIERS.values()) + ENV_IDS_LEADER + ("AUVFollow-v1",)

for _name in SCENARIOS:
    if f"AUVFollow-{_name}-v0" not in registry:
        register(id=f"AUVFollow-{_name}-v0", entry_point=_ENTRY,
                 vector_entry_point=_VECTOR_ENTRY, kwargs={"scenario": _name})
if "AUVFollow-v0" not in registry:
    register(id="AUVFollow-v0", entry_point=_ENTRY,
             vector_entry_point=_VECTOR_ENTRY)
for _tier in ALL_TIERS.values():
    if _tier.env_id not in registry:
        register(id=_tier.env_id, entry_point=_ENTRY, vector_entry_point=_VECTOR_ENTRY,
                 kwargs={"version": "v1", "tier": _tier.name})
if "AUVFollow-v1" not in registry:
    register(id="AUVFollow-v1", entry_point=_ENTRY, vector_entry_point=_VECTOR_ENTRY,
             kwargs={"version": "v1"})
