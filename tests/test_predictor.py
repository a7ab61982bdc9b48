"""The GCCP predictors and mask: shapes, padding, goal conditioning, constant velocity, masks, saving."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from helpers import TINY_ENCODER as TINY
from torch import nn

from gccp_envs.config import DT
from sb3_gccp.collision import CollisionChecker
from sb3_gccp.prediction import (
    ConstantVelocityPredictor,
    GCCPMask,
    PredictorConfig,
    TrajectoryPredictor,
    extrapolate,
    extrapolate_braking,
    load_predictor,
    save_predictor,
    yielding,
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


@pytest.mark.parametrize(
    "neighbour, allowed",
    [((15.0, 0.0, np.pi, 8.0), False), ((15.0, 6.0, np.pi, 8.0), True), ((-20.0, 0.0, 0.0, 5.0), True)],
    ids=["head-on", "next-lane", "behind"],
)
def test_mask_with_constant_velocity(neighbour, allowed):
    mask = GCCPMask(ConstantVelocityPredictor())
    out = mask(scene([(0.0, 0.0, 0.0, 8.0), neighbour]))
    assert out.shape == (G,) and out.dtype == bool
    assert (out == allowed).all()


class TowardsGoal(nn.Module):
    """A goal-following stub: the ego moves linearly to each subgoal over T_f steps, neighbours stand."""

    def forward(self, obs: dict[str, th.Tensor], goals: th.Tensor) -> th.Tensor:
        batch_size, num_goals = goals.shape[:2]
        fraction = th.arange(1, T_F + 1) / T_F
        out = obs["history"][:, None, :, -1:, 4:7].expand(batch_size, num_goals, V, T_F, 3).clone()
        out[:, :, 0] = goals[:, :, None] * fraction[:, None]
        return out


def test_mask_is_per_candidate():
    mask = GCCPMask(TowardsGoal())
    obs = scene([(0.0, 0.0, 0.0, 8.0), (14.0, 0.0, np.pi, 0.0)])  # a car standing 14 m ahead
    allowed = mask(obs)
    # Two half lengths (5 m cars) apart: the ego's final pose collides from x = 9 m on.
    np.testing.assert_array_equal(allowed, obs["subgoals"][:, 0] < 9.0)
    assert allowed.any() and not allowed.all()
    predicted = mask.predict(obs)
    assert predicted.shape == (G, V, T_F, 3)
    np.testing.assert_allclose(predicted[:, 0, -1], obs["subgoals"], atol=1e-5)


def test_extrapolate_continues_the_last_predicted_step():
    future = np.zeros((2, 3, 4, 3), np.float32)
    future[..., 0] = np.arange(1, 5) * 0.5  # 0.5 m per step along x
    future[..., 2] = 0.3
    longer = extrapolate(future, 3)
    assert longer.shape == (2, 3, 7, 3)
    np.testing.assert_array_equal(longer[..., :4, :], future)
    np.testing.assert_allclose(longer[0, 0, 4:, 0], [2.5, 3.0, 3.5])
    np.testing.assert_allclose(longer[..., 4:, 2], 0.3)
    assert extrapolate(future, 0) is future
    with pytest.raises(ValueError, match="extrapolate_steps"):
        GCCPMask(ConstantVelocityPredictor(), extrapolate_steps=-1)


def test_extrapolate_braking_stops_the_ego_at_its_deceleration():
    future = np.zeros((2, 4, 3), np.float32)
    future[..., 0] = np.arange(1, 5) * 0.8  # 8 m/s along x
    future[1, :, :2] = 0.0  # standing
    longer = extrapolate_braking(future, 30, deceleration=4.0)
    assert longer.shape == (2, 34, 3)
    np.testing.assert_array_equal(longer[:, :4], future)
    # 8 m/s braking at 4 m/s^2: 8 m to a stop after 2 s, then standing.
    np.testing.assert_allclose(longer[0, 4:, 0] - 3.2, np.minimum(8 * T - 2 * T**2, 8.0), atol=1e-5)
    assert np.all(longer[1, :, :2] == 0.0)
    assert extrapolate_braking(future, 0, 4.0) is future


T = DT * np.arange(1, 31)


def test_mask_lets_a_standing_ego_brake_instead_of_going_on():
    # The ego creeps at 1 m/s towards a car standing 6.6 m ahead (boxes 1.6 m apart): going on at
    # 1 m/s for 2 s meets it, braking from 1 m/s stops after 0.125 m.
    creep = scene([(0.0, 0.0, 0.0, 1.0), (6.6, 0.0, np.pi, 0.0)])
    hold = GCCPMask(ConstantVelocityPredictor(), extrapolate_steps=10)
    brake = GCCPMask(ConstantVelocityPredictor(), extrapolate_steps=10, ego_deceleration=4.0)
    assert not hold(creep).any() and brake(creep).all()
    with pytest.raises(ValueError, match="ego_deceleration"):
        GCCPMask(ConstantVelocityPredictor(), ego_deceleration=0.0)


def test_mask_extrapolation_and_margin_see_conflicts_the_paper_check_misses():
    # Head-on, 30 m apart at 8 m/s each: they meet after about 1.6 s, beyond T_f = 1 s.
    obs = scene([(0.0, 0.0, 0.0, 8.0), (30.0, 0.0, np.pi, 8.0)])
    assert GCCPMask(ConstantVelocityPredictor())(obs).all()
    assert not GCCPMask(ConstantVelocityPredictor(), extrapolate_steps=10)(obs).any()
    # A car standing 14 m ahead: with 2 m added to every box, candidates must stop 7 m short of it.
    stand = scene([(0.0, 0.0, 0.0, 8.0), (14.0, 0.0, np.pi, 0.0)])
    np.testing.assert_array_equal(
        GCCPMask(TowardsGoal(), CollisionChecker(margin=2.0))(stand), stand["subgoals"][:, 0] < 7.0
    )


@pytest.mark.parametrize(
    "neighbour, waits",
    [
        ((6.0, 2.0, np.pi, 0.0), True),  # standing, facing the ego, a corner of the ego in its lane
        ((6.0, 2.0, np.pi, 5.0), False),  # moving
        ((6.0, 2.0, 0.0, 0.0), False),  # standing, facing away
        ((6.0, 6.0, np.pi, 0.0), False),  # standing in the next lane
        ((16.0, 2.0, np.pi, 0.0), False),  # the ego beyond its reach
    ],
    ids=["waits", "moving", "facing-away", "next-lane", "far"],
)
def test_yielding_finds_the_standing_cars_the_ego_blocks(neighbour, waits):
    obs = scene([(0.0, 0.0, 0.0, 0.0), neighbour])
    np.testing.assert_array_equal(yielding(obs), [waits] + [False] * (V - 2))


class NeighboursGo(nn.Module):
    """A stub: the ego moves linearly to each subgoal over T_f steps, every neighbour drives 4 m on."""

    def forward(self, obs: dict[str, th.Tensor], goals: th.Tensor) -> th.Tensor:
        out = TowardsGoal()(obs, goals)
        fraction = th.arange(1, T_F + 1) / T_F
        heading = out[:, :, 1:, :, 2]
        out[:, :, 1:, :, 0] += 4.0 * fraction * th.cos(heading)
        out[:, :, 1:, :, 1] += 4.0 * fraction * th.sin(heading)
        return out


def test_mask_lets_the_ego_go_past_a_car_that_waits_for_it():
    # The ego stands across the lane of a car standing 2.5 m from it, which the predictor sends on into
    # the ego's path under every candidate; that car waits for the ego, so held where it stands it
    # leaves every candidate free (its box 1.25 m from the ego's path with a 0.5 m margin).
    obs = scene([(0.0, 0.0, 0.0, 0.0), (3.5, -5.0, np.pi / 2, 0.0)])
    assert not GCCPMask(NeighboursGo(), CollisionChecker(margin=1.0))(obs).any()
    held = GCCPMask(NeighboursGo(), CollisionChecker(margin=1.0), yield_margin=0.5)
    assert held(obs).all()
    assert not GCCPMask(NeighboursGo(), CollisionChecker(margin=1.0), yield_margin=2.5)(obs).any()
    # A car that moves is checked along its prediction as before.
    moving = scene([(0.0, 0.0, 0.0, 0.0), (3.5, -5.0, np.pi / 2, 3.0)])
    assert not held(moving).any()
    with pytest.raises(ValueError, match="yield_margin"):
        GCCPMask(ConstantVelocityPredictor(), yield_margin=-1.0)


def test_mask_allows_everything_without_neighbours():
    class Failing(nn.Module):
        def forward(self, obs, goals):
            raise AssertionError("the predictor must not run without neighbours")

    assert GCCPMask(Failing())(scene([(0.0, 0.0, 0.0, 8.0)])).all()


def test_mask_on_a_decider_env_observation():
    env = gym.make("GCCPDecider-v0", task="left", spawn_probability=0.3)
    obs, _ = env.reset(seed=3)
    mask = GCCPMask(tiny_predictor())
    assert mask.present(obs).any()
    assert mask.predict(obs).shape == (G, V, T_F, 3)
    env.unwrapped.set_mask_fn(mask)
    allowed = env.unwrapped.action_masks()
    assert allowed.shape == (G,) and allowed.dtype == bool and allowed.any()


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
