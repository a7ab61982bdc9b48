"""Frames, oriented boxes (checked against python-fcl) and lane-path projection."""

from __future__ import annotations

import fcl
import numpy as np
import pytest
from helpers import ego_frame
from hypothesis import assume, given
from hypothesis import strategies as st

from gccp_envs.action import EgoMotion, EgoState
from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.geometry import (
    PathSet,
    Segment,
    box_corners,
    boxes_overlap,
    dubins_length,
    from_frame,
    poses_to_frame,
    to_frame,
    wrap_angle,
)

angles = st.floats(-10.0, 10.0, allow_nan=False)
coords = st.floats(-100.0, 100.0, allow_nan=False)


# --- angles and frames ---------------------------------------------------------------------------
@given(angles)
def test_wrap_angle_range_and_equivalence(angle):
    wrapped = float(wrap_angle(angle))
    assert -np.pi <= wrapped < np.pi
    assert np.cos(wrapped) == pytest.approx(np.cos(angle), abs=1e-9)
    assert np.sin(wrapped) == pytest.approx(np.sin(angle), abs=1e-9)


def test_wrap_angle_examples():
    np.testing.assert_allclose(
        wrap_angle(np.array([0.0, np.pi / 2, 3 * np.pi / 2, -3 * np.pi / 2])),
        [0.0, np.pi / 2, -np.pi / 2, np.pi / 2],
        atol=1e-12,
    )
    assert float(wrap_angle(np.pi)) == pytest.approx(-np.pi)


@given(coords, coords, angles, st.floats(-50, 50), st.floats(-50, 50))
def test_to_frame_forward_and_right(ox, oy, heading, forward, right):
    """A point ``forward`` ahead and ``right`` to the right on screen reads (forward, right) in the frame."""
    # Right on screen of heading h (y down) is the heading rotated by +90 degrees: (-sin h, cos h).
    point = np.array(
        [
            ox + forward * np.cos(heading) - right * np.sin(heading),
            oy + forward * np.sin(heading) + right * np.cos(heading),
        ]
    )
    np.testing.assert_allclose(to_frame(point, np.array([ox, oy]), heading), [forward, right], atol=1e-7)


def test_to_frame_screen_directions():
    # Facing north (up on screen, heading -pi/2): east is on the right, so y > 0 in the ego frame.
    assert to_frame(np.array([1.0, 0.0]), np.zeros(2), -np.pi / 2)[1] == pytest.approx(1.0)
    # Facing east: south (y down) is on the right.
    np.testing.assert_allclose(to_frame(np.array([[3.0, 2.0]]), np.zeros(2), 0.0), [[3.0, 2.0]])


@given(coords, coords, angles, coords, coords)
def test_from_frame_inverts_to_frame(ox, oy, heading, x, y):
    origin, point = np.array([ox, oy]), np.array([x, y])
    np.testing.assert_allclose(
        from_frame(to_frame(point, origin, heading), origin, heading), point, atol=1e-7
    )


@given(coords, coords, angles, coords, coords, angles, st.floats(0.0, 20.0))
def test_poses_to_frame(ox, oy, h0, x, y, h, speed):
    out = poses_to_frame(np.array([x, y, h, speed]), np.array([ox, oy]), h0)
    np.testing.assert_allclose(out[:2], ego_frame(np.array([x, y]), ox, oy, h0), atol=1e-7)
    assert -np.pi <= out[2] < np.pi
    assert np.cos(out[2]) == pytest.approx(np.cos(h - h0), abs=1e-9)
    assert np.sin(out[2]) == pytest.approx(np.sin(h - h0), abs=1e-9)
    assert out[3] == speed  # extra columns untouched


# --- boxes -----------------------------------------------------------------------------------------
@given(coords, coords, angles, st.floats(0.5, 8.0), st.floats(0.5, 4.0))
def test_box_corners_geometry(x, y, heading, length, width):
    c = box_corners(np.array(x), np.array(y), np.array(heading), np.array(length), np.array(width))
    assert c.shape == (4, 2)
    np.testing.assert_allclose(c.mean(0), [x, y], atol=1e-9)
    edges = np.roll(c, -1, axis=0) - c
    np.testing.assert_allclose(np.hypot(*edges.T), [length, width, length, width], rtol=1e-9)
    # Counter-clockwise on the math plane: positive shoelace area.
    area = 0.5 * np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1])
    assert area == pytest.approx(length * width, rel=1e-9)
    # Corner 0 is a front corner: half a length ahead along the heading.
    assert np.dot(c[0] - [x, y], [np.cos(heading), np.sin(heading)]) == pytest.approx(length / 2)


def _fcl_box(x, y, heading, length, width):
    c, s = np.cos(heading), np.sin(heading)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return fcl.CollisionObject(fcl.Box(length, width, 1.0), fcl.Transform(rotation, np.array([x, y, 0.0])))


def _fcl_collide(a, b, grow=0.0):
    box_a = _fcl_box(a[0], a[1], a[2], a[3] + 2 * grow, a[4] + 2 * grow)
    box_b = _fcl_box(b[0], b[1], b[2], b[3] + 2 * grow, b[4] + 2 * grow)
    return fcl.collide(box_a, box_b, fcl.CollisionRequest(), fcl.CollisionResult()) > 0


box_params = st.tuples(
    st.floats(-6, 6), st.floats(-6, 6), st.floats(-np.pi, np.pi), st.floats(0.5, 6.0), st.floats(0.5, 3.0)
)


@given(box_params, box_params)
def test_boxes_overlap_matches_fcl(a, b):
    tolerance = 1e-3
    # Skip near-touching pairs, whose answer depends on how touching is counted.
    assume(_fcl_collide(a, b, -tolerance) == _fcl_collide(a, b, tolerance))
    expected = _fcl_collide(a, b)
    corners_a = box_corners(*(np.array(v) for v in a))
    corners_b = box_corners(*(np.array(v) for v in b))
    assert bool(boxes_overlap(corners_a, corners_b)) == expected
    assert bool(boxes_overlap(corners_b, corners_a)) == expected


def test_boxes_overlap_examples():
    def box(x, y, h=0.0, length=4.0, width=2.0):
        return box_corners(np.array(x), np.array(y), np.array(h), np.array(length), np.array(width))

    assert boxes_overlap(box(0, 0), box(3.9, 0))
    assert not boxes_overlap(box(0, 0), box(4.0, 0))  # touching end to end
    assert not boxes_overlap(box(0, 0), box(0, 2.0))  # touching side by side
    assert not boxes_overlap(box(0, 0), box(4.1, 0))
    # Separated only along an axis of the rotated box: a diamond next to a square's corner.
    assert not boxes_overlap(box(0, 0, 0, 2, 2), box(2.3, 2.3, np.pi / 4, 2, 2))
    assert boxes_overlap(box(0, 0, 0, 2, 2), box(1.6, 1.6, np.pi / 4, 2, 2))


def test_boxes_overlap_broadcasts():
    xs = np.array([0.0, 3.0, 10.0])
    a = box_corners(xs, np.zeros(3), np.zeros(3), np.full(3, 4.0), np.full(3, 2.0))
    result = boxes_overlap(a[:, None], a[None, :])
    assert result.shape == (3, 3)
    np.testing.assert_array_equal(result, [[True, True, False], [True, True, False], [False, False, True]])


# --- segments and path sets ------------------------------------------------------------------------
def test_segment_line_and_arc_poses():
    line = Segment.line(np.array([0.0, 10.0]), np.array([0.0, 0.0]))
    assert line.length == pytest.approx(10.0)
    x, y, h = line.pose(np.array([0.0, 4.0]))
    np.testing.assert_allclose(np.stack([x, y], -1), [[0, 10], [0, 6]])
    np.testing.assert_allclose(h, -np.pi / 2)
    # Quarter arc of radius 5 around the origin, phase 0 -> -pi/2: from (5, 0) to (0, -5), turning left.
    arc = Segment.arc(np.zeros(2), 5.0, 0.0, -np.pi / 2)
    assert arc.length == pytest.approx(5.0 * np.pi / 2)
    assert arc.sense == -1.0
    x, y, h = arc.pose(np.array([0.0, arc.length]))
    np.testing.assert_allclose(np.stack([x, y], -1), [[5, 0], [0, -5]], atol=1e-12)
    np.testing.assert_allclose(h, [-np.pi / 2, -np.pi])


@pytest.mark.parametrize("phase1", [np.pi / 2, -np.pi / 2])
def test_arc_heading_is_direction_of_motion(phase1):
    arc = Segment.arc(np.array([1.0, -2.0]), 7.0, 0.3, 0.3 + phase1)
    s = np.linspace(0.0, arc.length - 1e-3, 20)
    x0, y0, h = arc.pose(s)
    x1, y1, _ = arc.pose(s + 1e-4)
    np.testing.assert_allclose(np.arctan2(y1 - y0, x1 - x0), wrap_angle(h), atol=1e-4)


@pytest.fixture(scope="module")
def l_path() -> PathSet:
    """One path: 10 m north, a left quarter turn of radius 6, 10 m west; and a straight path east."""
    approach = Segment.line(np.array([0.0, 10.0]), np.array([0.0, 0.0]))
    turn = Segment.arc(np.array([-6.0, 0.0]), 6.0, 0.0, -np.pi / 2)
    leave = Segment.line(np.array([-6.0, -6.0]), np.array([-16.0, -6.0]))
    east = Segment.line(np.array([0.0, 0.0]), np.array([5.0, 0.0]))
    return PathSet([[approach, turn, leave], [east]])


def test_pathset_pose_at_and_clamping(l_path):
    assert l_path.lengths[0] == pytest.approx(20.0 + 3.0 * np.pi)
    np.testing.assert_allclose(l_path.pose_at(np.array(0), np.array(5.0)), [0.0, 5.0, -np.pi / 2], atol=1e-9)
    np.testing.assert_allclose(
        l_path.pose_at(np.array(0), np.array(12.0)),
        [-6.0 + 6.0 * np.cos(-2.0 / 6.0), 6.0 * np.sin(-2.0 / 6.0), -np.pi / 2 - 2.0 / 6.0],
        atol=1e-3,
    )
    end = l_path.pose_at(np.array(0), np.array(l_path.lengths[0]))
    np.testing.assert_allclose(l_path.pose_at(np.array(0), np.array(1e3)), end)
    np.testing.assert_allclose(l_path.pose_at(np.array(0), np.array(-5.0)), [0.0, 10.0, -np.pi / 2])
    # The shorter path is clamped at its own end, not the longest path's.
    np.testing.assert_allclose(l_path.pose_at(np.array(1), np.array(20.0)), [5.0, 0.0, 0.0], atol=1e-9)
    assert l_path.curvature[0, 150] == pytest.approx(1.0 / 6.0)
    assert l_path.curvature[0, 50] == 0.0


def test_pose_at_is_exact_at_the_path_end(l_path, layout):
    end = l_path.pose_at(np.array(0), np.array(l_path.lengths[0]))
    np.testing.assert_allclose(end, [-16.0, -6.0, -np.pi], atol=1e-6)
    # Every junction path ends on a straight exit lane: the pose at the end is on that line's end.
    for path in range(len(layout.paths)):
        move = layout.movements[path]
        exit_segment = layout._local_path(move)[2]
        local_end = np.array(exit_segment.start) + exit_segment.length * np.array(exit_segment.direction)
        angle = move.arm * np.pi / 2
        rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        pose = layout.paths.pose_at(np.array(path), np.array(layout.paths.lengths[path]))
        np.testing.assert_allclose(pose[:2], rot @ local_end, atol=1e-6)


def test_project_sign_is_right_on_screen(l_path):
    # Heading north on the approach, east (x > 0) is on the right.
    s, d = l_path.project(np.array([0, 0]), np.array([[1.0, 4.0], [-1.0, 4.0]]))
    np.testing.assert_allclose(s, [6.0, 6.0])
    np.testing.assert_allclose(d, [1.0, -1.0])
    # Heading west after the turn, north (y smaller) is on the right.
    s, d = l_path.project(np.array(0), np.array([-12.0, -7.5]))
    assert s == pytest.approx(10.0 + 3.0 * np.pi + 6.0)
    assert d == pytest.approx(1.5)


@given(st.integers(0, 1), st.floats(0.0, 1.0), st.floats(-1.5, 1.5))
def test_project_recovers_arc_length_and_offset(l_path, path, fraction, offset):
    # Within the sampled part of the path (the last 0.1 m is covered by the test above).
    s = fraction * (l_path.lengths[path] - l_path.resolution)
    x, y, h = l_path.pose_at(np.array(path), np.array(s))
    s_on, d_on = l_path.project(np.array(path), np.array([x, y]))
    assert s_on == pytest.approx(s, abs=1e-3)
    assert d_on == pytest.approx(0.0, abs=1e-3)
    assume(0.5 < s < l_path.lengths[path] - 0.5)
    point = np.array([x - offset * np.sin(h), y + offset * np.cos(h)])
    s_off, d_off = l_path.project(np.array(path), point)
    assert s_off == pytest.approx(s, abs=2e-3)
    assert d_off == pytest.approx(offset, abs=2e-3)


@given(st.data())
def test_layout_paths_project_round_trip(layout, data):
    """Every lane path of the junction: points sampled on it project back to their arc length."""
    paths = layout.paths
    path = data.draw(st.integers(0, len(paths) - 1))
    s = data.draw(st.floats(0.0, float(paths.lengths[path] - paths.resolution)))
    pose = paths.pose_at(np.array(path), np.array(s))
    s_on, d_on = paths.project(np.array(path), pose[:2])
    assert s_on == pytest.approx(s, abs=2e-3)
    assert d_on == pytest.approx(0.0, abs=2e-3)
    offset = data.draw(st.floats(-1.5, 1.5))
    assume(0.5 < s < paths.lengths[path] - 0.5)
    point = pose[:2] + offset * np.array([-np.sin(pose[2]), np.cos(pose[2])])
    s_off, d_off = paths.project(np.array(path), point)
    assert s_off == pytest.approx(s, abs=2e-3)
    assert d_off == pytest.approx(offset, abs=2e-3)
    # The tabulated lookup agrees to about a cell (0.5 m).
    s_tab, d_tab = paths.lookup(np.array(path), point)
    assert s_tab == pytest.approx(s_off, abs=0.75)
    assert d_tab == pytest.approx(d_off, abs=0.4)


def test_lookup_is_inf_off_the_band(layout):
    _, d = layout.paths.lookup(np.array([1, 1]), np.array([[2.0, 40.0], [40.0, 40.0]]))
    assert np.isfinite(d[0])
    assert np.isinf(d[1])  # 38 m from the lane
    _, d = layout.paths.lookup(np.array(1), np.array([500.0, 0.0]))
    assert np.isinf(d)  # outside the table


def test_dubins_length_examples():
    radius = 6.0
    ends = np.array([[10.0, 0.0, 0.0], [6.0, 6.0, np.pi / 2], [6.0, -6.0, -np.pi / 2], [0.0, 12.0, np.pi]])
    lengths = dubins_length(np.zeros(3), ends, radius)
    np.testing.assert_allclose(lengths, [10.0, np.pi * 3.0, np.pi * 3.0, np.pi * 6.0], atol=1e-6)


@given(
    st.floats(-np.pi, np.pi),
    st.floats(0.0, 8.0),
    st.lists(st.tuples(st.integers(0, 5), st.integers(1, 15)), min_size=1, max_size=6),
)
def test_dubins_length_never_exceeds_a_driven_path(heading, speed, segments):
    """Every path the ego's six actions drive is a forward path with turn radius >= 6 m, so Dubins'
    shortest is no longer than it (and no shorter than the straight line)."""
    config = IntersectionConfig()
    motion = EgoMotion(config)
    state = EgoState(0.0, 0.0, heading, speed)
    driven = 0.0
    for action, steps in segments:
        for _ in range(steps):
            before = state.speed
            state = motion.step(state, action)
            driven += 0.5 * (before + state.speed) * DT
    start, end = np.array([0.0, 0.0, heading]), np.array([[state.x, state.y, state.heading]])
    shortest = dubins_length(start, end, 1.0 / config.quick_turn_curvature)[0]
    assert np.hypot(state.x, state.y) - 1e-6 <= shortest <= driven + 1e-6


@pytest.mark.parametrize("action", [4, 5])
@pytest.mark.parametrize("heading", [-2.9, -1.65, 0.0, 0.42, 2.87])
@pytest.mark.parametrize("steps", [1, 2, 7, 20])
def test_dubins_length_of_a_quickest_turn_arc_is_the_arc(action, heading, steps):
    """An arc of the quickest turn shorter than half a circle is its own shortest path: the degenerate
    words (straight part and last turn of length zero) must not come out a full circle longer."""
    config = IntersectionConfig()
    motion = EgoMotion(config)
    state = EgoState(0.0, 0.0, heading, 5.0)
    for _ in range(steps):
        state = motion.step(state, action)
    shortest = dubins_length(
        np.array([0.0, 0.0, heading]), np.array([[state.x, state.y, state.heading]]), 6.0
    )
    assert shortest[0] == pytest.approx(5.0 * DT * steps, abs=1e-6)
