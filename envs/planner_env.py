"""``GCCPPlanner-v0``: the motion-planner's subgoal-conditioned env (paper III-D, r^m).

A subgoal is drawn from the N candidates at reset and every T_m steps (uniformly from those ahead, or
a "hold" at the candidate nearest the ego; see ``hold_probability``); the planner drives towards it with the 6
discrete actions. The episode ends on a collision, leaving the road, reaching
the task's exit (or another exit), or the time limit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from gccp_envs.action import EgoAction
from gccp_envs.base_env import IntersectionBaseEnv, Obs
from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.observation import pose_space, state_spaces
from gccp_envs.rewards import goal_errors, goal_reached, planner_reward
from gccp_envs.world import StepOutcome


def planner_spaces(config: IntersectionConfig) -> tuple[spaces.Dict, spaces.Discrete]:
    """The observation and action spaces of the motion-planner (and of the flat env) on ``config``."""
    return spaces.Dict({**state_spaces(config), "goal": pose_space()}), spaces.Discrete(len(EgoAction))


class GCCPPlannerEnv(IntersectionBaseEnv):
    """Subgoal-conditioned motion-planning env; ``action_masks()`` keeps the ego on the road."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.observation_space, self.action_space = planner_spaces(self.config)
        self._arrived = False
        self._holding = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Obs, dict[str, Any]]:
        """Start an episode; ``options={"task": "left"}`` picks the task of this episode."""
        self._reset_world(seed, options)
        self._holding = False
        self._choose_goal()
        return self._observe(), {"task": self.world.task}

    def _choose_goal(self) -> None:
        """A candidate drawn uniformly from those ahead and reachable within T_m steps or, with
        ``hold_probability`` (``hold_continue`` right after a hold), a hold: the candidate nearest the
        ego, which counts as reached only when the car stands on it. A car that waits keeps the same
        nearest lattice point, so waiting is paid r_arr every period; a car that drives on is not."""
        cfg = self.config
        threshold = cfg.hold_continue if self._holding else cfg.hold_probability
        self._holding = bool(self.np_random.random() < threshold)
        candidates = self.world.subgoal_candidates()
        ego = self.world.ego
        offsets = candidates[:, :2] - (ego.x, ego.y)
        distances = np.hypot(*offsets.T)
        if self._holding:
            index = int(np.argmin(distances))
        else:
            # Only candidates still ahead, so that a goal beside or behind the ego always means
            # "hold"; preferably those reachable within the period at cruise speed, so that driving on
            # pays (r_arr) and ending the episode early does not.
            ahead = (offsets @ (np.cos(ego.heading), np.sin(ego.heading)) > 0) & (
                distances > cfg.subgoal_reach_radius
            )
            reach = cfg.cruise_speed * cfg.decision_period * DT + cfg.subgoal_reach_radius
            reachable = ahead & (distances <= reach)
            pool = reachable if reachable.any() else ahead
            choices = np.flatnonzero(pool) if pool.any() else np.arange(len(candidates))
            index = int(choices[self.np_random.integers(len(choices))])
        self._subgoal = candidates[index].copy()
        self._arrived = False

    @property
    def subgoal(self) -> np.ndarray:
        """The current subgoal, a world pose (x, y, heading)."""
        assert self._subgoal is not None, "reset the env first"
        return self._subgoal

    def _observe(self) -> Obs:
        assert self._subgoal is not None
        return {**self._state(), "goal": self._in_ego_frame(self._subgoal)}

    def _goal_arrived(self, outcome: StepOutcome, errors: tuple[float, float]) -> bool:
        """Whether the goal was reached for the first time in this step."""
        arrived = not self._arrived and goal_reached(self.config, errors)
        if self._holding:
            arrived &= self.world.ego.speed < self.config.hold_stop_speed
        self._arrived |= arrived
        return arrived

    def _after_step(self) -> None:
        if self.world.steps % self.config.decision_period == 0:
            self._choose_goal()

    def step(self, action: np.int64 | int) -> tuple[Obs, float, bool, bool, dict[str, Any]]:
        """One 0.1 s step of an ego action."""
        action = self._check_action(action)
        assert self._subgoal is not None
        before = goal_errors(self.world.ego, self._subgoal)
        outcome = self.world.step(int(action))
        after = goal_errors(self.world.ego, self._subgoal)
        arrived = self._goal_arrived(outcome, after)
        terms = planner_reward(
            self.config, before, after, arrived, outcome.crashed, outcome.offroad, outcome.wrong_exit
        )
        if self._holding:
            terms["r_time"] = self.config.r_time_hold
        terminated = outcome.terminal
        truncated = not terminated and self._truncated()
        info: dict[str, Any] = {"reward_terms": terms, "goal_reached": arrived}
        if terminated or truncated:
            info.update(self._episode_info(outcome, truncated))
        elif arrived and not self._holding:
            # A reached subgoal is replaced at once: only a hold leaves a goal beside or behind the ego.
            self._choose_goal()
        else:
            self._after_step()
        return self._observe(), float(sum(terms.values())), terminated, truncated, info

    def action_masks(self) -> np.ndarray:
        """Actions that keep the ego on the road next step (never all False)."""
        return self.world.action_mask()
