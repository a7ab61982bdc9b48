"""The six ego actions: speed changes, turn directions and the exact pose change of one 0.1 s step."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gccp_envs.action import EgoAction, EgoMotion, EgoState
from gccp_envs.config import IntersectionConfig
from gccp_envs.geometry import box_corners
from gccp_envs.traffic import VEHICLE_LENGTH, VEHICLE_WIDTH

CFG = IntersectionConfig()
MOTION = EgoMotion(CFG)
TURNS = (
    EgoAction.SLOWLY_TURN_LEFT,
    EgoAction.SLOWLY_TURN_RIGHT,
    EgoAction.QUICKLY_TURN_LEFT,
    EgoAction.QUICKLY_TURN_RIGHT,
)


def test_six_actions_in_the_papers_order():
    assert [a.name for a in EgoAction] == [
        "SLOW_DOWN",
        "KEEP_DIRECTION",
        "SLOWLY_TURN_LEFT",
        "SLOWLY_TURN_RIGHT",
        "QUICKLY_TURN_LEFT",
        "QUICKLY_TURN_RIGHT",
    ]
    assert len(MOTION.curvature) == 6


def test_slow_down_reduces_speed_by_deceleration_times_dt():
    (dx, dy, dh), speed = MOTION.pose_change(8.0, EgoAction.SLOW_DOWN)
    assert speed == pytest.approx(8.0 - CFG.deceleration * 0.1)
    assert dx == pytest.approx(0.5 * (8.0 + speed) * 0.1)
    assert dy == 0.0 and dh == 0.0
    assert MOTION.pose_change(0.1, EgoAction.SLOW_DOWN)[1] == 0.0  # never negative


def test_keep_direction_accelerates_to_cruise_speed():
    assert MOTION.next_speed(5.0, EgoAction.KEEP_DIRECTION) == pytest.approx(5.0 + CFG.acceleration * 0.1)
    assert MOTION.next_speed(7.9, EgoAction.KEEP_DIRECTION) == CFG.cruise_speed  # capped
    assert MOTION.next_speed(CFG.cruise_speed, EgoAction.KEEP_DIRECTION) == CFG.cruise_speed
    # Above cruise speed it brakes back towards it, at most at the deceleration.
    assert MOTION.next_speed(10.0, EgoAction.KEEP_DIRECTION) == pytest.approx(10.0 - CFG.deceleration * 0.1)
    assert MOTION.next_speed(8.1, EgoAction.KEEP_DIRECTION) == CFG.cruise_speed


@pytest.mark.parametrize("action", TURNS)
def test_turns_hold_speed(action):
    assert MOTION.next_speed(6.5, action) == 6.5


@pytest.mark.parametrize(
    ("slow", "quick", "sign"),
    [
        (EgoAction.SLOWLY_TURN_LEFT, EgoAction.QUICKLY_TURN_LEFT, -1.0),
        (EgoAction.SLOWLY_TURN_RIGHT, EgoAction.QUICKLY_TURN_RIGHT, 1.0),
    ],
)
def test_turn_directions_and_rates(slow, quick, sign):
    """Left turns: dheading < 0 and dy < 0 in the ego frame (to the left on screen); right: both > 0."""
    (dx_s, dy_s, dh_s), _ = MOTION.pose_change(6.0, slow)
    (dx_q, dy_q, dh_q), _ = MOTION.pose_change(6.0, quick)
    assert np.sign(dh_s) == np.sign(dy_s) == np.sign(dh_q) == np.sign(dy_q) == sign
    assert dx_s > 0 and dx_q > 0
    assert abs(dh_q) > abs(dh_s)
    assert abs(dy_q) > abs(dy_s)
    distance = 0.6
    assert abs(dh_s) == pytest.approx(CFG.slow_turn_curvature * distance)
    assert abs(dh_q) == pytest.approx(CFG.quick_turn_curvature * distance)


def test_left_turn_decreases_world_heading():
    state = EgoState(0.0, 0.0, 0.0, 8.0)  # facing east
    after = MOTION.step(state, EgoAction.QUICKLY_TURN_LEFT)
    assert after.heading < 0.0
    assert after.y < 0.0  # towards the top of the screen: the left of an east-bound car
    after = MOTION.step(state, EgoAction.QUICKLY_TURN_RIGHT)
    assert after.heading > 0.0 and after.y > 0.0


@given(st.floats(0.0, 12.0), st.sampled_from(list(EgoAction)))
def test_pose_change_stays_on_the_arc(speed, action):
    """The chord points half-way through the turn and has at most the arc length."""
    (dx, dy, dh), new_speed = MOTION.pose_change(speed, action)
    arc = 0.5 * (speed + new_speed) * 0.1
    assert dh == pytest.approx(MOTION.curvature[action] * arc)
    chord = np.hypot(dx, dy)
    assert chord <= arc + 1e-12
    if chord > 0:
        assert np.arctan2(dy, dx) == pytest.approx(dh / 2.0)


@pytest.mark.parametrize("action", TURNS)
def test_pose_change_is_the_exact_arc_chord(action):
    (dx, dy, dh), speed = MOTION.pose_change(8.0, action)
    curvature = MOTION.curvature[action]
    arc = 0.5 * (8.0 + speed) * 0.1
    assert dh == pytest.approx(curvature * arc, abs=1e-12)
    # A circle of radius 1/curvature, tangent to the ego's x axis at the origin.
    assert dx == pytest.approx(np.sin(dh) / curvature, abs=1e-9)
    assert dy == pytest.approx((1.0 - np.cos(dh)) / curvature, abs=1e-9)


def test_step_rotates_the_pose_change_into_the_world():
    state = EgoState(10.0, 20.0, -np.pi / 2, 8.0)  # facing north (up on screen)
    (dx, dy, dh), speed = MOTION.pose_change(8.0, EgoAction.SLOWLY_TURN_RIGHT)
    after = MOTION.step(state, EgoAction.SLOWLY_TURN_RIGHT)
    # Forward is -y, the right on screen is +x.
    assert after.x == pytest.approx(10.0 + dy)
    assert after.y == pytest.approx(20.0 - dx)
    assert after.heading == pytest.approx(-np.pi / 2 + dh)
    assert after.speed == speed
    # Headings stay wrapped.
    assert (
        -np.pi <= MOTION.step(EgoState(0, 0, np.pi - 1e-3, 8.0), EgoAction.QUICKLY_TURN_RIGHT).heading < np.pi
    )


def test_stop_and_go():
    state = EgoState(0.0, 50.0, -np.pi / 2, CFG.cruise_speed)
    for _ in range(int(CFG.cruise_speed / (CFG.deceleration * 0.1)) + 1):
        state = MOTION.step(state, EgoAction.SLOW_DOWN)
    assert state.speed == 0.0
    stopped = state.as_array()
    for action in (EgoAction.SLOW_DOWN, EgoAction.QUICKLY_TURN_LEFT, EgoAction.SLOWLY_TURN_RIGHT):
        state = MOTION.step(state, action)  # no creeping, no turning on the spot
        np.testing.assert_array_equal(state.as_array(), stopped)
    speeds = []
    for _ in range(int(CFG.cruise_speed / (CFG.acceleration * 0.1)) + 2):
        state = MOTION.step(state, EgoAction.KEEP_DIRECTION)
        speeds.append(state.speed)
    assert np.all(np.diff(speeds) >= 0)
    assert state.speed == CFG.cruise_speed
    assert state.y < stopped[1] and state.x == pytest.approx(stopped[0])


@pytest.mark.parametrize("action", [-1, 6, 100])
def test_invalid_action(action):
    with pytest.raises(ValueError, match="invalid ego action"):
        MOTION.pose_change(5.0, action)


REAR = EgoMotion(IntersectionConfig(rear_axle_offset=1.5))


@given(st.floats(0.1, 12.0), st.sampled_from(list(EgoAction)), st.floats(-np.pi, np.pi))
def test_with_a_rear_axle_offset_the_point_behind_the_centre_drives_the_arc(speed, action, heading):
    """The point 1.5 m behind the centre moves as the centre does without the offset: a chord pointing
    half-way through the turn; the box keeps its heading change."""
    state = EgoState(3.0, -4.0, heading, speed)
    after, without = REAR.step(state, action), MOTION.step(state, action)

    def rear(s: EgoState) -> np.ndarray:
        return np.array([s.x, s.y]) - 1.5 * np.array([np.cos(s.heading), np.sin(s.heading)])

    np.testing.assert_allclose(
        rear(after) - rear(state), [without.x - state.x, without.y - state.y], atol=1e-9
    )
    assert after.heading == pytest.approx(without.heading) and after.speed == without.speed


def test_with_a_rear_axle_offset_the_rear_corners_swing_out_less():
    """Turning right, the rear left corner moves left (outwards) by less than when the box turns about
    its centre; the front moves further into the turn."""
    rear_left, front_right = 2, 0  # box_corners' order: (rear, left) and (front, right) in the ego frame

    def corner(s: EgoState, which: int) -> np.ndarray:
        return box_corners(s.x, s.y, s.heading, VEHICLE_LENGTH, VEHICLE_WIDTH)[which]

    turned_centre = turned_rear = EgoState(0.0, 0.0, 0.0, 6.0)
    for _ in range(5):
        turned_centre = MOTION.step(turned_centre, EgoAction.QUICKLY_TURN_RIGHT)
        turned_rear = REAR.step(turned_rear, EgoAction.QUICKLY_TURN_RIGHT)
    assert corner(turned_rear, rear_left)[1] > corner(turned_centre, rear_left)[1]  # less far left
    assert corner(turned_rear, front_right)[1] > corner(turned_centre, front_right)[1]


def test_step_many_follows_step_with_a_rear_axle_offset():
    poses, speeds = np.array([[1.0, 2.0, 0.3], [-4.0, 0.5, -2.0]]), np.array([7.0, 2.0])
    actions = np.array([EgoAction.QUICKLY_TURN_RIGHT, EgoAction.SLOWLY_TURN_LEFT])
    moved, new_speeds = REAR.step_many(poses, speeds, actions)
    for k in range(2):
        after = REAR.step(EgoState(*poses[k], speeds[k]), int(actions[k]))
        np.testing.assert_allclose(moved[k, :2], (after.x, after.y), atol=1e-12)
        assert new_speeds[k] == after.speed


def test_a_rear_axle_offset_outside_the_box_is_refused():
    with pytest.raises(ValueError, match="rear_axle_offset"):
        IntersectionConfig(rear_axle_offset=2.6)
    with pytest.raises(ValueError, match="rear_axle_offset"):
        IntersectionConfig(rear_axle_offset=-0.1)


@pytest.mark.parametrize("motion", [MOTION, REAR], ids=["centre", "rear axle"])
def test_two_arc_paths_are_the_poses_of_two_held_actions(motion):
    """At 5 m/s a turn action drives 0.5 m a step, the paths' spacing: a single arc is a turn held all
    along, a pair is one turn held for its first piece and another for the rest."""
    paths = motion.two_arc_paths(10.0, spacing=0.5, split=1.0)
    curvatures = list(np.unique(motion.curvature))
    start = EgoState(0.0, 0.0, 0.0, 5.0)
    quick_right = curvatures.index(motion.curvature[EgoAction.QUICKLY_TURN_RIGHT])
    held = motion.rollout(start, EgoAction.QUICKLY_TURN_RIGHT, 20)
    np.testing.assert_allclose(paths[quick_right], held, atol=1e-9)
    first = motion.rollout(start, EgoAction.SLOWLY_TURN_LEFT, 8)  # 4 m
    second = motion.rollout(EgoState(*first[-1], 5.0), EgoAction.QUICKLY_TURN_RIGHT, 12)
    expected = np.concatenate([first, second])
    assert np.abs(paths - expected).max(axis=(1, 2)).min() < 1e-9
    assert len(paths) == len(curvatures) + len(curvatures) * (len(curvatures) - 1) * 9


@pytest.mark.parametrize("motion", [MOTION, REAR], ids=["centre", "rear axle"])
def test_rollout_many_is_rollout_to_the_last_bit(motion):
    # The road-keeping mask rolls out every held action at once; the planner stage's data depend on
    # its booleans, so the poses must be those of the one-state loop, not merely close to them.
    rng = np.random.default_rng(0)
    states = np.column_stack(
        (rng.uniform(-30.0, 30.0, (120, 2)), rng.uniform(-4.0, 4.0, 120), rng.uniform(0.0, 8.0, 120))
    )
    states[:20, 3] = 0.0  # standing
    states[20:40, 3] = CFG.cruise_speed
    actions = np.arange(120) % len(motion.curvature)
    many = motion.rollout_many(states, actions, 9)
    one = np.stack(
        [motion.rollout(EgoState(*state), int(a), 9) for state, a in zip(states, actions, strict=True)]
    )
    np.testing.assert_array_equal(many, one)


def test_step_many_moves_along_the_chord_of_the_middle_heading_to_the_last_bit():
    # The search planner's rollouts, and so the planner stage's expert data, depend on the exact floats:
    # the rotated form x + cos(h) dx - sin(h) dy, equal in exact arithmetic, gave another planner.
    rng = np.random.default_rng(0)
    poses = rng.uniform(-30.0, 30.0, (200, 3))
    speeds = rng.uniform(0.0, 8.0, 200)
    actions = rng.integers(0, len(MOTION.curvature), 200)
    moved, new_speeds = MOTION.step_many(poses, speeds, actions)
    distance = 0.5 * (speeds + new_speeds) * 0.1
    turn = MOTION.curvature[actions] * distance
    chord = distance * np.sinc(turn / (2.0 * np.pi))
    middle = poses[:, 2] + turn / 2.0
    assert np.array_equal(moved[:, 0], poses[:, 0] + chord * np.cos(middle))
    assert np.array_equal(moved[:, 1], poses[:, 1] + chord * np.sin(middle))
