"""The SMARTS simulator (``simulator: smarts``): scenarios, episodes read as ours, fixes, cleanup."""

from __future__ import annotations

import types
from importlib.util import find_spec
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from helpers import sumo_children

import gccp_envs.smarts
from gccp_envs.config import TASKS, IntersectionConfig
from gccp_envs.scenario import layout_for
from gccp_envs.smarts.fixes import (
    MOVE_TO_XY_WARNING,
    apply_fixes,
    fix_numpy_product,
    fix_via_sort,
    product_needs_fix,
    via_sort_needs_fix,
)
from gccp_envs.smarts.scenario import MAP_FILE, MISSIONS_FILE, scenario_folder, traffic_specs
from gccp_envs.sumo.network import CACHE_VARIABLE, network_file
from gccp_envs.world import START_CLEARANCE, vehicle_sizes

needs_smarts = pytest.mark.skipif(
    find_spec("smarts") is None,
    reason="SMARTS is not installed (the smarts extra: pip install -e '.[smarts]')",
)

SMARTS = {"simulator": "smarts"}
OUTCOMES = ("is_success", "crashed", "offroad", "wrong_exit", "timeout")


def departures(route_file: str) -> list[tuple[str, str]]:
    """(route, departure time) of every vehicle of a SUMO route file."""
    import xml.etree.ElementTree as ET

    return [(v.get("route", ""), v.get("depart", "")) for v in ET.parse(route_file).getroot().iter("vehicle")]


def test_choosing_smarts_without_the_extra_fails_in_one_line_naming_it(monkeypatch):
    monkeypatch.setattr(gccp_envs.smarts, "find_spec", lambda name: None if name == "smarts" else object())
    with pytest.raises(
        ValueError, match=r"^simulator 'smarts' needs the smarts extra \(smarts not installed\)"
    ):
        IntersectionConfig(simulator="smarts")
    with pytest.raises(ValueError, match="unknown simulator 'carla'"):
        IntersectionConfig(simulator="carla")


@needs_smarts
def test_the_scenarios_build_from_scratch_with_flow_k_the_same_every_build(tmp_path, monkeypatch):
    config = IntersectionConfig(smarts_flows=2)
    layout = layout_for(config)
    built = {}
    for cache in ("first", "second"):
        monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / cache / "sumo"))
        for task in TASKS:
            folder = scenario_folder(config, layout, task)
            assert (folder / MAP_FILE).read_bytes() == network_file(layout).read_bytes()
            assert (folder / MISSIONS_FILE).is_file()
        built[cache] = [departures(traffic_specs(config, layout, k)[0]) for k in range(2)]
        assert not list((tmp_path / cache).rglob(".build-*"))  # no half-built folder is left
    flow0, flow1 = built["first"]
    assert len(flow0) > 10 and flow0 != flow1  # two different flows ...
    assert built["second"] == built["first"]  # ... each the same at every build


def neighbours(world) -> list[tuple[str, tuple[float, ...], float]]:
    """Id, position and speed of every SUMO vehicle the ego sees."""
    states = world.observation.neighborhood_vehicle_states or ()
    return sorted((s.id, tuple(np.round(s.position, 6)), round(float(s.speed), 6)) for s in states)


def left_turn_after_20_steps() -> list[tuple[str, tuple[float, ...], float]]:
    """The SUMO vehicles the ego sees after 20 steps of a left turn on flow 0 or 1 (generator seed 4)."""
    from gccp_envs.smarts.world import SmartsWorld

    world = SmartsWorld(IntersectionConfig(task="left", smarts_flows=2))
    try:
        world.reset(np.random.default_rng(4))
        for _ in range(20):
            world.step(0)
        return neighbours(world)
    finally:
        world.close()


@needs_smarts
def test_an_episode_on_a_scenario_built_on_first_use_is_the_episode_of_a_built_one(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / "sumo"))  # nothing built yet
    seen = [left_turn_after_20_steps() for _ in ("building", "built")]
    assert len(seen[0]) > 0
    assert seen[0] == seen[1]  # the build drew nothing from the random state SUMO's seed comes from


@needs_smarts
def test_a_sumo_start_that_smarts_retries_runs_the_same_flow(monkeypatch):
    # On a busy machine SUMO can take over TraCI's 5 s to start; SMARTS then starts it again.
    from smarts.core.utils.sumo_utils import TraciConn, traci

    connect = TraciConn.connect
    failed = []

    def too_late_once(self, *args, **kwargs):
        if not failed:
            failed.append(self)
            raise traci.exceptions.FatalTraCIError("could not connect in time")
        return connect(self, *args, **kwargs)

    seen = [left_turn_after_20_steps()]
    monkeypatch.setattr(TraciConn, "connect", too_late_once)
    seen.append(left_turn_after_20_steps())
    assert len(failed) == 1 and len(seen[0]) > 0
    assert seen[0] == seen[1]
    assert sumo_children() == []


@needs_smarts
def test_the_six_actions_move_the_ego_as_in_our_world():
    from gccp_envs.smarts.world import SmartsWorld

    world = SmartsWorld(IntersectionConfig(task="right", spawn_probability=0.0))
    try:
        world.reset(np.random.default_rng(0))
        for action in (1, 1, 2, 3, 4, 5, 0, 4):
            expected = world.motion.step(world.ego, action)
            world.step(action)
            assert world.ego.as_array() == pytest.approx(expected.as_array(), abs=1e-6)
    finally:
        world.close()


@needs_smarts
def test_an_episode_steps_and_ends_with_exactly_one_outcome():
    env = gym.make("GCCPPlanner-v0", task="straight", **SMARTS)
    try:
        env.reset(seed=3)
        env.action_space.seed(3)
        for _ in range(400):
            mask = env.unwrapped.action_masks()  # type: ignore[attr-defined]
            _, _, terminated, truncated, info = env.step(env.action_space.sample(mask.astype(np.int8)))
            if terminated or truncated:
                break
        assert terminated or truncated
        assert sum(bool(info[key]) for key in OUTCOMES) == 1
    finally:
        env.close()


@needs_smarts
@pytest.mark.parametrize("env_id", ["GCCPPlanner-v0", "GCCPDecider-v0", "GCCPFlat-v0"])
def test_the_envs_have_the_builtin_spaces_and_info_keys(env_id):
    envs = [gym.make(env_id, task="left"), gym.make(env_id, task="left", **SMARTS)]
    try:
        steps = []
        for env in envs:
            obs, _ = env.reset(seed=0)
            assert env.observation_space.contains(obs)
            steps.append(env.step(env.action_space.sample())[-1])
        assert envs[0].observation_space == envs[1].observation_space
        assert steps[0].keys() == steps[1].keys()
    finally:
        for env in envs:
            env.close()


@needs_smarts
def test_the_observation_of_a_standing_ego_and_a_known_neighbour_is_in_our_frames_and_sizes():
    env = gym.make("GCCPPlanner-v0", task="left", **SMARTS)
    try:
        env.reset(seed=5)
        world = env.unwrapped.world  # type: ignore[attr-defined]
        for _ in range(25):  # brake to a stand
            obs, _, terminated, truncated, _ = env.step(0)
            assert not (terminated or truncated)
        assert world.ego.speed == 0.0
        # The ego stands at the origin of its frame, facing along x, in its last two history vectors.
        assert obs["history"][0, -1, :8] == pytest.approx(np.zeros(8), abs=1e-4)
        # The nearest vehicle SMARTS reports is the first neighbour, where SMARTS says it is.
        ego = world.observation.ego_vehicle_state
        reported = world.observation.neighborhood_vehicle_states
        assert reported, "the flow of seed 5 has a vehicle near the ego"
        position = np.asarray(ego.position[:2], float)
        nearest = min(reported, key=lambda v: np.hypot(*(np.asarray(v.position[:2]) - position)))
        offset = np.asarray(nearest.position[:2], float) - position
        heading = float(ego.heading)
        forward, right = (-np.sin(heading), np.cos(heading)), (np.cos(heading), np.sin(heading))
        expected = (
            np.dot(offset, forward),
            np.dot(offset, right),
            (float(heading) - float(nearest.heading) + np.pi) % (2 * np.pi) - np.pi,
            nearest.speed,
        )
        assert obs["history"][1, -1, 4:8] == pytest.approx(expected, abs=1e-3)
        assert obs["history_mask"][1, -1] == 1.0
        # The sizes the GCCP check gives SMARTS's vehicles are the ones SMARTS reports.
        ego_size, traffic_size = vehicle_sizes(IntersectionConfig(**SMARTS))
        assert (ego.bounding_box.length, ego.bounding_box.width) == pytest.approx(ego_size)
        for vehicle in reported:
            assert (vehicle.bounding_box.length, vehicle.bounding_box.width) == pytest.approx(traffic_size)
    finally:
        env.close()


class _BrokenSort:
    def __call__(self, points):
        points.sort(key=lambda dist, _: dist)
        return points


class _GoodSort:
    def __call__(self, points):
        points.sort(key=lambda point: point[0])
        return points


def test_the_via_sort_fix_is_applied_only_while_needed():
    assert via_sort_needs_fix(_BrokenSort.__call__) and not via_sort_needs_fix(_GoodSort.__call__)
    with pytest.raises(TypeError):
        _BrokenSort()([(2.0, "b"), (1.0, "a")])
    assert fix_via_sort(_BrokenSort) and not fix_via_sort(_BrokenSort)
    assert _BrokenSort()([(2.0, "b"), (1.0, "a")]) == [(1.0, "a"), (2.0, "b")]
    assert not fix_via_sort(_GoodSort)


def test_the_numpy_product_fix_is_applied_only_while_needed():
    def largest(shapes):
        return max(shapes, key=lambda shape: np.product(shape))  # type: ignore[attr-defined]

    module = types.ModuleType("recorder")
    module.np = np  # type: ignore[attr-defined]
    module.largest = largest  # type: ignore[attr-defined]
    unused = types.ModuleType("unused")
    unused.np = np  # type: ignore[attr-defined]
    assert product_needs_fix(module) and not product_needs_fix(unused)
    assert fix_numpy_product(module) and not fix_numpy_product(module) and not fix_numpy_product(unused)
    assert module.np.product((2, 3)) == 6 and not hasattr(np, "product")  # numpy itself is untouched


@needs_smarts
def test_the_installed_smarts_is_fixed_once():
    from smarts.core.sensor import ViaSensor

    apply_fixes()
    assert not via_sort_needs_fix(ViaSensor.__call__)
    assert apply_fixes() == {"via_sort": False, "numpy_product": False}


@needs_smarts
def test_only_the_move_to_xy_warning_is_silenced():
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        apply_fixes()
        warnings.warn(f"{MOVE_TO_XY_WARNING}, use laneIndex instead.", UserWarning, stacklevel=1)
        warnings.warn("another warning", UserWarning, stacklevel=1)
    assert [str(w.message) for w in caught] == ["another warning"]


def within_clearance(world) -> set[str]:
    """Ids of the vehicles SMARTS reports within the start clearance of the ego."""
    observation = world.observation
    ego = np.asarray(observation.ego_vehicle_state.position[:2], float)
    return {
        state.id
        for state in observation.neighborhood_vehicle_states or ()
        if np.hypot(*(np.asarray(state.position[:2], float) - ego)) < START_CLEARANCE
    }


@needs_smarts
def test_the_start_is_cleared_of_sumo_vehicles_within_15_m_as_in_our_world():
    # Flow of seed 1002, left turn: a car passes the ego on the next lane as it enters.
    kept = gym.make("GCCPDecider-v0", task="left", smarts_clear_start=False, **SMARTS)
    cleared = gym.make("GCCPDecider-v0", task="left", **SMARTS)
    try:
        kept.reset(seed=1002)
        near = within_clearance(kept.unwrapped.world)  # type: ignore[attr-defined]
        assert near, "the flow of seed 1002 has a car within 15 m of the entering ego"
        world = cleared.unwrapped.world  # type: ignore[attr-defined]
        cleared.reset(seed=1002)
        table = world.traffic
        offsets = table.pose[table.indices, :2] - [world.ego.x, world.ego.y]
        assert np.all(np.hypot(*offsets.T) >= START_CLEARANCE)
        cleared.step(0)  # one decision: SMARTS no longer reports them, and nothing fails
        assert near.isdisjoint(state.id for state in world.observation.neighborhood_vehicle_states or ())
    finally:
        kept.close()
        cleared.close()


@needs_smarts
def test_no_sumo_or_temporary_folder_is_left_after_close():
    env = gym.make("GCCPPlanner-v0", task="left", **SMARTS)
    env.reset(seed=0)
    env.step(1)
    log_dir = Path(env.unwrapped.world._log_dir)  # type: ignore[attr-defined]
    assert sumo_children() and log_dir.is_dir()
    env.close()
    assert sumo_children() == [] and not log_dir.exists()


@needs_smarts
def test_no_sumo_or_temporary_folder_is_left_after_an_exception_inside_step(monkeypatch):
    env = gym.make("GCCPPlanner-v0", task="left", **SMARTS)
    env.reset(seed=0)
    world = env.unwrapped.world  # type: ignore[attr-defined]
    log_dir = Path(world._log_dir)

    def fail(actions):
        raise RuntimeError("inside SMARTS's step")

    monkeypatch.setattr(world._smarts, "step", fail)
    with pytest.raises(RuntimeError, match="inside SMARTS's step"):
        env.step(1)
    assert sumo_children() == [] and not log_dir.exists()
    env.reset(seed=1)  # the world starts a new SMARTS
    env.close()


@needs_smarts
@pytest.mark.slow
def test_subproc_vec_env_steps_smarts_worlds():
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = SubprocVecEnv([lambda: gym.make("gccp_envs:GCCPPlanner-v0", **SMARTS) for _ in range(2)])
    try:
        venv.seed(0)
        venv.reset()
        for _ in range(5):
            venv.step(np.ones(2, np.int64))
    finally:
        venv.close()


@needs_smarts
def test_the_bev_is_smarts_grid_map_and_agrees_with_our_layout():
    env = gym.make("GCCPPlanner-v0", task="left", **SMARTS)
    try:
        obs, _ = env.reset(seed=1)
        world = env.unwrapped.world  # type: ignore[attr-defined]
        observer = env.unwrapped.observer  # type: ignore[attr-defined]
        agreement, heading = [], world.ego.heading
        for step in range(30):
            grid = world.observation.drivable_area_grid_map.data[..., 0]
            assert np.array_equal(obs["bev"][0], (grid > 0).astype(np.uint8))
            world.sensed_bev = lambda: None  # the same pose drawn from our layout
            agreement.append(np.mean(observer.observe()["bev"] == obs["bev"]))
            del world.sensed_bev
            turn = step >= 10 and env.unwrapped.action_masks()[2]  # type: ignore[attr-defined]
            obs, _, terminated, truncated, _ = env.step(2 if turn else 1)  # on, then left where it may
            assert not (terminated or truncated)
        assert abs(world.ego.heading - heading) > 0.3  # the view turned with the ego
        assert min(agreement) > 0.97
        assert 0.1 < obs["bev"].mean() < 0.9
    finally:
        env.close()


def drive_recording_routes(task: str, routes: str) -> list[tuple[list[int], list[int], float]]:
    """Drive a task on an empty road with the scripted planner; every step's routes, our rule's routes and
    the largest median offset of SMARTS's waypoint paths from the task's lane paths they run on [m]."""
    from smarts.core.coordinates import Pose

    from gccp_envs.scripted import ScriptedPlanner
    from gccp_envs.smarts.world import ROUTE_LOOKAHEAD
    from gccp_envs.sumo.network import to_sumo
    from gccp_envs.world import IntersectionWorld

    env = gym.make("GCCPFlat-v0", task=task, smarts_routes=routes, spawn_probability=0.0, **SMARTS)
    steps = []
    try:
        obs, _ = env.reset(seed=4)
        world = env.unwrapped.world  # type: ignore[attr-defined]
        planner = ScriptedPlanner(world.config)
        paths = np.array(world._task_paths)
        for _ in range(200):
            state = world.observation.ego_vehicle_state
            waypoint_paths = world._simulation().road_map.waypoint_paths(
                Pose.from_center(state.position, state.heading), ROUTE_LOOKAHEAD, route=world._mission_route
            )
            offsets = [0.0]
            for waypoints in waypoint_paths:
                points = to_sumo(np.array([w.pos for w in waypoints], float))
                _, d = world.layout.paths.project(paths[:, None], points[None])
                nearest = int(np.argmin(np.abs(d).mean(axis=1)))
                if np.abs(d[nearest]).mean() < world.config.lane_width / 2.0:  # a path it runs on
                    offsets.append(float(np.median(np.abs(d[nearest]))))
            routes_now = list(world.ego_routes()[0])
            ours = list(IntersectionWorld._find_routes(world)[0])
            steps.append((routes_now, ours, max(offsets)))
            obs, _, terminated, truncated, info = env.step(planner(obs, env.unwrapped.action_masks()))  # type: ignore[attr-defined]
            if terminated or truncated:
                assert info["is_success"]
                return steps
        raise AssertionError("the scripted planner did not finish the task")
    finally:
        env.close()


@needs_smarts
def test_routes_from_smarts_waypoint_paths_lie_on_our_lane_paths():
    for task in ("left", "straight"):
        steps = drive_recording_routes(task, "waypoints")
        # SMARTS's waypoint paths along the mission run on our lane paths (its map is our layout).
        assert max(offset for _, _, offset in steps) < 0.05
        # Before the junction SMARTS offers the lanes our rule does.
        assert steps[0][0] == steps[0][1]
        if task == "left":  # one lane turns left: the same single route all the way
            assert all(routes == ours == steps[0][0] for routes, ours, _ in steps)
        else:  # in the junction SMARTS keeps both straight lanes, our rule only the ego's
            assert any(len(routes) == 2 and len(ours) == 1 for routes, ours, _ in steps)
    # With the layout's routes (the default) the world keeps our rule.
    assert all(routes == ours for routes, ours, _ in drive_recording_routes("straight", "layout"))


@needs_smarts
def test_without_the_grid_map_the_bev_is_drawn_from_our_layout():
    env = gym.make("GCCPPlanner-v0", task="left", smarts_grid_map=False, **SMARTS)
    try:
        obs, _ = env.reset(seed=1)
        world = env.unwrapped.world  # type: ignore[attr-defined]
        assert world.observation.drivable_area_grid_map is None
        assert world.sensed_bev() is None
        assert 0.1 < obs["bev"].mean() < 0.9
    finally:
        env.close()
