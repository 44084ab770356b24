"""auv_follow_env: delayed target following by an underwater robot, as Gymnasium envs.

Importing this package registers ``AUVFollow-S1-v0`` ... ``AUVFollow-S4-v0`` (the paper's
scenario presets) and ``AUVFollow-v0`` (``scenario=`` keyword); it does nothing else.
"""

from gymnasium.envs.registration import register, registry

from auv_follow_env.params import SCENARIOS, make_config, make_task_spec

__all__ = ["ENV_IDS", "make_config", "make_task_spec"]
__version__ = "0.1.0"

_ENTRY = "auv_follow_env.env:AUVFollowEnv"
_VECTOR_ENTRY = "auv_follow_env.vector_env:AUVFollowVectorEnv"
_STEPS = 1200  # 60 s at dt = 0.05 s

ENV_IDS: tuple[str, ...] = tuple(f"AUVFollow-{s}-v0" for s in SCENARIOS) + ("AUVFollow-v0",)

for _name in SCENARIOS:
    if f"AUVFollow-{_name}-v0" not in registry:
        register(id=f"AUVFollow-{_name}-v0", entry_point=_ENTRY, max_episode_steps=_STEPS,
                 vector_entry_point=_VECTOR_ENTRY, kwargs={"scenario": _name})
if "AUVFollow-v0" not in registry:
    register(id="AUVFollow-v0", entry_point=_ENTRY, max_episode_steps=_STEPS,
             vector_entry_point=_VECTOR_ENTRY)
