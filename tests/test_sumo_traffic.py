"""SUMO traffic (``traffic: sumo``): SUMO's drivers see the ego, flows are seeded, nothing is left behind."""

from __future__ import annotations

import subprocess
import sys
import tempfile

import gymnasium as gym
import libsumo
import numpy as np
import pytest
from helpers import sumo_children

from gccp_envs.config import IntersectionConfig
from gccp_envs.scenario import layout_for
from gccp_envs.sumo import simulation
from gccp_envs.sumo.network import heading_to_sumo_angle, to_sumo
from gccp_envs.sumo.traffic import EGO_ID, SumoTraffic
from gccp_envs.traffic import Obstacle
from sb3_gccp.cli import main

SUMO = {"traffic": "sumo"}


@pytest.fixture(params=["libsumo", "traci"])
def interface(request, monkeypatch):
    """Run SUMO in this process (libsumo) or as a process over TraCI."""
    if request.param == "traci":
        monkeypatch.setattr(simulation, "libsumo_free", lambda: False)
    return request.param


def priority_road_car_beside(ego: Obstacle | None) -> tuple[bool, float, float, bool]:
    """Drive one car of the priority road (westwards at y = -2) for 20 s beside ``ego`` (None: none).

    :return: whether it crashed, the lowest x its centre reached, its last speed, and whether SUMO had
        the ego on one of its lanes at every step
    """
    config = IntersectionConfig(spawn_probability=0.0, traffic="sumo")
    layout = layout_for(config)
    traffic = SumoTraffic(layout, config, np.random.default_rng(0))
    traffic.spawn(layout.paths_from(3, lane=0, turn="straight")[0], 0.0, speed=7.0)
    lowest_x, crashed, on_lane = np.inf, False, True
    for _ in range(200):
        traffic.step(ego)
        if ego is not None:
            on_lane &= traffic.sumo.api.vehicle.getLaneID(EGO_ID) != ""
        crashed |= traffic.detect_crashes(ego)
        (slot,) = traffic.indices
        lowest_x = min(lowest_x, traffic.pose[slot, 0])
    traffic.close()
    return crashed, lowest_x, float(traffic.speed[slot]), on_lane


def ego_going_north(x: float) -> Obstacle:
    """An ego standing at (x, -2) inside the junction, heading north on the south arm's straight movement
    (its lanes at x = 2 and 6), in the path of the priority road's car above."""
    layout = layout_for(IntersectionConfig())
    return Obstacle(x, -2.0, -np.pi / 2, 0.0, path=layout.paths_from(0, lane=0, turn="straight")[0])


def test_an_npc_brakes_for_an_ego_standing_in_its_path():
    ego = ego_going_north(2.0)  # on its lane where the two roads cross
    crashed, lowest_x, speed, _ = priority_road_car_beside(ego)
    assert not crashed and speed < 0.1
    assert lowest_x - 2.5 > ego.x + 1.0  # its front stopped short of the ego's side
    assert priority_road_car_beside(None)[1] < -20.0  # without the ego it drives through


def test_an_npc_brakes_for_an_ego_standing_off_its_lanes_inside_the_junction():
    # 3.5 m left of its movement's lanes (a wide turn can leave it there): placed exactly, SUMO would
    # keep it on no lane, and its drivers would not see it
    ego = ego_going_north(-1.5)
    crashed, lowest_x, speed, on_lane = priority_road_car_beside(ego)
    assert on_lane
    assert not crashed and speed < 0.1
    assert lowest_x - 2.5 > ego.x + 1.0


def test_the_egos_sumo_position_follows_our_kinematics_each_step():
    env = gym.make("GCCPPlanner-v0", traffic="sumo", spawn_probability=0.2)
    env.reset(seed=1)
    world = env.unwrapped.world
    api = world.traffic.sumo.api
    rng = np.random.default_rng(0)
    for _ in range(40):
        action = rng.choice(np.flatnonzero(env.unwrapped.action_masks()))
        _, _, terminated, truncated, _ = env.step(action)
        ego = world.ego
        front = np.array([ego.x, ego.y]) + 2.5 * np.array([np.cos(ego.heading), np.sin(ego.heading)])
        # within half a lane of its movement's lanes, as here, the ego is placed exactly
        np.testing.assert_allclose(api.vehicle.getPosition(EGO_ID), to_sumo(front), atol=1e-6)
        angle = float(heading_to_sumo_angle(ego.heading))
        assert api.vehicle.getAngle(EGO_ID) == pytest.approx(angle, abs=1e-6)
        if terminated or truncated:
            break
    env.close()


def flow(env: gym.Env, seed: int, steps: int = 30) -> list[np.ndarray]:
    """Unique ids and poses of the other vehicles over an episode's first steps, the ego holding on."""
    env.reset(seed=seed)
    traffic = env.unwrapped.world.traffic
    seen = []
    for _ in range(steps):
        env.step(1)
        idx = traffic.indices[np.argsort(traffic.uid[traffic.indices])]
        seen.append(np.column_stack((traffic.uid[idx], traffic.pose[idx], traffic.speed[idx])))
    return seen


def test_the_same_seed_gives_the_same_flow():
    env = gym.make("GCCPPlanner-v0", traffic="sumo", spawn_probability=0.2)
    first = flow(env, seed=3)
    assert env.unwrapped.world.traffic.sumo.in_process
    again = flow(env, seed=3)
    # A second env of the process runs SUMO over TraCI: the same flow too.
    other_env = gym.make("GCCPPlanner-v0", traffic="sumo", spawn_probability=0.2)
    elsewhere = flow(other_env, seed=3)
    assert not other_env.unwrapped.world.traffic.sumo.in_process
    different = flow(env, seed=4)
    env.close()
    other_env.close()
    assert sum(len(step) for step in first) > 100
    for a, b, c in zip(first, again, elsewhere, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    assert any(a.shape != d.shape or not np.array_equal(a, d) for a, d in zip(first, different, strict=True))


def test_traffic_sumo_without_the_extra_is_a_one_line_error(monkeypatch, capsys):
    for module in ("sumo", "sumolib", "traci", "libsumo"):
        monkeypatch.setitem(sys.modules, module, None)  # as if never installed: imports fail
    with pytest.raises(ValueError, match=r"sumo extra") as err:
        IntersectionConfig(traffic="sumo")
    assert "\n" not in str(err.value) and 'pip install -e ".[sumo]"' in str(err.value)
    assert main(["config", "--set", "traffic=sumo"]) == 2
    message = capsys.readouterr().err
    assert message.count("\n") == 1 and "sumo extra" in message
    assert IntersectionConfig().traffic == "builtin"  # the default needs no SUMO


def test_an_unknown_traffic_is_rejected_by_name():
    with pytest.raises(ValueError, match="unknown traffic 'carla': expected one of builtin, sumo"):
        IntersectionConfig.from_dict({"traffic": "carla"})


def test_no_sumo_process_or_temporary_file_is_left_after_close(interface, tmp_path, monkeypatch):
    monkeypatch.setenv("GCCP_SUMO_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    env = gym.make("GCCPPlanner-v0", traffic="sumo")
    env.reset(seed=0)
    for _ in range(5):
        env.step(1)
    assert bool(sumo_children()) == (interface == "traci")
    env.close()
    assert sumo_children() == []
    assert not libsumo.simulation.isLoaded()
    assert list((tmp_path / "tmp").iterdir()) == []
    (network,) = (tmp_path / "cache").iterdir()  # the cached network, nothing half-built
    assert not network.name.startswith(".")


def test_an_exception_inside_step_ends_sumo(interface, monkeypatch):
    env = gym.make("GCCPPlanner-v0", traffic="sumo")
    env.reset(seed=0)

    def fail(*args: object) -> None:
        raise RuntimeError("boom")

    with monkeypatch.context() as patch:
        patch.setattr(SumoTraffic, "_read_states", fail)
        with pytest.raises(RuntimeError, match="boom"):
            env.step(1)
    assert sumo_children() == []
    assert not libsumo.simulation.isLoaded()
    env.reset(seed=0)  # a new episode starts a new SUMO
    env.step(1)
    env.close()
    assert sumo_children() == []


def test_gccp_envs_imports_no_sumo_with_builtin_traffic():
    script = (
        "import sys, gymnasium as gym, gccp_envs\n"
        "env = gym.make('GCCPPlanner-v0'); env.reset(seed=0); env.step(1); env.close()\n"
        "print(sorted(m for m in ('sumo', 'sumolib', 'traci', 'libsumo', 'sb3_gccp') if m in sys.modules))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"
