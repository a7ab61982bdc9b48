"""What the planner, decider and flat envs share: config, world, state, episode info, rendering."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from gccp_envs.config import IntersectionConfig
from gccp_envs.geometry import FloatArray
from gccp_envs.observation import SceneObserver
from gccp_envs.world import StepOutcome, make_world

Obs = dict[str, np.ndarray]


def make_config(
    config: IntersectionConfig | Mapping[str, Any] | None, overrides: Mapping[str, Any]
) -> IntersectionConfig:
    """A config from a config object or a mapping plus keyword overrides (unknown keys rejected)."""
    if isinstance(config, IntersectionConfig):
        return config.replace(**overrides) if overrides else config
    return IntersectionConfig.from_dict(config, **overrides)


class IntersectionBaseEnv(gym.Env):
    """Base of the three envs. Subclasses define the goal part of the observation and the step.

    :param config: an :class:`IntersectionConfig` or a mapping of its fields
    :param render_mode: ``None`` or ``"rgb_array"``
    :param overrides: more config fields, e.g. ``gym.make("GCCPPlanner-v0", task="left")``
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        config: IntersectionConfig | Mapping[str, Any] | None = None,
        render_mode: str | None = None,
        **overrides: Any,
    ) -> None:
        self.config = make_config(config, overrides)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"unsupported render_mode {render_mode!r}: expected None or 'rgb_array'")
        self.render_mode = render_mode
        self.world = make_world(self.config)
        self.observer = SceneObserver(self.world)
        self._subgoal: FloatArray | None = None
        self._renderer: Any = None

    # --- helpers for subclasses ----------------------------------------------------------------------
    def _reset_world(self, seed: int | None, options: dict[str, Any] | None) -> None:
        super().reset(seed=seed)
        task = (options or {}).get("task")
        self.world.reset(self.np_random, task)

    def _state(self) -> Obs:
        return self.observer.observe()

    def _in_ego_frame(self, poses: FloatArray) -> np.ndarray:
        return self.observer.to_ego(poses)

    def _check_action(self, action: Any) -> int:
        """The action as an int, or ``ValueError`` naming it."""
        value = np.asarray(action)
        assert isinstance(self.action_space, gym.spaces.Discrete)
        n = int(self.action_space.n)
        if value.size != 1 or not np.issubdtype(value.dtype, np.integer) or not 0 <= value.item() < n:
            raise ValueError(f"invalid action {action!r}: expected an integer in [0, {n - 1}]")
        return int(value.item())

    def _truncated(self) -> bool:
        return self.world.time >= self.config.duration - 1e-9

    def _episode_info(self, outcome: StepOutcome, truncated: bool) -> dict[str, Any]:
        """Outcome flags; ``is_success`` means this task's own exit was reached."""
        return {
            "task": self.world.task,
            "is_success": outcome.success,
            "crashed": outcome.crashed,
            "offroad": outcome.offroad,
            "wrong_exit": outcome.wrong_exit,
            "timeout": truncated and not outcome.terminal,
        }

    # --- rendering -----------------------------------------------------------------------------------
    def _render_extras(self) -> dict[str, Any]:
        return {"candidates": self.world.subgoal_candidates(), "chosen": self._subgoal}

    def render(self) -> np.ndarray | None:
        """An RGB frame (H, W, 3) of the junction, or ``None`` without a render mode."""
        if self.render_mode is None:
            return None
        from gccp_envs.rendering import IntersectionRenderer

        if self._renderer is None:
            self._renderer = IntersectionRenderer(self.world.layout)
        return self._renderer.frame(self.world, **self._render_extras())

    def close(self) -> None:
        """Release the renderer and the simulation (SUMO's or SMARTS's ends)."""
        self._renderer = None
        self.world.close()
