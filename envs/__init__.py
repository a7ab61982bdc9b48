"""The intersection world of sb3_gccp, installed as ``gccp_envs``.

Importing it registers the three environments with gymnasium:

- ``GCCPPlanner-v0``: the motion-planner's subgoal-conditioned env,
- ``GCCPDecider-v0``: the decision-maker's option env (action = subgoal index),
- ``GCCPFlat-v0``: the baselines' env (planner state/actions/reward, task goal as goal).
"""

from gymnasium.envs.registration import register, registry

from gccp_envs.config import DT, TASKS, IntersectionConfig

ENV_IDS = {
    "GCCPPlanner-v0": "gccp_envs.planner_env:GCCPPlannerEnv",
    "GCCPDecider-v0": "gccp_envs.option_env:GCCPDeciderEnv",
    "GCCPFlat-v0": "gccp_envs.flat_env:GCCPFlatEnv",
}

for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in registry:
        # Episodes end by the env's own time limit (config ``duration``).
        register(id=_env_id, entry_point=_entry_point, disable_env_checker=True)

__all__ = ["DT", "ENV_IDS", "TASKS", "IntersectionConfig"]
