"""The intersection world of sb3_gccp, installed as ``gccp_envs``.

Importing it registers the three environments with gymnasium:

- ``GCCPPlanner-v0``: the motion-planner's subgoal-conditioned env,
- ``GCCPDecider-v0``: the decision-maker's option env (action = subgoal index),
- ``GCCPFlat-v0``: the baselines' env (planner state/actions/reward, task goal as goal).
"""

from gymnasium.envs.registration import register, registry

from gccp_envs.config import DT, TASKS, IntersectionConfig

PLANNER_ENV_ID = "GCCPPlanner-v0"
"""The motion-planner's env: ego actions towards a subgoal."""
DECIDER_ENV_ID = "GCCPDecider-v0"
"""The decision-maker's option env: a subgoal index, then T_m steps of a planner."""
FLAT_ENV_ID = "GCCPFlat-v0"
"""The flat baselines' env: ego actions towards the task goal."""
ENV_IDS = {
    PLANNER_ENV_ID: "gccp_envs.planner_env:GCCPPlannerEnv",
    DECIDER_ENV_ID: "gccp_envs.option_env:GCCPDeciderEnv",
    FLAT_ENV_ID: "gccp_envs.flat_env:GCCPFlatEnv",
}

for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in registry:
        # Episodes end by the env's own time limit (config ``duration``).
        register(id=_env_id, entry_point=_entry_point, disable_env_checker=True)

__all__ = ["DECIDER_ENV_ID", "DT", "ENV_IDS", "FLAT_ENV_ID", "PLANNER_ENV_ID", "TASKS", "IntersectionConfig"]
