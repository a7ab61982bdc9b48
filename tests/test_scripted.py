"""Scripted controllers: pure pursuit planner and farthest-subgoal decider."""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from helpers import path_pose, place_ego, place_ego_on_path

from gccp_envs.action import EgoAction
from gccp_envs.config import IntersectionConfig
from gccp_envs.scripted import ROLLOUT_CACHE_SIZE, FarthestSubgoalDecider, ScriptedPlanner, SearchPlanner

PLANNER = ScriptedPlanner(IntersectionConfig())


def planner_obs(goal, speed):
    history = np.zeros((6, 10, 9), np.float32)
    history[0, -1, 7] = speed
    return {"goal": np.asarray(goal, np.float32), "history": history}


@pytest.mark.parametrize(
    ("goal", "speed", "action"),
    [
        ((15.0, 0.0, 0.0), 8.0, EgoAction.KEEP_DIRECTION),
        ((15.0, 1.0, 0.0), 8.0, EgoAction.KEEP_DIRECTION),  # pursuit curvature 0.009: nearest is straight
        ((10.0, 3.0, 0.0), 8.0, EgoAction.SLOWLY_TURN_RIGHT),  # y > 0: right on screen
        ((10.0, -3.0, 0.0), 8.0, EgoAction.SLOWLY_TURN_LEFT),
        ((6.0, -4.0, 0.0), 6.0, EgoAction.QUICKLY_TURN_LEFT),
        ((3.0, 0.0, 0.0), 8.0, EgoAction.SLOW_DOWN),  # too fast to stop on the goal
        ((-1.0, 0.0, 0.0), 2.0, EgoAction.SLOW_DOWN),  # behind: stand still
        ((10.0, -3.0, 0.0), 0.0, EgoAction.KEEP_DIRECTION),  # standing: get going before turning
    ],
)
def test_scripted_planner_actions(goal, speed, action):
    assert PLANNER(planner_obs(goal, speed)) == action


def test_scripted_planner_respects_the_mask():
    mask = np.ones(6, bool)
    mask[EgoAction.SLOWLY_TURN_RIGHT] = False
    action = PLANNER(planner_obs((10.0, 3.0, 0.0), 8.0), mask)
    assert action != EgoAction.SLOWLY_TURN_RIGHT and mask[action]
    assert action in (EgoAction.KEEP_DIRECTION, EgoAction.QUICKLY_TURN_RIGHT)
    only_slow_down = np.eye(6, dtype=bool)[EgoAction.SLOW_DOWN]
    assert PLANNER(planner_obs((15.0, 3.0, 0.0), 8.0), only_slow_down) == EgoAction.SLOW_DOWN


def test_scripted_planner_reaches_and_stops_on_a_goal():
    # A long decision period keeps the goal fixed for the whole run.
    env = gym.make("GCCPPlanner-v0", spawn_probability=0.0, task="straight", decision_period=50).unwrapped
    obs, _ = env.reset(seed=0)
    place_ego_on_path(env.world, 2, 30.0, 8.0)
    env._subgoal = path_pose(env.world.layout, 2, 45.0)
    env._holding = True  # a hold: the goal is not replaced once reached
    obs = env._observe()
    reached = False
    for _ in range(45):
        obs, _, terminated, _, info = env.step(PLANNER(obs, env.action_masks()))
        reached |= info["goal_reached"]
        assert not terminated
    assert reached
    assert env.world.ego.speed == 0.0
    assert np.hypot(*obs["goal"][:2]) < 1.5


@pytest.mark.parametrize("goal", [(0.3, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.8, 0.0, 0.0)])
def test_scripted_planner_holds_still_on_its_goal(goal):
    assert PLANNER(planner_obs(goal, 0.0)) == EgoAction.SLOW_DOWN


@pytest.mark.parametrize(
    ("goal", "speed", "action"),
    [
        ((-1.0, 0.0, 0.25), 8.0, EgoAction.QUICKLY_TURN_RIGHT),  # 0.133 rad per step, to 0.12
        ((-1.0, 0.0, 0.09), 8.0, EgoAction.SLOWLY_TURN_RIGHT),  # 0.067 rad per step, to 0.02
        ((-1.0, 0.0, -0.25), 8.0, EgoAction.QUICKLY_TURN_LEFT),
        ((-1.0, 0.0, 0.04), 8.0, EgoAction.SLOW_DOWN),  # aligned enough
        ((-1.0, 0.0, 0.25), 0.8, EgoAction.SLOW_DOWN),  # too slow to turn: stop
    ],
)
def test_scripted_planner_turns_into_line_before_it_stops(goal, speed, action):
    aligned = ScriptedPlanner(IntersectionConfig(scripted_stop_aligned=True))
    assert aligned(planner_obs(goal, speed)) == action
    assert PLANNER(planner_obs(goal, speed)) == EgoAction.SLOW_DOWN  # the default brakes at once


def test_scripted_planner_stops_in_line_with_its_lane():
    # Left of its lane and heading 0.2 rad across it at 8 m/s, told to hold on its lane.
    config = IntersectionConfig(spawn_probability=0.0, task="straight", decision_period=50)
    headings = {}
    for aligned in (True, False):
        env = gym.make("GCCPPlanner-v0", config=replace(config, scripted_stop_aligned=aligned)).unwrapped
        env.reset(seed=0)
        lane = path_pose(env.world.layout, 2, 30.0)
        place_ego(env.world, lane[0], lane[1], lane[2] - 0.2, 8.0)
        env._subgoal, env._holding = lane, True
        obs = env._observe()
        planner = ScriptedPlanner(env.config)
        for _ in range(30):
            obs, *_ = env.step(planner(obs, env.action_masks()))
        assert env.world.ego.speed == 0.0
        headings[aligned] = abs(float(obs["goal"][2]))
    assert headings[True] < 0.05 < 0.15 < headings[False]


@pytest.mark.parametrize(
    ("goal", "speed", "action"),
    [
        ((10.0, -3.0, 0.0), 2.0, EgoAction.KEEP_DIRECTION),  # pursuit 0.055: straight is nearer than 1/6
        ((6.0, -4.0, 0.0), 2.0, EgoAction.QUICKLY_TURN_LEFT),  # pursuit 0.154
        ((10.0, 3.0, 0.0), 2.0, EgoAction.KEEP_DIRECTION),
        ((10.0, -3.0, 0.0), 5.0, EgoAction.SLOWLY_TURN_LEFT),  # fast enough: the nearest curvature
        ((1.5, 0.0, 0.0), 0.5, EgoAction.KEEP_DIRECTION),  # about to stop: no faster than the goal allows
    ],
)
def test_scripted_planner_accelerates_through_slow_turns(goal, speed, action):
    brisk = ScriptedPlanner(IntersectionConfig(scripted_turn_speed=4.0))
    assert brisk(planner_obs(goal, speed)) == action
    if goal == (10.0, -3.0, 0.0):
        assert PLANNER(planner_obs(goal, speed)) == EgoAction.SLOWLY_TURN_LEFT  # the default holds 2 m/s


def test_scripted_planner_does_not_crawl_through_a_turn_from_a_stop():
    # Standing at the stop line of a left turn, sent 25 m on along it: by default the ego turns at the
    # 1 m/s it first accelerates to; with scripted_turn_speed it gets through the turn, on the road.
    config = IntersectionConfig(spawn_probability=0.0, task="left", decision_period=100)
    travelled, speeds = {}, {}
    for turn_speed in (1.0, 4.0):
        env = gym.make("GCCPPlanner-v0", config=replace(config, scripted_turn_speed=turn_speed)).unwrapped
        env.reset(seed=0)
        layout = env.world.layout
        path = layout.paths_from(0, turn="left")[0]
        place_ego_on_path(env.world, path, layout.stop_s - 2.5, 0.0)
        env._subgoal, env._holding = path_pose(layout, path, layout.stop_s + 25.0), True
        obs = env._observe()
        planner = ScriptedPlanner(env.config)
        start = np.array([env.world.ego.x, env.world.ego.y])
        top = 0.0
        for _ in range(60):
            obs, _, terminated, _, _ = env.step(planner(obs, env.action_masks()))
            assert not terminated  # neither off the road nor past the exit
            top = max(top, env.world.ego.speed)
        travelled[turn_speed] = float(np.hypot(env.world.ego.x - start[0], env.world.ego.y - start[1]))
        speeds[turn_speed] = top
    assert speeds[1.0] < 1.5 < 3.5 < speeds[4.0]
    assert travelled[1.0] < 8.0 < 15.0 < travelled[4.0]


def test_farthest_subgoal_decider():
    decider = FarthestSubgoalDecider()
    subgoals = np.zeros((12, 3), np.float32)
    subgoals[:, 0] = np.arange(12) % 5
    assert decider({"subgoals": subgoals}) == 4
    mask = np.zeros(12, bool)
    mask[[1, 7]] = True
    assert decider({"subgoals": subgoals}, mask) == 7


SEARCH = SearchPlanner(IntersectionConfig())


def test_search_planner_rollout_is_the_egos_kinematics():
    from gccp_envs.action import EgoMotion, EgoState

    motion = EgoMotion(IntersectionConfig())
    poses = SEARCH.rollout(5.0)
    for row in (0, len(SEARCH.sequences) // 2, len(SEARCH.sequences) - 1):
        state = EgoState(0.0, 0.0, 0.0, 5.0)
        for step, action in enumerate(SEARCH.sequences[row]):
            state = motion.step(state, int(action))
            np.testing.assert_allclose(poses[row, step, :2], (state.x, state.y), atol=1e-9)
            assert abs(np.angle(np.exp(1j * (poses[row, step, 2] - state.heading)))) < 1e-9


def test_search_planner_keeps_its_recently_used_rollouts_up_to_the_cache_size():
    planner = SearchPlanner(IntersectionConfig())
    first = planner.rollout(0.0)
    for k in range(ROLLOUT_CACHE_SIZE + 10):
        planner.rollout(1.0 + 0.01 * k)
        assert planner.rollout(0.0) is first  # used at every step: never the one dropped
    assert len(planner._rollouts) == ROLLOUT_CACHE_SIZE
    newest = round(1.0 + 0.01 * (ROLLOUT_CACHE_SIZE + 9), 6)
    assert 1.0 not in planner._rollouts and newest in planner._rollouts


def test_search_planner_on_road_needs_all_four_corners_on_the_road_or_beyond_the_view():
    config = IntersectionConfig()
    size, reach = config.bev_size, config.bev_extent / 2.0
    behind = np.zeros((size, size), np.float32)
    behind[size // 2 :] = 1.0  # the road is the half of the view behind the ego (forward is up)
    poses = np.array(
        [
            [-10.0, 0.0, 0.0],  # behind: on the road
            [10.0, 0.0, 0.0],  # ahead: off it
            [0.0, 0.0, 0.0],  # the front corners ahead, the rear ones behind: off it
            [-4.0, 0.0, np.pi / 2],  # across, all four corners behind
            [reach + 10.0, 0.0, 0.0],  # beyond the view: counts as on the road
            [-reach - 10.0, reach + 10.0, 1.0],
        ]
    )
    np.testing.assert_array_equal(SEARCH.on_road(poses, behind), [True, False, False, True, True, True])
    np.testing.assert_array_equal(SEARCH.on_road(poses, np.ones((size, size))), [True] * 6)
    np.testing.assert_array_equal(SEARCH.on_road(poses, np.zeros((size, size))), [False] * 4 + [True] * 2)


def test_search_planner_reads_the_road_from_its_cached_rollout_as_from_the_poses():
    rng = np.random.default_rng(0)
    bev = (rng.random((IntersectionConfig().bev_size,) * 2) < 0.97).astype(np.float32)
    planner = SearchPlanner(IntersectionConfig())
    poses, pixels, _ = planner._cached(6.0)
    cached = planner._on_road(pixels, bev)
    np.testing.assert_array_equal(cached, planner.on_road(poses, bev))
    assert 0 < cached.mean() < 1


@pytest.mark.parametrize(
    ("goal", "speed", "action"),
    [
        ((15.0, 0.0, 0.0), 4.0, EgoAction.KEEP_DIRECTION),  # accelerating arrives soonest
        ((10.0, -4.0, 0.0), 6.0, EgoAction.QUICKLY_TURN_LEFT),  # a lane change: the S-curve starts left
        ((10.0, 4.0, 0.0), 6.0, EgoAction.QUICKLY_TURN_RIGHT),
        ((0.5, 0.0, 0.0), 3.0, EgoAction.SLOW_DOWN),  # reached: stop on it
        ((-1.0, 0.0, 0.0), 2.0, EgoAction.SLOW_DOWN),  # behind: stand still
    ],
)
def test_search_planner_actions(goal, speed, action):
    assert SEARCH(planner_obs(goal, speed)) == action


@pytest.mark.parametrize("goal", [(1.9, 0.0, 0.0), (1.8, 0.6, 0.1)])
def test_search_planner_stands_on_a_goal_just_ahead_on_its_lane(goal):
    assert SEARCH(planner_obs(goal, 8.0)) == EgoAction.SLOW_DOWN
    without_rule = SearchPlanner(IntersectionConfig(), hold_distance=0.0)
    assert without_rule(planner_obs(goal, 8.0)) != EgoAction.SLOW_DOWN


def test_search_planner_held_on_a_point_just_ahead_stands_on_it():
    from gccp_envs.action import EgoMotion, EgoState
    from gccp_envs.geometry import poses_to_frame

    config = IntersectionConfig()
    motion, state = EgoMotion(config), EgoState(-1.8, 0.0, 0.0, 8.0)
    for step in range(40):
        if step % config.decision_period == 0:  # as the planner env holds: the nearest lattice point
            goal = np.array([config.subgoal_spacing * round(state.x / config.subgoal_spacing), 0.3, 0.0])
        local = poses_to_frame(goal, np.array([state.x, state.y]), state.heading)
        state = motion.step(state, SEARCH(planner_obs(local, state.speed)))
    assert state.speed == 0.0 and abs(state.y) < 0.5  # stopped, and on its lane


@pytest.mark.parametrize("goal", [(-4.0, 0.2, 0.0), (-7.5, -1.0, 0.0)])
def test_search_planner_braking_behind_brakes_for_a_passed_goal_on_its_lane(goal):
    braking = SearchPlanner(IntersectionConfig(), brake_behind=True)
    assert braking(planner_obs(goal, 8.0)) == EgoAction.SLOW_DOWN
    assert SEARCH(planner_obs(goal, 8.0)) != EgoAction.SLOW_DOWN  # 3 m or more behind: drives on


def test_search_planner_braking_behind_drives_on_for_a_goal_beside_it():
    braking = SearchPlanner(IntersectionConfig(), brake_behind=True)
    obs = planner_obs((-4.0, 4.0, 0.0), 8.0)  # behind, on the next lane
    assert braking(obs) == SEARCH(obs) != EgoAction.SLOW_DOWN


def test_search_planner_braking_behind_within_a_heading_drives_on_when_askew():
    aligned = SearchPlanner(IntersectionConfig(), brake_behind=True, brake_behind_heading=0.1)
    assert aligned(planner_obs((-5.0, 0.3, 0.05), 8.0)) == EgoAction.SLOW_DOWN
    askew = planner_obs((-5.4, -1.37, 0.19), 5.0)  # a short lane change passed beside its goal
    assert aligned(askew) == SEARCH(askew) != EgoAction.SLOW_DOWN
    with pytest.raises(ValueError, match="brake_behind_heading"):
        SearchPlanner(IntersectionConfig(), brake_behind=True, brake_behind_heading=-0.1)


def test_search_planner_respects_the_mask():
    mask = np.ones(6, bool)
    mask[EgoAction.QUICKLY_TURN_LEFT] = False
    action = SEARCH(planner_obs((10.0, -4.0, 0.0), 6.0), mask)
    assert mask[action]


def test_search_planner_never_takes_a_masked_action():
    only_turns = np.zeros(6, bool)
    only_turns[[EgoAction.SLOWLY_TURN_LEFT, EgoAction.SLOWLY_TURN_RIGHT]] = True
    for goal, speed in (((0.5, 0.0, 0.0), 3.0), ((-1.0, 0.0, 0.0), 2.0), ((15.0, 0.0, 0.0), 4.0)):
        assert only_turns[SEARCH(planner_obs(goal, speed), only_turns)]


@pytest.mark.parametrize("goal", [(4.6, 14.0, 1.32), (3.8, 16.3, 1.43)])
def test_search_planner_drives_off_from_a_standstill_for_a_goal_out_of_reach(goal):
    # Stopped inside a turn, sent to a candidate beyond 3 s of driving: every sequence that waits before
    # it speeds up scores alike, and one chosen once was chosen at every step (the ego stood for good).
    from gccp_envs.action import EgoMotion, EgoState
    from gccp_envs.geometry import poses_to_frame

    motion, state, goal = EgoMotion(IntersectionConfig()), EgoState(0.0, 0.0, 0.0, 0.0), np.asarray(goal)
    for _ in range(30):
        local = poses_to_frame(goal, np.array([state.x, state.y]), state.heading)
        state = motion.step(state, SEARCH(planner_obs(local, state.speed)))
    assert np.hypot(state.x, state.y) > 1.0


def drive_with_peak_lateral_acceleration(planner, goal, speed=8.0, steps=25):
    """The actions the planner takes driving the ego's kinematics from the origin toward ``goal`` (held
    fixed in the world), and the peak lateral acceleration [m/s²] of those steps."""
    from gccp_envs.action import EgoMotion, EgoState
    from gccp_envs.geometry import poses_to_frame

    motion, state, goal = EgoMotion(planner.config), EgoState(0, 0, 0, speed), np.asarray(goal)
    actions, peak = [], 0.0
    for _ in range(steps):
        local = poses_to_frame(goal, np.array([state.x, state.y]), state.heading)
        action = planner(planner_obs(local, state.speed))
        nxt = motion.step(state, action)
        peak = max(peak, ((state.speed + nxt.speed) / 2) ** 2 * abs(motion.curvature[action]))
        actions.append(action)
        state = nxt
    return actions, peak


def test_search_planner_with_a_lateral_acceleration_limit_brakes_before_a_tight_turn():
    # A right turn of radius 7 m ahead at cruise speed: unlimited, the planner holds 8 m/s into it and
    # takes quick turns (10.7 m/s² at 8 m/s); limited to SUMO's 5.5 m/s², it brakes first.
    config, turn = IntersectionConfig(), [14.0, 7.0, np.pi / 2]
    assert drive_with_peak_lateral_acceleration(SearchPlanner(config), turn)[1] > 8.0
    limited = SearchPlanner(config, max_lateral_acceleration=5.5)
    assert drive_with_peak_lateral_acceleration(limited, turn)[1] <= 5.5 + 1e-9


def test_search_planner_limit_from_goal_heading_spares_lane_changes_but_not_turns():
    # Limited only for goals heading 0.5 rad or more off the ego's: the lane change at cruise speed is
    # the unlimited planner's (its quick turns exceed the limit), the right turn still the limited one's.
    config, turn, lane_change = IntersectionConfig(), [14.0, 7.0, np.pi / 2], [15.0, 4.0, 0.0]
    unlimited = SearchPlanner(config)
    everywhere = SearchPlanner(config, max_lateral_acceleration=5.5)
    on_turns = SearchPlanner(config, max_lateral_acceleration=5.5, limit_from_goal_heading=0.5)
    free_actions, free_peak = drive_with_peak_lateral_acceleration(unlimited, lane_change, steps=15)
    assert free_peak > 5.5
    assert drive_with_peak_lateral_acceleration(everywhere, lane_change, steps=15)[0] != free_actions
    assert drive_with_peak_lateral_acceleration(on_turns, lane_change, steps=15)[0] == free_actions
    assert drive_with_peak_lateral_acceleration(on_turns, turn)[1] <= 5.5 + 1e-9
    with pytest.raises(ValueError, match="limit_from_goal_heading"):
        SearchPlanner(config, max_lateral_acceleration=5.5, limit_from_goal_heading=-0.1)


def drive_search_planner(goal, speed, steps=30):
    """Steps until the search planner, driving the ego's kinematics from the origin, reaches ``goal``
    as the env counts it (None if it does not within ``steps``)."""
    from gccp_envs.action import EgoMotion, EgoState
    from gccp_envs.geometry import poses_to_frame
    from gccp_envs.rewards import goal_errors, goal_reached

    config = IntersectionConfig()
    motion, state, goal = EgoMotion(config), EgoState(0.0, 0.0, 0.0, speed), np.asarray(goal)
    for step in range(steps):
        if goal_reached(config, goal_errors(state, goal)):
            return step
        local = poses_to_frame(goal, np.array([state.x, state.y]), state.heading)
        state = motion.step(state, SEARCH(planner_obs(local, state.speed)))
    return None


@pytest.mark.parametrize(
    ("goal", "speed"),
    [((15.0, 0.0, 0.0), 8.0), ((12.0, -4.0, 0.0), 8.0), ((10.0, 4.0, 0.0), 6.0), ((15.0, 10.0, 1.2), 7.0)],
)
def test_search_planner_reaches_goals_with_its_margin(goal, speed):
    assert drive_search_planner(goal, speed) is not None


@pytest.mark.parametrize(
    ("goal", "speed"), [((4.6, -4.2, 0.0), 8.0), ((4.4, 4.0, 0.0), 5.6), ((5.0, 4.0, 0.0), 8.0)]
)
def test_search_planner_reaches_short_lane_changes_within_the_tolerance(goal, speed):
    # No sequence arrives within the planner's margin here; one within the env's own tolerance does.
    assert drive_search_planner(goal, speed) is not None
