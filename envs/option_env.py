"""``GCCPDecider-v0``: the decision-maker's option env (paper III-D, r^d, Algorithm 1).

The action is a subgoal index. The env runs a motion-planner towards that subgoal for T_m steps
(fewer if the episode ends) and returns the decision-maker's reward. The planner is any callable of
(observation, action mask) to an ego action: the scripted pure-pursuit planner by default, or a
trained one that the agent package passes in (``sb3_gccp`` wraps its frozen MaskablePPO planner so).
``action_masks()`` asks a mask function (the GCCP module) which subgoals are safe; without one, or
while masks are off, all are. With the world key ``observe_mask`` the observation also carries that
verdict (``subgoal_allowed``), as the paper's decision-maker observes the collision risk mask.
Each step's ``info`` carries what the predictor's replay buffer needs, as raw features (never
normalised): the observation the decision was made from (``decision_obs``), the chosen subgoal in
its ego frame (``subgoal``) and the ground-truth future of the decision (``future``, ``future_mask``:
the next T_f poses of the ego and the neighbours of that observation), plus ``masked_share``, the
share of candidates the mask function ruled out. ``set_planner_step_callback`` installs a function
called after every planner step of an option, to follow the world at 0.1 s (e.g. to record a video).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces

from gccp_envs.action import EgoAction
from gccp_envs.base_env import IntersectionBaseEnv, Obs
from gccp_envs.config import IntersectionConfig
from gccp_envs.observation import pose_space, state_spaces
from gccp_envs.rewards import decider_reward, goal_errors, goal_reached, planner_reward
from gccp_envs.scripted import ScriptedPlanner
from gccp_envs.world import StepOutcome

Planner = Callable[[Obs, np.ndarray], int]
"""A motion-planner: (planner observation, action mask) -> ego action."""
MaskFunction = Callable[[Obs], np.ndarray]
"""A subgoal mask: decider observation -> bool (N,), True where the subgoal is allowed. One may also have
a method ``latest_collision(obs, exclude=None)`` -> bool (N,): the candidates whose predicted collision comes
latest, those in the bool (N,) ``exclude`` left out, for the world keys ``fallback_go_on`` and
``fallback_go_on_skips_hold`` (``exclude`` is passed only with the latter)."""
GO_ON_SPEED = 1.0
"""Speed [m/s] from which the ego counts as driving, for ``fallback_go_on``."""
VERDICT_KEY = "subgoal_allowed"
"""Observation key of the mask function's verdict per candidate, with the world key ``observe_mask``."""
PlannerStepCallback = Callable[["GCCPDeciderEnv"], None]
"""Called with the env after every planner step inside an option."""


def decider_spaces(config: IntersectionConfig) -> tuple[spaces.Dict, spaces.Discrete]:
    """The observation and action spaces of the decision-maker on ``config``: N subgoal candidates."""
    n = config.num_subgoals
    observation: dict[str, spaces.Space] = {
        **state_spaces(config),
        "task_goal": pose_space(),
        "subgoals": pose_space(n),
    }
    if config.observe_mask:
        observation[VERDICT_KEY] = spaces.Box(0.0, 1.0, (n,), np.float32)
    return spaces.Dict(observation), spaces.Discrete(n)


class GCCPDeciderEnv(IntersectionBaseEnv):
    """Option env whose action is one of the N subgoal candidates.

    :param planner: the motion-planner run for each option; default :class:`ScriptedPlanner`
    :param mask_fn: the subgoal mask (GCCP); default none (every subgoal allowed)
    """

    def __init__(
        self,
        *args: Any,
        planner: Planner | None = None,
        mask_fn: MaskFunction | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.observation_space, self.action_space = decider_spaces(self.config)
        self.planner: Planner = planner or ScriptedPlanner(self.config)
        self.mask_fn = mask_fn
        self._last_obs: Obs | None = None
        self._masked: np.ndarray | None = None
        self._going_on = False
        self._verdict = np.ones(self.config.num_subgoals, bool)
        self._subgoal: np.ndarray | None = None
        self._planner_step_callback: PlannerStepCallback | None = None

    def set_mask_fn(self, mask_fn: MaskFunction | None) -> None:
        """Install (or remove with ``None``) the subgoal mask; callable through ``env_method``."""
        self.mask_fn = mask_fn

    def set_planner_step_callback(self, callback: PlannerStepCallback | None) -> None:
        """Install (or remove with ``None``) a function called with the env after every planner step of
        an option, so that the world can be followed at 0.1 s rather than once per decision."""
        self._planner_step_callback = callback

    @property
    def subgoal(self) -> np.ndarray | None:
        """The subgoal (x, y, heading) of the current or last option in the world frame; None before the
        first step of an episode."""
        return None if self._subgoal is None else self._subgoal.copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Obs, dict[str, Any]]:
        """Start an episode; ``options={"task": "left"}`` picks the task of this episode."""
        self._reset_world(seed, options)
        self._subgoal = None
        self._masked = None
        self._last_obs = self._observe()
        return self._last_obs, {"task": self.world.task}

    def _observe(self) -> Obs:
        world = self.world
        obs = {
            **self._state(),
            "task_goal": self._in_ego_frame(world.task_goal),
            "subgoals": self._in_ego_frame(world.subgoal_candidates()),
        }
        if self.config.observe_mask:
            self._verdict = self._check(obs)
            obs[VERDICT_KEY] = self._verdict.astype(np.float32)
        return obs

    def _check(self, obs: Obs) -> np.ndarray:
        """The mask function's verdict on ``obs``: (N,) bool, True where allowed; all True without one."""
        n = self.config.num_subgoals
        if self.mask_fn is None:
            return np.ones(n, bool)
        return np.asarray(self.mask_fn(obs), bool).reshape(n)

    def action_masks(self) -> np.ndarray:
        """Allowed subgoals. If the mask function allows none, only the nearest candidate is allowed:
        holding back is the least risky choice when every subgoal is predicted to collide; with
        ``fallback_go_on``, while the ego drives inside the junction, the candidates whose collision is
        predicted latest. With ``observe_mask`` the verdict is the one the observation shows."""
        n = self.config.num_subgoals
        self._going_on = False
        if self._last_obs is None:
            self._masked = np.zeros(n, bool)
            return np.ones(n, bool)
        mask = self._verdict if self.config.observe_mask else self._check(self._last_obs)
        self._masked = ~mask
        if not mask.any():
            mask = self._fallback(self._last_obs)
        return mask

    def _fallback(self, obs: Obs) -> np.ndarray:
        """The candidates allowed when the mask function allows none (see :meth:`action_masks`)."""
        latest = getattr(self.mask_fn, "latest_collision", None)
        driving = self.world.ego.speed >= GO_ON_SPEED
        hold = np.zeros(self.config.num_subgoals, bool)
        hold[int(np.argmin(np.hypot(*obs["subgoals"][:, :2].T)))] = True
        if self.config.fallback_go_on and latest is not None and driving and self.world.ego_in_junction():
            self._going_on = True
            ranked = latest(obs, exclude=hold) if self.config.fallback_go_on_skips_hold else latest(obs)
            return np.asarray(ranked, bool).reshape(self.config.num_subgoals)
        return hold

    def step(self, action: np.int64 | int) -> tuple[Obs, float, bool, bool, dict[str, Any]]:
        """Run the planner towards subgoal ``action`` for up to T_m steps."""
        index = self._check_action(action)
        world, cfg = self.world, self.config
        decision_obs = self._last_obs if self._last_obs is not None else self._observe()
        masked_share = float(self._masked.mean()) if self._masked is not None else 0.0
        self._subgoal = world.subgoal_candidates()[index].copy()
        record = world.begin_decision()
        distance = goal_errors(world.ego, self._subgoal)[0]
        reached, planner_return = False, 0.0
        outcome, truncated = StepOutcome(), False
        held = self._masked is not None and bool(self._masked.all()) and not self._going_on
        brake = cfg.fallback_brakes and held
        for _ in range(cfg.decision_period):
            allowed = world.action_mask()
            before = goal_errors(world.ego, self._subgoal)
            if brake and world.ego.speed > 0.0 and allowed[EgoAction.SLOW_DOWN]:
                ego_action = int(EgoAction.SLOW_DOWN)
            else:
                planner_obs = {**self._state(), "goal": self._in_ego_frame(self._subgoal)}
                ego_action = int(self.planner(planner_obs, allowed))
                if cfg.standing_turn_drives and self._turns_standing(ego_action, before[0], allowed):
                    ego_action = int(EgoAction.KEEP_DIRECTION)
            outcome = world.step(ego_action)
            if self._planner_step_callback is not None:
                self._planner_step_callback(self)
            after = goal_errors(world.ego, self._subgoal)
            arrived = not reached and goal_reached(cfg, after)
            reached |= arrived
            planner_return += sum(
                planner_reward(
                    cfg, before, after, arrived, outcome.crashed, outcome.offroad, outcome.wrong_exit
                ).values()
            )
            truncated = not outcome.terminal and self._truncated()
            if outcome.terminal or truncated:
                break
        paid = reached and (distance > cfg.subgoal_reach_radius or not cfg.r_subgoal_needs_travel)
        terms = decider_reward(cfg, outcome.success, paid, distance)
        future, future_mask = world.decision_future(record)
        info: dict[str, Any] = {
            "reward_terms": terms,
            "subgoal_reached": reached,
            "planner_return": planner_return,
            "decision_obs": decision_obs,
            "subgoal": decision_obs["subgoals"][index],
            "masked_share": masked_share,
            "future": future,
            "future_mask": future_mask,
        }
        if outcome.terminal or truncated:
            info.update(self._episode_info(outcome, truncated))
        self._last_obs = self._observe()
        return self._last_obs, float(sum(terms.values())), outcome.terminal, truncated, info

    def _turns_standing(self, action: int, distance: float, allowed: np.ndarray) -> bool:
        """Whether ``action`` is a turn that leaves a standing ego standing (a turn holds the speed) while
        its subgoal lies ``distance`` away, beyond the reach radius, and 'keep direction' is allowed."""
        return (
            self.world.ego.speed == 0.0
            and action not in (EgoAction.SLOW_DOWN, EgoAction.KEEP_DIRECTION)
            and distance > self.config.subgoal_reach_radius
            and bool(allowed[EgoAction.KEEP_DIRECTION])
        )

    def _render_extras(self) -> dict[str, Any]:
        return {**super()._render_extras(), "masked": self._masked}
