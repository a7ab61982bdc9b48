"""Subgoal candidates: 12 poses on the task's routes, a 5 m lattice anchored at the stop line."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import EMPTY, forget_ego_caches, path_pose, place_ego_on_path
from hypothesis import given
from hypothesis import strategies as st

from gccp_envs.action import EgoState
from gccp_envs.config import IntersectionConfig
from gccp_envs.scenario import layout_for
from gccp_envs.subgoals import SubgoalSampler
from gccp_envs.world import IntersectionWorld

PER_ROUTE = 4  # ceil(12 candidates / 3 routes)


@pytest.fixture(scope="module")
def world():
    world = IntersectionWorld(EMPTY)
    world.reset(np.random.default_rng(0), "straight")
    return world


def candidates_at(world, task, path, s, lateral=0.0):
    """Candidates of an ego on ``path`` at ``s`` (optionally shifted right by ``lateral``) for ``task``."""
    if world.task != task:
        world.reset(np.random.default_rng(0), task)
    pose = place_ego_on_path(world, path, s, 5.0)
    if lateral:
        world.ego.x -= lateral * np.sin(pose[2])
        world.ego.y += lateral * np.cos(pose[2])
        forget_ego_caches(world)
    return world.subgoal_candidates()


def on_path(layout, path, poses):
    """Arc lengths of poses on a path, checking they lie on it with its heading."""
    s, d = layout.paths.project(np.full(len(poses), path), poses[:, :2])
    np.testing.assert_allclose(d, 0.0, atol=1e-3)
    np.testing.assert_allclose(
        layout.paths.pose_at(np.full(len(poses), path), s)[:, 2], poses[:, 2], atol=1e-3
    )
    return s


def test_straight_task_far_before_the_stop_line(world, layout):
    ego_s = 31.3
    cands = candidates_at(world, "straight", 2, ego_s)
    assert cands.shape == (12, 3)
    # Route 0 is the ego's own lane (path 2), route 1 the other straight lane (path 1).
    for route, path in enumerate((2, 1)):
        s = on_path(layout, path, cands[route * PER_ROUTE : (route + 1) * PER_ROUTE])
        np.testing.assert_allclose(s, [30.0, 35.0, 40.0, 45.0], atol=1e-3)
    # Padding: 12 - 8 copies of the real candidate closest to the task goal.
    real, padding = cands[:8], cands[8:]
    closest = real[np.argmin(np.hypot(*(real[:, :2] - world.task_goal[:2]).T))]
    np.testing.assert_array_equal(padding, np.repeat(closest[None], 4, 0))
    assert closest[1] == pytest.approx(path_pose(layout, 2, 45.0)[1])  # the farthest ahead


@given(st.sampled_from([1, 2]), st.floats(5.0, 72.5), st.floats(-1.0, 1.0))
def test_lattice_window_and_stop_line(world, path, ego_s, lateral):
    layout = world.layout
    cands = candidates_at(world, "straight", path, ego_s, lateral)
    own = cands[:PER_ROUTE]
    s = on_path(layout, path, own)
    ahead = s - ego_s
    assert np.all(ahead >= -2.5 - 1e-6)  # half a spacing behind at most...
    assert np.all(ahead < 17.5 + 1e-6)  # ...within the 20 m window
    np.testing.assert_allclose(np.diff(s), 5.0, atol=1e-3)  # spaced 5 m, nearest first
    offsets = (s - layout.stop_s) / 5.0
    np.testing.assert_allclose(offsets, np.round(offsets), atol=1e-3)  # anchored at the stop line
    if layout.stop_s - 17.5 < ego_s <= layout.stop_s + 2.5:
        # One candidate sits exactly on the stop line.
        assert np.any(np.all(np.isclose(own, path_pose(layout, path, layout.stop_s), atol=1e-9), axis=1))
    if ego_s < layout.stop_s:
        assert len(np.unique(cands[:8], axis=0)) == 8  # both straight lanes are routes


@pytest.mark.parametrize(("task", "path"), [("left", 0), ("right", 3)])
@pytest.mark.parametrize("ego_path", [1, 2])
def test_turn_task_has_four_distinct_candidates_and_eight_padded(world, layout, task, path, ego_path):
    """A turn has one route, whichever lane the ego starts on."""
    cands = candidates_at(world, task, ego_path, 40.0)
    assert len(np.unique(cands, axis=0)) == 4
    s = on_path(layout, path, cands[:4])
    np.testing.assert_allclose(s, [40.0, 45.0, 50.0, 55.0], atol=1e-3)
    np.testing.assert_array_equal(cands[4:], np.repeat(cands[3][None], 8, 0))  # farthest = closest to goal


def test_candidates_follow_the_turn_inside_the_junction(world, layout):
    cands = candidates_at(world, "left", 0, layout.stop_s + 8.0)
    s = on_path(layout, 0, cands[:4])
    np.testing.assert_allclose(s, layout.stop_s + np.array([10.0, 15.0, 20.0, 25.0]), atol=1e-3)
    assert np.all(np.diff(np.unwrap(cands[:4, 2])) < 0)  # turning left: headings decrease


def test_candidates_stop_at_the_end_of_the_path(world, layout):
    length = layout.paths.lengths[2]
    cands = candidates_at(world, "straight", 2, length - 7.0, lateral=0.5)  # path 1 is 4.5 m away
    s = on_path(layout, 2, cands[:2])
    np.testing.assert_allclose(s, [160.0, 165.0], atol=1e-3)
    # Past the task goal, the candidate closest to it is the nearer one, not the farthest.
    np.testing.assert_array_equal(cands[2:], np.repeat(cands[0][None], 10, 0))


def test_sampler_pads_with_the_task_goal_without_candidates():
    cfg = IntersectionConfig()
    layout = layout_for(cfg)
    goal = np.array([1.0, 2.0, 0.5])
    cands = SubgoalSampler(layout, cfg).sample([], np.zeros(0), goal)
    np.testing.assert_array_equal(cands, np.repeat(goal[None], 12, 0))


def test_candidates_are_cached_per_step_and_refreshed_by_step(make_world):
    world = make_world("straight", seed=3)
    first = world.subgoal_candidates()
    assert world.subgoal_candidates() is first
    path, layout = 2, world.layout
    x, y, h = path_pose(layout, path, 60.0)
    world.ego = EgoState(x, y, h, 0.0)  # moved without telling the cache
    world.step(0)
    s = on_path(layout, path, world.subgoal_candidates()[:4])
    np.testing.assert_allclose(s, [60.0, 65.0, 70.0, 75.0], atol=1e-3)
