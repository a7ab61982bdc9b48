"""The GCCP module (paper III-C): goal-conditioned trajectory prediction and the subgoal mask.

:class:`TrajectoryPredictor` is the paper's goal-conditioned trajectory predictor: the shared scene
encoder (:class:`~sb3_gccp.networks.SceneEncoder`) gives each vehicle its concatenated 5L feature
(history, interaction, route attention, drivable area and the ego's subgoal feature) and a 2-layer
MLP decodes it into the vehicle's next T_f poses (x, y, heading) at 0.1 s. The scene is encoded once
per decision and combined with all N = 12 subgoal candidates in one batched forward.

The decoder predicts each vehicle's displacement from its current pose, in that vehicle's own frame
(forward, left, heading change), and the pose is added back. A vehicle keeping its lane then has the
same target wherever it is and however it is oriented in the ego frame, so the decoder learns motion
rather than the layout of the scene; positions leave the decoder in units of the encoder's
``distance_scale`` so that its outputs are of order one. With ``cv_residual`` (ours, off by default)
the decoder gives the correction to the constant-velocity displacement instead.

:class:`ConstantVelocityPredictor` is the "w/ CV" ablation (IV-A-2) and ``goal_condition=False``
the "w/o goal condition" one. :class:`GCCPMask` turns a predictor and the
:class:`~sb3_gccp.collision.CollisionChecker` into the decider env's mask function.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from torch import nn

from gccp_envs.config import DT, IntersectionConfig, reject_unknown_keys, require_int
from gccp_envs.traffic import VEHICLE_LENGTH, VEHICLE_WIDTH
from sb3_gccp.collision import CollisionChecker
from sb3_gccp.networks import EncoderConfig, SceneEncoder

STATE_KEYS = ("history", "history_mask", "routes", "routes_mask", "bev")
"""Observation keys the predictors read: the environment state s_t (paper III-B-1)."""


@dataclass(frozen=True)
class PredictorConfig:
    """Configuration of the goal-conditioned trajectory predictor (paper III-C-1)."""

    encoder: Mapping[str, Any] = field(default_factory=dict)
    """:class:`~sb3_gccp.networks.EncoderConfig` fields of the scene encoder; missing ones keep defaults."""
    decoder_hidden: int = 256
    """Width of the hidden layer of the 2-layer MLP trajectory decoder (paper: not given)."""
    goal_condition: bool = True
    """Feed the subgoal feature to the decoder; False is the "w/o goal condition" ablation (IV-A-2)."""
    cv_residual: bool = False
    """Decode the correction to a constant-velocity future instead of the whole displacement (ours,
    off by default as in the paper): an untrained decoder then already predicts constant velocity."""

    def __post_init__(self) -> None:
        EncoderConfig.from_dict(self.encoder)
        require_int("decoder_hidden", self.decoder_hidden)
        for name in ("goal_condition", "cv_residual"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a boolean, got {getattr(self, name)!r}")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None = None) -> PredictorConfig:
        """Build a config from a mapping (for example a YAML map), rejecting unknown keys by name.

        :param values: field values; missing fields keep their defaults
        :return: the validated config
        """
        values = dict(values or {})
        reject_unknown_keys(values, cls, "predictor config")
        return cls(**values)

    @property
    def encoder_config(self) -> EncoderConfig:
        """The scene encoder's validated config."""
        return EncoderConfig.from_dict(self.encoder)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (dicts, lists, numbers) as saved with the weights; :meth:`from_dict` reads it back."""
        values = dataclasses.asdict(self)
        values["encoder"] = {
            key: list(value) if isinstance(value, tuple) else value for key, value in self.encoder.items()
        }
        return values


def current_poses(obs: Mapping[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
    """Every vehicle's current pose and speed, read from its last real history vector.

    The ego's pose is the origin of the ego frame by definition; absent vehicles get zeros.

    :param obs: ``history`` (B, V, T_h, 9) and ``history_mask`` (B, V, T_h)
    :return: poses (B, V, 3) = (x, y, heading) and speeds (B, V)
    """
    history, mask = obs["history"], obs["history_mask"] > 0
    steps = history.shape[2]
    order = th.arange(1, steps + 1, device=history.device)
    # The latest real vector has the largest step number among the real ones (0 where none is real).
    last = (mask * order).argmax(-1)  # (B, V)
    index = last[..., None, None].expand(*last.shape, 1, history.shape[-1])
    state = history.gather(2, index).squeeze(2)[..., 4:8] * mask.any(-1, keepdim=True)
    pose = th.cat((th.zeros_like(state[:, :1, :3]), state[:, 1:, :3]), 1)
    return pose, state[..., 3]


def future_times(horizon: int) -> th.Tensor:
    """The times [s] of the T_f predicted poses: DT, 2 DT, ..., T_f DT."""
    return DT * th.arange(1, horizon + 1, dtype=th.float32)


def constant_velocity_displacement(speed: th.Tensor, times: th.Tensor) -> th.Tensor:
    """Each vehicle's displacement in its own frame when it keeps its heading and speed.

    :param speed: (...) speeds [m/s]
    :param times: (T,) future times [s]
    :return: (..., T, 3) (forward, left, heading change)
    """
    forward = speed[..., None] * times
    zeros = th.zeros_like(forward)
    return th.stack((forward, zeros, zeros), -1)


def wrap_angle(angle: th.Tensor) -> th.Tensor:
    """Wrap angles to [-pi, pi) (differentiable almost everywhere).

    :param angle: angles [rad]
    :return: the wrapped angles
    """
    return th.remainder(angle + th.pi, 2 * th.pi) - th.pi


def from_vehicle_frames(local: th.Tensor, pose: th.Tensor) -> th.Tensor:
    """Poses given in each vehicle's frame, expressed in the ego frame.

    :param local: (..., 3) displacements (forward, left, heading change) from ``pose``
    :param pose: (..., 3) the vehicles' poses in the ego frame, broadcastable to ``local``
    :return: (..., 3) poses in the ego frame, headings wrapped to [-pi, pi)
    """
    cos, sin = th.cos(pose[..., 2]), th.sin(pose[..., 2])
    forward, left, turn = local.unbind(-1)
    x = pose[..., 0] + cos * forward - sin * left
    y = pose[..., 1] + sin * forward + cos * left
    return th.stack((x, y, wrap_angle(pose[..., 2] + turn)), -1)


class TrajectoryPredictor(nn.Module):
    """The paper's goal-conditioned trajectory predictor (III-C-1, Fig. 2).

    :param config: sizes and ablation switch (default :class:`PredictorConfig`)
    :param horizon: T_f, future poses per vehicle (default: the world's ``prediction_horizon``)
    :param bev_shape: (channels, height, width) of the bird's-eye view (default: the world's)
    """

    output_scale: th.Tensor
    times: th.Tensor

    def __init__(
        self,
        config: PredictorConfig | None = None,
        horizon: int | None = None,
        bev_shape: tuple[int, int, int] | None = None,
    ) -> None:
        super().__init__()
        self.config = config = config or PredictorConfig()
        world = IntersectionConfig()
        self.horizon = horizon or world.prediction_horizon
        self.bev_shape = bev_shape or (1, world.bev_size, world.bev_size)
        self.encoder = SceneEncoder(config.encoder_config, bev_shape=self.bev_shape)
        hidden = nn.Linear(self.encoder.vehicle_feature_size, config.decoder_hidden)
        output = nn.Linear(config.decoder_hidden, self.horizon * 3)
        if config.cv_residual:  # start from no correction: an untrained predictor is constant velocity
            nn.init.zeros_(output.weight)
            nn.init.zeros_(output.bias)
        self.decoder = nn.Sequential(hidden, nn.ReLU(), output)
        scale = th.tensor([config.encoder_config.distance_scale] * 2 + [1.0])
        self.register_buffer("output_scale", scale, persistent=False)
        self.register_buffer("times", future_times(self.horizon), persistent=False)

    def forward(self, obs: Mapping[str, th.Tensor], goals: th.Tensor) -> th.Tensor:
        """Predict the future of every vehicle under each of G subgoals.

        :param obs: state tensors (see :meth:`~sb3_gccp.networks.SceneEncoder.encode`), B scenes
        :param goals: (B, G, 3) subgoal poses (x, y, heading) in the ego frame
        :return: (B, G, V, T_f, 3) predicted poses (x, y, heading) in the ego frame of the observation;
            meaningless for absent vehicles
        """
        scene = self.encoder.encode(obs)
        if self.config.goal_condition:
            goal_features = self.encoder.goal_features(goals)
        else:
            goal_features = scene.drivable.new_zeros(*goals.shape[:2], scene.drivable.shape[-1])
        features = self.encoder.vehicle_features(scene, goal_features)  # (B, G, V, 5L)
        batch, num_goals, vehicles, _ = features.shape
        local = self.decoder(features).view(batch, num_goals, vehicles, self.horizon, 3) * self.output_scale
        pose, speed = current_poses(obs)
        if self.config.cv_residual:
            local = local + constant_velocity_displacement(speed, self.times)[:, None]
        return from_vehicle_frames(local, pose[:, None, :, None])


class ConstantVelocityPredictor(nn.Module):
    """The "w/ CV" ablation (IV-A-2): every vehicle keeps its current heading and speed.

    :param horizon: T_f, future poses per vehicle at ``DT`` (default: the world's ``prediction_horizon``)
    """

    times: th.Tensor

    def __init__(self, horizon: int | None = None) -> None:
        super().__init__()
        self.horizon = horizon or IntersectionConfig().prediction_horizon
        self.register_buffer("times", future_times(self.horizon), persistent=False)

    def forward(self, obs: Mapping[str, th.Tensor], goals: th.Tensor) -> th.Tensor:
        """Extrapolate every vehicle's current pose along its heading at its speed; goals are ignored.

        :param obs: ``history`` (B, V, T_h, 9) and ``history_mask`` (B, V, T_h)
        :param goals: (B, G, 3) subgoal poses; only their number is used
        :return: (B, G, V, T_f, 3) poses in the ego frame (absent vehicles stay at the origin)
        """
        pose, speed = current_poses(obs)
        future = from_vehicle_frames(constant_velocity_displacement(speed, self.times), pose[:, :, None])
        return future[:, None].expand(goals.shape[0], goals.shape[1], *future.shape[1:])


YIELD_SPEED = 0.5
"""Below this speed [m/s] a neighbour counts as standing (for ``GCCPMask``'s ``yield_margin``)."""
YIELD_REACH = 8.0
"""How far [m] ahead of a standing neighbour's front the ego's box must reach for it to wait for the ego."""
YIELD_LATERAL = 0.5
"""... and how far [m] beyond its sides."""


def latest_states(obs: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Each neighbour's pose (x, y, heading) in the ego frame, (N_s, 3), and speed, (N_s,), from its last
    real history vector (zeros where absent); the numpy twin of :func:`current_poses` for one observation."""
    history = np.asarray(obs["history"])[1:]
    mask: np.ndarray = np.asarray(obs["history_mask"])[1:] > 0
    real = np.asarray(mask.any(-1))
    last = np.where(real, mask.shape[-1] - 1 - mask[:, ::-1].argmax(-1), 0)
    state = np.asarray(history[np.arange(len(history)), last, 4:8], np.float64) * real[:, None]
    return state[:, :3], state[:, 3]


def yielding(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """Which neighbours stand with a corner of the ego's box in their lane ahead (within
    ``YIELD_LATERAL`` of their sides), within ``YIELD_REACH`` of their front: the traffic waits there for
    the ego to clear its path.

    :param obs: one decider observation
    :return: (N_s,) bool
    """
    pose, speed = latest_states(obs)
    half_length, half_width = VEHICLE_LENGTH / 2.0, VEHICLE_WIDTH / 2.0
    # The ego's corners, at the origin of its frame, in each neighbour's frame.
    corners = np.array([(a * half_length, b * half_width) for a in (1, -1) for b in (1, -1)])
    c, s = np.cos(pose[:, 2:]), np.sin(pose[:, 2:])
    dx, dy = corners[None, :, 0] - pose[:, :1], corners[None, :, 1] - pose[:, 1:2]
    along, lateral = dx * c + dy * s, -dx * s + dy * c  # (N_s, 4)
    ahead = (along > half_length) & (along < half_length + YIELD_REACH)
    in_lane = np.abs(lateral) < half_width + YIELD_LATERAL
    present = np.asarray(obs["history_mask"])[1:].any(-1)
    return np.asarray(present & (speed < YIELD_SPEED) & (ahead & in_lane).any(-1))


class GCCPMask:
    """The GCCP module as the decider env's mask function: which subgoal candidates are safe (III-C-2).

    For one decider observation it predicts the future of the ego and the neighbours under each of
    the N candidates (one batched forward of the predictor) and lets the collision checker compare
    the ego's future with every present neighbour's. Install it with the env's ``set_mask_fn``.

    :param predictor: a :class:`TrajectoryPredictor`, :class:`ConstantVelocityPredictor` or any module
        with their call signature
    :param checker: the collision checker (default :class:`~sb3_gccp.collision.CollisionChecker`)
    :param extrapolate_steps: check this many 0.1 s steps beyond the predicted T_f as well, every
        vehicle going on at the speed and heading of its last predicted step (0: the paper)
    :param ego_deceleration: in those steps the ego brakes at this deceleration [m/s^2] instead, to a
        stop (it can always brake after its subgoal); ``None``: it goes on like the others
    :param yield_margin: a neighbour that stands with the ego's box in its lane ahead (see
        :func:`yielding`) waits for the ego, so it is checked where it stands, with this box margin [m],
        instead of along its predicted future; ``None``: every neighbour along its prediction (the paper)
    """

    def __init__(
        self,
        predictor: nn.Module,
        checker: CollisionChecker | None = None,
        extrapolate_steps: int = 0,
        ego_deceleration: float | None = None,
        yield_margin: float | None = None,
    ) -> None:
        if extrapolate_steps < 0:
            raise ValueError(f"extrapolate_steps must be non-negative, got {extrapolate_steps!r}")
        if ego_deceleration is not None and ego_deceleration <= 0:
            raise ValueError(f"ego_deceleration must be positive or None, got {ego_deceleration!r}")
        if yield_margin is not None and yield_margin < 0:
            raise ValueError(f"yield_margin must be non-negative or None, got {yield_margin!r}")
        self.predictor = predictor.eval()
        self.checker = checker or CollisionChecker()
        self.extrapolate_steps = extrapolate_steps
        self.ego_deceleration = ego_deceleration
        self.yield_checker = None if yield_margin is None else self.checker.with_margin(yield_margin)

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
        waiting = yielding(obs) & present if self.yield_checker is not None else np.zeros_like(present)
        allowed = self.checker.action_mask(future[:, 0], future[:, 1:], present & ~waiting)
        if waiting.any():
            assert self.yield_checker is not None
            standing = np.broadcast_to(latest_states(obs)[0][None, :, None], future[:, 1:].shape)
            allowed &= self.yield_checker.action_mask(future[:, 0], standing, waiting)
        return allowed


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


def save_predictor(predictor: TrajectoryPredictor, path: str | Path) -> None:
    """Save a predictor's config, horizon, BEV shape and weights with ``torch.save`` (plain data only).

    :param predictor: the predictor
    :param path: the file to write
    """
    th.save(
        {
            "config": predictor.config.to_dict(),
            "horizon": predictor.horizon,
            "bev_shape": list(predictor.bev_shape),
            "state_dict": predictor.state_dict(),
        },
        path,
    )


def load_predictor(path: str | Path, device: str | th.device = "cpu") -> TrajectoryPredictor:
    """Load a predictor saved by :func:`save_predictor` (``torch.load`` with ``weights_only=True``).

    :param path: the saved file
    :param device: where to put the weights
    :return: the predictor, in eval mode
    """
    saved = th.load(path, map_location=device, weights_only=True)
    predictor = TrajectoryPredictor(
        PredictorConfig.from_dict(saved["config"]), saved["horizon"], tuple(saved["bev_shape"])
    )
    predictor.load_state_dict(saved["state_dict"])
    return predictor.to(device).eval()
