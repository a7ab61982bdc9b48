"""The GCCP mask (paper III-C-2): which subgoal candidates are safe, from predicted futures.

:class:`GCCPMask` predicts the future of the ego and the neighbours under every candidate and lets
the :class:`~sb3_gccp.gccp.collision.CollisionChecker` compare them; how (box margin, steps beyond
T_f, the ego braking in them, neighbours that wait for the ego) is a
:class:`~sb3_gccp.gccp.settings.GCCPCheck`. It is the decider env's mask function.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch as th
from torch import nn

from gccp_envs.config import DT
from gccp_envs.world import BUILTIN_SIZES, VehicleSizes
from sb3_gccp.gccp.collision import CollisionChecker
from sb3_gccp.gccp.predictor import STATE_KEYS
from sb3_gccp.gccp.settings import GCCPCheck

YIELD_SPEED = 0.5
"""Below this speed [m/s] a neighbour counts as standing (for ``GCCPMask``'s ``yield_margin``)."""
YIELD_REACH = 8.0
"""How far [m] ahead of a standing neighbour's front the ego's box must reach for it to wait for the ego."""
YIELD_LATERAL = 0.5
"""... and how far [m] beyond its sides."""


def latest_states(obs: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Each neighbour's pose (x, y, heading) in the ego frame, (N_s, 3), and speed, (N_s,), from its last
    real history vector (zeros where absent); the numpy twin of
    :func:`~sb3_gccp.gccp.predictor.current_poses` for one observation."""
    history = np.asarray(obs["history"])[1:]
    mask: np.ndarray = np.asarray(obs["history_mask"])[1:] > 0
    real = np.asarray(mask.any(-1))
    last = np.where(real, mask.shape[-1] - 1 - mask[:, ::-1].argmax(-1), 0)
    state = np.asarray(history[np.arange(len(history)), last, 4:8], np.float64) * real[:, None]
    return state[:, :3], state[:, 3]


def yielding(obs: Mapping[str, np.ndarray], sizes: VehicleSizes = BUILTIN_SIZES) -> np.ndarray:
    """Which neighbours stand with a corner of the ego's box in their lane ahead (within
    ``YIELD_LATERAL`` of their sides), within ``YIELD_REACH`` of their front: the traffic waits there for
    the ego to clear its path.

    :param obs: one decider observation
    :param sizes: (length, width) [m] of the ego and of the neighbours
    :return: (N_s,) bool
    """
    pose, speed = latest_states(obs)
    (ego_length, ego_width), (length, width) = sizes
    # The ego's corners, at the origin of its frame, in each neighbour's frame.
    corners = np.array([(a * ego_length / 2.0, b * ego_width / 2.0) for a in (1, -1) for b in (1, -1)])
    c, s = np.cos(pose[:, 2:]), np.sin(pose[:, 2:])
    dx, dy = corners[None, :, 0] - pose[:, :1], corners[None, :, 1] - pose[:, 1:2]
    along, lateral = dx * c + dy * s, -dx * s + dy * c  # (N_s, 4)
    ahead = (along > length / 2.0) & (along < length / 2.0 + YIELD_REACH)
    in_lane = np.abs(lateral) < width / 2.0 + YIELD_LATERAL
    present = np.asarray(obs["history_mask"])[1:].any(-1)
    return np.asarray(present & (speed < YIELD_SPEED) & (ahead & in_lane).any(-1))


class GCCPMask:
    """The GCCP module as the decider env's mask function: which subgoal candidates are safe (III-C-2).

    For one decider observation it predicts the future of the ego and the neighbours under each of
    the N candidates (one batched forward of the predictor) and lets the collision checker compare
    the ego's future with every present neighbour's. Install it with the env's ``set_mask_fn``.

    :param predictor: a :class:`~sb3_gccp.gccp.predictor.TrajectoryPredictor`,
        :class:`~sb3_gccp.gccp.predictor.ConstantVelocityPredictor` or any module with their call signature
    :param check: how futures are checked (default: the paper's check, :class:`GCCPCheck` ())
    :param sizes: (length, width) [m] of the ego and of the neighbours, before ``check.margin``
        (default: our world's cars; :meth:`GCCPCheck.make_mask` gives the world's)
    """

    def __init__(
        self, predictor: nn.Module, check: GCCPCheck | None = None, sizes: VehicleSizes = BUILTIN_SIZES
    ) -> None:
        self.check = check = check or GCCPCheck()
        self.sizes = sizes
        self.predictor = predictor.eval()
        self.checker = CollisionChecker(*sizes, margin=check.margin)
        self.extrapolate_steps = check.extrapolate_steps
        self.ego_deceleration = check.ego_deceleration
        yield_margin, fallback = check.yield_margin, check.fallback_margin
        self.yield_checker = None if yield_margin is None else self.checker.with_margin(yield_margin)
        self.fallback_checker = None if fallback is None else self.checker.with_margin(fallback)
        self._checked: tuple[Mapping[str, np.ndarray], np.ndarray, np.ndarray] | None = None

    def predict(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Predicted futures under every candidate, e.g. for plotting (paper Fig. 8).

        :param obs: one decider observation (numpy, no batch axis) with the state arrays and ``subgoals``
        :return: (N, V, T_f, 3) poses (x, y, heading) in the ego frame
        """
        tensors = {key: th.from_numpy(np.asarray(obs[key]))[None] for key in STATE_KEYS}
        goals = th.from_numpy(np.asarray(obs["subgoals"], dtype=np.float32))[None]
        with th.inference_mode():
            return self.predictor(tensors, goals)[0].numpy()

    def present(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Which neighbours (rows 1..N_s) exist in the observation.

        :param obs: one decider observation
        :return: (N_s,) bool
        """
        return np.asarray(np.asarray(obs["history_mask"])[1:].any(-1), dtype=bool)

    def __call__(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """The allowed subgoals of one decider observation.

        :param obs: one decider observation (numpy, no batch axis)
        :return: (N,) bool, True where the ego's predicted future collides with no neighbour's
        """
        present = self.present(obs)
        if not present.any():  # nothing to collide with: skip the prediction
            return np.ones(len(obs["subgoals"]), bool)
        predicted = self.predict(obs)
        future = extrapolate(predicted, self.extrapolate_steps)
        if self.ego_deceleration is not None and self.extrapolate_steps:
            future[:, 0] = extrapolate_braking(predicted[:, 0], self.extrapolate_steps, self.ego_deceleration)
        waiting = np.zeros_like(present)
        if self.yield_checker is not None:
            waiting = yielding(obs, self.sizes) & present
        self._checked = (obs, future, present & ~waiting)
        allowed = self.checker.action_mask(future[:, 0], future[:, 1:], present & ~waiting)
        if not allowed.any() and self.fallback_checker is not None:
            allowed = self.fallback_checker.action_mask(future[:, 0], future[:, 1:], present & ~waiting)
        if waiting.any():
            assert self.yield_checker is not None
            standing = np.broadcast_to(latest_states(obs)[0][None, :, None], future[:, 1:].shape)
            allowed &= self.yield_checker.action_mask(future[:, 0], standing, waiting)
        return allowed

    def latest_collision(
        self, obs: Mapping[str, np.ndarray], exclude: np.ndarray | None = None
    ) -> np.ndarray:
        """The candidates whose first predicted collision comes latest, for an env to fall back on when
        :meth:`__call__` allows none (the option env's ``fallback_go_on``): the futures and boxes of the
        check, the last ``__call__``'s when it was asked about the same observation.

        :param obs: one decider observation (numpy, no batch axis)
        :param exclude: (N,) bool, candidates left out of the ranking (all of them: none left out)
        :return: (N,) bool, True for every candidate whose first collision is at the latest step
        """
        n = len(obs["subgoals"])
        ranked = np.ones(n, bool) if exclude is None else ~np.asarray(exclude, bool).reshape(n)
        if not ranked.any():
            ranked[:] = True
        if self._checked is None or self._checked[0] is not obs:
            self(obs)
        if self._checked is None or self._checked[0] is not obs:  # nothing to collide with
            return ranked
        _, future, present = self._checked
        first = np.where(ranked, self.checker.first_collision(future[:, 0], future[:, 1:], present), -1)
        return np.asarray(first == first.max())


def extrapolate(future: np.ndarray, steps: int) -> np.ndarray:
    """Predicted poses followed by ``steps`` more, each vehicle keeping the displacement per step and
    the heading of its last predicted step (the first step's displacement from the origin when T_f is 1).

    :param future: (..., T_f, 3) poses (x, y, heading)
    :param steps: extra steps
    :return: (..., T_f + steps, 3)
    """
    if steps == 0:
        return future
    last, step = _last_step(future)
    k = np.arange(1, steps + 1, dtype=future.dtype)[:, None]
    return _append(future, last, last[..., :2] + k * step)


def extrapolate_braking(future: np.ndarray, steps: int, deceleration: float) -> np.ndarray:
    """Predicted poses followed by ``steps`` more of braking to a stop: from the speed of the last
    predicted step (as in :func:`extrapolate`), along its direction, at ``deceleration``.

    :param future: (..., T_f, 3) poses (x, y, heading)
    :param steps: extra steps
    :param deceleration: [m/s^2]
    :return: (..., T_f + steps, 3)
    """
    if steps == 0:
        return future
    last, step = _last_step(future)
    length = np.hypot(step[..., :1], step[..., 1:])  # (..., 1, 1)
    speed = length / DT
    t = np.arange(1, steps + 1, dtype=np.float64)[:, None] * DT
    travelled = np.minimum(speed * t - 0.5 * deceleration * t**2, speed**2 / (2.0 * deceleration))
    return _append(future, last, last[..., :2] + travelled * step / np.maximum(length, 1e-9))


def _last_step(future: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The last predicted pose (..., 1, 3) and its displacement (..., 1, 2) from the one before (from the
    origin when T_f is 1)."""
    last = future[..., -1:, :]
    previous = future[..., -2:-1, :] if future.shape[-2] > 1 else np.zeros_like(last)
    return last, last[..., :2] - previous[..., :2]


def _append(future: np.ndarray, last: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``future`` followed by the positions ``xy`` (..., steps, 2), all at the heading of ``last``."""
    heading = np.broadcast_to(last[..., 2:], (*xy.shape[:-1], 1))
    return np.concatenate([future, np.concatenate([xy, heading], -1).astype(future.dtype)], axis=-2)
