"""The GCCP mask: candidates masked by predicted collisions, the check's extensions, the env's mask."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from test_predictor import T_F, G, V, scene, tiny_predictor
from torch import nn

from gccp_envs.config import DT
from sb3_gccp.gccp.mask import GCCPMask, extrapolate, extrapolate_braking, yielding
from sb3_gccp.gccp.predictor import ConstantVelocityPredictor
from sb3_gccp.gccp.settings import GCCPCheck


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


SMARTS_SIZES = ((3.68, 1.47), (3.68, 1.47))


def test_the_boxes_have_the_sizes_the_mask_is_given():
    obs = scene([(0.0, 0.0, 0.0, 8.0), (14.0, 0.0, np.pi, 0.0)])
    allowed = GCCPMask(TowardsGoal(), sizes=SMARTS_SIZES)(obs)
    np.testing.assert_array_equal(allowed, obs["subgoals"][:, 0] < 14.0 - 3.68)
    # The standing car waits for a 5 m ego 12.5 m away (its front 10 m from the ego's), not for a smaller one.
    stand = scene([(0.0, 0.0, 0.0, 0.0), (12.5, 0.5, np.pi, 0.0)])
    assert yielding(stand)[0] and not yielding(stand, SMARTS_SIZES)[0]


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
    hold = GCCPMask(ConstantVelocityPredictor(), GCCPCheck(extrapolate_steps=10))
    brake = GCCPMask(ConstantVelocityPredictor(), GCCPCheck(extrapolate_steps=10, ego_deceleration=4.0))
    assert not hold(creep).any() and brake(creep).all()


def test_mask_extrapolation_and_margin_see_conflicts_the_paper_check_misses():
    # Head-on, 30 m apart at 8 m/s each: they meet after about 1.6 s, beyond T_f = 1 s.
    obs = scene([(0.0, 0.0, 0.0, 8.0), (30.0, 0.0, np.pi, 8.0)])
    assert GCCPMask(ConstantVelocityPredictor())(obs).all()
    assert not GCCPMask(ConstantVelocityPredictor(), GCCPCheck(extrapolate_steps=10))(obs).any()
    # A car standing 14 m ahead: with 2 m added to every box, candidates must stop 7 m short of it.
    stand = scene([(0.0, 0.0, 0.0, 8.0), (14.0, 0.0, np.pi, 0.0)])
    np.testing.assert_array_equal(
        GCCPMask(TowardsGoal(), GCCPCheck(margin=2.0))(stand), stand["subgoals"][:, 0] < 7.0
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
    assert not GCCPMask(NeighboursGo(), GCCPCheck(margin=1.0))(obs).any()
    held = GCCPMask(NeighboursGo(), GCCPCheck(margin=1.0, yield_margin=0.5))
    assert held(obs).all()
    assert not GCCPMask(NeighboursGo(), GCCPCheck(margin=1.0, yield_margin=2.5))(obs).any()
    # A car that moves is checked along its prediction as before.
    moving = scene([(0.0, 0.0, 0.0, 0.0), (3.5, -5.0, np.pi / 2, 3.0)])
    assert not held(moving).any()


def test_a_fallback_margin_checks_again_only_when_no_candidate_passes():
    # A car stands beside the ego, 2.7 m from its centre line: with 1 m margins the boxes overlap where
    # the ego stands, so every candidate fails, the hold too; with the paper's boxes none does.
    beside = scene([(0.0, 0.0, 0.0, 0.0), (3.0, 2.7, 0.0, 0.0)])
    assert not GCCPMask(TowardsGoal(), GCCPCheck(margin=1.0))(beside).any()
    assert GCCPMask(TowardsGoal(), GCCPCheck(margin=1.0, fallback_margin=0.0))(beside).all()
    assert not GCCPMask(TowardsGoal(), GCCPCheck(margin=1.0, fallback_margin=0.8))(beside).any()
    # Where some candidates pass with the margin, the fallback changes nothing.
    ahead = scene([(0.0, 0.0, 0.0, 8.0), (14.0, 0.0, np.pi, 0.0)])
    plain = GCCPMask(TowardsGoal(), GCCPCheck(margin=1.0))(ahead)
    assert plain.any() and not plain.all()
    fallback = GCCPMask(TowardsGoal(), GCCPCheck(margin=1.0, fallback_margin=0.0))
    np.testing.assert_array_equal(fallback(ahead), plain)


def test_latest_collision_names_the_candidates_that_meet_the_car_last():
    # A car stands 9 m ahead and the ego goes on 2 s beyond each prediction at its last step's speed:
    # every candidate reaches the car, the nearest (2 m ahead, 0.2 m per step) last.
    obs = scene([(0.0, 0.0, 0.0, 8.0), (9.0, 0.0, np.pi, 0.0)])
    mask = GCCPMask(TowardsGoal(), GCCPCheck(extrapolate_steps=20))
    assert not mask(obs).any()
    np.testing.assert_array_equal(mask.latest_collision(obs), np.arange(G) == 0)
    # Asked about another observation than the last one checked, it checks that one.
    clear = scene([(0.0, 0.0, 0.0, 8.0), (-30.0, 0.0, 0.0, 0.0)])
    assert GCCPMask(TowardsGoal(), GCCPCheck(extrapolate_steps=20)).latest_collision(clear).all()
    assert mask.latest_collision(clear).all() and mask.latest_collision(obs)[0]


def test_latest_collision_leaves_out_the_excluded_candidates():
    # The same car 9 m ahead: without the nearest candidate, the next nearest meets it last.
    obs = scene([(0.0, 0.0, 0.0, 8.0), (9.0, 0.0, np.pi, 0.0)])
    mask = GCCPMask(TowardsGoal(), GCCPCheck(extrapolate_steps=20))
    first = mask.checker.first_collision(*_futures(mask, obs))
    latest = mask.latest_collision(obs, exclude=np.arange(G) == 0)
    assert not latest[0] and latest.any()
    np.testing.assert_array_equal(latest, (first == first[1:].max()) & (np.arange(G) > 0))
    # All left out: ranked as if none were; nothing to collide with: every candidate not left out.
    np.testing.assert_array_equal(mask.latest_collision(obs, exclude=np.ones(G, bool)), np.arange(G) == 0)
    clear = scene([(0.0, 0.0, 0.0, 8.0), (-30.0, 0.0, 0.0, 0.0)])
    np.testing.assert_array_equal(mask.latest_collision(clear, exclude=np.arange(G) == 0), np.arange(G) > 0)


def _futures(mask, obs):
    """The ego's and the neighbours' checked futures and presence of ``mask``'s last check of ``obs``."""
    mask(obs)
    _, future, present = mask._checked
    return future[:, 0], future[:, 1:], present


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
