"""The world: episode start, outcomes (success only at the task's own exit), action masks, futures."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ego_frame, place_ego
from hypothesis import given
from hypothesis import strategies as st

from gccp_envs.action import EgoAction, EgoState
from gccp_envs.config import IntersectionConfig
from gccp_envs.scenario import TURN_OFFSET
from gccp_envs.traffic import VEHICLE_LENGTH
from gccp_envs.world import IntersectionWorld, StepOutcome

# Just before each exit (the outbound lanes, 0.5 m before the exit distance), heading out.
EXITS = {
    "left": (-32.5, -2.0, np.pi),
    "straight": (6.0, -32.5, -np.pi / 2),
    "right": (32.5, 6.0, 0.0),
}


def test_reset_places_the_ego_on_the_south_arm():
    cfg = IntersectionConfig(spawn_probability=0.12)
    world = IntersectionWorld(cfg)
    for seed in range(5):
        world.reset(np.random.default_rng(seed))
        ego, layout = world.ego, world.layout
        assert world.task in ("left", "straight", "right")
        assert world.steps == 0 and world.time == 0.0
        assert ego.heading == pytest.approx(-np.pi / 2)
        assert min(abs(ego.x - 2.0), abs(ego.x - 6.0)) < 1e-9  # the centre of one of its two lanes
        distance = ego.y - layout.junction
        assert cfg.ego_start_distance[0] - 1e-9 <= distance <= cfg.ego_start_distance[1] + 1e-9
        assert 0.0 <= ego.speed <= cfg.ego_start_speed[1]
        assert world.ego_on_road(ego)
        np.testing.assert_allclose(world.task_goal, layout.task_goal(world.task))
        # Traffic was warmed up, and none of it is near the ego.
        idx = world.traffic.indices
        assert world.traffic.spawned > 0
        assert np.all(np.hypot(*(world.traffic.pose[idx, :2] - [ego.x, ego.y]).T) >= 15.0)


def test_reset_task_option_and_ego_lane_task():
    world = IntersectionWorld(IntersectionConfig(spawn_probability=0.0, ego_lane="task"))
    for seed in range(4):
        world.reset(np.random.default_rng(seed), "left")
        assert world.task == "left"
        assert world.ego.x == pytest.approx(2.0)  # left turns start from lane 0
        world.reset(np.random.default_rng(seed), "right")
        assert world.ego.x == pytest.approx(6.0)
    with pytest.raises(ValueError, match="unknown task 'diagonal'"):
        world.reset(np.random.default_rng(0), "diagonal")


def test_standing_start_anywhere_on_the_tasks_path():
    world = IntersectionWorld(IntersectionConfig(spawn_probability=0.12, ego_start_standing=1.0))
    layout = world.layout
    inside = 0
    for seed in range(30):
        world.reset(np.random.default_rng(seed), "left")
        ego = world.ego
        assert ego.speed == 0.0 and world.ego_on_road(ego)
        path = np.array(world._task_paths)
        s, d = layout.paths.project(path, np.array([[ego.x, ego.y]] * len(path)))
        on = int(np.argmin(np.abs(d)))
        assert abs(d[on]) < 1e-3
        assert layout.stop_s - 10.0 - 1e-3 <= s[on] <= layout.junction_end_s[path[on]] + 5.0 + 1e-3
        inside += layout.stop_s < s[on] < layout.junction_end_s[path[on]]
        idx = world.traffic.indices
        assert np.all(np.hypot(*(world.traffic.pose[idx, :2] - [ego.x, ego.y]).T) >= 15.0)
    assert inside >= 10  # most draws are inside the turn, where a held car must drive off again


def test_no_standing_start_keeps_the_episodes():
    plain, zero = IntersectionWorld(IntersectionConfig()), IntersectionWorld(
        IntersectionConfig(ego_start_standing=0.0)
    )
    for seed in range(3):
        plain.reset(np.random.default_rng(seed))
        zero.reset(np.random.default_rng(seed))
        assert plain.ego == zero.ego


@pytest.mark.parametrize("task", sorted(EXITS))
@pytest.mark.parametrize("exit_task", sorted(EXITS))
def test_success_only_at_the_tasks_own_exit(make_world, task, exit_task):
    world = make_world(task)
    place_ego(world, *EXITS[exit_task], 8.0)
    outcome = world.step(EgoAction.KEEP_DIRECTION)
    assert outcome.success == (task == exit_task)
    assert outcome.wrong_exit == (task != exit_task)
    assert outcome.terminal
    assert not outcome.crashed and not outcome.offroad


@pytest.mark.parametrize("task", sorted(EXITS))
def test_no_outcome_before_the_exit_distance(make_world, task):
    world = make_world(task)
    x, y, h = EXITS[task]
    # 2 m further back: one step does not reach the exit distance yet.
    place_ego(world, x - 2.0 * np.cos(h), y - 2.0 * np.sin(h), h, 8.0)
    assert world.step(EgoAction.KEEP_DIRECTION) == StepOutcome()


def test_driving_back_out_on_an_inbound_lane_is_no_exit(make_world):
    world = make_world("left")
    place_ego(world, -32.5, 2.0, np.pi, 8.0)  # west arm, but on the inbound (east-bound) lanes
    outcome = world.step(EgoAction.KEEP_DIRECTION)
    assert not outcome.success and not outcome.wrong_exit and not outcome.terminal


def test_step_outcome_terminal():
    assert not StepOutcome().terminal
    for flag in ("crashed", "offroad", "success", "wrong_exit"):
        assert StepOutcome(**{flag: True}).terminal


def test_crash_with_traffic(make_world):
    world = make_world()
    place_ego(world, 6.0, 40.0, -np.pi / 2, 8.0)
    world.traffic.spawn(2, 83.0 - 40.0 + VEHICLE_LENGTH - 0.2, speed=0.0)  # just ahead, touching
    outcome = world.step(EgoAction.KEEP_DIRECTION)
    assert outcome.crashed and outcome.terminal


def test_off_road(make_world):
    world = make_world()
    place_ego(world, 6.0, 50.0, -np.pi / 2 + 0.4, 8.0)
    assert world.ego_on_road(world.ego)
    outcome = world.step(EgoAction.SLOWLY_TURN_RIGHT)
    assert outcome.offroad and outcome.terminal


def test_action_mask_keeps_the_ego_on_the_road(make_world):
    world = make_world()
    # At the right kerb of the south arm, heading 23 degrees off the road: only a quick left
    # turn keeps all four corners on the road.
    state = (6.0, 50.0, -np.pi / 2 + 0.4, 8.0)
    place_ego(world, *state)
    assert world.ego_on_road(world.ego)
    mask = world.action_mask()
    np.testing.assert_array_equal(mask, [False, False, False, False, True, False])
    for action in EgoAction:
        place_ego(world, *state)
        assert world.step(action).offroad != mask[action]


def test_action_mask_looks_ahead_for_a_way_to_stay_on_the_road(make_world):
    # Near the right kerb, heading 17 degrees towards it: every action keeps the car on the road for
    # one step, but after a quick right turn no action held for 0.4 s more avoids the kerb.
    state = (5.75, 50.0, -np.pi / 2 + 0.3, 8.0)
    one_step = make_world(mask_lookahead=1, mask_drive_on=0.0)
    place_ego(one_step, *state)
    assert one_step.action_mask().all()
    world = make_world(mask_drive_on=0.0)
    place_ego(world, *state)
    np.testing.assert_array_equal(world.action_mask(), [True] * 5 + [False])
    for hold in EgoAction:
        place_ego(world, *state)
        outcomes = [world.step(EgoAction.QUICKLY_TURN_RIGHT)] + [world.step(hold) for _ in range(4)]
        assert any(o.offroad for o in outcomes), hold


def test_action_mask_all_allowed_in_the_middle_of_the_road(make_world):
    world = make_world()
    place_ego(world, 4.0, 50.0, -np.pi / 2, 8.0)
    assert world.action_mask().all()


def test_action_mask_never_all_false(make_world):
    world = make_world()
    place_ego(world, 30.0, 30.0, 0.0, 8.0)  # off the road: every action stays off it
    np.testing.assert_array_equal(world.action_mask(), np.ones(6, bool))


def test_action_mask_is_computed_once_per_pose_of_the_ego(make_world, monkeypatch):
    world = make_world()
    state = (6.0, 50.0, -np.pi / 2 + 0.4, 8.0)  # at the kerb: only a quick left turn is allowed
    place_ego(world, *state)
    calls = []
    compute = world._road_keeping_mask
    monkeypatch.setattr(world, "_road_keeping_mask", lambda: calls.append(1) or compute())
    first = world.action_mask()
    first[:] = True  # the caller's copy: the next call is not changed by it
    np.testing.assert_array_equal(world.action_mask(), [False, False, False, False, True, False])
    assert len(calls) == 1
    world.ego.heading = -np.pi / 2  # a new pose (also when changed in place): computed again
    assert world.action_mask().all()
    assert len(calls) == 2
    world.step(EgoAction.KEEP_DIRECTION)
    world.action_mask()
    assert len(calls) == 3


@given(
    st.floats(-90, 90),
    st.floats(-90, 90),
    st.floats(-np.pi, np.pi),
    st.floats(0.0, 12.0),
    st.sampled_from([0.0, 10.0]),
)
def test_action_mask_is_never_empty(x, y, heading, speed, drive_on):
    world = _shared_world(drive_on)
    world.ego = EgoState(x, y, heading, speed)
    mask = world.action_mask()
    assert mask.shape == (6,) and mask.dtype == bool
    assert mask.any()


_WORLDS: dict[float, IntersectionWorld] = {}


def _shared_world(drive_on: float = 0.0) -> IntersectionWorld:
    if drive_on not in _WORLDS:
        world = IntersectionWorld(IntersectionConfig(spawn_probability=0.0, mask_drive_on=drive_on))
        world.reset(np.random.default_rng(0), "straight")
        _WORLDS[drive_on] = world
    return _WORLDS[drive_on]


def test_history_window_and_validity(make_world):
    world = make_world(seed=2)
    slots = np.array([world.ego_slot])
    poses, valid = world.poses_between(-5, 3, slots, world.slot_uids(slots))
    # The ego's back-filled past is valid; steps not simulated yet are not.
    np.testing.assert_array_equal(valid[:, 0], [True] * 6 + [False] * 3)
    np.testing.assert_allclose(poses[5, 0], world.ego.as_array())
    for _ in range(3):
        world.step(EgoAction.KEEP_DIRECTION)
    poses, valid = world.poses_between(3, 3, slots, world.slot_uids(slots))
    assert valid.all()
    np.testing.assert_allclose(poses[0, 0], world.ego.as_array())
    # Older than the history buffer: invalid.
    _, valid = world.poses_between(3 - world._hist_len, 3 - world._hist_len, slots, world.slot_uids(slots))
    assert not valid.any()


def test_decision_future_is_what_happened(make_world):
    world = make_world(seed=0, spawn_probability=0.2)
    record = world.begin_decision()
    origin, heading = record.origin.copy(), record.heading
    driven = []
    neighbours = record.slots[1:]
    npc = []
    for action in [1, 1, 2, 2, 4, 0, 0, 3, 5, 1]:
        world.step(action)
        driven.append(world.ego.as_array()[:3])
        npc.append(world.traffic.pose[neighbours].copy())
    future, present = world.decision_future(record)
    assert future.shape == (6, 10, 3) and present.shape == (6, 10)
    driven = np.array(driven)
    np.testing.assert_allclose(future[0, :, :2], ego_frame(driven[:, :2], *origin, heading), atol=1e-4)
    np.testing.assert_allclose(np.cos(future[0, :, 2]), np.cos(driven[:, 2] - heading), atol=1e-5)
    assert present[0].all()
    for row, _ in enumerate(neighbours, start=1):
        alive = present[row]
        track = np.array(npc)[:, row - 1]
        np.testing.assert_allclose(
            future[row, alive, :2], ego_frame(track[alive, :2], *origin, heading), atol=1e-4
        )
    assert len(neighbours) > 0
    np.testing.assert_array_equal(present[len(record.slots) :], False)
    np.testing.assert_array_equal(future[~present], 0.0)


def test_decision_future_of_an_early_end_is_partial(make_world):
    world = make_world(seed=0)
    record = world.begin_decision()
    for _ in range(4):
        world.step(EgoAction.KEEP_DIRECTION)
    _, present = world.decision_future(record)
    np.testing.assert_array_equal(present[0], [True] * 4 + [False] * 6)


def test_task_offsets():
    assert TURN_OFFSET == {"left": 1, "straight": 2, "right": 3}


def test_stop_and_go_in_the_world(make_world):
    world = make_world()
    place_ego(world, 6.0, 60.0, -np.pi / 2, 8.0)
    for _ in range(20):  # 8 m/s at 4 m/s^2: stopped after 2 s
        world.step(EgoAction.SLOW_DOWN)
    assert world.ego.speed == 0.0
    stopped = world.ego.as_array()
    assert stopped[1] == pytest.approx(60.0 - 8.0)  # braking distance v^2 / (2 a)
    for _ in range(5):
        assert world.step(EgoAction.SLOW_DOWN) == StepOutcome()
        np.testing.assert_array_equal(world.ego.as_array(), stopped)
    for _ in range(45):  # 0.2 m/s per step: cruise speed after 40 steps
        assert not world.step(EgoAction.KEEP_DIRECTION).terminal
    assert world.ego.speed == world.config.cruise_speed
    assert world.ego.x == pytest.approx(6.0) and world.ego.y < stopped[1]


# Coming out of a right turn at cruise speed beside the kerb (the south arm's right turn exits east; the
# exit's right lane has its kerb at y = 8): no action held for 1 s keeps the box on the road, so the
# mask falls back to the actions that keep it there for one step, the quick right turn among them.
# After that turn every way on leaves the road within 10 m.
BESIDE_THE_KERB = (11.062, 7.573, -0.3643, 8.0)


def test_drive_on_mask_refuses_an_action_after_which_every_way_on_leaves_the_road(make_world):
    without = make_world(mask_drive_on=0.0)
    place_ego(without, *BESIDE_THE_KERB)
    np.testing.assert_array_equal(without.action_mask(), [True, True, False, True, False, True])
    world = make_world(mask_drive_on=10.0)
    place_ego(world, *BESIDE_THE_KERB)
    np.testing.assert_array_equal(world.action_mask(), [True, True, False, True, False, False])
    # After the quick right turn no two actions, one after the other, keep the box on the road for
    # 10 m; after the slow one some do (though no single action held does).
    for first, trapped in ((EgoAction.QUICKLY_TURN_RIGHT, True), (EgoAction.SLOWLY_TURN_RIGHT, False)):
        after = world.motion.step(EgoState(*BESIDE_THE_KERB), first)
        assert world.ego_on_road(after)
        assert _drives_on(world, after, steps=13) != trapped, first  # 13 steps at 8 m/s: 10.4 m


def _drives_on(world: IntersectionWorld, start: EgoState, steps: int) -> bool:
    """Whether some action held for k steps and then another for the rest keeps the ego on the road."""
    for a in EgoAction:
        for k in range(steps + 1):
            for b in EgoAction:
                state, on_road = start, True
                for step in range(steps):
                    state = world.motion.step(state, a if step < k else b)
                    if not world.ego_on_road(state):
                        on_road = False
                        break
                if on_road:
                    return True
    return False


def test_drive_on_mask_changes_nothing_on_an_open_lane(make_world):
    world = make_world(mask_drive_on=10.0)
    place_ego(world, 4.0, 50.0, -np.pi / 2, 8.0)
    assert world.action_mask().all()
    place_ego(world, 6.0, 50.0, -np.pi / 2 + 0.4, 8.0)  # at the kerb: only the quick left turn, as without
    np.testing.assert_array_equal(world.action_mask(), [False, False, False, False, True, False])


@pytest.mark.parametrize("value", [-1.0, 31.0, True, "10"])
def test_drive_on_mask_out_of_range_is_refused(value):
    with pytest.raises(ValueError, match="mask_drive_on"):
        IntersectionConfig(mask_drive_on=value)
