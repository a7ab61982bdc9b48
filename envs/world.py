"""The simulation behind every env: road, traffic, ego, pose history and episode outcomes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gccp_envs.action import EgoMotion, EgoState
from gccp_envs.config import DT, TASKS, IntersectionConfig
from gccp_envs.geometry import FloatArray, box_corners, from_frame, poses_to_frame
from gccp_envs.scenario import TURN_OFFSET, IntersectionLayout, layout_for
from gccp_envs.subgoals import SubgoalSampler
from gccp_envs.traffic import VEHICLE_LENGTH, VEHICLE_WIDTH, Obstacle, Traffic, TrafficTable

EGO_ARM = 0
"""The ego always enters from the south arm."""
STANDING_START_BEFORE = 10.0
"""A standing start (``ego_start_standing``) lies at most this far [m] before the stop line ..."""
STANDING_START_AFTER = 5.0
"""... and at most this far [m] past the junction box."""
START_CLEARANCE = 15.0
"""No other vehicle is within this distance [m] of the ego when it enters: none of them saw it arrive."""


def make_traffic(
    layout: IntersectionLayout, config: IntersectionConfig, rng: np.random.Generator
) -> TrafficTable:
    """The traffic of config ``traffic``: ours, or SUMO's (imported only when chosen)."""
    if config.traffic == "sumo":
        from gccp_envs.sumo.traffic import SumoTraffic

        return SumoTraffic(layout, config, rng)
    return Traffic(layout, config, rng)


def make_world(config: IntersectionConfig) -> IntersectionWorld:
    """The world of config ``simulator``: ours, or SMARTS's (imported only when chosen)."""
    if config.simulator == "smarts":
        from gccp_envs.smarts.world import SmartsWorld

        return SmartsWorld(config)
    return IntersectionWorld(config)


VehicleSizes = tuple[tuple[float, float], tuple[float, float]]
"""(length, width) [m] of the ego and of the other vehicles."""
BUILTIN_SIZES: VehicleSizes = ((VEHICLE_LENGTH, VEHICLE_WIDTH), (VEHICLE_LENGTH, VEHICLE_WIDTH))
"""Our world's cars, and SUMO's with ``traffic: sumo``: 5 x 2 m, the ego as every other."""


def vehicle_sizes(config: IntersectionConfig) -> VehicleSizes:
    """The sizes of the ego and of the other vehicles in the world of config ``simulator`` (SMARTS not
    imported)."""
    if config.simulator == "smarts":
        from gccp_envs.smarts import VEHICLE_SIZE

        return VEHICLE_SIZE, VEHICLE_SIZE
    return BUILTIN_SIZES


@dataclass(frozen=True)
class StepOutcome:
    """What happened to the ego in one step."""

    crashed: bool = False
    offroad: bool = False
    success: bool = False
    wrong_exit: bool = False

    @property
    def terminal(self) -> bool:
        """Whether the episode ends."""
        return self.crashed or self.offroad or self.success or self.wrong_exit


@dataclass(frozen=True)
class DecisionRecord:
    """Who was in the state at a decision point, to collect their ground-truth futures later."""

    step: int
    slots: NDArray[np.int64]
    uids: NDArray[np.int64]
    origin: FloatArray
    heading: float


class IntersectionWorld:
    """One intersection episode: call :meth:`reset`, then :meth:`step` with ego actions."""

    def __init__(self, config: IntersectionConfig) -> None:
        self.config = config
        self.layout = layout_for(config)
        self.motion = EgoMotion(config)
        self.sampler = SubgoalSampler(self.layout, config)
        self.ego_slot = config.max_vehicles
        """Slot of the ego in the pose history (after the traffic's slots)."""
        # Long enough for the state's T_h + 1 poses and for a decision's future, read T_m steps later.
        self._hist_len = max(config.history_length + 1, config.decision_period) + 1
        self.rng = np.random.default_rng()
        self.traffic = self._make_traffic()
        self.task = "straight"
        self.ego = EgoState(0.0, 0.0, 0.0, 0.0)
        self.steps = 0
        self.task_goal = np.zeros(3)
        self._task_paths: list[int] = []
        self._candidates: FloatArray | None = None
        self._routes: tuple[list[int], FloatArray] | None = None
        self._mask: tuple[tuple[float, ...], NDArray[np.bool_]] | None = None
        """The ego's (x, y, heading, speed) and its action mask, computed once per pose."""
        self._drive_on_paths: tuple[FloatArray, FloatArray] | None = None
        """The paths :meth:`_can_drive_on` tries, single arcs and pairs, made on first use."""

    def _make_traffic(self) -> TrafficTable:
        return make_traffic(self.layout, self.config, self.rng)

    # --- episode -------------------------------------------------------------------------------------
    def reset(self, rng: np.random.Generator, task: str | None = None) -> None:
        """Start an episode: populate the traffic, then place the ego on its arm.

        :param rng: the source of all randomness of the episode
        :param task: 'left' | 'straight' | 'right'; default the config's (drawn if 'mixed')
        """
        cfg = self.config
        self.rng = rng
        self._begin_episode(task)
        self.traffic.reset(rng)
        warmup = round(cfg.warmup_time / DT)
        for step in range(-warmup, 0):
            self._spawn_traffic(None)
            self.traffic.step(None)
            self.traffic.detect_crashes(None)
            self.steps = step
            self._record(ego=False)
        self.steps = 0
        self._place_ego()
        self._record()
        self._backfill_history(np.array([self.ego_slot]))
        self._candidates = self._routes = None

    def _begin_episode(self, task: str | None) -> None:
        """Set the task (the config's if ``None``, drawn if 'mixed') and empty the pose history."""
        task = task or self.config.task
        if task == "mixed":
            task = TASKS[int(self.rng.integers(len(TASKS)))]
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r}: expected one of {', '.join(TASKS)}")
        self.task = task
        self.task_goal = self.layout.task_goal(task)
        self._task_paths = self.layout.paths_from(EGO_ARM, turn=task)
        self._hist = np.zeros((self._hist_len, self.ego_slot + 1, 4))
        self._hist_uid = np.full((self._hist_len, self.ego_slot + 1), -1, np.int64)

    def _backfill_history(self, slots: NDArray[np.int64]) -> None:
        """Give vehicles just recorded a past: they arrived at constant speed along their heading."""
        row = self.steps % self._hist_len
        now, uids = self._hist[row, slots], self._hist_uid[row, slots]
        for k in range(1, self._hist_len):
            back = now[:, 3] * k * DT
            past = self.steps - k
            self._hist[past % self._hist_len, slots] = np.column_stack(
                (now[:, 0] - back * np.cos(now[:, 2]), now[:, 1] - back * np.sin(now[:, 2]), now[:, 2:])
            )
            self._hist_uid[past % self._hist_len, slots] = uids

    def _place_ego(self) -> None:
        """Put the ego at its drawn start, with no other vehicle within ``START_CLEARANCE`` of it."""
        path, s, speed = self._draw_ego_start()
        x, y, heading = self.layout.paths.pose_at(np.array(path), np.array(s))
        traffic = self.traffic
        idx = traffic.indices
        traffic.remove(idx[np.hypot(traffic.pose[idx, 0] - x, traffic.pose[idx, 1] - y) < START_CLEARANCE])
        speed = self._start_speed(path, s, speed)
        self.ego = EgoState(float(x), float(y), float(heading), speed)

    def _draw_ego_start(self) -> tuple[int, float, float]:
        """The ego's start: a lane path of its arm, an arc length on it and a speed; with
        ``ego_start_standing``, at rest on one of its task's paths, possibly inside the junction."""
        cfg, layout, rng = self.config, self.layout, self.rng
        lanes = (
            range(layout.lanes)
            if cfg.ego_lane == "random"
            else sorted({layout.movements[p].lane for p in self._task_paths})
        )
        lane = int(rng.choice(list(lanes)))  # drawn first either way: the draws that follow stay as they were
        if cfg.ego_start_standing and rng.uniform() < cfg.ego_start_standing:
            path = int(rng.choice(self._task_paths))
            end = layout.junction_end_s[path] + STANDING_START_AFTER
            s = rng.uniform(layout.stop_s - STANDING_START_BEFORE, end)
            return path, float(s), 0.0
        path = layout.paths_from(EGO_ARM, lane=lane)[0]
        s = layout.stop_s - rng.uniform(*cfg.ego_start_distance)
        return path, float(s), float(rng.uniform(*cfg.ego_start_speed))

    def _start_speed(self, path: int, s: float, speed: float) -> float:
        """``speed``, capped so that the ego can stop 4 m behind the vehicle ahead of it on ``path``."""
        traffic, layout = self.traffic, self.layout
        idx = traffic.indices
        ahead_s, ahead_d = layout.paths.lookup(np.full(len(idx), path), traffic.pose[idx, :2])
        ahead = (np.abs(ahead_d) < VEHICLE_WIDTH + 0.5) & (ahead_s > s)
        gap = float(np.min(ahead_s[ahead] - s, initial=np.inf)) - VEHICLE_LENGTH
        return float(min(speed, np.sqrt(2.0 * self.config.deceleration * max(gap - 4.0, 0.0))))

    def _spawn_traffic(self, ego: Obstacle | None) -> None:
        if self.rng.uniform() < self.config.spawn_probability:
            self.traffic.spawn_random(ego)

    def step(self, action: int) -> StepOutcome:
        """Move the ego by one action, then the traffic; detect the outcome."""
        self.ego = self.motion.step(self.ego, action)
        ego = self.ego_obstacle()
        self.traffic.step(ego)
        crashed = self.traffic.detect_crashes(ego)
        self._spawn_traffic(ego)
        self.steps += 1
        self._candidates = self._routes = None
        self._record()
        exit_arm = self.layout.exit_reached(np.array([self.ego.x, self.ego.y]))
        success = exit_arm == TURN_OFFSET[self.task]
        return StepOutcome(
            crashed=crashed,
            offroad=not self.ego_on_road(self.ego),
            success=success,
            wrong_exit=exit_arm is not None and not success,
        )

    def close(self) -> None:
        """Release the traffic (SUMO's simulation ends)."""
        self.traffic.close()

    @property
    def time(self) -> float:
        """Seconds since the ego appeared."""
        return self.steps * DT

    # --- ego queries ---------------------------------------------------------------------------------
    def ego_obstacle(self) -> Obstacle:
        """The ego as the traffic sees it."""
        return Obstacle(self.ego.x, self.ego.y, self.ego.heading, self.ego.speed, path=self._task_paths[0])

    def ego_in_junction(self) -> bool:
        """Whether the ego's centre is inside the junction box, past its stop line and not yet past the
        exit's."""
        return max(abs(self.ego.x), abs(self.ego.y)) < self.layout.junction

    def ego_on_road(self, ego: EgoState) -> bool:
        """Whether all four corners of the ego's box are on the drivable area."""
        return bool(self._on_road(np.array([[ego.x, ego.y, ego.heading]]))[0])

    def _on_road(self, poses: FloatArray) -> NDArray[np.bool_]:
        corners = box_corners(poses[:, 0], poses[:, 1], poses[:, 2], VEHICLE_LENGTH, VEHICLE_WIDTH)
        return np.all(self.layout.is_drivable(corners[..., 0], corners[..., 1]), axis=-1)

    def sensed_bev(self) -> NDArray[np.uint8] | None:
        """The bird's-eye view as the simulator's own sensor gives it, (S, S) 0/1 with the ego at the
        centre, forward up; None where the observation draws it from the layout (ours)."""
        return None

    def action_mask(self) -> NDArray[np.bool_]:
        """Actions after which the ego can stay on the road.

        An action is allowed if the ego is on the road after it and, for ``mask_lookahead - 1`` more
        steps, some action held all along keeps it there. If no action passes, the actions that keep
        it on the road for the next step are allowed; if none does either, all of them. With
        ``mask_drive_on``, of those only the actions after which the ego can drive on that far
        (:meth:`_can_drive_on`), unless none can. Computed once per pose of the ego (an env's wrapper and
        its policy may both ask at the same step).
        """
        ego = (self.ego.x, self.ego.y, self.ego.heading, self.ego.speed)
        if self._mask is None or self._mask[0] != ego:
            self._mask = (ego, self._road_keeping_mask())
        return self._mask[1].copy()

    def _road_keeping_mask(self) -> NDArray[np.bool_]:
        """:meth:`action_mask`, computed."""
        motion, n = self.motion, len(self.motion.curvature)
        next_states = [motion.step(self.ego, action) for action in range(n)]
        poses = np.array([(s.x, s.y, s.heading) for s in next_states])
        next_step = self._on_road(poses)
        later = self.config.mask_lookahead - 1
        mask = next_step.copy()
        passed = np.flatnonzero(next_step)
        if later > 0 and len(passed):
            # Every passing action followed by every action held: (passed, held, later) poses at once.
            starts = np.repeat([next_states[action].as_array() for action in passed], n, axis=0)
            held = np.tile(np.arange(n), len(passed))
            poses_later = motion.rollout_many(starts, held, later).reshape(-1, 3)
            kept = self._on_road(poses_later).reshape(len(passed), n, later)
            mask[passed] = kept.all(axis=-1).any(axis=-1)
        if not mask.any():
            mask = next_step if next_step.any() else np.ones_like(next_step)
        if self.config.mask_drive_on:
            allowed = mask.copy()
            allowed[mask] = self._can_drive_on(poses[mask])
            if allowed.any():
                return allowed
        return mask

    def _can_drive_on(self, poses: FloatArray) -> NDArray[np.bool_]:
        """Whether from each pose (n, 3) some path of two arcs keeps the box on the road for
        ``mask_drive_on`` metres (:meth:`EgoMotion.two_arc_paths`). The single arcs are tried first: on a
        lane or in the junction one of them nearly always passes."""
        if self._drive_on_paths is None:
            paths = self.motion.two_arc_paths(self.config.mask_drive_on)
            singles = len(np.unique(self.motion.curvature))
            self._drive_on_paths = (paths[:singles], paths[singles:])
        passed = np.zeros(len(poses), dtype=bool)
        for paths in self._drive_on_paths:
            todo = np.flatnonzero(~passed)
            if not len(todo):
                break
            x, y, heading = (poses[todo, k, None, None] for k in range(3))
            positions = from_frame(paths[..., :2], (x, y), heading)
            world = np.concatenate((positions, (heading + paths[..., 2])[..., None]), axis=-1)
            on_road = self._on_road(world.reshape(-1, 3)).reshape(world.shape[:-1])
            passed[todo] = on_road.all(axis=-1).any(axis=-1)
        return passed

    def ego_routes(self) -> tuple[list[int], FloatArray]:
        """The ego's routes towards its task goal (see :meth:`_find_routes`), cached per step."""
        if self._routes is None:
            self._routes = self._find_routes()
        return self._routes

    def _find_routes(self) -> tuple[list[int], FloatArray]:
        """The ego's routes towards its task goal, nearest first, and its arc length on each.

        Before the stop line every path of the task is a route (a lane change may lead to it);
        after it, only paths within a lane width of the ego.
        """
        stop_s, lane_width = self.layout.stop_s, self.config.lane_width
        return self._nearest_routes(self._task_paths, lambda s, d: (s < stop_s) | (np.abs(d) < lane_width))

    def _nearest_routes(
        self,
        paths: list[int],
        keep: Callable[[FloatArray, FloatArray], NDArray[np.bool_]] | None = None,
    ) -> tuple[list[int], FloatArray]:
        """Up to ``num_routes`` of ``paths``, nearest the ego first, and the ego's arc length on each.

        :param keep: which paths may be routes, from the ego's arc length and lateral offset on each
            (the nearest path if none may); default all
        """
        lane_paths = np.array(paths)
        s, d = self.layout.paths.project(lane_paths, np.array([self.ego.x, self.ego.y]))
        order = np.argsort(np.abs(d))
        if keep is not None:
            kept = order[keep(s[order], d[order])]
            order = kept if len(kept) else order[:1]
        order = order[: self.config.num_routes]
        return [int(lane_paths[k]) for k in order], s[order]

    def subgoal_candidates(self) -> FloatArray:
        """The N subgoal candidates (x, y, heading) in world coordinates, cached per step."""
        if self._candidates is None:
            routes, s = self.ego_routes()
            self._candidates = self.sampler.sample(routes, s, self.task_goal)
        return self._candidates

    def neighbours(self) -> NDArray[np.int64]:
        """Slots of the N_s nearest other vehicles within the observation radius, nearest first."""
        idx = self.traffic.indices
        dist = np.hypot(self.traffic.pose[idx, 0] - self.ego.x, self.traffic.pose[idx, 1] - self.ego.y)
        order = np.argsort(dist, kind="stable")
        order = order[dist[order] <= self.config.observation_radius]
        return idx[order[: self.config.num_neighbours]]

    # --- pose history and ground-truth futures -----------------------------------------------------
    def _record(self, ego: bool = True) -> None:
        row = self.steps % self._hist_len
        traffic = self.traffic
        self._hist_uid[row] = -1
        idx = traffic.indices
        self._hist[row, idx, :3] = traffic.pose[idx]
        self._hist[row, idx, 3] = traffic.speed[idx]
        self._hist_uid[row, idx] = traffic.uid[idx]
        if ego:
            self._hist[row, self.ego_slot] = self.ego.as_array()
            self._hist_uid[row, self.ego_slot] = 0

    def slot_uids(self, slots: NDArray[np.int64]) -> NDArray[np.int64]:
        """Current unique ids of slots (the ego's is 0 in the history, never reused)."""
        uids = np.where(slots == self.ego_slot, 0, self.traffic.uid[np.minimum(slots, self.ego_slot - 1)])
        return uids.astype(np.int64)

    def poses_between(
        self, first: int, last: int, slots: NDArray[np.int64], uids: NDArray[np.int64]
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """World poses (x, y, heading, speed) of slots at steps first..last, and where they are valid.

        A pose is valid if it was recorded for the same vehicle (slots are reused) and is still in
        the history window.
        """
        steps = np.arange(first, last + 1)
        rows = steps % self._hist_len
        poses = self._hist[rows][:, slots]
        valid = (
            (self._hist_uid[rows][:, slots] == uids[None])
            & (steps <= self.steps)[:, None]
            & (steps > self.steps - self._hist_len)[:, None]
        )
        return poses, valid

    def begin_decision(self) -> DecisionRecord:
        """Remember the ego and the neighbours of the state now, for :meth:`decision_future`."""
        slots = np.concatenate([[self.ego_slot], self.neighbours()]).astype(np.int64)
        return DecisionRecord(
            self.steps,
            slots,
            self.slot_uids(slots),
            np.array([self.ego.x, self.ego.y]),
            self.ego.heading,
        )

    def decision_future(self, record: DecisionRecord) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth next T_f poses (x, y, heading) in the decision's ego frame, with presence flags.

        Rows follow the state's vehicle order (ego first) padded to N_s + 1; steps not simulated yet
        (the episode ended) are absent.
        """
        horizon, rows = self.config.prediction_horizon, self.config.num_neighbours + 1
        poses, valid = self.poses_between(record.step + 1, record.step + horizon, record.slots, record.uids)
        future = np.zeros((rows, horizon, 3), np.float32)
        present = np.zeros((rows, horizon), bool)
        n = len(record.slots)
        future[:n] = poses_to_frame(poses[..., :3], record.origin, record.heading).transpose(1, 0, 2)
        present[:n] = valid.T
        future[~present] = 0.0
        return future, present
