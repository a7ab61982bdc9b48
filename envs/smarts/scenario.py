"""The three tasks as SMARTS scenarios, written with ``smarts.sstudio`` into a cache folder on first use.

One scenario folder per task, with our junction as SUMO network (``envs/sumo/network.py``, the same file
the ``sumo`` backend drives) and the ego's mission from the south arm to the task's exit arm, entering after
``warmup_time``; and one folder of ``smarts_flows`` traffic variations the three share, SUMO flows at our
density and speeds.

A flow is SMARTS's: sstudio writes randomly spaced flows and ``duarouter`` draws every departure when the
scenario is built, with seed ``k`` for variation ``k`` (sstudio's ``seed + iteration``). So flow ``k`` is
the same vehicles at the same times in every episode that draws it; SUMO's ``--seed`` (which SMARTS draws
from Python's ``random``, seeded per episode by the world) only varies the drivers' speed factors and noise.
"""

from __future__ import annotations

import hashlib
import math
import random
import shutil
from importlib.metadata import version
from pathlib import Path
from typing import Any

from gccp_envs.config import DT, TASKS, IntersectionConfig
from gccp_envs.scenario import TURN_OFFSET, IntersectionLayout
from gccp_envs.sumo.network import (
    build_once,
    cache_root,
    inbound_edge,
    network_file,
    outbound_edge,
    sumo_lane_index,
)

MAP_FILE = "map.net.xml"
"""Name SMARTS looks for in a scenario folder."""
MISSIONS_FILE = Path("build") / "missions.pkl"
"""What ``gen_scenario`` writes last: its presence means a scenario is built."""
SUMO_SPEED_LIMIT = 13.89
"""Speed limit [m/s] netconvert gives our edges (its default); SUMO's drivers' desired speed is a factor
of it."""
EGO_ID = "ego"
"""SMARTS agent id of the ego."""


def scenario_root(config: IntersectionConfig, layout: IntersectionLayout) -> Path:
    """The folder of the three task scenarios of a config: named by the layout and a digest of every key
    the scenarios depend on and of the SMARTS version."""
    network = network_file(layout)
    keys = (
        network.parent.name,
        config.spawn_probability,
        config.npc_speed_range,
        config.npc_time_headway,
        config.warmup_time,
        config.ego_start_distance,
        config.exit_distance,
        config.duration,
        config.smarts_flows,
        version("smarts"),
    )
    digest = hashlib.sha256(repr(keys).encode()).hexdigest()[:12]
    return cache_root().parent / "smarts" / f"{network.parent.name}-{digest}"


def scenario_folder(config: IntersectionConfig, layout: IntersectionLayout, task: str) -> Path:
    """The scenario folder of ``task`` (our junction and the ego's mission), generated on first use.

    :raises ValueError: an unknown task
    """
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}: expected one of {', '.join(TASKS)}")
    folder = scenario_root(config, layout) / task
    mission = _mission(config, layout, task)
    build_once(folder, str(MISSIONS_FILE), lambda build: _generate(layout, build, ego_missions=[mission]))
    return folder


def traffic_specs(config: IntersectionConfig, layout: IntersectionLayout, k: int) -> list[str]:
    """The route file of traffic variation ``k``, shared by the three tasks (none without traffic); the
    variations are generated on first use (``duarouter`` for each: a few seconds for 50)."""
    folder = scenario_root(config, layout) / "traffic"
    build_once(folder, MAP_FILE, lambda build: _generate(layout, build, traffic=_variations(config, layout)))
    path = folder / "build" / "traffic" / f"{flow_name(k)}.rou.xml"
    return [str(path)] if path.is_file() else []


def _generate(layout: IntersectionLayout, folder: Path, **parts: Any) -> None:
    """A scenario of our junction and ``parts`` (sstudio's ``traffic``, ``ego_missions``) in ``folder``.

    sstudio's build draws from Python's ``random``, from which SMARTS also draws SUMO's seed at every reset;
    its state is put back afterwards, so that an episode that builds a scenario on first use runs as it does
    on a built one."""
    from smarts.sstudio import gen_scenario
    from smarts.sstudio import sstypes as t

    shutil.copyfile(network_file(layout), folder / MAP_FILE)
    state = random.getstate()
    try:
        gen_scenario(t.Scenario(**parts), output_dir=folder, seed=0)
    finally:
        random.setstate(state)


def flow_name(k: int) -> str:
    """Name of traffic variation ``k`` (its route file is ``build/traffic/<name>.rou.xml``)."""
    return f"flow{k:03d}"


def _variations(config: IntersectionConfig, layout: IntersectionLayout) -> dict[str, Any] | None:
    """``smarts_flows`` copies of our flows, whose departures duarouter draws with seeds 0, 1, ... (none
    without traffic)."""
    from smarts.sstudio import sstypes as t

    flows = _flows(config, layout)
    if not flows:
        return None
    traffic = t.Traffic(flows=flows)
    return {flow_name(k): traffic for k in range(config.smarts_flows)}


def _flows(config: IntersectionConfig, layout: IntersectionLayout) -> list[Any]:
    """One randomly spaced flow per movement, at the rate our traffic spawns it.

    Ours spawns with ``spawn_probability`` per step on one of the ``4 * lanes`` inbound lanes, then on one
    of the movements from that lane, all uniformly: so a movement's rate is that chance per second over
    the lanes and the lane's movements. Desired speeds and headways have the means and spreads of ours.
    Departures stop after the longest episode (warm-up plus time limit), which keeps the build short.
    Without traffic (``spawn_probability`` 0) there are no flows.
    """
    if config.spawn_probability == 0.0:
        return []
    from smarts.sstudio import sstypes as t

    low, high = config.npc_speed_range
    actor = t.TrafficActor(
        name="car",
        speed=t.Distribution(
            mean=(low + high) / 2.0 / SUMO_SPEED_LIMIT,
            sigma=(high - low) / math.sqrt(12.0) / SUMO_SPEED_LIMIT,
        ),
        max_speed=high,
        tau=sum(config.npc_time_headway) / 2.0,
    )
    per_lane = config.spawn_probability / DT / (4 * layout.lanes)
    flows = []
    for p, move in enumerate(layout.movements):
        moves_from_lane = int((layout.path_entry == layout.path_entry[p]).sum())
        route = t.Route(
            begin=(inbound_edge(move.arm), sumo_lane_index(layout, move.lane), 0.0),
            end=(outbound_edge(move.exit_arm), sumo_lane_index(layout, move.exit_lane), "max"),
        )
        flows.append(
            t.Flow(
                route=route,
                rate=3600.0 * per_lane / moves_from_lane,
                actors={actor: 1.0},
                randomly_spaced=True,
                end=config.warmup_time + config.duration,
            )
        )
    return flows


def _mission(config: IntersectionConfig, layout: IntersectionLayout, task: str) -> Any:
    """The ego's mission: from the south arm's lane of the task, at the mean start distance, to the task's
    exit arm at the exit distance; the adapter moves its start every episode as our world draws it."""
    from smarts.sstudio import sstypes as t

    path = layout.paths_from(0, turn=task)[0]
    move = layout.movements[path]
    start = layout.stop_s - sum(config.ego_start_distance) / 2.0
    route = t.Route(
        begin=(inbound_edge(0), sumo_lane_index(layout, move.lane), start),
        end=(outbound_edge(TURN_OFFSET[task]), sumo_lane_index(layout, move.exit_lane), config.exit_distance),
    )
    return t.Mission(route=route, start_time=config.warmup_time)
