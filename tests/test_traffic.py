"""Other vehicles: spawning, car following, stopping for the ego, yielding at the junction, no crashes."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import path_pose

from gccp_envs.config import IntersectionConfig
from gccp_envs.geometry import box_corners, boxes_overlap
from gccp_envs.traffic import VEHICLE_LENGTH, Obstacle, Traffic

CFG = IntersectionConfig(spawn_probability=0.1)


def make_traffic(layout, seed=0):
    return Traffic(layout, CFG, np.random.default_rng(seed))


def test_spawn_places_vehicle_on_its_path(layout):
    traffic = make_traffic(layout)
    slot = traffic.spawn(5, 12.0, speed=6.0)
    assert slot == 0
    np.testing.assert_allclose(traffic.pose[slot], path_pose(layout, 5, 12.0))
    assert traffic.speed[slot] == 6.0
    assert traffic.active.sum() == 1 and traffic.spawned == 1
    assert CFG.npc_speed_range[0] <= traffic.desired_speed[slot] <= CFG.npc_speed_range[1]
    # No second vehicle within 15 m of the first, but one on another arm is fine.
    assert traffic.spawn(5, 20.0) is None
    assert traffic.spawn(1, 0.0) == 1
    assert traffic.uid[1] == 1


def test_spawn_caps_speed_behind_an_obstacle(layout):
    traffic = make_traffic(layout)
    x, y, h = path_pose(layout, 1, 30.0)
    slot = traffic.spawn(1, 0.0, ego=Obstacle(x, y, h, 0.0), speed=15.0)
    gap = 30.0 - VEHICLE_LENGTH
    # The obstacle's arc length comes from the 0.5 m lookup table.
    assert traffic.speed[slot] == pytest.approx(
        np.sqrt(2.0 * traffic.driver.comfort_decel * (gap - 2.0)), rel=0.02
    )
    assert traffic.spawn(1, 20.0, ego=Obstacle(x, y, h, 0.0)) is None  # too close to the ego


def test_spawn_fails_when_full(layout):
    traffic = Traffic(layout, CFG.replace(max_vehicles=2), np.random.default_rng(0))
    assert traffic.spawn(1, 0.0) is not None
    assert traffic.spawn(5, 0.0) is not None
    assert traffic.spawn(9, 0.0) is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_crashes_without_ego(layout, seed):
    rng = np.random.default_rng(seed)
    traffic = Traffic(layout, CFG, rng)
    for _ in range(300):
        if rng.uniform() < CFG.spawn_probability:
            traffic.spawn_random()
        traffic.step()
        assert not traffic.detect_crashes()
    assert traffic.spawned >= 10  # there was traffic to crash
    assert traffic.crashed_uids == set()
    assert not traffic.crashed.any()


def test_vehicles_leave_at_the_end_of_their_path(layout):
    traffic = make_traffic(layout)
    slot = traffic.spawn(2, layout.paths.lengths[2] - 3.0, speed=8.0)
    for _ in range(10):
        traffic.step()
    assert not traffic.active[slot]


def test_stops_behind_a_stopped_ego_and_never_touches_it(layout):
    traffic = make_traffic(layout)
    ego_s = 40.0
    x, y, h = path_pose(layout, 2, ego_s)
    ego = Obstacle(float(x), float(y), float(h), 0.0)
    ego_box = box_corners(
        np.array(ego.x), np.array(ego.y), np.array(ego.heading), np.array(ego.length), np.array(ego.width)
    )
    slot = traffic.spawn(2, 0.0, speed=10.0)
    assert traffic.speed[slot] > 8.0  # it comes in fast
    for _ in range(200):
        traffic.step(ego)
        assert not traffic.detect_crashes(ego)
        assert not boxes_overlap(traffic._corners(np.array([slot]))[0], ego_box)
    gap = ego_s - traffic.s[slot] - VEHICLE_LENGTH
    assert traffic.speed[slot] == pytest.approx(0.0, abs=0.05)
    assert traffic.driver.min_gap - 0.5 < gap < traffic.driver.min_gap + 1.5


def test_follows_a_slower_vehicle_without_crashing(layout):
    traffic = make_traffic(layout)
    lead = traffic.spawn(6, 30.0, speed=3.0)
    traffic.desired_speed[lead] = 3.0
    follower = traffic.spawn(6, 0.0, speed=10.0)
    traffic.desired_speed[follower] = 10.0
    for _ in range(150):
        traffic.step()
        assert not traffic.detect_crashes()
    assert traffic.s[lead] - traffic.s[follower] > VEHICLE_LENGTH + traffic.driver.min_gap - 0.5
    assert traffic.speed[follower] == pytest.approx(3.0, abs=0.5)


def _cross(layout, major_path=None, steps=200):
    """A minor-road vehicle on the south arm heading for the stop line, optionally with a slow
    committed major-road vehicle crossing its path; returns the per-step states."""
    traffic = make_traffic(layout, seed=1)
    major = None
    if major_path is not None:
        major = traffic.spawn(major_path, layout.stop_s - 0.5, speed=1.0)
        traffic.committed[major] = True
        traffic.desired_speed[major] = 2.0  # a slow crossing: about 10 s in the shared zone
    minor = traffic.spawn(1, layout.stop_s - 25.0, speed=8.0)
    rows = []
    for _ in range(steps):
        traffic.step()
        assert not traffic.detect_crashes()
        major_rear = (
            np.inf if major is None or not traffic.active[major] else traffic.s[major] - VEHICLE_LENGTH / 2.0
        )
        rows.append((traffic.s[minor] + VEHICLE_LENGTH / 2.0, traffic.speed[minor], major_rear))
    return np.array(rows)


def test_minor_road_waits_for_committed_major_vehicle(layout):
    major_path = 5  # west arm (priority road), straight on, crossing the south arm's path 1
    assert layout.path_major[major_path] and not layout.path_major[1]
    assert layout.conflict[1, major_path]
    rows = _cross(layout, major_path)
    front, speed, major_rear = rows.T
    in_zone = major_rear < layout.zone_end[major_path, 1]
    assert in_zone[:20].all()
    # While the major vehicle is in the shared zone, the minor one stays behind its stop line...
    assert np.all(front[in_zone] <= layout.stop_s)
    # ... and it really waits there (stopped close to the line), then goes once the zone is clear.
    waiting = speed < 0.1
    assert waiting.any()
    assert np.all(front[waiting] > layout.stop_s - 4.0)
    assert front[-1] > layout.stop_s + 10.0


def test_minor_road_goes_without_conflicting_traffic(layout):
    front, speed, _ = _cross(layout, None, steps=60).T
    assert speed.min() > 3.0  # it does not stop at the line on an empty junction
    assert front[-1] > layout.stop_s


def test_ego_standing_in_the_junction_blocks_entry(layout):
    traffic = make_traffic(layout)
    # The ego stands across path 5 inside the junction.
    x, y, h = path_pose(layout, 5, layout.stop_s + 13.0)
    ego = Obstacle(float(x), float(y), float(h) + np.pi / 2, 0.0)
    slot = traffic.spawn(5, layout.stop_s - 20.0, speed=6.0)
    for _ in range(120):
        traffic.step(ego)
        assert not traffic.detect_crashes(ego)
    assert not traffic.committed[slot]
    assert traffic.s[slot] + VEHICLE_LENGTH / 2.0 <= layout.stop_s


def test_priority_key_orders_major_straight_first(layout):
    traffic = make_traffic(layout)
    # Minor left, minor straight (20 m ahead on the same lane), major straight, major left.
    slots = [traffic.spawn(p, s) for p, s in ((0, 0.0), (1, 20.0), (5, 0.0), (4, 20.0))]
    keys = traffic.priority_key(np.array(slots))
    assert keys[2] < keys[3] < keys[1] < keys[0]


def test_crash_detection_marks_and_removes_crashed_vehicles(layout):
    traffic = make_traffic(layout)
    a = traffic.spawn(1, 80.0, speed=0.0)
    b = traffic.spawn(5, 0.0, speed=0.0)
    assert a is not None and b is not None
    traffic.s[b] = 85.0  # moved onto the first one inside the junction (spawn keeps 15 m apart)
    traffic._refresh_poses()
    assert not traffic.detect_crashes()
    assert traffic.crashed[[a, b]].all()
    assert traffic.crashed_uids == {int(traffic.uid[a]), int(traffic.uid[b])}
    s_before = traffic.s[[a, b]].copy()
    for _ in range(int(CFG.crashed_vehicle_lifetime / 0.1) - 2):
        traffic.step()
    np.testing.assert_array_equal(traffic.s[[a, b]], s_before)  # crashed vehicles do not move
    assert traffic.active[[a, b]].all()
    for _ in range(5):
        traffic.step()
    assert not traffic.active[[a, b]].any()


def test_ego_hit_is_reported(layout):
    traffic = make_traffic(layout)
    x, y, h = path_pose(layout, 2, 40.0)
    slot = traffic.spawn(2, 43.0, speed=0.0)
    assert traffic.detect_crashes(Obstacle(float(x), float(y), float(h), 5.0))
    assert traffic.crashed[slot]
    assert not make_traffic(layout).detect_crashes(Obstacle(float(x), float(y), float(h), 5.0))


def _minor_in_major_stream(layout, patience, steps=300, warmup=120):
    """A minor-road car (path 1) at its stop line while major-road cars (path 5) cross its path every
    2.5 s, too close together for its gap; returns the traffic, the minor car's slot, its front per step
    after it appeared and per step the least speed of an uncommitted major car near its stop line."""
    traffic = Traffic(layout, CFG.replace(npc_patience=patience), np.random.default_rng(0))
    minor = None
    fronts, major_stops = [], []
    for step in range(warmup + steps):
        if step % 25 == 0:
            traffic.spawn(5, 0.0, speed=8.0)
        if step == warmup:  # the stream has reached the junction
            minor = traffic.spawn(1, layout.stop_s - 8.0, speed=0.0)
        traffic.step()
        assert not traffic.detect_crashes()
        if minor is None:
            continue
        idx = traffic.indices
        major = idx[(traffic.path[idx] == 5) & ~traffic.committed[idx]]
        near_line = major[traffic.s[major] > layout.stop_s - 10.0]
        major_stops.append(traffic.speed[near_line].min() if len(near_line) else np.inf)
        fronts.append(traffic.s[minor] + VEHICLE_LENGTH / 2.0 if traffic.active[minor] else np.inf)
    return traffic, minor, np.array(fronts), np.array(major_stops)


def test_null_patience_is_allowed():
    assert IntersectionConfig(npc_patience=None).npc_patience is None


def test_without_patience_a_dense_priority_stream_holds_the_minor_road(layout):
    traffic, minor, fronts, _ = _minor_in_major_stream(layout, None)
    assert not traffic.committed[minor]
    assert np.all(fronts <= layout.stop_s)
    assert traffic.waited[minor] > 20.0
    assert not traffic.impatient(np.array([minor]))[0]


def test_an_impatient_car_goes_first_and_the_priority_stream_stops_for_it(layout):
    patience = 8.0
    traffic, minor, fronts, major_stops = _minor_in_major_stream(layout, patience)
    entered = int(np.argmax(fronts > layout.stop_s))
    assert fronts[entered] > layout.stop_s  # it entered ...
    assert entered * 0.1 > patience  # ... only once out of patience ...
    assert entered * 0.1 < patience + 10.0  # ... and soon after: committed traffic clears in seconds
    # A priority car stopped at its own stop line for it (it was not yet committed).
    assert major_stops.min() < 0.1
    assert traffic.waited[minor] >= patience and traffic.impatient(np.array([minor]))[0]


def test_impatience_outranks_the_priority_road(layout):
    traffic = make_traffic(layout)
    minor, major = traffic.spawn(1, 20.0), traffic.spawn(5, 0.0)
    before = traffic.priority_key(np.array([minor, major]))
    assert before[1] < before[0]
    traffic.waited[minor] = CFG.npc_patience
    after = traffic.priority_key(np.array([minor, major]))
    assert after[0] < after[1]
