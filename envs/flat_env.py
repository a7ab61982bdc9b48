"""``GCCPFlat-v0``: the baselines' env (paper IV-A-1).

The motion-planner's state, actions and reward, with the task goal in place of the subgoal: r_arr is
paid when the task's exit is reached.
"""

from __future__ import annotations

from gccp_envs.planner_env import GCCPPlannerEnv
from gccp_envs.world import StepOutcome


class GCCPFlatEnv(GCCPPlannerEnv):
    """Flat (non-hierarchical) driving towards the task goal."""

    def _choose_goal(self) -> None:
        self._subgoal = self.world.task_goal.copy()
        self._arrived = False

    def _goal_arrived(self, outcome: StepOutcome, errors: tuple[float, float]) -> bool:
        return outcome.success

    def _after_step(self) -> None:
        """The task goal never changes within an episode."""

    def _render_extras(self) -> dict[str, object]:
        return {"candidates": None, "chosen": self._subgoal}
