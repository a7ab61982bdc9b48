"""Other vehicles: the table the world reads (:class:`TrafficTable`) and our drivers that fill it
(:class:`Traffic`, config ``traffic: builtin``), route-following IDM drivers that yield by priority at the
junction. SUMO's drivers fill the same table with ``traffic: sumo`` (:mod:`gccp_envs.sumo`).

Every vehicle drives one lane path (no lane changes). Longitudinal control is the Intelligent Driver
Model towards the nearest obstacle ahead on its path: any vehicle, the ego included, whose box reaches
the path. Entering the junction follows a commit protocol that keeps crossing traffic apart:

- a vehicle commits to crossing when it reaches its commit point (where it can still stop comfortably
  at the stop line) and no conflicting vehicle is committed and still inside the shared zone, no
  conflicting vehicle with priority would reach the zone before it clears it, and the ego is not
  standing on its path inside the junction;
- until it commits it stops at the stop line; committed vehicles never yield on conflicts, so every
  waiting vehicle eventually goes;
- a vehicle that has stood at its stop line for ``npc_patience`` seconds goes before every vehicle
  that has not (SUMO's impatience): priority traffic not yet committed stops at its own stop line, which
  it can still do comfortably, and the impatient vehicle enters once the committed traffic has cleared.

Priority: out of patience first, then the east-west road, then straight-on and right turns before left
turns, then first come.
All state lives in fixed-capacity numpy arrays, so a step costs a few dozen vectorised operations.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.geometry import FloatArray, box_corners, boxes_overlap, wrap_angle
from gccp_envs.scenario import IntersectionLayout

VEHICLE_LENGTH = 5.0
"""Length [m] of every vehicle (highway-env's)."""
VEHICLE_WIDTH = 2.0
"""Width [m] of every vehicle (highway-env's)."""
STANDING = 0.5
"""Below this speed [m/s] a vehicle at its stop line counts as standing there (for its patience)."""
AT_THE_LINE = 2.0
"""A vehicle whose front is within this distance [m] of its stop line is at the line (for its patience;
a yielding vehicle stops ``DriverModel.stop_margin`` = 1 m before it)."""


@dataclass(frozen=True)
class DriverModel:
    """IDM constants of the other vehicles."""

    max_accel: float = 2.0
    """IDM maximum acceleration [m/s^2]."""
    comfort_decel: float = 3.0
    """IDM comfortable deceleration [m/s^2]; also sets the commit point before the stop line."""
    max_decel: float = 8.0
    """Hardest braking [m/s^2]."""
    min_gap: float = 2.0
    """IDM jam distance s0 [m], bumper to bumper."""
    lateral_margin: float = 0.4
    """Extra clearance [m] when deciding whether a box reaches a path."""
    lookahead: float = 60.0
    """Obstacles farther ahead than this [m] are ignored."""
    gap_time: float = 1.5
    """Seconds of margin between clearing a conflict zone and a priority vehicle reaching it."""
    stop_margin: float = 1.0
    """A yielding vehicle stops this far [m] before the stop line."""


@dataclass(frozen=True)
class Obstacle:
    """A vehicle the traffic must not hit but does not drive (the ego)."""

    x: float
    y: float
    heading: float
    speed: float
    length: float = VEHICLE_LENGTH
    width: float = VEHICLE_WIDTH
    path: int | None = None
    """Lane path of its task, for a traffic that routes it in its own simulation (SUMO's)."""


class TrafficTable(ABC):
    """The other vehicles of one episode as the world reads them, in fixed-capacity arrays (inactive
    slots are ignored). A backend drives them: :class:`Traffic` (ours) or
    :class:`gccp_envs.sumo.traffic.SumoTraffic` (SUMO's); crashes are detected here, for both.

    :param layout: the junction
    :param config: the world config
    :param rng: the source of the first episode's randomness
    """

    def __init__(
        self, layout: IntersectionLayout, config: IntersectionConfig, rng: np.random.Generator
    ) -> None:
        self.layout = layout
        self.config = config
        self.reset(rng)

    def reset(self, rng: np.random.Generator) -> None:
        """Empty the road for a new episode whose randomness is ``rng``."""
        self.rng = rng
        m = self.config.max_vehicles
        self.active = np.zeros(m, bool)
        self.path = np.zeros(m, np.int64)
        """Lane path each vehicle drives along."""
        self.s = np.zeros(m)
        """Arc length [m] of each vehicle's centre along its path."""
        self.speed = np.zeros(m)
        self.crashed = np.zeros(m, bool)
        self.crash_timer = np.zeros(m)
        self.uid = np.full(m, -1, np.int64)
        """Unique id of each vehicle in the episode (slots are reused)."""
        self.length = np.full(m, VEHICLE_LENGTH)
        self.width = np.full(m, VEHICLE_WIDTH)
        self.pose = np.zeros((m, 3))
        """World pose (x, y, heading) of each vehicle's centre."""
        self.spawned = 0
        """Vehicles spawned this episode."""
        self.crashed_uids: set[int] = set()
        """Unique ids of the vehicles that crashed into another vehicle or the ego this episode."""

    @property
    def indices(self) -> NDArray[np.int64]:
        """Slots of the active vehicles."""
        return np.flatnonzero(self.active)

    @abstractmethod
    def spawn_random(self, ego: Obstacle | None = None) -> int | None:
        """Spawn one vehicle at the start of a random inbound lane on a random allowed movement."""

    @abstractmethod
    def step(self, ego: Obstacle | None = None) -> None:
        """Advance all vehicles by one 0.1 s step, then remove those that left or crashed long ago."""

    def remove(self, slots: NDArray[np.int64]) -> None:
        """Take vehicles off the road."""
        self.active[slots] = False

    def close(self) -> None:  # noqa: B027  (a hook: only a backend running a simulation has one to end)
        """Release what the traffic holds outside this object (nothing here)."""

    def detect_crashes(self, ego: Obstacle | None = None) -> bool:
        """Mark vehicles whose boxes overlap another's; return whether the ego was hit."""
        idx = self.indices
        if not len(idx):
            return False
        xy = self.pose[idx, :2]
        near = (
            np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1]) < VEHICLE_LENGTH + 0.5
        )
        i, j = np.nonzero(np.triu(near, 1))
        hit = np.zeros(len(idx), bool)
        if len(i):
            overlap = boxes_overlap(self._corners(idx[i]), self._corners(idx[j]))
            hit[i[overlap]] = hit[j[overlap]] = True
        ego_hit = False
        if ego is not None:
            close = np.flatnonzero(np.hypot(xy[:, 0] - ego.x, xy[:, 1] - ego.y) < VEHICLE_LENGTH + ego.length)
            if len(close):
                ego_box = box_corners(
                    np.array(ego.x),
                    np.array(ego.y),
                    np.array(ego.heading),
                    np.array(ego.length),
                    np.array(ego.width),
                )
                by_ego = boxes_overlap(self._corners(idx[close]), ego_box[None])
                hit[close[by_ego]] = True
                ego_hit = bool(by_ego.any())
        newly = idx[hit & ~self.crashed[idx]]
        self.crashed[newly] = True
        self.speed[newly] = 0.0
        self.crashed_uids.update(int(u) for u in self.uid[newly])
        return ego_hit

    def _corners(self, slots: NDArray[np.int64]) -> FloatArray:
        pose = self.pose[slots]
        return box_corners(pose[:, 0], pose[:, 1], pose[:, 2], self.length[slots], self.width[slots])


class Traffic(TrafficTable):
    """Our drivers: IDM along their lane paths and the commit protocol at the junction (module doc)."""

    def __init__(
        self,
        layout: IntersectionLayout,
        config: IntersectionConfig,
        rng: np.random.Generator,
        driver: DriverModel | None = None,
    ) -> None:
        self.driver = driver or DriverModel()
        super().__init__(layout, config, rng)

    def reset(self, rng: np.random.Generator) -> None:
        """Empty the road for a new episode whose randomness is ``rng``."""
        super().reset(rng)
        m = self.config.max_vehicles
        self.desired_speed = np.ones(m)
        self.headway = np.ones(m)
        self.committed = np.zeros(m, bool)
        self.waited = np.zeros(m)
        """Seconds each vehicle has stood at its stop line, not committed."""
        self.order = np.zeros(m, np.int64)
        self._next_uid = 0

    # --- bookkeeping -------------------------------------------------------------------------------
    def _refresh_poses(self) -> None:
        idx = self.indices
        if len(idx):
            self.pose[idx] = self.layout.paths.pose_at(self.path[idx], self.s[idx])

    def priority_key(self, idx: NDArray[np.int64]) -> NDArray[np.int64]:
        """Sort key of vehicles: lower goes first (out of patience, priority road, not turning left,
        first come)."""
        rank = 2 * (~self.layout.path_major[self.path[idx]]) + (self.layout.path_turn[self.path[idx]] == 0)
        rank = rank.astype(np.int64) - 4 * self.impatient(idx)
        return rank * 10**9 + self.order[idx]

    def impatient(self, idx: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Whether each vehicle has stood at its stop line for ``npc_patience`` seconds."""
        patience = self.config.npc_patience
        return np.zeros(len(idx), bool) if patience is None else self.waited[idx] >= patience - 1e-6

    # --- spawning ------------------------------------------------------------------------------------
    def spawn(
        self, path: int, s: float, ego: Obstacle | None = None, speed: float | None = None
    ) -> int | None:
        """Place a vehicle on ``path`` at arc length ``s`` if there is room; return its slot.

        The speed is capped so that the vehicle can stop comfortably behind whatever is ahead.
        """
        free = np.flatnonzero(~self.active)
        if not len(free):
            return None
        xy = self.layout.paths.pose_at(np.array(path), np.array(s))[:2]
        others = self._obstacle_table(ego)
        if len(others[0]) and np.min(np.hypot(others[0] - xy[0], others[1] - xy[1])) < 15.0:
            return None
        slot = int(free[0])
        low, high = self.config.npc_speed_range
        self.desired_speed[slot] = self.rng.uniform(low, high)
        self.headway[slot] = self.rng.uniform(*self.config.npc_time_headway)
        gap, _ = self._gaps(
            np.array([path]),
            np.array([s]),
            np.array([VEHICLE_LENGTH]),
            np.array([VEHICLE_WIDTH]),
            others,
            np.array([-2]),
        )
        safe = np.sqrt(2.0 * self.driver.comfort_decel * max(float(gap[0]) - self.driver.min_gap, 0.0))
        start_speed = self.desired_speed[slot] if speed is None else speed
        self.active[slot], self.path[slot], self.s[slot] = True, path, s
        self.speed[slot] = min(start_speed, safe)
        self.committed[slot] = self.crashed[slot] = False
        self.crash_timer[slot] = self.waited[slot] = 0.0
        self.uid[slot] = self._next_uid
        self.order[slot] = self._next_uid
        self._next_uid += 1
        self.spawned += 1
        self.pose[slot] = self.layout.paths.pose_at(np.array(path), np.array(s))
        return slot

    def spawn_random(self, ego: Obstacle | None = None) -> int | None:
        """Spawn one vehicle at the start of a random inbound lane on a random allowed movement."""
        layout = self.layout
        entry = int(self.rng.integers(4 * layout.lanes))
        choices = np.flatnonzero(layout.path_entry == entry)
        path = int(self.rng.choice(choices))
        return self.spawn(path, float(self.rng.uniform(0.0, 2.0)), ego)

    # --- one step ----------------------------------------------------------------------------------
    def step(self, ego: Obstacle | None = None) -> None:
        """Advance all vehicles by one 0.1 s step, then remove those that left or crashed long ago."""
        idx = self.indices
        if len(idx):
            obstacles = self._obstacle_table(ego)
            gap, lead_speed = self._gaps(
                self.path[idx], self.s[idx], self.length[idx], self.width[idx], obstacles, idx
            )
            stop_gap = self._junction_control(idx, ego)
            use_stop = stop_gap < gap
            gap = np.where(use_stop, stop_gap, gap)
            lead_speed = np.where(use_stop, 0.0, lead_speed)
            accel = self._idm(idx, gap, lead_speed)
            moving = ~self.crashed[idx]
            new_speed = np.maximum(self.speed[idx] + accel * DT, 0.0)
            advance = np.where(moving, 0.5 * (self.speed[idx] + new_speed) * DT, 0.0)
            self.s[idx] += advance
            self.speed[idx] = np.where(moving, new_speed, 0.0)
            past_line = self.s[idx] + self.length[idx] / 2.0 > self.layout.stop_s
            self.committed[idx] |= past_line
        self._refresh_poses()
        self.crash_timer[self.crashed] += DT
        done = self.active & (
            (self.s >= self.layout.paths.lengths[self.path] - 1.0)
            | (self.crash_timer > self.config.crashed_vehicle_lifetime)
        )
        self.remove(np.flatnonzero(done))

    # --- driver model --------------------------------------------------------------------------------
    def _obstacle_table(self, ego: Obstacle | None) -> tuple[FloatArray, ...]:
        """Columns x, y, heading, speed, length, width, slot (-1 for the ego) of everything on the road."""
        idx = self.indices
        cols = [
            self.pose[idx, 0],
            self.pose[idx, 1],
            self.pose[idx, 2],
            self.speed[idx],
            self.length[idx],
            self.width[idx],
            idx.astype(float),
        ]
        if ego is not None:
            extra = [ego.x, ego.y, ego.heading, ego.speed, ego.length, ego.width, -1.0]
            cols = [np.append(c, e) for c, e in zip(cols, extra, strict=True)]
        return tuple(cols)

    def _gaps(
        self,
        path: NDArray[np.int64],
        s: FloatArray,
        length: FloatArray,
        width: FloatArray,
        obstacles: tuple[FloatArray, ...],
        slots: NDArray[np.int64],
    ) -> tuple[FloatArray, FloatArray]:
        """Bumper gap to, and along-path speed of, the nearest obstacle ahead on each vehicle's path.

        When two vehicles each see the other ahead (crossing paths), only the one with lower priority
        treats the other as an obstacle.
        """
        ox, oy, oh, ov, ol, ow, oslot = obstacles
        n = len(path)
        if not len(ox):
            return np.full(n, np.inf), np.zeros(n)
        paths = self.layout.paths
        proj_s, proj_d = paths.lookup(path[:, None], np.stack((ox, oy), -1)[None])
        path_heading = paths.pose_at(np.broadcast_to(path[:, None], proj_s.shape), proj_s)[..., 2]
        rel = wrap_angle(oh[None] - path_heading)
        cos_r, sin_r = np.abs(np.cos(rel)), np.abs(np.sin(rel))
        lateral_extent = ol[None] / 2.0 * sin_r + ow[None] / 2.0 * cos_r
        longitudinal_extent = ol[None] / 2.0 * cos_r + ow[None] / 2.0 * sin_r
        on_path = np.abs(proj_d) < width[:, None] / 2.0 + lateral_extent + self.driver.lateral_margin
        ahead = (proj_s > s[:, None]) & (oslot[None] != slots[:, None])
        gap = proj_s - longitudinal_extent - s[:, None] - length[:, None] / 2.0
        sees = on_path & ahead & (gap < self.driver.lookahead)
        if np.array_equal(oslot[:n], slots):
            # The rows are the table's first columns: settle mutual sightings by priority.
            square = sees[:, :n]
            key = self.priority_key(slots)
            square &= ~(square & square.T & (key[:, None] < key[None, :]))
        gap = np.where(sees, gap, np.inf)
        nearest = np.argmin(gap, axis=1)
        rows = np.arange(n)
        lead_gap = gap[rows, nearest]
        lead_speed = np.maximum(ov[nearest] * np.cos(rel[rows, nearest]), 0.0)
        return lead_gap, np.where(np.isfinite(lead_gap), lead_speed, 0.0)

    def _idm(self, idx: NDArray[np.int64], gap: FloatArray, lead_speed: FloatArray) -> FloatArray:
        drv = self.driver
        v = self.speed[idx]
        sample = np.minimum(
            (self.s[idx] / self.layout.paths.resolution).astype(np.int64),
            self.layout.speed_profile.shape[1] - 1,
        )
        v_des = np.maximum(
            np.minimum(self.desired_speed[idx], self.layout.speed_profile[self.path[idx], sample]),
            0.5,
        )
        free = drv.max_accel * (1.0 - (v / v_des) ** 4)
        desired_gap = drv.min_gap + np.maximum(
            v * self.headway[idx] + v * (v - lead_speed) / (2.0 * np.sqrt(drv.max_accel * drv.comfort_decel)),
            0.0,
        )
        interaction = np.where(
            np.isfinite(gap), drv.max_accel * (desired_gap / np.maximum(gap, 0.01)) ** 2, 0.0
        )
        return np.clip(free - interaction, -drv.max_decel, drv.max_accel)

    # --- junction protocol ---------------------------------------------------------------------------
    def _distance_to_stop(self, idx: NDArray[np.int64]) -> FloatArray:
        return self.layout.stop_s - (self.s[idx] + self.length[idx] / 2.0)

    def _blocked(self, i: NDArray[np.int64], ego: Obstacle | None) -> NDArray[np.bool_]:
        """Whether each not-yet-committed vehicle in ``i`` must wait at its stop line now."""
        layout, drv = self.layout, self.driver
        j = self.indices
        pi, pj = self.path[i][:, None], self.path[j][None, :]
        conflict = layout.conflict[pi, pj] & (i[:, None] != j[None, :])
        j_zone_end = layout.zone_end[pj, pi]
        j_inside = self.s[j][None, :] - self.length[j][None, :] / 2.0 < j_zone_end
        by_committed = conflict & self.committed[j][None, :] & j_inside
        # Priority traffic that would reach the shared zone before this vehicle clears it.
        key_i, key_j = self.priority_key(i), self.priority_key(j)
        j_first = key_j[None, :] < key_i[:, None]
        j_eta = (
            np.maximum(layout.zone_start[pj, pi] - (self.s[j] + self.length[j] / 2.0)[None, :], 0.0)
            / np.maximum(self.speed[j], 1.0)[None, :]
        )
        j_eta[:, self.impatient(j)] = 0.0  # it goes as soon as the committed traffic has cleared
        clear_distance = layout.zone_end[pi, pj] + self.length[i][:, None] / 2.0 - self.s[i][:, None]
        v = self.speed[i][:, None]
        clear_time = (
            np.sqrt(v**2 + 2.0 * drv.max_accel * np.maximum(clear_distance, 0.0)) - v
        ) / drv.max_accel
        by_priority = (
            conflict & ~self.committed[j][None, :] & j_first & j_inside & (j_eta < clear_time + drv.gap_time)
        )
        blocked = (by_committed | by_priority).any(axis=1)
        if ego is not None:
            blocked |= self._ego_in_junction_path(i, ego)
        return blocked

    def _ego_in_junction_path(self, i: NDArray[np.int64], ego: Obstacle) -> NDArray[np.bool_]:
        layout = self.layout
        if max(abs(ego.x), abs(ego.y)) > layout.junction + ego.length:
            return np.zeros(len(i), bool)
        s, d = layout.paths.project(self.path[i], np.array([ego.x, ego.y]))
        reach = VEHICLE_WIDTH / 2.0 + ego.length / 2.0 + self.driver.lateral_margin
        return (
            (np.abs(d) < reach)
            & (s > layout.stop_s - ego.length)
            & (s < layout.junction_end_s[self.path[i]] + ego.length)
        )

    def _junction_control(self, idx: NDArray[np.int64], ego: Obstacle | None) -> FloatArray:
        """Commit waiting vehicles that may enter; return the gap to the stop line of the others.

        Vehicles at their commit point enter in priority order; one that conflicts with a vehicle
        committed earlier in the same step waits for the next step.
        """
        drv, layout = self.driver, self.layout
        gaps = np.full(len(idx), np.inf)
        rows = np.flatnonzero(~self.committed[idx])
        if not len(rows):
            return gaps
        waiting = idx[rows]
        v = self.speed[waiting]
        distance = self._distance_to_stop(waiting)
        self.waited[waiting] += np.where((distance < AT_THE_LINE) & (v < STANDING), DT, 0.0)
        blocked = self._blocked(waiting, ego)
        commit_distance = drv.min_gap + v**2 / (2.0 * drv.comfort_decel) + v * DT
        ready = np.flatnonzero(~blocked & (distance <= commit_distance + drv.stop_margin))
        entered: list[int] = []
        for k in ready[np.argsort(self.priority_key(waiting[ready]))]:
            slot = waiting[k]
            if entered and layout.conflict[self.path[slot], self.path[entered]].any():
                blocked[k] = True
                continue
            self.committed[slot] = True
            entered.append(slot)
        stop = np.maximum(distance - drv.stop_margin + drv.min_gap, 0.0)
        gaps[rows[blocked]] = stop[blocked]
        return gaps
