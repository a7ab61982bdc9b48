"""The junction layout: lanes, movements, drivable area, exits, task goals, conflicts."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import path_pose
from hypothesis import given
from hypothesis import strategies as st

from gccp_envs.config import IntersectionConfig
from gccp_envs.scenario import MAJOR_ARMS, TURN_OFFSET, layout_for


def test_layout_is_cached_per_config(layout):
    assert layout_for(IntersectionConfig(task="left", spawn_probability=0.0)) is layout
    assert layout.junction == pytest.approx(IntersectionConfig().junction_half_size)
    assert layout.half_width == pytest.approx(IntersectionConfig().road_half_width)


def test_movements(layout):
    # Per arm: lane 0 turns left or goes straight, lane 1 goes straight or turns right.
    assert len(layout.movements) == 16
    for move in layout.movements:
        assert move.exit_arm == (move.arm + TURN_OFFSET[move.turn]) % 4
        if move.turn == "left":
            assert move.lane == 0 and move.exit_lane == 0
        elif move.turn == "right":
            assert move.lane == 1 and move.exit_lane == 1
        else:
            assert move.exit_lane == move.lane
    assert layout.paths_from(0, turn="left") == [0]
    assert layout.paths_from(0, turn="straight") == [1, 2]
    assert layout.paths_from(0, turn="right") == [3]
    assert layout.paths_from(0, lane=1) == [2, 3]
    np.testing.assert_array_equal(layout.path_major, np.isin(layout.path_arm, MAJOR_ARMS))


def test_ego_arm_lanes_drive_north_on_the_right(layout):
    """Arm 0 is south; its inbound lanes run north (heading -pi/2) on the east half, lane 0 innermost."""
    for path, x in ((1, 2.0), (2, 6.0)):
        start = path_pose(layout, path, 0.0)
        np.testing.assert_allclose(start, [x, layout.junction + layout.approach_length, -np.pi / 2])
        np.testing.assert_allclose(path_pose(layout, path, layout.stop_s), [x, layout.junction, -np.pi / 2])


@pytest.mark.parametrize(("turn", "delta"), [("left", -np.pi / 2), ("straight", 0.0), ("right", np.pi / 2)])
def test_turns_change_heading_with_the_frame_convention(layout, turn, delta):
    """A left turn decreases the heading, a right turn increases it."""
    for arm in range(4):
        path, *_ = layout.paths_from(arm, turn=turn)
        s = np.linspace(0.0, layout.paths.lengths[path], 200)
        headings = np.unwrap(layout.paths.pose_at(np.full(200, path), s)[:, 2])
        assert headings[-1] - headings[0] == pytest.approx(delta, abs=1e-6)
        assert np.all(np.diff(headings) * np.sign(delta) >= -1e-9)  # monotonic
        start = path_pose(layout, path, 0.0)
        # Every arm is the previous one rotated by +90 degrees (south -> west -> north -> east).
        angle = arm * np.pi / 2
        south = path_pose(layout, layout.paths_from(0, turn=turn)[0], 0.0)
        rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        np.testing.assert_allclose(start[:2], rot @ south[:2], atol=1e-9)


def test_path_lengths_and_junction_ends(layout):
    j, a, x0, x1 = layout.junction, layout.approach_length, 2.0, 6.0
    for path, move in enumerate(layout.movements):
        if move.turn == "straight":
            connector = 2 * j
        elif move.turn == "left":
            connector = (j + x0) * np.pi / 2
        else:
            connector = (j - x1) * np.pi / 2
        assert layout.junction_end_s[path] == pytest.approx(a + connector)
        assert layout.paths.lengths[path] == pytest.approx(2 * a + connector)


def test_drivable_area(layout):
    points = {
        (0.0, 0.0): True,  # centre
        (7.9, 80.0): True,  # south arm, outer edge
        (8.1, 80.0): False,
        (-80.0, -7.9): True,  # west arm
        (30.0, 30.0): False,  # between the arms
        (12.0, 12.0): False,  # inside the corner kerb circle
        (9.0, 9.0): True,  # rounded corner, still in the junction box
        (9.5, 9.5): False,  # just inside the kerb circle (radius 5 around (13, 13))
        (0.0, 84.0): False,  # past the end of the arm
    }
    xy = np.array(list(points))
    np.testing.assert_array_equal(layout.is_drivable(xy[:, 0], xy[:, 1]), list(points.values()))


def test_exit_reached_only_on_outbound_lanes(layout):
    d = layout.junction + layout.exit_distance + 1.0
    assert layout.exit_reached(np.array([-2.0, d])) == 0  # south, outbound (west half)
    assert layout.exit_reached(np.array([2.0, d])) is None  # south, inbound
    assert layout.exit_reached(np.array([-d, -2.0])) == 1  # west, outbound (north half)
    assert layout.exit_reached(np.array([-d, 2.0])) is None
    assert layout.exit_reached(np.array([6.0, -d])) == 2  # north, outbound (east half)
    assert layout.exit_reached(np.array([d, 6.0])) == 3  # east, outbound (south half)
    assert layout.exit_reached(np.array([d - 2.0, 6.0])) is None  # not far enough yet
    assert layout.exit_reached(np.array([0.0, 0.0])) is None


@pytest.mark.parametrize(
    ("task", "goal"),
    [
        ("left", (-33.0, -4.0, -np.pi)),
        ("straight", (4.0, -33.0, -np.pi / 2)),
        ("right", (33.0, 4.0, 0.0)),
    ],
)
def test_task_goal(layout, task, goal):
    np.testing.assert_allclose(layout.task_goal(task), goal, atol=1e-9)
    # The goal lies between the two exit lanes of the task's path and counts as reached.
    assert layout.exit_reached(layout.task_goal(task)[:2]) == TURN_OFFSET[task]
    path, *_ = layout.paths_from(0, turn=task)
    _, d = layout.paths.project(np.array(path), layout.task_goal(task)[:2])
    assert abs(d) == pytest.approx(2.0)


def test_conflicts(layout):
    np.testing.assert_array_equal(layout.conflict, layout.conflict.T)
    same_entry = layout.path_entry[:, None] == layout.path_entry[None, :]
    assert not layout.conflict[same_entry].any()
    assert layout.conflict[1, 5]  # north-bound straight crosses east-bound straight
    assert layout.conflict[0, 9]  # left turn from the south crosses straight traffic from the north
    assert not layout.conflict[1, 9]  # opposite straight lanes are 4 m apart
    assert not layout.conflict[3, 9]  # a right turn stays clear of the opposite straight lane
    inside = layout.conflict
    assert np.all(layout.zone_start[inside] >= layout.stop_s)
    end = np.broadcast_to(layout.junction_end_s[:, None], inside.shape)[inside]
    assert np.all(layout.zone_end[inside] <= end + layout.paths.resolution)
    assert np.all(layout.zone_start[inside] <= layout.zone_end[inside])


def test_speed_profile_slows_for_turns(layout):
    profile, res = layout.speed_profile, layout.paths.resolution
    mid_turn = int((layout.stop_s + 5.0) / res)
    assert profile[1, mid_turn] == pytest.approx(12.0)  # straight: top speed
    assert profile[3, mid_turn] == pytest.approx(np.sqrt(2.5 * 7.0))  # right turn, radius 7
    assert profile[0, mid_turn] == pytest.approx(np.sqrt(2.5 * 15.0))  # left turn, radius 15
    # Braking into the turn never needs more than the comfortable deceleration.
    decel = (profile[:, :-1] ** 2 - profile[:, 1:] ** 2) / (2 * res)
    assert decel.max() <= 2.0 + 1e-9


@given(st.floats(-90, 90), st.floats(-90, 90))
def test_drivable_symmetry(layout, x, y):
    """The junction is symmetric under the four rotations and the mirror."""
    base = layout.is_drivable(np.array(x), np.array(y))
    for px, py in ((-y, x), (-x, -y), (y, -x), (-x, y)):
        assert layout.is_drivable(np.array(px), np.array(py)) == base


def test_road_network_for_drawing(layout):
    net = layout.road_network()
    lanes = net.lanes_list()
    # 8 inbound + 8 outbound straight lanes and 16 connectors.
    assert len(lanes) == 32
    lane = net.get_lane(("ir0", "il2", 0))
    np.testing.assert_allclose(lane.position(0.0, 0.0), [2.0, layout.junction], atol=1e-9)
