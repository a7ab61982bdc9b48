"""The state in the ego frame: known scenes give known history, route and bird's-eye-view arrays."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ego_frame, path_pose, place_ego, place_ego_on_path

from gccp_envs.action import EgoAction
from gccp_envs.observation import SceneObserver, state_spaces

DT = 0.1


def straight_path(layout, arm, lane):
    return layout.paths_from(arm, lane=lane, turn="straight")[0]


def test_observation_matches_its_spaces(make_world):
    world = make_world("straight", seed=0, spawn_probability=0.1)
    obs = SceneObserver(world).observe()
    spaces = state_spaces(world.config)
    assert set(obs) == set(spaces)
    for key, space in spaces.items():
        assert obs[key].shape == space.shape, key
        assert obs[key].dtype == space.dtype, key
        assert space.contains(obs[key]), key
    assert obs["history"].shape == (6, 10, 9)
    assert obs["routes"].shape == (6, 3, 50, 8)
    assert obs["bev"].shape == (1, 64, 64)


def test_ego_history_after_reset_is_a_constant_speed_line(make_world):
    world = make_world("straight", seed=4)
    obs = SceneObserver(world).observe()
    v = world.ego.speed
    assert v > 0
    hist = obs["history"][0]
    back = -np.arange(10, 0, -1) * v * DT  # oldest first
    expected = np.zeros((10, 9), np.float32)
    expected[:, 0], expected[:, 4] = back, back + v * DT
    expected[:, 3] = expected[:, 7] = v
    np.testing.assert_allclose(hist, expected, atol=1e-4)
    np.testing.assert_array_equal(obs["history_mask"][0], np.ones(10))
    np.testing.assert_array_equal(hist[-1, 4:8], [0.0, 0.0, 0.0, np.float32(v)])


@pytest.mark.parametrize("action", list(EgoAction))
def test_ego_history_after_a_step(make_world, action):
    world = make_world("straight", seed=0)
    place_ego_on_path(world, 2, 40.0, 6.0)
    before = world.ego.as_array()
    world.step(action)
    after = world.ego
    last = SceneObserver(world).observe()["history"][0, -1]
    np.testing.assert_allclose(last[4:8], [0.0, 0.0, 0.0, after.speed], atol=1e-5)
    prev_xy = ego_frame(before[:2], after.x, after.y, after.heading)
    np.testing.assert_allclose(last[0:2], prev_xy, atol=1e-5)
    assert last[2] == pytest.approx(before[2] - after.heading, abs=1e-6)
    assert last[3] == pytest.approx(before[3])
    assert last[8] == 0.0
    if action in (EgoAction.SLOWLY_TURN_LEFT, EgoAction.QUICKLY_TURN_LEFT):
        assert last[2] > 0 and last[1] < 0  # after a left turn, the past pose is behind on the left


CASES = {  # ego lane, vehicle lane, vehicle arc length ahead, expected (x, y) in the ego frame
    "ahead": (0, 0, 10.0, (10.0, 0.0)),
    "right": (0, 1, 5.0, (5.0, 4.0)),
    "left": (1, 0, 5.0, (5.0, -4.0)),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("arm", range(4))
def test_neighbour_in_the_ego_frame(make_world, arm, case):
    """A vehicle 10 m ahead reads (10, 0); one in the lane to the right on screen has y = +4."""
    ego_lane, lane, ahead, expected = CASES[case]
    world = make_world("straight", seed=0)
    layout = world.layout
    place_ego_on_path(world, straight_path(layout, arm, ego_lane), 40.0, 0.0)
    slot = world.traffic.spawn(straight_path(layout, arm, lane), 40.0 + ahead, speed=0.0)
    assert slot is not None
    world._record()
    world.step(EgoAction.SLOW_DOWN)  # the ego stays, the vehicle starts to roll
    obs = SceneObserver(world).observe()
    hist, mask = obs["history"], obs["history_mask"]
    # Seen at two steps: exactly one vector, the latest.
    np.testing.assert_array_equal(mask[1], [0] * 9 + [1])
    np.testing.assert_array_equal(hist[1, :-1], 0.0)
    np.testing.assert_allclose(hist[1, -1, 0:4], [*expected, 0.0, 0.0], atol=1e-4)
    np.testing.assert_allclose(hist[1, -1, 4:7], [*expected, 0.0], atol=0.05)
    assert hist[1, -1, 4] > hist[1, -1, 0]  # it moved forward
    assert hist[1, -1, 7] == pytest.approx(0.2)  # IDM start: 2 m/s^2 for 0.1 s
    assert hist[1, -1, 8] == 1.0
    # The ego itself did not move.
    np.testing.assert_allclose(hist[0, -1, :8], 0.0, atol=1e-5)
    # Padding rows are zero and masked.
    np.testing.assert_array_equal(hist[2:], 0.0)
    np.testing.assert_array_equal(mask[2:], 0.0)
    np.testing.assert_array_equal(obs["routes"][2:], 0.0)
    np.testing.assert_array_equal(obs["routes_mask"][2:], 0.0)
    # The neighbour's two routes start at its position: exactly on its own path, to the 0.5 m
    # lookup table on the other movement open from its lane.
    np.testing.assert_array_equal(obs["routes_mask"][1].sum(-1), [50, 50, 0])
    start_error = np.hypot(*(obs["routes"][1, :2, 0, :2] - np.array(expected)).T)
    assert start_error.min() < 0.05
    assert start_error.max() < 0.4


def test_neighbours_nearest_first_within_radius(make_world):
    world = make_world("straight", seed=0)
    layout = world.layout
    place_ego_on_path(world, 2, 20.0, 0.0)
    far = world.traffic.spawn(2, 75.5, speed=0.0)  # 55.5 m ahead: beyond the 50 m radius
    mid = world.traffic.spawn(2, 50.0, speed=0.0)
    near = world.traffic.spawn(1, 30.0, speed=0.0)
    np.testing.assert_array_equal(world.neighbours(), [near, mid])
    assert far is not None
    world._record()
    world.step(EgoAction.SLOW_DOWN)
    obs = SceneObserver(world).observe()
    np.testing.assert_allclose(obs["history"][1, -1, 4:6], (10.0, -4.0), atol=0.05)
    np.testing.assert_allclose(obs["history"][2, -1, 4:6], (30.0, 0.0), atol=0.05)
    np.testing.assert_array_equal(obs["history"][1:3, -1, 8], [1.0, 2.0])
    assert obs["history_mask"][3:].sum() == 0
    assert layout.paths.lengths[2] > 75.5


def test_reused_slot_does_not_inherit_history(make_world):
    world = make_world("straight", seed=0)
    place_ego_on_path(world, 2, 20.0, 0.0)
    first = world.traffic.spawn(1, 30.0, speed=0.0)
    world._record()
    for _ in range(4):
        world.step(EgoAction.SLOW_DOWN)
    world.traffic.remove(np.array([first]))
    second = world.traffic.spawn(2, 35.0, speed=0.0)
    assert second == first  # the slot is reused
    world._record()
    world.step(EgoAction.SLOW_DOWN)
    mask = SceneObserver(world).observe()["history_mask"]
    np.testing.assert_array_equal(mask[1], [0] * 9 + [1])


def test_ego_routes_are_waypoints_every_metre(make_world):
    world = make_world("straight", seed=0)
    place_ego_on_path(world, 1, 40.0, 5.0)  # inner lane; the other straight lane is on its right
    obs = SceneObserver(world).observe()
    routes, mask = obs["routes"], obs["routes_mask"]
    k = np.arange(50, dtype=np.float32)
    # Route 0: the ego's own lane straight ahead; route 1: the lane 4 m to the right.
    for j, y in ((0, 0.0), (1, 4.0)):
        np.testing.assert_allclose(routes[0, j, :, 0], k, atol=1e-4)
        np.testing.assert_allclose(routes[0, j, :, 3], k + 1, atol=1e-4)
        np.testing.assert_allclose(routes[0, j, :, [1, 4]], y, atol=1e-4)
        np.testing.assert_allclose(routes[0, j, :, [2, 5]], 0.0, atol=1e-6)
        np.testing.assert_array_equal(routes[0, j, :, 6], 0.0)  # vehicle index
        np.testing.assert_array_equal(routes[0, j, :, 7], float(j))  # route index
        np.testing.assert_array_equal(mask[0, j], 1.0)
    # The straight task has only two routes: the third is padding.
    np.testing.assert_array_equal(routes[0, 2], 0.0)
    np.testing.assert_array_equal(mask[0, 2], 0.0)


def test_turning_route_is_spaced_one_metre_and_turns_left(make_world):
    world = make_world("left", seed=0)
    layout = world.layout
    place_ego_on_path(world, 0, 60.0, 5.0)
    routes, mask = (SceneObserver(world).observe()[key] for key in ("routes", "routes_mask"))
    np.testing.assert_array_equal(mask[0].sum(-1), [50, 0, 0])  # one route for a turn
    route = routes[0, 0]
    step = np.hypot(route[:, 3] - route[:, 0], route[:, 4] - route[:, 1])
    assert np.all(step <= 1.0 + 1e-5) and np.all(step > 0.99)
    np.testing.assert_allclose(route[1:, :3], route[:-1, 3:6], atol=1e-6)  # vectors chain up
    assert route[-1, 4] < -10.0  # the turn bends to the left (y < 0)
    assert route[-1, 5] < -1.0  # heading turned left
    end = ego_frame(path_pose(layout, 0, 110.0)[:2], world.ego.x, world.ego.y, world.ego.heading)
    np.testing.assert_allclose(route[-1, 3:5], end, atol=1e-3)


def test_route_mask_at_the_end_of_the_path(make_world):
    world = make_world("straight", seed=0)
    layout = world.layout
    place_ego_on_path(world, 2, layout.paths.lengths[2] - 10.5, 5.0)
    mask = SceneObserver(world).observe()["routes_mask"][0, 0]
    np.testing.assert_array_equal(mask, [1] * 10 + [0] * 40)


def test_neighbour_routes_are_the_movements_open_from_its_lane(make_world):
    world = make_world("straight", seed=0)
    place_ego_on_path(world, 2, 60.0, 0.0)
    slot = world.traffic.spawn(11, 60.0, speed=0.0)  # north arm, outer lane: straight or right
    world._record()
    world.step(EgoAction.SLOW_DOWN)
    obs = SceneObserver(world).observe()
    np.testing.assert_array_equal(obs["routes_mask"][1].sum(-1), [50, 50, 0])
    assert slot is not None
    # Both start where the vehicle is, heading south (backwards in the ego frame).
    pos = ego_frame(world.traffic.pose[slot, :2], world.ego.x, world.ego.y, world.ego.heading)
    np.testing.assert_allclose(obs["routes"][1, :2, 0, :2], [pos, pos], atol=0.5)
    np.testing.assert_allclose(np.abs(obs["routes"][1, :2, 0, 2]), np.pi, atol=1e-3)
    np.testing.assert_array_equal(obs["routes"][1, :2, :, 6], 1.0)


def test_bev_rows_ahead_columns_left_to_right(make_world):
    world = make_world("straight", seed=0)
    place_ego(world, 6.0, 30.0, -np.pi / 2, 5.0)  # outer lane of the south arm, 17 m before the line
    bev = SceneObserver(world).observe()["bev"][0]
    assert bev.dtype == np.uint8
    assert bev[31:33, 31:33].all()  # the ego stands on the road
    # Row 0 is 24.6 m ahead, inside the crossing road: drivable across the whole width.
    assert bev[0].all()
    # The last row is 24.6 m behind, on the 16 m wide arm: the road spans 14 m to the left of
    # the ego and 2 m to its right, so columns 14..34 are drivable.
    expected = np.zeros(64, np.uint8)
    expected[14:35] = 1
    np.testing.assert_array_equal(bev[-1], expected)


@pytest.mark.parametrize("arm", [1, 2, 3])
def test_bev_is_the_same_on_every_arm(make_world, arm):
    """The junction is symmetric under rotation, and the view turns with the ego."""
    world = make_world("straight", seed=0)
    observer = SceneObserver(world)
    place_ego(world, 6.0, 30.0, -np.pi / 2, 5.0)
    south = observer.observe()["bev"]
    angle = arm * np.pi / 2
    x, y = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]) @ [6.0, 30.0]
    place_ego(world, x, y, -np.pi / 2 + angle, 5.0)
    np.testing.assert_array_equal(observer.observe()["bev"], south)
    # Mirrored across the arm's axis, the view is mirrored left to right.
    place_ego(world, -6.0, 30.0, -np.pi / 2, 5.0)
    np.testing.assert_array_equal(observer.observe()["bev"], south[:, :, ::-1])


def test_to_ego(make_world):
    world = make_world("straight", seed=0)
    place_ego(world, 6.0, 30.0, -np.pi / 2, 5.0)
    out = SceneObserver(world).to_ego(np.array([[6.0, 20.0, -np.pi / 2], [10.0, 30.0, 0.0]]))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, [[10.0, 0.0, 0.0], [0.0, 4.0, np.pi / 2]], atol=1e-5)
