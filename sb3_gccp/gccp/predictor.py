"""The GCCP trajectory predictors (paper III-C-1): goal-conditioned, and the ablations' ones.

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
the "w/o goal condition" one. :class:`~sb3_gccp.gccp.mask.GCCPMask` turns a predictor into the decider
env's mask function.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch as th
from torch import nn

from gccp_envs.config import DT, IntersectionConfig, reject_unknown_keys, require_int
from sb3_gccp.networks import EncoderConfig, SceneEncoder
from sb3_gccp.safe_loading import first_line

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
    :raises ValueError: one line, when the file is damaged or not a predictor saved so
    """
    if not Path(path).is_file():
        raise ValueError(f"predictor not found: {path}")
    try:
        saved = th.load(path, map_location=device, weights_only=True)
        predictor = TrajectoryPredictor(
            PredictorConfig.from_dict(saved["config"]), int(saved["horizon"]), tuple(saved["bev_shape"])
        )
        predictor.load_state_dict(saved["state_dict"])
    except (
        Exception
    ) as err:  # a damaged or foreign file: torch, its unpickler and the checks raise many kinds
        raise ValueError(f"{path} is not a predictor saved by sb3_gccp: {first_line(err)}") from err
    return predictor.to(device).eval()


def check_predictor_world(
    predictor: TrajectoryPredictor, world: IntersectionConfig, path: str | Path
) -> None:
    """Raise ``ValueError`` (one line) unless a loaded predictor reads the bird's-eye view of ``world``.

    :param path: how messages name the predictor
    """
    given = (1, world.bev_size, world.bev_size)
    if tuple(predictor.bev_shape) != given:
        raise ValueError(
            f"{path} was trained on a bev of shape {tuple(predictor.bev_shape)}, this world gives {given}: "
            "bev_size differs from its training"
        )
