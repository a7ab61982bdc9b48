"""GCCPDecider-v0: options of T_m planner steps, ground-truth futures and the subgoal mask."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from helpers import ego_frame, place_ego

from gccp_envs.action import EgoAction
from gccp_envs.config import DT
from gccp_envs.option_env import GCCPDeciderEnv
from gccp_envs.scripted import ScriptedPlanner


class RecordingPlanner:
    """Wraps a planner and records the ego pose and the arguments of every call."""

    def __init__(self, env: GCCPDeciderEnv, inner=None) -> None:
        self.env = env
        self.inner = inner or ScriptedPlanner(env.config)
        self.poses: list[np.ndarray] = []
        self.goals: list[np.ndarray] = []
        self.masks: list[np.ndarray] = []

    def __call__(self, obs, mask):
        self.poses.append(self.env.world.ego.as_array()[:3])
        self.goals.append(obs["goal"].copy())
        self.masks.append(np.asarray(mask).copy())
        return self.inner(obs, mask)


def make(seed=0, **kwargs):
    env = gym.make("GCCPDecider-v0", **{"spawn_probability": 0.15, "task": "straight", **kwargs}).unwrapped
    obs, _ = env.reset(seed=seed)
    return env, obs


def test_observation_holds_candidates_and_task_goal_in_the_ego_frame():
    env, obs = make()
    world = env.world
    np.testing.assert_allclose(obs["subgoals"], env.observer.to_ego(world.subgoal_candidates()))
    np.testing.assert_allclose(obs["task_goal"], env.observer.to_ego(world.task_goal))
    ego = world.ego
    goal_xy = ego_frame(world.task_goal[:2], ego.x, ego.y, ego.heading)
    np.testing.assert_allclose(obs["task_goal"][:2], goal_xy, atol=1e-3)
    assert obs["subgoals"].shape == (12, 3)
    assert np.all(obs["subgoals"][:, 0] > -2.5 - 1e-3)  # candidates lie ahead (half a spacing back at most)


def test_a_step_runs_the_planner_for_the_decision_period():
    env, _ = make(seed=1)
    planner = RecordingPlanner(env)
    env.planner = planner
    chosen = env.world.subgoal_candidates()[5].copy()
    assert env.subgoal is None
    _, _, terminated, truncated, info = env.step(5)
    assert not terminated and not truncated
    assert env.world.steps == 10
    assert len(planner.poses) == 10
    assert info["future"].shape == (6, 10, 3) and info["future"].dtype == np.float32
    assert info["future_mask"].shape == (6, 10) and info["future_mask"].dtype == bool
    assert isinstance(info["planner_return"], float)
    np.testing.assert_array_equal(env.subgoal, chosen)
    # The planner saw the chosen subgoal, from where the ego was at each step, and a 6-action mask.
    first = planner.poses[0]
    np.testing.assert_allclose(planner.goals[0][:2], ego_frame(chosen[:2], *first), atol=1e-3)
    assert all(mask.shape == (6,) and mask.any() for mask in planner.masks)


def test_future_of_the_ego_is_what_it_drove():
    env, _ = make(seed=2)
    planner = RecordingPlanner(env)
    env.planner = planner
    start = env.world.ego.as_array()[:3]
    _, _, terminated, _, info = env.step(3)
    assert not terminated
    driven = np.array([*planner.poses[1:], env.world.ego.as_array()[:3]])  # poses after steps 1..10
    future, present = info["future"], info["future_mask"]
    assert present[0].all()
    np.testing.assert_allclose(future[0, :, :2], ego_frame(driven[:, :2], *start), atol=1e-4)
    np.testing.assert_allclose(np.cos(future[0, :, 2]), np.cos(driven[:, 2] - start[2]), atol=1e-5)
    np.testing.assert_allclose(np.sin(future[0, :, 2]), np.sin(driven[:, 2] - start[2]), atol=1e-5)
    assert np.all(np.diff(future[0, :, 0]) >= -1e-6)  # it drove forward


def test_future_of_the_neighbours_matches_the_world_history():
    env, obs = make(seed=3, spawn_probability=0.25)
    world = env.world
    start = world.ego.as_array()[:3]
    slots = world.neighbours()
    uids = world.traffic.uid[slots].copy()
    assert len(slots) >= 1
    # The rows of the future follow the rows of the observation the decision was taken on.
    np.testing.assert_array_equal(obs["history_mask"][1 : 1 + len(slots), -1], 1.0)
    _, _, _, _, info = env.step(2)
    future, present = info["future"], info["future_mask"]
    poses, valid = world.poses_between(1, 10, slots, uids)
    np.testing.assert_array_equal(present[1 : 1 + len(slots)], valid.T)
    for row in range(len(slots)):
        ok = valid[:, row]
        np.testing.assert_allclose(future[1 + row, ok, :2], ego_frame(poses[ok, row, :2], *start), atol=1e-4)
    np.testing.assert_array_equal(present[1 + len(slots) :], False)
    np.testing.assert_array_equal(future[~present], 0.0)


def test_an_option_ends_early_with_the_episode():
    env, _ = make(seed=0, spawn_probability=0.0)
    place_ego(env.world, 6.0, -31.0, -np.pi / 2, 8.0)  # 2 m before the straight exit
    _, _, terminated, _, info = env.step(3)
    assert terminated and info["is_success"]
    steps = env.world.steps
    assert 1 <= steps < 10
    np.testing.assert_array_equal(info["future_mask"][0], [True] * steps + [False] * (10 - steps))


def test_no_mask_function_allows_everything():
    env, _ = make()
    np.testing.assert_array_equal(env.action_masks(), np.ones(12, bool))


def test_mask_function_result_is_used():
    env, obs = make()
    wanted = np.zeros(12, bool)
    wanted[[2, 7]] = True
    seen = []
    env.set_mask_fn(lambda o: (seen.append(o), wanted)[1])
    np.testing.assert_array_equal(env.action_masks(), wanted)
    assert seen[0] is env._last_obs
    np.testing.assert_array_equal(seen[0]["subgoals"], obs["subgoals"])
    env.set_mask_fn(None)
    assert env.action_masks().all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_all_false_mask_allows_only_the_nearest_candidate(seed):
    env, _ = make(seed=seed, mask_fn=lambda o: np.zeros(12, bool))
    for _ in range(2):
        mask = env.action_masks()
        assert mask.sum() == 1
        nearest = np.argmin(np.hypot(*env._last_obs["subgoals"][:, :2].T))
        assert mask[nearest]
        _, _, terminated, truncated, _ = env.step(int(np.flatnonzero(mask)[0]))
        if terminated or truncated:
            break
    np.testing.assert_array_equal(env._masked, np.ones(12, bool))  # drawn as all masked


def test_mask_function_given_at_construction():
    env = GCCPDeciderEnv(spawn_probability=0.0, mask_fn=lambda o: np.arange(12) < 3)
    env.reset(seed=0)
    np.testing.assert_array_equal(env.action_masks(), np.arange(12) < 3)


def test_custom_planner_drives():
    env, _ = make(seed=0, spawn_probability=0.0)
    env.planner = lambda obs, mask: int(EgoAction.SLOW_DOWN)
    for _ in range(3):
        env.step(0)
    assert env.world.ego.speed == 0.0
    assert env.world.steps == 30


def test_future_survives_a_long_decision_period():
    env, _ = make(seed=0, spawn_probability=0.0, decision_period=20, history_length=2, prediction_horizon=5)
    _, _, terminated, truncated, info = env.step(3)
    assert not terminated and not truncated and env.world.steps == 20
    assert info["future"].shape == (6, 5, 3)
    np.testing.assert_array_equal(info["future_mask"][0], np.ones(5, bool))


def test_planner_step_callback_follows_every_step_of_an_option():
    env, _ = make(seed=1)
    seen: list[int] = []
    env.set_planner_step_callback(lambda e: seen.append(e.world.steps))
    env.step(3)
    assert seen == list(range(1, 11))
    env.set_planner_step_callback(None)
    env.step(3)
    assert len(seen) == 10


@pytest.mark.parametrize(("needs_travel", "r_subgoal"), [(False, 0.5), (True, 0.0)])
def test_holding_on_the_candidate_under_the_ego_is_paid_only_without_needs_travel(needs_travel, r_subgoal):
    env, obs = make(seed=2, spawn_probability=0.0, r_subgoal_needs_travel=needs_travel)
    for _ in range(4):  # hold until the ego stands on its nearest candidate
        nearest = int(np.argmin(np.hypot(*obs["subgoals"][:, :2].T)))
        obs, _, _, _, info = env.step(nearest)
    assert env.world.ego.speed == 0.0
    nearest = int(np.argmin(np.hypot(*obs["subgoals"][:, :2].T)))
    assert np.hypot(*obs["subgoals"][nearest, :2]) <= env.config.subgoal_reach_radius
    *_, info = env.step(nearest)
    assert info["subgoal_reached"]
    assert info["reward_terms"]["r_subgoal"] == r_subgoal


@pytest.mark.parametrize("brakes", [False, True])
def test_fallback_brakes_when_no_candidate_passes(brakes):
    env, _ = make(seed=0, spawn_probability=0.0, fallback_brakes=brakes, mask_fn=lambda o: np.zeros(12, bool))
    planner = RecordingPlanner(env, inner=lambda obs, mask: int(EgoAction.KEEP_DIRECTION))
    env.planner = planner
    start = env.world.ego.speed
    assert start > 1.0
    env.step(int(np.flatnonzero(env.action_masks())[0]))
    if brakes:  # 'slow down' at the world's deceleration until the ego stands; the planner only then
        expected = max(start - env.config.deceleration * DT * env.config.decision_period, 0.0)
        assert env.world.ego.speed == pytest.approx(expected)
        assert len(planner.poses) == 0 if expected > 0 else len(planner.poses) < 10
    else:
        assert env.world.ego.speed >= start
        assert len(planner.poses) == 10


def test_fallback_brakes_leave_the_planner_alone_when_a_candidate_passes():
    env, _ = make(seed=0, spawn_probability=0.0, fallback_brakes=True, mask_fn=lambda o: np.arange(12) < 3)
    planner = RecordingPlanner(env, inner=lambda obs, mask: int(EgoAction.KEEP_DIRECTION))
    env.planner = planner
    start = env.world.ego.speed
    env.step(int(np.flatnonzero(env.action_masks())[0]))
    assert len(planner.poses) == 10 and env.world.ego.speed >= start


@pytest.mark.parametrize("task", ["left", "straight"])
def test_fallback_keys_never_act_without_a_mask_function(task):
    keys = {"fallback_brakes": True, "fallback_go_on": True}
    runs = []
    for world in ({}, keys):  # w/o GCCP: every candidate passes, so neither fallback is ever reached
        env, _ = make(seed=3, task=task, **world)
        trace = []
        for action in (3, 3, 0, 5, 3, 3, 3, 3):
            assert env.action_masks().all()
            _, reward, terminated, truncated, _ = env.step(action)
            trace.append((*env.world.ego.as_array(), reward))
            if terminated or truncated:
                break
        runs.append(trace)
    np.testing.assert_array_equal(runs[0], runs[1])


class NothingPasses:
    """A mask function that allows no candidate and predicts the latest collision under candidate 7."""

    def __call__(self, obs):
        return np.zeros(12, bool)

    def latest_collision(self, obs):
        return np.arange(12) == 7


@pytest.mark.parametrize("go_on", [False, True])
@pytest.mark.parametrize(
    "y, speed, inside",
    [(20.0, 6.0, False), (5.0, 6.0, True), (5.0, 0.5, True)],
    ids=["before", "driving", "standing"],
)
def test_fallback_goes_on_only_while_the_ego_drives_inside_the_junction(go_on, y, speed, inside):
    env, _ = make(seed=0, spawn_probability=0.0, fallback_go_on=go_on, mask_fn=NothingPasses())
    place_ego(env.world, 6.0, y, -np.pi / 2, speed)  # on the straight path from the south arm
    env._last_obs = env._observe()
    assert env.world.ego_in_junction() == inside
    nearest = int(np.argmin(np.hypot(*env._last_obs["subgoals"][:, :2].T)))
    expected = 7 if go_on and inside and speed >= 1.0 else nearest
    assert np.flatnonzero(env.action_masks()).tolist() == [expected]
    np.testing.assert_array_equal(env._masked, np.ones(12, bool))  # drawn as all masked either way


@pytest.mark.parametrize("y, brakes", [(20.0, True), (5.0, False)], ids=["before", "inside"])
def test_fallback_brakes_before_the_junction_and_goes_on_inside(y, brakes):
    keys = {"fallback_brakes": True, "fallback_go_on": True}
    env, _ = make(seed=0, spawn_probability=0.0, mask_fn=NothingPasses(), **keys)
    planner = RecordingPlanner(env, inner=lambda obs, mask: int(EgoAction.KEEP_DIRECTION))
    env.planner = planner
    place_ego(env.world, 6.0, y, -np.pi / 2, 6.0)
    env._last_obs = env._observe()
    env.step(int(np.flatnonzero(env.action_masks())[0]))
    if brakes:
        assert env.world.ego.speed < 6.0 and len(planner.poses) < 10
    else:
        assert env.world.ego.speed >= 6.0 and len(planner.poses) == 10


@pytest.mark.parametrize("skips", [False, True])
def test_fallback_go_on_skips_hold_leaves_the_nearest_candidate_out_of_the_ranking(skips):
    class RanksTheHold(NothingPasses):
        """Ranks the nearest candidate latest unless it is left out."""

        def latest_collision(self, obs, exclude=None):
            nearest = np.arange(12) == int(np.argmin(np.hypot(*obs["subgoals"][:, :2].T)))
            return nearest if exclude is None else ~exclude & (np.arange(12) == 7)

    keys = {"fallback_go_on": True, "fallback_go_on_skips_hold": skips}
    env, _ = make(seed=0, spawn_probability=0.0, mask_fn=RanksTheHold(), **keys)
    place_ego(env.world, 6.0, 5.0, -np.pi / 2, 6.0)  # driving inside the junction
    env._last_obs = env._observe()
    nearest = int(np.argmin(np.hypot(*env._last_obs["subgoals"][:, :2].T)))
    assert nearest != 7
    assert np.flatnonzero(env.action_masks()).tolist() == [7 if skips else nearest]


def test_fallback_go_on_holds_with_a_mask_function_that_cannot_rank():
    env, _ = make(seed=0, spawn_probability=0.0, fallback_go_on=True, mask_fn=lambda o: np.zeros(12, bool))
    place_ego(env.world, 6.0, 5.0, -np.pi / 2, 6.0)
    env._last_obs = env._observe()
    nearest = int(np.argmin(np.hypot(*env._last_obs["subgoals"][:, :2].T)))
    assert np.flatnonzero(env.action_masks()).tolist() == [nearest]


def test_observe_mask_shows_the_verdict_the_action_mask_uses():
    verdict = np.arange(12) % 3 == 0
    env, obs = make(seed=0, observe_mask=True, mask_fn=lambda o: verdict)
    assert env.observation_space["subgoal_allowed"].shape == (12,)
    assert env.observation_space.contains(obs)
    np.testing.assert_array_equal(obs["subgoal_allowed"], verdict.astype(np.float32))
    np.testing.assert_array_equal(env.action_masks(), verdict)
    obs, *_ = env.step(0)
    np.testing.assert_array_equal(obs["subgoal_allowed"], verdict.astype(np.float32))


def test_observe_mask_shows_a_closed_check_before_the_fallback():
    env, obs = make(seed=0, observe_mask=True, mask_fn=lambda o: np.zeros(12, bool))
    assert not obs["subgoal_allowed"].any()
    assert env.action_masks().sum() == 1  # the env still falls back to the nearest candidate


def test_without_observe_mask_the_observation_has_no_verdict():
    env, obs = make(seed=0, mask_fn=lambda o: np.ones(12, bool))
    assert "subgoal_allowed" not in obs and "subgoal_allowed" not in env.observation_space.spaces


@pytest.mark.parametrize("drives", [False, True])
def test_standing_turn_drives_moves_a_standing_ego_whose_planner_turns(drives):
    env, _ = make(seed=0, spawn_probability=0.0, standing_turn_drives=drives)
    planner = RecordingPlanner(env, inner=lambda obs, mask: int(EgoAction.QUICKLY_TURN_LEFT))
    env.planner = planner
    place_ego(env.world, 6.0, 20.0, -np.pi / 2, 0.0)  # standing on the south arm
    env._last_obs = env._observe()
    farthest = int(np.argmax(np.hypot(*env._last_obs["subgoals"][:, :2].T)))
    env.step(farthest)
    assert len(planner.poses) == 10
    if drives:  # 'keep direction' while it stands, then the planner's turns hold the speed it gained
        assert env.world.ego.speed == pytest.approx(env.config.acceleration * DT)
    else:
        assert env.world.ego.speed == 0.0
        np.testing.assert_allclose(env.world.ego.as_array()[:2], (6.0, 20.0))


def test_standing_turn_drives_leaves_a_standing_ego_on_its_subgoal():
    env, _ = make(seed=0, spawn_probability=0.0, standing_turn_drives=True)
    env.planner = lambda obs, mask: int(EgoAction.QUICKLY_TURN_LEFT)
    place_ego(env.world, 6.0, 20.0, -np.pi / 2, 0.0)
    env._last_obs = env._observe()
    nearest = int(np.argmin(np.hypot(*env._last_obs["subgoals"][:, :2].T)))
    assert np.hypot(*env._last_obs["subgoals"][nearest, :2]) <= env.config.subgoal_reach_radius
    env.step(nearest)
    assert env.world.ego.speed == 0.0
