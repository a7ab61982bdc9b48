"""Scripted controllers: a geometric motion-planner and a simple decision-maker.

They make the option env usable before anything is trained, serve as sanity baselines, and drive
the tests. Both take observations exactly as the learned policies do.
"""

from __future__ import annotations

import numpy as np

from gccp_envs.action import EgoAction
from gccp_envs.config import IntersectionConfig


class ScriptedPlanner:
    """Pure pursuit towards the goal point, braking to stop on it.

    Call it with a planner observation (``goal`` in the ego frame) and the action mask.
    """

    def __init__(self, config: IntersectionConfig) -> None:
        self.config = config
        slow, quick = config.slow_turn_curvature, config.quick_turn_curvature
        self._turns = {
            EgoAction.KEEP_DIRECTION: 0.0,
            EgoAction.SLOWLY_TURN_LEFT: -slow,
            EgoAction.SLOWLY_TURN_RIGHT: slow,
            EgoAction.QUICKLY_TURN_LEFT: -quick,
            EgoAction.QUICKLY_TURN_RIGHT: quick,
        }

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The action for one step."""
        cfg = self.config
        x, y = float(obs["goal"][0]), float(obs["goal"][1])
        speed = float(obs["history"][0, -1, 7])
        distance = float(np.hypot(x, y))
        # Stop on the goal: brake when faster than the speed that still stops in the distance left.
        target_speed = min(cfg.cruise_speed, np.sqrt(2.0 * cfg.deceleration * max(distance - 1.0, 0.0)))
        if x < 0.5:  # goal beside or behind: stand still rather than circle
            target_speed = 0.0
        curvature = 2.0 * y / max(distance**2, 1e-6)
        ranked = sorted(self._turns, key=lambda a: abs(self._turns[a] - curvature))
        if target_speed == 0.0 or speed > target_speed + 0.2:
            ranked = [EgoAction.SLOW_DOWN, *ranked]
        elif ranked[0] != EgoAction.KEEP_DIRECTION and speed < 1.0 and target_speed > 0.0:
            ranked = [EgoAction.KEEP_DIRECTION, *ranked]  # turning needs speed
        for action in ranked:
            if action_mask is None or action_mask[int(action)]:
                return int(action)
        return int(EgoAction.SLOW_DOWN)


class FarthestSubgoalDecider:
    """Always the candidate farthest ahead on the best route (a subgoal index for the option env)."""

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The subgoal index for one decision."""
        forward = obs["subgoals"][:, 0].astype(float)
        if action_mask is not None:
            forward = np.where(action_mask, forward, -np.inf)
        return int(np.argmax(forward))
