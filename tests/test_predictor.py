"""The GCCP predictors: shapes, padding, goal conditioning, constant velocity, residual decoder, saving."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from helpers import TINY_ENCODER as TINY
from torch import nn

from gccp_envs.config import DT
from sb3_gccp.gccp.predictor import (
    ConstantVelocityPredictor,
    PredictorConfig,
    TrajectoryPredictor,
    load_predictor,
    save_predictor,
)

V, T_H, T_F, G = 6, 10, 10, 12


def tiny_predictor(
    goal_condition: bool = True, seed: int = 0, cv_residual: bool = False
) -> TrajectoryPredictor:
    th.manual_seed(seed)
    return TrajectoryPredictor(
        PredictorConfig(
            encoder=TINY, decoder_hidden=32, goal_condition=goal_condition, cv_residual=cv_residual
        )
    )


def straight_history(x: float, y: float, heading: float, speed: float, index: int) -> np.ndarray:
    """(T_h, 9) history vectors of a vehicle that drove straight at constant speed to (x, y)."""
    back = speed * DT * np.arange(T_H, -1, -1)  # distance behind the current pose, oldest first
    poses = np.stack(
        [
            x - back * np.cos(heading),
            y - back * np.sin(heading),
            np.full_like(back, heading),
            np.full_like(back, speed),
        ],
        -1,
    )
    return np.concatenate([poses[:-1], poses[1:], np.full((T_H, 1), index)], -1)


def scene(
    vehicles: list[tuple[float, float, float, float]], subgoals: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """One decider observation: the ego (row 0, at the origin, heading 0) at ``vehicles[0]``'s speed and
    neighbours at (x, y, heading, speed); other rows absent, no routes, everything drivable."""
    history = np.zeros((V, T_H, 9), np.float32)
    mask = np.zeros((V, T_H), np.float32)
    for i, (x, y, heading, speed) in enumerate(vehicles):
        history[i] = straight_history(x, y, heading, speed, i)
        mask[i] = 1.0
    if subgoals is None:
        subgoals = np.stack([np.linspace(2.0, 24.0, G), np.zeros(G), np.zeros(G)], -1)
    return {
        "history": history,
        "history_mask": mask,
        "routes": np.zeros((V, 3, 50, 8), np.float32),
        "routes_mask": np.zeros((V, 3, 50), np.float32),
        "bev": np.ones((1, 64, 64), np.uint8),
        "task_goal": np.array([40.0, 0.0, 0.0], np.float32),
        "subgoals": np.asarray(subgoals, np.float32),
    }


def batch(*observations: dict[str, np.ndarray]) -> dict[str, th.Tensor]:
    return {key: th.as_tensor(np.stack([obs[key] for obs in observations])) for key in observations[0]}


def random_scenes(size: int = 3, seed: int = 0) -> dict[str, th.Tensor]:
    """Scenes with 1-4 neighbours in random motion, short histories and a route for the ego."""
    rng = np.random.default_rng(seed)
    observations = []
    for _ in range(size):
        vehicles = [(0.0, 0.0, 0.0, rng.uniform(0, 8))] + [
            (*rng.uniform(-30, 30, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0, 10))
            for _ in range(rng.integers(1, 5))
        ]
        obs = scene(vehicles, rng.uniform(-20, 20, (G, 3)))
        obs["history_mask"][:, : rng.integers(0, T_H)] = 0.0  # seen for a shorter time
        obs["history"][obs["history_mask"] == 0] = 0.0
        obs["routes"][0, 0, :, 0] = np.arange(50)
        obs["routes"][0, 0, :, 3] = np.arange(1, 51)
        obs["routes_mask"][0, 0] = 1.0
        observations.append(obs)
    return batch(*observations)


def test_predictor_output_shape_and_goal_batching():
    predictor = tiny_predictor().eval()
    obs = random_scenes(size=2)
    out = predictor(obs, obs["subgoals"])
    assert out.shape == (2, G, V, T_F, 3)
    assert th.isfinite(out).all()
    # One batched forward over the 12 candidates equals 12 forwards of one candidate each.
    for g in (0, 7):
        th.testing.assert_close(out[:, g : g + 1], predictor(obs, obs["subgoals"][:, g : g + 1]))


def test_padding_and_absent_vehicles_do_not_change_predictions():
    predictor = tiny_predictor().eval()
    obs = random_scenes()
    noisy = dict(obs)
    for key in ("history", "routes"):
        padded = obs[f"{key}_mask"][..., None] == 0
        noisy[key] = th.where(padded, th.randn(obs[key].shape) * 100, obs[key])
    assert (obs["history_mask"][:, 5] == 0).all()  # vehicle 5 is absent everywhere: only noise
    th.testing.assert_close(
        predictor(noisy, obs["subgoals"]), predictor(obs, obs["subgoals"]), rtol=0, atol=1e-5
    )


def test_goal_conditioning_changes_the_ego_prediction_and_the_ablation_ignores_goals():
    obs = random_scenes(size=1)
    goals = th.tensor([[[5.0, 0.0, 0.0], [15.0, -4.0, -0.8]]])
    conditioned = tiny_predictor(goal_condition=True)(obs, goals)
    assert (conditioned[0, 0, 0] - conditioned[0, 1, 0]).abs().max() > 1e-3
    unconditioned = tiny_predictor(goal_condition=False)(obs, goals)
    th.testing.assert_close(unconditioned[:, 0], unconditioned[:, 1])


def test_decoder_outputs_are_displacements_in_each_vehicle_frame():
    predictor = tiny_predictor()
    last = predictor.decoder[-1]
    assert isinstance(last, nn.Linear)
    with th.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    obs = batch(scene([(0.0, 0.0, 0.0, 5.0), (10.0, 5.0, np.pi / 2, 6.0)]))
    out = predictor(obs, obs["subgoals"])
    th.testing.assert_close(out[0, :, 0], th.zeros(G, T_F, 3))  # the ego stays at the origin
    th.testing.assert_close(out[0, :, 1], th.tensor([10.0, 5.0, np.pi / 2]).expand(G, T_F, 3))
    with th.no_grad():
        last.bias.view(T_F, 3)[:, 0] = 0.1  # 0.1 * distance_scale = 2 m forward
    out = predictor(obs, obs["subgoals"])
    th.testing.assert_close(out[0, 0, 1, 0], th.tensor([10.0, 7.0, np.pi / 2]))  # forward is +y for it


def test_constant_velocity_predictor_extrapolates_straight_lines():
    obs = batch(scene([(0.0, 0.0, 0.0, 8.0), (10.0, 5.0, np.pi / 2, 5.0), (-3.0, 2.0, 3 * np.pi / 4, 2.0)]))
    out = ConstantVelocityPredictor()(obs, obs["subgoals"])
    assert out.shape == (1, G, V, T_F, 3)
    t = DT * np.arange(1, T_F + 1)
    zeros = np.zeros(T_F)
    expected = [
        np.stack([8.0 * t, zeros, zeros], -1),
        np.stack([np.full(T_F, 10.0), 5.0 + 5.0 * t, np.full(T_F, np.pi / 2)], -1),
        np.stack([-3.0 - 2.0 * t / np.sqrt(2), 2.0 + 2.0 * t / np.sqrt(2), np.full(T_F, 3 * np.pi / 4)], -1),
    ]
    for i, poses in enumerate(expected):
        for g in (0, G - 1):
            np.testing.assert_allclose(out[0, g, i].numpy(), poses, atol=1e-5)


def test_residual_decoder_starts_at_constant_velocity_and_corrects_it():
    predictor = tiny_predictor(cv_residual=True)  # untrained: no correction yet
    last = predictor.decoder[-1]
    assert isinstance(last, nn.Linear)
    obs = batch(scene([(0.0, 0.0, 0.0, 8.0), (10.0, 5.0, np.pi / 2, 5.0), (-3.0, 2.0, 3 * np.pi / 4, 2.0)]))
    cv = ConstantVelocityPredictor()(obs, obs["subgoals"])
    present = obs["history_mask"][0].any(-1)
    th.testing.assert_close(predictor(obs, obs["subgoals"])[:, :, present], cv[:, :, present])
    with th.no_grad():
        last.bias.view(T_F, 3)[:, 1] = 0.05  # 0.05 * distance_scale = 1 m to the left of the CV future
    out = predictor(obs, obs["subgoals"])
    th.testing.assert_close(out[0, 3, 1, :, 0], cv[0, 3, 1, :, 0] - 1.0)  # left of +y is -x


def test_save_and_load_round_trip(tmp_path):
    predictor = tiny_predictor(goal_condition=False, cv_residual=True).eval()
    path = tmp_path / "predictor.pt"
    save_predictor(predictor, path)
    saved = th.load(path, weights_only=True)
    assert saved["config"]["encoder"] == TINY
    loaded = load_predictor(path)
    assert loaded.config == predictor.config and not loaded.config.goal_condition
    assert loaded.config.cv_residual
    obs = random_scenes(size=2)
    th.testing.assert_close(loaded(obs, obs["subgoals"]), predictor(obs, obs["subgoals"]), rtol=0, atol=0)


@pytest.mark.parametrize(
    "values, message",
    [
        ({"decoder_hiden": 8}, "decoder_hidden"),
        ({"encoder": {"hidden": 8}}, "hidden"),
        ({"decoder_hidden": 0}, "decoder_hidden"),
        ({"goal_condition": "no"}, "goal_condition"),
        ({"cv_residual": 1}, "cv_residual"),
    ],
)
def test_config_rejects_bad_values(values, message):
    with pytest.raises(ValueError, match=message):
        PredictorConfig.from_dict(values)
