"""The GCCP collision checker: SAT against python-fcl, and the mask's meaning."""

from __future__ import annotations

import fcl
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from gccp_envs.geometry import poses_overlap
from sb3_gccp.gccp.collision import COLLISION_LOGIT, CollisionChecker

coordinate = st.floats(-8.0, 8.0)
angle = st.floats(-np.pi, np.pi)
length = st.floats(1.0, 6.0)


def fcl_overlap(a, size_a, b, size_b) -> bool:
    objects = []
    for pose, (long, wide) in ((a, size_a), (b, size_b)):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        objects.append(
            fcl.CollisionObject(fcl.Box(long, wide, 1.0), fcl.Transform(rotation, [pose[0], pose[1], 0.0]))
        )
    return fcl.collide(*objects, fcl.CollisionRequest(), fcl.CollisionResult()) > 0


@given(coordinate, coordinate, angle, angle, length, length, length, length)
def test_poses_overlap_agrees_with_fcl(x, y, ha, hb, la, wa, lb, wb):
    a, b = np.array([0.0, 0.0, ha]), np.array([x, y, hb])
    ours = bool(poses_overlap(a, (la, wa / 2), b, (lb, wb / 2)))
    # Pairs within a millimetre of contact are ambiguous between implementations: skip them.
    grown = bool(poses_overlap(a, (la + 2e-3, wa / 2 + 2e-3), b, (lb, wb / 2)))
    shrunk = bool(poses_overlap(a, (la - 2e-3, wa / 2 - 2e-3), b, (lb, wb / 2)))
    if grown == shrunk:
        assert ours == fcl_overlap(a, (la, wa / 2), b, (lb, wb / 2))


@given(coordinate, coordinate, angle, angle, length, length)
def test_poses_overlap_of_same_size_boxes_agrees_with_fcl(x, y, ha, hb, la, wa):
    # Same (length, width) numbers take the shortcut that reuses a's half-extent sums for b's axes.
    a, b, size = np.array([0.0, 0.0, ha]), np.array([x, y, hb]), (la, wa / 2)
    ours = bool(poses_overlap(a, size, b, size))
    grown = bool(poses_overlap(a, (la + 2e-3, wa / 2 + 2e-3), b, size))
    shrunk = bool(poses_overlap(a, (la - 2e-3, wa / 2 - 2e-3), b, size))
    if grown == shrunk:
        assert ours == fcl_overlap(a, size, b, size)


def test_checker_with_explicit_sizes_matches_its_default_sizes():
    # Per-neighbour size arrays take the general path, the default sizes the same-size shortcut.
    rng = np.random.default_rng(0)
    checker = CollisionChecker(margin=0.5)
    ego, neighbours = rng.uniform(-20, 20, (12, 10, 3)), rng.uniform(-20, 20, (12, 5, 10, 3))
    present = np.array([True, True, False, True, True])
    sizes = np.tile(CollisionChecker().neighbour_size, (5, 1))
    default = checker.collides(ego, neighbours, present)
    assert 0 < default.sum() < 12
    np.testing.assert_array_equal(checker.collides(ego, neighbours, present, neighbour_sizes=sizes), default)


def straight(x0: float, y0: float, heading: float, speed: float, steps: int = 10) -> np.ndarray:
    t = np.arange(1, steps + 1) * 0.1
    return np.column_stack(
        [x0 + speed * t * np.cos(heading), y0 + speed * t * np.sin(heading), np.full(steps, heading)]
    )


def test_head_on_candidate_is_masked_and_a_clear_road_is_not():
    checker = CollisionChecker()
    # Candidate 0 drives north into an oncoming car; candidate 1 stays put; neighbour 1 is far away.
    ego = np.stack([straight(0.0, 0.0, -np.pi / 2, 8.0), straight(0.0, 0.0, -np.pi / 2, 0.0)])
    oncoming = straight(0.0, -14.0, np.pi / 2, 8.0)
    far = straight(40.0, 40.0, 0.0, 8.0)
    neighbours = np.stack([np.stack([oncoming, far])] * 2)
    assert checker.collides(ego, neighbours, np.array([True, True])).tolist() == [True, False]
    np.testing.assert_array_equal(
        checker.logit_mask(ego, neighbours, np.array([True, True])), [COLLISION_LOGIT, 0.0]
    )
    assert checker.action_mask(ego, neighbours, np.array([True, True])).tolist() == [False, True]
    # An absent neighbour never collides, whatever its (padded) poses.
    assert not checker.collides(ego, neighbours, np.array([False, True])).any()
    # Per-step presence: the oncoming car only exists for the first two steps, before the contact.
    present = np.zeros((2, 2, 10), bool)
    present[:, 0, :2] = True
    assert not checker.collides(ego, neighbours, present).any()


def test_first_collision_is_the_step_the_boxes_first_overlap():
    checker = CollisionChecker()
    # Candidate 0 drives north into a car coming south at 8 m/s from 14 m: the centres close at 16 m/s,
    # and 5 m cars overlap once they are less than 5 m apart, at step 6 (index 5). Candidate 1 stands,
    # and the car is still 6 m from it at the last step. Boxes 2 m longer overlap below 7 m: steps 5 and 9.
    ego = np.stack([straight(0.0, 0.0, -np.pi / 2, 8.0), straight(0.0, 0.0, -np.pi / 2, 0.0)])
    neighbours = np.stack([straight(0.0, -14.0, np.pi / 2, 8.0)[None]] * 2)
    present = np.array([True])
    assert checker.first_collision(ego, neighbours, present).tolist() == [5, 10]
    np.testing.assert_array_equal(checker.collides(ego, neighbours, present), [True, False])
    assert checker.with_margin(2.0).first_collision(ego, neighbours, present).tolist() == [4, 8]
    assert checker.first_collision(ego, neighbours, np.array([False])).tolist() == [10, 10]


def test_margin_and_sizes_widen_the_boxes():
    ego = straight(0.0, 0.0, 0.0, 0.0, steps=1)[None]
    beside = straight(0.0, 2.2, 0.0, 0.0, steps=1)[None, None]  # 0.2 m gap between 2 m wide cars
    assert not CollisionChecker().collides(ego, beside, np.array([True]))[0]
    assert CollisionChecker(margin=0.5).collides(ego, beside, np.array([True]))[0]
    assert CollisionChecker().collides(ego, beside, np.array([True]), np.array([[5.0, 2.6]]))[0]
