"""The world stepped by SMARTS (config ``simulator: smarts``): the only module that imports SMARTS.

- **Episodes**: one SMARTS instance per world, with SUMO's traffic, on the task's scenario
  (:mod:`gccp_envs.smarts.scenario`). ``reset`` draws the task, the traffic variation (flow ``k`` of
  ``smarts_flows``), SUMO's seed and the ego's start from the episode's generator, as our world draws them;
  SMARTS runs the traffic for ``warmup_time`` and puts the ego in at its start; with ``smarts_clear_start``
  SUMO's vehicles within 15 m of it are taken off the road, as our world starts an episode. A SUMO that
  SMARTS has to start again runs the same flow (:class:`SeededSumoTrafficSimulation`).
- **The ego** moves by SMARTS's ``RelativeTargetPose``: our action's pose change over 0.1 s
  (:class:`~gccp_envs.action.EgoMotion`), turned into SMARTS's frame. Its pose is read back from SMARTS;
  its speed is the one our kinematics gave, as in our world.
- **Other vehicles** are SMARTS's neighbour states within ``observation_radius`` plus 15 m, in the traffic
  table the observation reads, each on the lane path nearest to it. Vehicles the ego first sees get a past
  at constant speed, as the ego does.
- **The bird's-eye view** is SMARTS's drivable-area grid map around the ego, heading up
  (``smarts_grid_map``; else drawn from our layout of the same map, as in our world).
- **The routes** are lane paths of ours: with ``smarts_routes: waypoints`` those SMARTS's waypoint paths
  along the ego's mission run on, else chosen by our rule. Their points and the subgoals come from our
  layout either way: SMARTS's map is that layout, built by ``netconvert``.
- **Outcomes** are SMARTS's events: a collision, off road, the goal (the task's exit, our test) reached.
  A wrong exit is ours (SMARTS has no such event). SMARTS ends nothing else: no off-route, wrong-way or
  not-moving ends, no step limit (``duration`` truncates, as in our world).

SMARTS's coordinates are SUMO's: a point (x, y) of ours is (x, -y) there; its heading is 0 to the north and
grows anticlockwise, ours grows clockwise from the east, so ``ours = -(smarts + pi / 2)``.
"""

from __future__ import annotations

import random
import shutil
import tempfile
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from smarts.core.agent_interface import (
    AgentInterface,
    DoneCriteria,
    DrivableAreaGridMap,
    NeighborhoodVehicles,
)
from smarts.core.controllers import ActionSpaceType
from smarts.core.coordinates import Heading, Point, Pose
from smarts.core.plan import NavigationMission, PositionalGoal, Start
from smarts.core.scenario import Scenario
from smarts.core.smarts import SMARTS
from smarts.core.sumo_traffic_simulation import SumoTrafficSimulation

from gccp_envs.action import EgoState
from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.geometry import FloatArray, wrap_angle
from gccp_envs.scenario import TURN_OFFSET, IntersectionLayout
from gccp_envs.smarts.fixes import apply_fixes
from gccp_envs.smarts.scenario import EGO_ID, scenario_folder, traffic_specs
from gccp_envs.sumo.network import to_sumo
from gccp_envs.sumo.simulation import closing_on_error
from gccp_envs.traffic import Obstacle, TrafficTable
from gccp_envs.world import START_CLEARANCE, IntersectionWorld, StepOutcome

NEIGHBOURHOOD_MARGIN = 15.0
"""Metres beyond ``observation_radius`` within which SMARTS reports other vehicles, so that a neighbour of
a decision stays in the table for the T_f steps of its ground-truth future."""
ROUTE_LOOKAHEAD = 10
"""Waypoints (1 m apart) of each of SMARTS's waypoint paths read to tell which of our lane paths it runs on
(``smarts_routes: waypoints``)."""
HEADING_WEIGHT = 2.0
"""Metres of lateral offset one radian of heading difference counts as, when a vehicle's lane path is
chosen (so that a car on the junction's crossing lanes gets the path it drives along)."""


class SeededSumoTrafficSimulation(SumoTrafficSimulation):
    """SMARTS's SUMO traffic, whose SUMO runs the same flow when SMARTS has to start it again.

    SMARTS starts SUMO with a ``--seed`` drawn from Python's ``random``. When TraCI does not connect within
    5 s (SUMO slow to start on a busy machine), SMARTS starts SUMO again with the next draw: another flow,
    and every later draw of the episode shifted. Here every start or reload within one ``setup`` draws from
    the state ``random`` had when it began, so a retried start runs the flow of a first-time one; a start
    that connects at once draws as before.
    """

    _random_state: Any = None

    def setup(self, scenario: Any) -> Any:
        self._random_state = random.getstate()
        try:
            return super().setup(scenario)
        finally:
            self._random_state = None

    def _base_sumo_load_params(self) -> list[str]:
        if self._random_state is not None:
            random.setstate(self._random_state)
        return list(super()._base_sumo_load_params())


def smarts_heading(heading: FloatArray | float) -> FloatArray:
    """SMARTS's heading [rad, 0 north, anticlockwise] of our headings, and ours of SMARTS's (the map is its
    own inverse)."""
    return wrap_angle(-np.asarray(heading, float) - np.pi / 2.0)


def relative_target_pose(ego: EgoState, after: EgoState) -> NDArray[np.float64]:
    """SMARTS's ``RelativeTargetPose`` action (dx, dy, dheading in its world frame) from ``ego`` to
    ``after``."""
    dx, dy = to_sumo(np.array([after.x - ego.x, after.y - ego.y]))
    return np.array([dx, dy, -float(wrap_angle(after.heading - ego.heading))])


@dataclass(frozen=True, unsafe_hash=True)
class ExitGoal(PositionalGoal):
    """Our task success as SMARTS's goal: the ego's centre past the exit distance on the task's exit arm
    (``layout.exit_reached``). Its position and radius, the exit road's middle and half width, give SMARTS's
    route planner its target."""

    arm: int = 0
    """The task's exit arm."""
    layout: IntersectionLayout | None = None

    def is_reached(self, vehicle_state: Any) -> bool:
        """Whether the ego (SMARTS's vehicle state) has left the junction on the exit arm."""
        assert self.layout is not None
        position = to_sumo(np.asarray(vehicle_state.pose.position[:2], float))
        return self.layout.exit_reached(position) == self.arm


class SmartsTraffic(TrafficTable):
    """The other vehicles as SMARTS reports them around the ego, filled by :meth:`fill` every step."""

    def reset(self, rng: np.random.Generator) -> None:
        """Empty the table for a new episode."""
        super().reset(rng)
        self._slot_of: dict[str, int] = {}
        self._next_uid = 1

    def spawn_random(self, ego: Obstacle | None = None) -> None:
        """SMARTS spawns (its scenario's flows); nothing to do."""

    def step(self, ego: Obstacle | None = None) -> None:
        """SMARTS steps the traffic (:class:`SmartsWorld`); nothing to do."""

    def fill(self, states: Any) -> None:
        """The table from SMARTS's neighbour states (a vehicle keeps its slot while it is reported)."""
        seen = {state.id: state for state in states}
        for name in [n for n in self._slot_of if n not in seen]:
            self.active[self._slot_of.pop(name)] = False
        for name in seen:
            if name not in self._slot_of and not self.active.all():
                slot = int(np.flatnonzero(~self.active)[0])
                self._slot_of[name] = slot
                self.active[slot] = True
                self.uid[slot] = self._next_uid
                self._next_uid += 1
                self.spawned += 1
        if not self._slot_of:
            return
        slots = np.fromiter(self._slot_of.values(), np.int64, len(self._slot_of))
        report = [seen[name] for name in self._slot_of]
        self.pose[slots, :2] = to_sumo(np.array([s.position[:2] for s in report], float))
        self.pose[slots, 2] = smarts_heading(np.array([float(s.heading) for s in report]))
        self.speed[slots] = [s.speed for s in report]
        self.length[slots] = [s.bounding_box.length for s in report]
        self.width[slots] = [s.bounding_box.width for s in report]
        self._locate(slots)

    def _locate(self, slots: NDArray[np.int64]) -> None:
        """Each vehicle's lane path: the nearest one heading its way; ``s`` its arc length there."""
        paths = self.layout.paths
        every = np.broadcast_to(
            np.arange(len(self.layout.movements)), (len(slots), len(self.layout.movements))
        )
        s, d = paths.project(every, self.pose[slots, None, :2])
        along = paths.pose_at(every, np.clip(s, 0.0, paths.lengths[every]))[..., 2]
        turn = np.abs(wrap_angle(along - self.pose[slots, None, 2]))
        nearest = np.argmin(np.abs(d) + HEADING_WEIGHT * turn, axis=1)
        rows = np.arange(len(slots))
        self.path[slots] = nearest
        self.s[slots] = s[rows, nearest]


class SmartsWorld(IntersectionWorld):
    """One intersection episode simulated by SMARTS, read through the same interface as ours."""

    def __init__(self, config: IntersectionConfig) -> None:
        super().__init__(config)
        self._smarts: Any = None
        self._log_dir: str | None = None
        self.flow = 0
        """Traffic variation of the current episode."""
        self.observation: Any = None
        """SMARTS's observation of the ego at the current step."""
        self._mission_route: Any = None

    def _make_traffic(self) -> TrafficTable:
        return SmartsTraffic(self.layout, self.config, self.rng)

    @property
    def smarts_traffic(self) -> SmartsTraffic:
        """The traffic table, as the SMARTS table it is."""
        assert isinstance(self.traffic, SmartsTraffic)
        return self.traffic

    # --- SMARTS ----------------------------------------------------------------------------------------
    def _simulation(self) -> Any:
        """The SMARTS instance of this world, started on first use."""
        if self._smarts is None:
            apply_fixes()
            config = self.config
            grid_map: DrivableAreaGridMap | bool = False
            if config.smarts_grid_map:
                resolution = config.bev_extent / config.bev_size
                grid_map = DrivableAreaGridMap(config.bev_size, config.bev_size, resolution)
            interface = AgentInterface(
                action=ActionSpaceType.RelativeTargetPose,
                neighborhood_vehicle_states=NeighborhoodVehicles(
                    radius=self.config.observation_radius + NEIGHBOURHOOD_MARGIN
                ),
                done_criteria=DoneCriteria(
                    off_route=False, on_shoulder=False, wrong_way=False, not_moving=False
                ),
                drivable_area_grid_map=grid_map,
            )
            self._log_dir = tempfile.mkdtemp(prefix="gccp-smarts-")
            self._smarts = SMARTS(
                {EGO_ID: interface},
                traffic_sims=[SeededSumoTrafficSimulation(headless=True, time_resolution=DT)],
                envision=None,
                fixed_timestep_sec=DT,
            )
        return self._smarts

    def close(self) -> None:
        """End SMARTS and its SUMO, and remove SUMO's logs."""
        if self._smarts is not None:
            smarts, self._smarts = self._smarts, None
            self._mission_route = None
            smarts.destroy()
        if self._log_dir is not None:
            shutil.rmtree(self._log_dir, ignore_errors=True)
            self._log_dir = None

    # --- episode -------------------------------------------------------------------------------------
    def reset(self, rng: np.random.Generator, task: str | None = None) -> None:
        """Start an episode: SMARTS runs flow ``k`` for the warm-up, then puts the ego at its start.

        :param rng: the source of all randomness of the episode
        :param task: 'left' | 'straight' | 'right'; default the config's (drawn if 'mixed')
        """
        self.rng = rng
        self._begin_episode(task)
        self.traffic.reset(rng)
        self.flow = int(rng.integers(self.config.smarts_flows))
        sumo_seed = int(rng.integers(2**31 - 1))
        path, s, speed = self._draw_ego_start()
        start = self.layout.paths.pose_at(np.array(path), np.array(s))
        with closing_on_error(self.close):
            simulation = self._simulation()
            random.seed(sumo_seed)  # SMARTS draws SUMO's --seed from Python's random at every reset
            observation = simulation.reset(self._scenario(start))[EGO_ID]
            self._mission_route = self._route_of_mission(simulation)
            cleared = self._clear_start(simulation, observation) if self.config.smarts_clear_start else set()
        self.steps = 0
        self._read(observation, ignore=cleared)
        self.ego.speed = self._start_speed(path, s, speed)
        self._record()
        self._backfill_history(np.concatenate([[self.ego_slot], self.traffic.indices]).astype(np.int64))
        self._candidates = self._routes = None

    @staticmethod
    def _clear_start(simulation: Any, observation: Any) -> set[str]:
        """Take SUMO's vehicles within ``START_CLEARANCE`` of the ego off the road as it enters
        (``smarts_clear_start``), as our world does; their ids."""
        ego = np.asarray(observation.ego_vehicle_state.position[:2], float)
        near = {
            state.id
            for state in observation.neighborhood_vehicle_states or ()
            if np.hypot(*(np.asarray(state.position[:2], float) - ego)) < START_CLEARANCE
        }
        sumo = next(p for p in simulation.providers if isinstance(p, SumoTrafficSimulation))
        for vehicle_id in near:
            sumo.remove_actor(vehicle_id)
            simulation.provider_removing_actor(sumo, vehicle_id)
        return near

    @staticmethod
    def _route_of_mission(simulation: Any) -> Any:
        """The route SMARTS's planner made for the ego's mission (its roads)."""
        vehicle_id = simulation.vehicle_index.vehicle_ids_by_owner_id(EGO_ID)[0]
        sensor_state = simulation.sensor_manager.sensor_state_for_actor_id(vehicle_id)
        return sensor_state.get_plan(simulation.road_map).route

    def _find_routes(self) -> tuple[list[int], FloatArray]:
        """The ego's routes (``smarts_routes``), nearest first, and its arc length on each.

        With 'waypoints', the task's lane paths that SMARTS's waypoint paths along the mission run on: a
        waypoint path runs on the lane path its first ``ROUTE_LOOKAHEAD`` metres stay within half a lane
        width of on average. Our rule's routes when none does (the ego has left the mission's roads).
        """
        if self.config.smarts_routes != "waypoints" or self._mission_route is None:
            return super()._find_routes()
        layout = self.layout
        paths = np.array(self._task_paths)
        state = self.observation.ego_vehicle_state
        pose = Pose.from_center(state.position, state.heading)
        waypoint_paths = self._simulation().road_map.waypoint_paths(
            pose, ROUTE_LOOKAHEAD, route=self._mission_route
        )
        matched: list[int] = []
        for waypoints in waypoint_paths:
            points = to_sumo(np.array([w.pos for w in waypoints], float))
            _, d = layout.paths.project(paths[:, None], points[None])
            offset = np.abs(d).mean(axis=1)
            best = int(np.argmin(offset))
            if offset[best] < self.config.lane_width / 2.0 and paths[best] not in matched:
                matched.append(int(paths[best]))
        if not matched:
            return super()._find_routes()
        return self._nearest_routes(matched)

    def _scenario(self, start: FloatArray) -> Any:
        """The task's scenario with flow ``k`` and the ego's mission from ``start`` to the task's exit."""
        folder = scenario_folder(self.config, self.layout, self.task)
        scenario = Scenario(
            str(folder),
            traffic_specs=traffic_specs(self.config, self.layout, self.flow),
            log_dir=self._log_dir,
        )
        goal_x, goal_y = to_sumo(self.task_goal[:2])
        goal = ExitGoal(
            position=Point(goal_x, goal_y),
            radius=self.layout.half_width,
            arm=TURN_OFFSET[self.task],
            layout=self.layout,
        )
        x, y = to_sumo(start[:2])
        begin = Start(np.array([x, y]), Heading(float(smarts_heading(start[2]))), from_front_bumper=False)
        scenario.set_ego_missions(
            {EGO_ID: NavigationMission(start=begin, goal=goal, start_time=self.config.warmup_time)}
        )
        return scenario

    def step(self, action: int) -> StepOutcome:
        """Move the ego by one action through SMARTS, which moves the traffic; read the outcome."""
        after = self.motion.step(self.ego, action)
        with closing_on_error(self.close):
            observations, _, _, _ = self._simulation().step({EGO_ID: relative_target_pose(self.ego, after)})
        self.steps += 1
        self._candidates = self._routes = None
        observation = observations.get(EGO_ID)
        if observation is None:  # SMARTS removed the ego: the episode had ended
            raise RuntimeError("SMARTS has no ego after the episode ended: reset the env")
        self._read(observation, speed=after.speed)
        self._record()
        events = observation.events
        exit_arm = self.layout.exit_reached(np.array([self.ego.x, self.ego.y]))
        success = bool(events.reached_goal)
        return StepOutcome(
            crashed=len(events.collisions) > 0,
            offroad=bool(events.off_road),
            success=success,
            wrong_exit=exit_arm is not None and not success,
        )

    def sensed_bev(self) -> NDArray[np.uint8] | None:
        """SMARTS's drivable-area grid map (``smarts_grid_map``): heading up, as our bird's-eye view."""
        grid = None if self.observation is None else self.observation.drivable_area_grid_map
        if grid is None:
            return None
        return (np.asarray(grid.data)[..., 0] > 0).astype(np.uint8)

    def _read(self, observation: Any, speed: float | None = None, ignore: set[str] | None = None) -> None:
        """The ego's pose (and, without ``speed``, SMARTS's speed) and the traffic table from SMARTS, without
        the vehicles ``ignore`` names (taken off the road since SMARTS observed them)."""
        self.observation = observation
        state = observation.ego_vehicle_state
        x, y = to_sumo(np.asarray(state.position[:2], float))
        heading = float(smarts_heading(float(state.heading)))
        self.ego = EgoState(float(x), float(y), heading, float(state.speed if speed is None else speed))
        states = observation.neighborhood_vehicle_states or ()
        if ignore:  # only at a cleared start
            states = [state for state in states if state.id not in ignore]
        self.smarts_traffic.fill(states)
