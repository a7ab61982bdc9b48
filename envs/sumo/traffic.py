"""SUMO's drivers on our junction: the traffic table filled from SUMO every 0.1 s step.

- **Flows** are ours, drawn as the builtin traffic draws them and from the same keys: each step a spawn
  with ``spawn_probability`` on a random inbound lane and a random movement allowed from it, desired speed
  from ``npc_speed_range`` and time headway (SUMO's ``tau``) from ``npc_time_headway``. SUMO inserts the
  vehicle at the next step if it fits; one it cannot insert then is dropped, as ours drops a spawn
  without room.
- **Driving** is SUMO's as it ships: the Krauss model with its ``sigma`` noise, lane changes, the
  priority junction with its gap acceptance and impatience. Nothing of ours is added on top.
- **The ego** is a SUMO vehicle on its task's route, placed every step at the pose our kinematics gave
  (``moveToXY``, as SMARTS couples its agents), so SUMO's drivers see it and react to it; its speed in
  SUMO is the distance it moved over the step. Where its front is more than half a lane off every lane
  of its movement (a wide turn), it is placed on the nearest point of its route's lanes instead, since
  SUMO keeps a vehicle placed off its lanes on no lane, unseen by its drivers.
- **Collisions** are ours, as for the builtin traffic: boxes that overlap. SUMO does not check them
  (``--collision.action none``); a crashed vehicle stops where it is and leaves after
  ``crashed_vehicle_lifetime``.

The table's pose is each vehicle's centre, half a length behind SUMO's front bumper; its path is the lane
path of its movement nearest to it (SUMO's drivers may change lanes) and ``s`` its arc length there.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from traci import constants as tc

from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.geometry import FloatArray
from gccp_envs.scenario import IntersectionLayout
from gccp_envs.sumo.network import (
    heading_to_sumo_angle,
    inbound_edge,
    network_file,
    outbound_edge,
    route_id,
    sumo_angle_to_heading,
    sumo_lane_index,
    to_sumo,
)
from gccp_envs.sumo.simulation import SumoSimulation, closing_on_error
from gccp_envs.traffic import VEHICLE_LENGTH, VEHICLE_WIDTH, Obstacle, TrafficTable

EGO_ID = "ego"
"""SUMO id of the ego (the other vehicles' ids are their unique ids)."""
VEHICLE_TYPE = "car"
"""SUMO vehicle type of every vehicle: SUMO's default passenger car with our box."""
SUMO_OPTIONS = (
    "--step-length",
    str(DT),
    "--collision.action",
    "none",
    "--no-step-log",
    "true",
    "--no-warnings",
    "true",
    "--duration-log.disable",
    "true",
)
"""Options of every SUMO run besides the network and the seed: our step, our collision checks, quiet."""
STATE = (tc.VAR_POSITION, tc.VAR_ANGLE, tc.VAR_SPEED)
"""What SUMO reports of every vehicle after each step (the front bumper's position)."""
KEEP_ROUTE_EXACT = 3
"""``moveToXY`` mode: the vehicle keeps its route (bit 0) and stands at the exact position given (bit 1)."""
KEEP_ROUTE_ON_LANE = 1
"""``moveToXY`` mode: the vehicle keeps its route and stands on the nearest point of its route's lanes."""


class SumoTraffic(TrafficTable):
    """The other vehicles driven by SUMO, one SUMO instance per object (started on first use).

    :param layout: the junction (its SUMO network is built or read from the cache now)
    :param config: the world config (the same density keys as the builtin traffic)
    :param rng: the source of the first episode's randomness
    """

    def __init__(
        self, layout: IntersectionLayout, config: IntersectionConfig, rng: np.random.Generator
    ) -> None:
        self._simulation: SumoSimulation | None = None
        self._network = network_file(layout)
        self._candidates = _same_movement_paths(layout)
        super().__init__(layout, config, rng)

    def reset(self, rng: np.random.Generator) -> None:
        """Empty the road for a new episode; SUMO restarts, seeded from ``rng``, at the first step."""
        super().reset(rng)
        self._seed = int(rng.integers(2**31 - 1))
        self._loaded = False
        self._next_uid = 0
        self._route_path = np.zeros(self.config.max_vehicles, np.int64)
        """Lane path each vehicle was spawned on: its movement."""
        self._vehicle_id = [""] * self.config.max_vehicles
        self._slot_of: dict[str, int] = {}
        self._waiting: dict[str, int] = {}
        """Vehicles added but not inserted yet, with the path they were spawned on."""
        self._ego_added = False

    def close(self) -> None:
        """End the SUMO instance (a new one starts at the next episode's first step)."""
        if self._simulation is not None:
            self._simulation.close()
            self._simulation = None
            self._loaded = False

    @property
    def sumo(self) -> SumoSimulation:
        """The running SUMO instance of this episode, started or reloaded on first use."""
        if self._simulation is None:
            self._simulation = SumoSimulation(self._options())
        elif not self._loaded:
            self._simulation.load(self._options())
        if not self._loaded:
            self._prepare(self._simulation.api)
            self._loaded = True
        return self._simulation

    def _options(self) -> list[str]:
        return ["--net-file", str(self._network), "--seed", str(self._seed), *SUMO_OPTIONS]

    def _prepare(self, api: Any) -> None:
        """Declare the routes of every movement and the vehicle type of a fresh simulation."""
        for arm, exit_arm in sorted({(move.arm, move.exit_arm) for move in self.layout.movements}):
            api.route.add(route_id(arm, exit_arm), [inbound_edge(arm), outbound_edge(exit_arm)])
        api.vehicletype.copy("DEFAULT_VEHTYPE", VEHICLE_TYPE)
        api.vehicletype.setLength(VEHICLE_TYPE, VEHICLE_LENGTH)
        api.vehicletype.setWidth(VEHICLE_TYPE, VEHICLE_WIDTH)

    # --- spawning ------------------------------------------------------------------------------------
    def spawn(self, path: int, s: float, ego: Obstacle | None = None, speed: float | None = None) -> None:
        """Ask SUMO for a vehicle on ``path`` (an approach lane) with its centre at arc length ``s``.

        It is inserted at the next step if SUMO finds room, else dropped; its slot is known from then on.
        Its speed is ``speed`` capped at its desired speed (SUMO refuses more), by default the highest
        SUMO deems safe.
        """
        if len(self._slot_of) + len(self._waiting) >= self.config.max_vehicles:
            return
        desired = self.rng.uniform(*self.config.npc_speed_range)
        headway = self.rng.uniform(*self.config.npc_time_headway)
        move = self.layout.movements[path]
        name = str(self._next_uid)
        self._next_uid += 1
        with closing_on_error(self.close):
            vehicle = self.sumo.api.vehicle
            vehicle.add(
                name,
                route_id(move.arm, move.exit_arm),
                VEHICLE_TYPE,
                departLane=str(sumo_lane_index(self.layout, move.lane)),
                departPos=str(s + VEHICLE_LENGTH / 2.0),
                departSpeed="max" if speed is None else str(min(speed, desired)),
            )
            vehicle.setMaxSpeed(name, desired)
            vehicle.setTau(name, headway)
        self._waiting[name] = path

    def spawn_random(self, ego: Obstacle | None = None) -> None:
        """Spawn one vehicle at the start of a random inbound lane on a random allowed movement (drawn as
        the builtin traffic draws it); it appears after the next step."""
        layout = self.layout
        entry = int(self.rng.integers(4 * layout.lanes))
        path = int(self.rng.choice(np.flatnonzero(layout.path_entry == entry)))
        self.spawn(path, float(self.rng.uniform(0.0, 2.0)), ego)

    def remove(self, slots: NDArray[np.int64]) -> None:
        """Take vehicles off the road, in SUMO too."""
        slots = np.atleast_1d(slots)
        if not len(slots):
            return
        with closing_on_error(self.close):
            vehicle = self.sumo.api.vehicle
            for slot in slots:
                name = self._vehicle_id[slot]
                vehicle.unsubscribe(name)  # libsumo fails the next step on a removed vehicle's subscription
                vehicle.remove(name)
                del self._slot_of[name]
        super().remove(slots)

    # --- one step ------------------------------------------------------------------------------------
    def step(self, ego: Obstacle | None = None) -> None:
        """Place the ego, advance SUMO by one 0.1 s step and read every vehicle back."""
        with closing_on_error(self.close):
            api = self.sumo.api
            if ego is not None:
                self._place_ego(api, ego)
            api.simulationStep()
            for name in api.simulation.getPendingVehicles():
                api.vehicle.remove(name)  # no room to insert it: dropped, as ours drops a spawn
                self._waiting.pop(name, None)
            self._admit(api, api.simulation.getDepartedIDList())
            for name in api.simulation.getArrivedIDList():
                slot = self._slot_of.pop(name, None)
                if slot is not None:
                    self.active[slot] = False
            self._read_states(api.vehicle.getAllSubscriptionResults())
        self.crash_timer[self.crashed] += DT
        self.remove(np.flatnonzero(self.active & (self.crash_timer > self.config.crashed_vehicle_lifetime)))

    def detect_crashes(self, ego: Obstacle | None = None) -> bool:
        """Mark vehicles whose boxes overlap another's (ours); stop the newly crashed ones in SUMO."""
        before = self.crashed.copy()
        ego_hit = super().detect_crashes(ego)
        newly = np.flatnonzero(self.crashed & ~before)
        if len(newly):
            with closing_on_error(self.close):
                vehicle = self.sumo.api.vehicle
                for slot in newly:
                    vehicle.setSpeedMode(self._vehicle_id[slot], 0)  # stop at once, whatever the deceleration
                    vehicle.setSpeed(self._vehicle_id[slot], 0.0)
        return ego_hit

    def _place_ego(self, api: Any, ego: Obstacle) -> None:
        """Move the ego's SUMO vehicle to its pose, adding it on its task's route the first time."""
        vehicle = api.vehicle
        if ego.path is None:
            raise ValueError("SUMO traffic routes the ego on its task: Obstacle.path must be given")
        if not self._ego_added:
            move = self.layout.movements[ego.path]
            vehicle.add(EGO_ID, route_id(move.arm, move.exit_arm), VEHICLE_TYPE)
            vehicle.setLength(EGO_ID, ego.length)
            vehicle.setWidth(EGO_ID, ego.width)
            self._ego_added = True
        direction = np.array([np.cos(ego.heading), np.sin(ego.heading)])
        front = np.array([ego.x, ego.y]) + ego.length / 2.0 * direction
        x, y = to_sumo(front)
        angle = float(heading_to_sumo_angle(ego.heading))
        vehicle.moveToXY(
            EGO_ID, "", -1, float(x), float(y), angle, keepRoute=self._keep_route(ego.path, front)
        )

    def _keep_route(self, path: int, front: FloatArray) -> int:
        """How ``moveToXY`` places the ego whose front is at ``front``: at that exact position while it
        lies within half a lane of one of the lane paths of its movement, else on the nearest point of
        its route's lanes. SUMO puts a vehicle placed exactly but off its route's lanes on no lane at
        all, where its drivers do not see it (a wide turn through the junction does that)."""
        paths = self._candidates[path]
        _, lateral = self.layout.paths.project(paths[paths >= 0], front)
        return (
            KEEP_ROUTE_EXACT
            if np.min(np.abs(lateral)) <= self.config.lane_width / 2.0
            else KEEP_ROUTE_ON_LANE
        )

    def _admit(self, api: Any, departed: Sequence[str]) -> None:
        """Give the vehicles SUMO inserted this step a slot, and subscribe to their state."""
        for name in departed:
            if name == EGO_ID:
                continue
            slot = int(np.flatnonzero(~self.active)[0])  # spawns stop before the table is full
            self.active[slot] = True
            self.crashed[slot] = False
            self.crash_timer[slot] = 0.0
            self.uid[slot] = int(name)
            self._route_path[slot] = self._waiting.pop(name)
            self._vehicle_id[slot] = name
            self._slot_of[name] = slot
            self.spawned += 1
            api.vehicle.subscribe(name, STATE)

    def _read_states(self, states: dict[str, dict[int, object]]) -> None:
        """Poses, speeds, paths and arc lengths of the active vehicles from SUMO's report."""
        if not self._slot_of:
            return
        slots = np.fromiter(self._slot_of.values(), np.int64, len(self._slot_of))
        report = [states[name] for name in self._slot_of]
        front = to_sumo(np.array([r[tc.VAR_POSITION] for r in report], float))
        heading = sumo_angle_to_heading(np.array([r[tc.VAR_ANGLE] for r in report], float))
        half = self.length[slots, None] / 2.0
        centre = front - half * np.stack((np.cos(heading), np.sin(heading)), -1)
        self.pose[slots] = np.column_stack((centre, heading))
        self.speed[slots] = np.array([r[tc.VAR_SPEED] for r in report], float)
        candidates = self._candidates[self._route_path[slots]]
        s, d = self.layout.paths.project(np.maximum(candidates, 0), centre[:, None])
        nearest = np.argmin(np.where(candidates >= 0, np.abs(d), np.inf), axis=1)
        rows = np.arange(len(slots))
        self.path[slots] = candidates[rows, nearest]
        self.s[slots] = s[rows, nearest]


def _same_movement_paths(layout: IntersectionLayout) -> NDArray[np.int64]:
    """For every path, the paths of the same entry arm and turn (its movement on any lane), -1 padded."""
    groups = [
        [q for q, other in enumerate(layout.movements) if (other.arm, other.turn) == (move.arm, move.turn)]
        for move in layout.movements
    ]
    table = np.full((len(groups), max(map(len, groups))), -1, np.int64)
    for p, group in enumerate(groups):
        table[p, : len(group)] = group
    return table
