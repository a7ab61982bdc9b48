"""Scripted controllers: a geometric motion-planner and a simple decision-maker.

They make the option env usable before anything is trained, serve as sanity baselines, and drive
the tests. Both take observations exactly as the learned policies do.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from gccp_envs.action import EgoAction, EgoMotion
from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.geometry import wrap_angle

ALIGNED = 0.05
"""Heading error [rad] a turn must remove before the stopping scripted planner takes it."""

_ACCELERATING_TURN = (EgoAction.KEEP_DIRECTION, EgoAction.QUICKLY_TURN_LEFT, EgoAction.QUICKLY_TURN_RIGHT)
"""The actions the scripted planner steers with below ``scripted_turn_speed``."""


class ScriptedPlanner:
    """Pure pursuit towards the goal point, braking to stop on it (with ``scripted_stop_aligned``, a
    turn towards the goal's heading first where one step of it removes more than ``ALIGNED``).

    Call it with a planner observation (``goal`` in the ego frame) and the action mask.
    """

    def __init__(self, config: IntersectionConfig) -> None:
        self.config = config
        slow, quick = config.slow_turn_curvature, config.quick_turn_curvature
        self._turns = {
            EgoAction.KEEP_DIRECTION: 0.0,
            EgoAction.SLOWLY_TURN_LEFT: -slow,
            EgoAction.SLOWLY_TURN_RIGHT: slow,
            EgoAction.QUICKLY_TURN_LEFT: -quick,
            EgoAction.QUICKLY_TURN_RIGHT: quick,
        }

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The action for one step."""
        cfg = self.config
        x, y = float(obs["goal"][0]), float(obs["goal"][1])
        speed = float(obs["history"][0, -1, 7])
        distance = float(np.hypot(x, y))
        # Stop on the goal: brake when faster than the speed that still stops in the distance left.
        target_speed = min(cfg.cruise_speed, np.sqrt(2.0 * cfg.deceleration * max(distance - 1.0, 0.0)))
        if x < 0.5:  # goal beside or behind: stand still rather than circle
            target_speed = 0.0
        curvature = 2.0 * y / max(distance**2, 1e-6)
        ranked = sorted(self._turns, key=lambda a: abs(self._turns[a] - curvature))
        if target_speed == 0.0 and cfg.scripted_stop_aligned and speed > 1.0:
            # Stopping: a turn that brings the heading closer to the goal's first, then braking.
            misalignment = float(obs["goal"][2])
            turns = {a: misalignment - k * speed * DT for a, k in self._turns.items()}
            best = min(turns, key=lambda a: abs(turns[a]))
            first = [best] if abs(turns[best]) < abs(misalignment) - ALIGNED else []
            ranked = [*first, EgoAction.SLOW_DOWN, *ranked]
        elif target_speed == 0.0 or speed > target_speed + 0.2:
            ranked = [EgoAction.SLOW_DOWN, *ranked]
        elif ranked[0] != EgoAction.KEEP_DIRECTION and speed < 1.0 and target_speed > 0.0:
            ranked = [EgoAction.KEEP_DIRECTION, *ranked]  # turning needs speed
        elif ranked[0] != EgoAction.KEEP_DIRECTION and speed < min(cfg.scripted_turn_speed, target_speed):
            # A turn holds the speed: alternate accelerating straight with quick turns, pursuit's
            # feedback choosing which, until the turn can be driven at speed.
            ranked = [a for a in ranked if a in _ACCELERATING_TURN] + ranked
        for action in ranked:
            if action_mask is None or action_mask[int(action)]:
                return int(action)
        return int(EgoAction.SLOW_DOWN)


HOLD_SPEED_COST = 0.2
"""Steps of later arrival [1/(m/s)] the search planner trades for each m/s less at the end on a hold."""
CRAWL_SPEED = 1.0
"""Below this speed [m/s], with the goal out of reach, the search planner speeds up ('keep direction')."""
ROLLOUT_CACHE_SIZE = 128
"""Rollouts the search planner keeps, by speed, the least recently used dropped first (about 4.1 MB
each). Speeds recur: a turn holds its speed, and from a standstill or at cruise speed the ego passes the
same ones; over 20,000 expert steps 128 of them missed as rarely as 512 kept first in, first out."""
BOX_HALF_LENGTH = 2.5
"""Half the ego's length [m] (the vehicles' 5 m)."""
BOX_HALF_WIDTH = 1.0
"""Half the ego's width [m] (the vehicles' 2 m)."""


class SearchPlanner:
    """Earliest arrival over a fixed library of action sequences, by the ego's exact kinematics.

    Every step it rolls out, from the ego's speed, each sequence of the library for ``horizon`` steps:
    one action held, then another held to the end (all 6 x 6 pairs and switch times), and the lane
    change's S-curve: a turn, the opposite turn, then 'keep direction' or 'slow down'. A sequence counts
    only up to its first step whose box leaves the drivable area of the observation's BEV. It takes the
    first action of the sequence that reaches the goal (within ``radius_share`` of the reach radius and
    ``heading_share`` of the heading tolerance, or, if none does, within the full radius and tolerance)
    soonest, the faster of equally soon ones, or, if none does, of the one that ends on the goal's
    line, heading its way, at speed. A goal beside or behind the ego within 3 m (farther on its lane with
    ``brake_behind``), or already reached, means braking. It never takes a masked action (unless all
    are masked). Like :class:`ScriptedPlanner` it sees the observation only and ignores traffic (the
    decision-maker's job); it reaches more subgoals because it plans the heading as well as the position
    (docs/results.md, the motion-planner).
    """

    def __init__(
        self,
        config: IntersectionConfig,
        horizon: int = 30,
        radius_share: float = 0.75,
        heading_share: float = 0.8,
        hold_distance: float | None = None,
        max_lateral_acceleration: float | None = None,
        limit_from_goal_heading: float = 0.0,
        brake_behind: bool = False,
        brake_behind_heading: float = np.pi,
    ) -> None:
        if max_lateral_acceleration is not None and not max_lateral_acceleration > 0:
            raise ValueError(f"max_lateral_acceleration must be positive, got {max_lateral_acceleration!r}")
        if not 0.0 <= brake_behind_heading <= np.pi:
            raise ValueError(f"brake_behind_heading must be in [0, pi], got {brake_behind_heading!r}")
        if not 0.0 <= limit_from_goal_heading < np.pi:
            raise ValueError(f"limit_from_goal_heading must be in [0, pi), got {limit_from_goal_heading!r}")
        self.config = config
        self.horizon = horizon
        self.max_lateral_acceleration = max_lateral_acceleration
        """Lateral acceleration [m/s²] no step of a chosen sequence may exceed (speed² x the action's
        curvature), unless no allowed sequence keeps within it: a turn too tight for the speed is entered
        only after braking. None: no limit."""
        self.limit_from_goal_heading = limit_from_goal_heading
        """The limit holds only for a goal whose heading differs from the ego's by at least this [rad]: 0,
        for every goal; about 0.5, for a goal on a turn but not one on the next lane (a lane change at
        speed needs quick turns)."""
        self.hold_distance = config.subgoal_reach_radius if hold_distance is None else hold_distance
        """A goal on the ego's lane at most this far ahead [m] is a hold (a subgoal drawn to drive to lies
        farther: ``GCCPPlanner-v0`` draws them beyond the reach radius): of the sequences that reach it
        soonest, take the one that ends slowest, so that the car stands on it rather than drives
        through it. 0: only goals behind, or reached, mean braking."""
        self.brake_behind = bool(brake_behind)
        """Brake for a goal behind the ego on its lane (less than 0.5 m ahead, at most ``radius_share`` of the
        reach radius to the side) however far behind it lies. False: only within 3 m; a hold passed by more
        drives on at speed to the next redraw (docs/experiments/: a teacher that brakes behind its hold)."""
        self.brake_behind_heading = float(brake_behind_heading)
        """With ``brake_behind``: only for a goal whose heading is within this [rad] of the ego's, so that a
        short lane change passed beside its goal (the ego still askew) drives on. pi: any heading."""
        self.radius = config.subgoal_reach_radius * radius_share
        self.heading = config.subgoal_reach_heading * heading_share
        self.motion = EgoMotion(config)
        t = np.arange(horizon)[None]
        # One action, then another from a switch step on (a switch at the horizon: the first alone).
        first, switch, second = (v.ravel() for v in np.meshgrid(range(6), range(1, horizon + 1), range(6)))
        single = (switch == horizon) & (second > 0)
        first, switch, second = first[~single], switch[~single], second[~single]
        pairs = np.where(t < switch[:, None], first[:, None], second[:, None])
        # S-curves: turn, opposite turn, then straight on or braking; each arc at most 1.5 s.
        opposite = {2: 3, 3: 2, 4: 5, 5: 4}
        arc = range(1, min(horizon, 16))
        rows = [
            np.where(t < k1, a, np.where(t < k1 + k2, opposite[a], end))[0]
            for a in opposite
            for k1 in arc
            for k2 in arc
            if k1 + k2 < horizon
            for end in (EgoAction.KEEP_DIRECTION, EgoAction.SLOW_DOWN)
        ]
        self.sequences = np.concatenate([pairs, np.array(rows)]).astype(np.int64)
        """(S, horizon) actions of the library."""
        self._turn_curvature = np.abs(self.motion.curvature[self.sequences])
        """(S, horizon) curvature [1/m] of each step of the library, for the lateral acceleration limit."""
        self._rollouts: OrderedDict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()

    def rollout(self, speed: float) -> np.ndarray:
        """Ego-frame poses (x, y, heading) of every sequence from the origin at ``speed``, (S, horizon, 3).

        Cached by speed (to 1 um/s): a car at cruise speed or standing asks for the same rollout again.
        """
        return self._cached(speed)[0]

    def _cached(self, speed: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rollout at ``speed``, its corners' flat BEV pixels (:meth:`corner_pixels`; those outside
        the view index the pixel after its last) and the speed after each step, (S, horizon)."""
        key = round(float(speed), 6)
        cached = self._rollouts.get(key)
        if cached is not None:
            self._rollouts.move_to_end(key)
            return cached
        if len(self._rollouts) >= ROLLOUT_CACHE_SIZE:
            self._rollouts.popitem(last=False)
        poses = self._rollout(key)
        pixels, inside = self.corner_pixels(poses, self.config.bev_size)
        # A corner outside the view reads one pixel past the end of the view, which counts as road.
        pixels = np.where(inside, pixels, self.config.bev_size**2)
        steps = np.diff(poses[..., :2], axis=1, prepend=0.0)
        speed_after = np.hypot(steps[..., 0], steps[..., 1]) / DT
        cached = self._rollouts[key] = (poses, pixels, speed_after)
        return cached

    def _rollout(self, speed: float) -> np.ndarray:
        n = len(self.sequences)
        pose, v = np.zeros((n, 3)), np.full(n, speed)
        poses = np.empty((n, self.horizon, 3))
        for step in range(self.horizon):
            pose, v = self.motion.step_many(pose, v, self.sequences[:, step])
            poses[:, step] = pose
        return poses

    def on_road(self, poses: np.ndarray, bev: np.ndarray) -> np.ndarray:
        """Whether the corners of the ego's box, slightly shrunk for the BEV's pixel size, are on the
        drivable area of the bird's-eye view at each ego-frame pose; poses beyond the view count as on it.

        :param poses: (..., 3) ego-frame poses
        :param bev: (S, S) drivable area, ego at the centre, forward up (the observation's ``bev[0]``)
        """
        pixels, inside = self.corner_pixels(poses, bev.shape[0])
        return self._on_road(np.where(inside, pixels, bev.size), bev)

    @staticmethod
    def _on_road(pixels: np.ndarray, bev: np.ndarray) -> np.ndarray:
        """Whether all four corners are on the road, (...); ``pixels`` (..., 4) index the flat view, and
        the index one past its end stands for a corner outside it (on the road)."""
        road = np.empty(bev.size + 1, np.uint8)
        np.greater(bev.ravel(), 0, out=road[:-1])
        road[-1] = 1
        corners = np.ascontiguousarray(road[pixels])
        # The four 0/1 bytes of a pose read as one 32-bit word: all four on the road is 0x01010101.
        return corners.view(np.uint32)[..., 0] == 0x01010101

    def corner_pixels(self, poses: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
        """Flat BEV pixel index of each corner of the ego's box (shrunk by half a pixel) at each pose,
        (..., 4), and whether it lies inside the view (those outside index pixel 0)."""
        pixel = self.config.bev_extent / size
        half_length, half_width = BOX_HALF_LENGTH - pixel / 2.0, BOX_HALF_WIDTH - pixel / 2.0
        c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
        pixels, inside = [], []
        for along, side in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            x = poses[..., 0] + along * half_length * c - side * half_width * s
            y = poses[..., 1] + along * half_length * s + side * half_width * c
            row = np.floor(size / 2.0 - x / pixel).astype(np.int32)
            col = np.floor(y / pixel + size / 2.0).astype(np.int32)
            within = (row >= 0) & (row < size) & (col >= 0) & (col < size)
            pixels.append(np.where(within, row * size + col, 0))
            inside.append(within)
        return np.stack(pixels, -1), np.stack(inside, -1)

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The action for one step."""
        cfg = self.config
        gx, gy, gh = (float(v) for v in obs["goal"][:3])
        speed = float(obs["history"][0, -1, 7])
        distance = float(np.hypot(gx, gy))
        allowed = np.ones(6, bool) if action_mask is None else np.asarray(action_mask, bool)
        behind = gx < 0.5 and (distance < 3.0 or self._passed_on_its_lane(gy, gh))
        stop = behind or (distance <= self.radius and abs(gh) <= self.heading)
        if stop and allowed[EgoAction.SLOW_DOWN]:
            return int(EgoAction.SLOW_DOWN)
        poses, pixels, speed_after = self._cached(speed)
        on_road = np.ones(poses.shape[:2], bool)
        if "bev" in obs:
            bev = obs["bev"][0]
            own_size = bev.shape[0] == self.config.bev_size
            on_road = self._on_road(pixels, bev) if own_size else self.on_road(poses, bev)
        if stop:
            end_speed = speed_after[:, -1]
            return self._slowest_on_road(poses, end_speed, np.all(on_road, axis=1), obs["goal"], allowed)
        miss = np.hypot(poses[..., 0] - gx, poses[..., 1] - gy)
        turn = np.abs((poses[..., 2] - gh + np.pi) % (2.0 * np.pi) - np.pi)
        # Only what is driven before the first step off the road counts.
        before_off = np.logical_and.accumulate(on_road, axis=1)
        hit = (miss <= self.radius) & (turn <= self.heading) & before_off
        # Where no sequence arrives with the margin, one that arrives within the env's own tolerance
        # (short lane changes, mostly) still beats ending on the goal's line.
        first = self.sequences[:, 0]
        usable = allowed[first] | ~allowed.any()
        limited = self.max_lateral_acceleration is not None
        if limited and abs(float(wrap_angle(gh))) >= self.limit_from_goal_heading:
            gentle = usable & self._gentle(speed_after)
            usable = gentle if gentle.any() else usable
        if not (hit & usable[:, None]).any():
            hit = (miss <= cfg.subgoal_reach_radius) & (turn <= cfg.subgoal_reach_heading) & before_off
        reached = hit.any(1)
        arrival = hit.argmax(1)
        if gx <= self.hold_distance and abs(gy) <= self.radius and (reached & usable).any():
            # A hold on the ego's lane: of the sequences that reach it soonest, the one that ends slowest.
            cost = np.where(reached & usable, arrival + HOLD_SPEED_COST * speed_after[:, -1], np.inf)
            return int(first[np.argmin(cost)])
        if speed < CRAWL_SPEED and allowed[EgoAction.KEEP_DIRECTION] and not (reached & usable).any():
            # Out of reach from a standstill or a crawl: drive off. Standing, every action but 'keep
            # direction' leaves the ego in the same state, and a turn holds a crawl: a sequence that waits
            # before it speeds up would be chosen again at the next step, for ever.
            usable &= first == EgoAction.KEEP_DIRECTION
        # Out of reach: get onto the goal's line (its lane) at the end, without losing speed.
        lateral = np.abs(-(poses[:, -1, 0] - gx) * np.sin(gh) + (poses[:, -1, 1] - gy) * np.cos(gh))
        slack = 1.0 - speed_after / cfg.cruise_speed
        line = lateral + 3.0 * turn[:, -1] + 4.0 * slack[:, -1] + 100.0 * ~before_off[:, -1]
        # Soonest arrival; between equally soon ones, the faster (it needs less to go on).
        cost = np.where(
            reached, arrival + 0.5 * slack[np.arange(len(arrival)), arrival], self.horizon + 1 + line
        )
        return int(first[np.argmin(np.where(usable, cost, np.inf))])

    def _passed_on_its_lane(self, gy: float, gh: float) -> bool:
        """With ``brake_behind``: whether a goal behind the ego at ``gy`` to the side, heading ``gh`` from
        the ego's, lies on its lane and (``brake_behind_heading``) points its way."""
        return self.brake_behind and abs(gy) <= self.radius and abs(gh) <= self.brake_behind_heading

    def _gentle(self, speed_after: np.ndarray) -> np.ndarray:
        """Sequences whose every step keeps within :attr:`max_lateral_acceleration`, (S,)."""
        return np.all(speed_after**2 * self._turn_curvature <= self.max_lateral_acceleration, axis=1)

    def _slowest_on_road(
        self,
        poses: np.ndarray,
        end_speed: np.ndarray,
        on_road: np.ndarray,
        goal: np.ndarray,
        allowed: np.ndarray,
    ) -> int:
        """First action of the sequence that stays on the road (``on_road`` per sequence) and ends
        slowest (``end_speed``; a turn where braking straight would leave the road, then braking), the
        nearer to the goal between equally slow ones."""
        miss = np.hypot(poses[:, -1, 0] - goal[0], poses[:, -1, 1] - goal[1])
        first = self.sequences[:, 0]
        usable = (allowed[first] | ~allowed.any()) & on_road
        if not usable.any():
            usable = allowed[first] | ~allowed.any()
        cost = end_speed + 0.01 * miss
        return int(first[np.argmin(np.where(usable, cost, np.inf))])


class FarthestSubgoalDecider:
    """Always the candidate farthest ahead on the best route (a subgoal index for the option env)."""

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The subgoal index for one decision."""
        forward = obs["subgoals"][:, 0].astype(float)
        if action_mask is not None:
            forward = np.where(action_mask, forward, -np.inf)
        return int(np.argmax(forward))
