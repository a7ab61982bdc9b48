"""The road: an unsignalised four-way junction with multi-lane approaches and a priority road.

Arms are numbered as in highway-env: 0 south, 1 west, 2 north, 3 east. The ego always comes from the
south; destination arm 1 is a left turn, 2 straight on, 3 a right turn. The east-west road has priority.
Lane 0 is the innermost lane of an arm. Turning left is allowed from lane 0, turning right from the
outermost lane, going straight from every lane, each into the exit lane of the same rank.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from highway_env.road.lane import CircularLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork
from numpy.typing import NDArray

from gccp_envs.config import TASKS, IntersectionConfig
from gccp_envs.geometry import FloatArray, PathSet, Segment, wrap_angle

TURN_OFFSET = {"left": 1, "straight": 2, "right": 3}
"""Exit arm minus entry arm (mod 4) of each movement."""
MAJOR_ARMS = (1, 3)
"""Arms of the priority road."""
CONFLICT_DISTANCE = 3.5
"""Paths closer than this [m] inside the junction conflict; parallel lanes are a lane width apart."""


@dataclass(frozen=True)
class Movement:
    """One lane path through the junction: entry arm and lane, turn, exit arm and lane."""

    arm: int
    lane: int
    turn: str
    exit_arm: int
    exit_lane: int


def _rotation(arm: int) -> FloatArray:
    angle = arm * np.pi / 2.0
    return np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])


def _rotate_segment(seg: Segment, arm: int) -> Segment:
    rot = _rotation(arm)
    if seg.radius == 0.0:
        start, direction = rot @ np.array(seg.start), rot @ np.array(seg.direction)
        return Segment(seg.length, (start[0], start[1]), (direction[0], direction[1]))
    center = rot @ np.array(seg.center)
    return Segment(
        seg.length,
        center=(center[0], center[1]),
        radius=seg.radius,
        phase0=seg.phase0 + arm * np.pi / 2.0,
        sense=seg.sense,
    )


class IntersectionLayout:
    """Geometry of the junction: lane paths, conflict zones, speed profiles and the drivable area."""

    def __init__(
        self,
        lanes: int,
        lane_width: float,
        corner_radius: float,
        approach_length: float,
        exit_distance: float,
        max_lateral_accel: float = 2.5,
        comfort_decel: float = 2.0,
        top_speed: float = 12.0,
    ) -> None:
        self.lanes = lanes
        self.lane_width = lane_width
        self.half_width = lanes * lane_width
        self.corner_radius = corner_radius
        self.junction = self.half_width + corner_radius
        self.approach_length = approach_length
        self.exit_distance = exit_distance
        self.extent = self.junction + approach_length
        self.movements: list[Movement] = []
        segments: list[list[Segment]] = []
        for arm in range(4):
            for lane in range(lanes):
                for turn in TASKS:
                    if (turn == "left" and lane != 0) or (turn == "right" and lane != lanes - 1):
                        continue
                    exit_lane = {"left": 0, "right": lanes - 1}.get(turn, lane)
                    move = Movement(arm, lane, turn, (arm + TURN_OFFSET[turn]) % 4, exit_lane)
                    self.movements.append(move)
                    segments.append([_rotate_segment(seg, arm) for seg in self._local_path(move)])
        self.paths = PathSet(segments)
        self.paths.build_lookup(self.extent + 5.0)
        self.stop_s = approach_length
        """Arc length of the stop line on every path."""
        self.junction_end_s = np.array([approach_length + path[1].length for path in segments])
        self.path_arm = np.array([m.arm for m in self.movements])
        self.path_lane = np.array([m.lane for m in self.movements])
        self.path_entry = self.path_arm * lanes + self.path_lane
        self.path_turn = np.array([TASKS.index(m.turn) for m in self.movements])
        self.path_major = np.isin(self.path_arm, MAJOR_ARMS)
        self.speed_profile = self._speed_profiles(max_lateral_accel, comfort_decel, top_speed)
        self.zone_start, self.zone_end = self._conflict_zones()
        self.conflict = np.isfinite(self.zone_start)

    # --- construction ----------------------------------------------------------------------------
    def lane_offset(self, lane: int) -> float:
        """Distance [m] of a lane's centre line from the road's centre line."""
        return self.lane_width / 2.0 + lane * self.lane_width

    def _local_path(self, move: Movement) -> list[Segment]:
        """Segments of a movement from arm 0, before rotation to its arm."""
        j, a = self.junction, self.approach_length
        x_in = self.lane_offset(move.lane)
        approach = Segment.line(np.array([x_in, j + a]), np.array([x_in, j]))
        exit_lane = self.lane_offset(move.exit_lane)
        if move.turn == "straight":
            connector = Segment.line(np.array([x_in, j]), np.array([x_in, -j]))
            exit_line = Segment.line(np.array([x_in, -j]), np.array([x_in, -j - a]))
        elif move.turn == "left":
            connector = Segment.arc(np.array([-j, j]), j + x_in, 0.0, -np.pi / 2.0)
            exit_line = Segment.line(np.array([-j, -exit_lane]), np.array([-j - a, -exit_lane]))
        else:
            connector = Segment.arc(np.array([j, j]), j - x_in, np.pi, 1.5 * np.pi)
            exit_line = Segment.line(np.array([j, exit_lane]), np.array([j + a, exit_lane]))
        return [approach, connector, exit_line]

    def _speed_profiles(self, max_lateral_accel: float, decel: float, top_speed: float) -> FloatArray:
        """Highest speed at every sample that still allows comfortable braking into the turns."""
        curvature = self.paths.curvature
        limit = np.where(curvature > 0, np.sqrt(max_lateral_accel / np.maximum(curvature, 1e-9)), top_speed)
        limit = np.minimum(limit, top_speed)
        step = 2.0 * decel * self.paths.resolution
        for k in range(limit.shape[1] - 2, -1, -1):
            limit[:, k] = np.minimum(limit[:, k], np.sqrt(limit[:, k + 1] ** 2 + step))
        return limit

    def _conflict_zones(self) -> tuple[FloatArray, FloatArray]:
        """Zone ``[start[p, q], end[p, q]]`` of path p inside the junction where it comes near path q.

        Pairs with the same entry lane queue behind each other instead and get no zone (``inf``).
        """
        n = len(self.movements)
        start, end = np.full((n, n), np.inf), np.full((n, n), np.inf)
        res = self.paths.resolution
        for p in range(n):
            s = np.arange(self.stop_s, self.junction_end_s[p] + res, res)
            points = self.paths.pose_at(np.full(len(s), p), s)[:, :2]
            for q in range(n):
                if self.path_entry[p] == self.path_entry[q]:
                    continue
                sq, _dq = self.paths.project(np.full(len(s), q), points)
                on_q = self.paths.pose_at(np.full(len(s), q), sq)[:, :2]
                near = np.hypot(*(points - on_q).T) < CONFLICT_DISTANCE
                if near.any():
                    start[p, q], end[p, q] = s[near].min(), s[near].max()
        return start, end

    # --- queries -----------------------------------------------------------------------------------
    def paths_from(self, arm: int, lane: int | None = None, turn: str | None = None) -> list[int]:
        """Indices of the paths entering on ``arm`` (and ``lane``) making ``turn``."""
        return [
            i
            for i, m in enumerate(self.movements)
            if m.arm == arm and (lane is None or m.lane == lane) and (turn is None or m.turn == turn)
        ]

    def is_drivable(self, x: FloatArray, y: FloatArray) -> NDArray[np.bool_]:
        """Whether world points lie on the road: both roads plus the rounded junction corners."""
        ax, ay = np.abs(x), np.abs(y)
        w, j = self.half_width, self.junction
        roads = ((ax <= w) & (ay <= self.extent)) | ((ay <= w) & (ax <= self.extent))
        corners = (ax <= j) & (ay <= j) & ((ax - j) ** 2 + (ay - j) ** 2 >= self.corner_radius**2)
        return roads | corners

    def to_arm(self, arm: int, points: FloatArray) -> FloatArray:
        """Express world points in the frame of ``arm`` (the frame in which that arm is the south one)."""
        return points @ _rotation(arm)

    def exit_reached(self, position: FloatArray) -> int | None:
        """The arm whose outbound lanes ``position`` has left the junction on, past the exit distance."""
        for arm in range(4):
            x, y = self.to_arm(arm, position)
            if -self.half_width <= x <= 0.0 and y >= self.junction + self.exit_distance:
                return arm
        return None

    def task_goal(self, task: str) -> FloatArray:
        """The task goal (x, y, heading): the middle of the exit road at the exit distance."""
        arm = TURN_OFFSET[task]
        local = np.array([-self.half_width / 2.0, self.junction + self.exit_distance])
        x, y = _rotation(arm) @ local
        return np.array([x, y, float(wrap_angle(np.pi / 2.0 + arm * np.pi / 2.0))])

    def road_network(self) -> RoadNetwork:
        """A highway-env road network of the same lanes, used to draw the road."""
        net = RoadNetwork()
        n, c, s = LineType.NONE, LineType.CONTINUOUS, LineType.STRIPED
        outer = self.lanes - 1
        added: set[tuple[str, int]] = set()
        for move in self.movements:
            approach, connector, exit_line = (
                _rotate_segment(seg, move.arm) for seg in self._local_path(move)
            )
            if ("in", move.arm * self.lanes + move.lane) not in added:
                added.add(("in", move.arm * self.lanes + move.lane))
                net.add_lane(
                    f"o{move.arm}",
                    f"ir{move.arm}",
                    self._hw_lane(approach, [s if move.lane == 0 else n, c if move.lane == outer else s]),
                )
            right_kerb = c if move.turn == "right" else n
            net.add_lane(f"ir{move.arm}", f"il{move.exit_arm}", self._hw_lane(connector, [n, right_kerb]))
            if ("out", move.exit_arm * self.lanes + move.exit_lane) not in added:
                added.add(("out", move.exit_arm * self.lanes + move.exit_lane))
                net.add_lane(
                    f"il{move.exit_arm}",
                    f"o{move.exit_arm}",
                    self._hw_lane(exit_line, [n, c if move.exit_lane == outer else s]),
                )
        return net

    @staticmethod
    def _hw_lane(seg: Segment, line_types: list[LineType]) -> StraightLane | CircularLane:
        if seg.radius == 0.0:
            start = np.array(seg.start)
            end = start + seg.length * np.array(seg.direction)
            return StraightLane(start, end, line_types=line_types)
        return CircularLane(
            np.array(seg.center),
            seg.radius,
            seg.phase0,
            seg.phase0 + seg.sense * seg.length / seg.radius,
            clockwise=seg.sense > 0,
            line_types=line_types,
        )


@lru_cache(maxsize=8)
def _cached_layout(
    lanes: int,
    lane_width: float,
    corner_radius: float,
    approach_length: float,
    exit_distance: float,
) -> IntersectionLayout:
    return IntersectionLayout(lanes, lane_width, corner_radius, approach_length, exit_distance)


def layout_for(config: IntersectionConfig) -> IntersectionLayout:
    """The (per-process cached) layout of a config."""
    return _cached_layout(
        config.lanes_per_approach,
        config.lane_width,
        config.corner_radius,
        config.approach_length,
        config.exit_distance,
    )
