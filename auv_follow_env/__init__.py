"""auv_follow_env: delayed target following by an underwater robot, as Gymnasium envs.

The ids are registered without ``max_episode_steps``: the env truncates itself after
``episode_s`` (60 s = 1200 steps by default), so overriding ``episode_s`` or ``dt`` through
``gym.make`` can never be cut short by a registered TimeLimit that the env cannot see
(Gymnasium 1.x hides it from the env).

Importing this package registers ``AUVFollow-S1-v0`` ... ``AUVFollow-S4-v0`` (the paper's
scenario presets) and ``AUVFollow-v0`` (``scenario=`` keyword); it does nothing else.
"""

from gymnasium.envs.registration import register, registry

from auv_follow_env.params import SCENARIOS, make_config, make_task_spec

__all__ = ["ENV_IDS", "make_config", "make_task_spec"]
__version__ = "0.1.0"

_ENTRY = "auv_follow_env.env:AUVFollowEnv"
_VECTOR_ENTRY = "auv_follow_env.vector_env:AUVFollowVectorEnv"

ENV_IDS: tuple[str, ...] = tuple(f"AUVFollow-{s}-v0" for s in SCENARIOS) + ("AUVFollow-v0",)

for _name in SCENARIOS:
    if f"AUVFollow-{_name}-v0" not in registry:
        register(id=f"AUVFollow-{_name}-v0", entry_point=_ENTRY,
                 vector_entry_point=_VECTOR_ENTRY, kwargs={"scenario": _name})
if "AUVFollow-v0" not in registry:
    register(id="AUVFollow-v0", entry_point=_ENTRY,
             vector_entry_point=_VECTOR_ENTRY)
