"""Ego motion: the paper's N_a = 6 discrete actions, each a pose change reached in 0.1 s (III-D-2).

An action fixes a speed change and a path curvature; the pose change (dx, dy, dheading) in the ego
frame is the exact arc driven in one step at the mean speed. Turning needs speed: a stopped ego cannot
turn on the spot, it first accelerates with 'keep direction'.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.geometry import FloatArray, wrap_angle


class EgoAction(IntEnum):
    """The six motion-planner actions, in the paper's order."""

    SLOW_DOWN = 0
    KEEP_DIRECTION = 1
    SLOWLY_TURN_LEFT = 2
    SLOWLY_TURN_RIGHT = 3
    QUICKLY_TURN_LEFT = 4
    QUICKLY_TURN_RIGHT = 5


@dataclass
class EgoState:
    """World pose and speed of the ego."""

    x: float
    y: float
    heading: float
    speed: float

    def as_array(self) -> FloatArray:
        """(x, y, heading, speed)."""
        return np.array([self.x, self.y, self.heading, self.speed])


class EgoMotion:
    """Maps each action to a speed change and a curvature, and applies it for one step."""

    def __init__(self, config: IntersectionConfig) -> None:
        self.config = config
        slow, quick = config.slow_turn_curvature, config.quick_turn_curvature
        # A left turn decreases the heading (highway-env's frame, y down on screen).
        self.curvature = np.array([0.0, 0.0, -slow, slow, -quick, quick])

    def next_speed(self, speed: float, action: int) -> float:
        """Speed after one step: brake, accelerate back to cruise speed, or hold while turning."""
        cfg = self.config
        if action == EgoAction.SLOW_DOWN:
            return max(speed - cfg.deceleration * DT, 0.0)
        if action == EgoAction.KEEP_DIRECTION:
            return max(min(speed + cfg.acceleration * DT, cfg.cruise_speed), speed - cfg.deceleration * DT)
        return speed

    def pose_change(self, speed: float, action: int) -> tuple[FloatArray, float]:
        """Pose change (dx, dy, dheading) in the ego frame over one step, and the new speed.

        :param speed: current speed [m/s]
        :param action: an :class:`EgoAction`
        :return: ((dx, dy, dheading), new speed)
        """
        if not 0 <= int(action) < len(self.curvature):
            raise ValueError(
                f"invalid ego action {action!r}: expected an integer in [0, {len(self.curvature) - 1}]"
            )
        new_speed = self.next_speed(speed, int(action))
        distance = 0.5 * (speed + new_speed) * DT
        dheading = float(self.curvature[int(action)] * distance)
        dx, dy = self._shift(distance, dheading)
        return np.array([dx, dy, dheading]), new_speed

    @staticmethod
    def _chord(distance: FloatArray | float, turn: FloatArray | float) -> FloatArray | float:
        """Length of the chord of an arc of ``distance`` [m] turning ``turn`` [rad]: shorter than the arc
        by sinc(turn / 2); it points half-way through the turn."""
        return distance * np.sinc(turn / (2.0 * np.pi))

    def _shift(
        self, distance: FloatArray | float, turn: FloatArray | float
    ) -> tuple[FloatArray | float, FloatArray | float]:
        """The box centre's shift (dx, dy) in the ego frame when the turning point drives an arc of
        ``distance`` [m] and ``turn`` [rad] (floats, or arrays of one shape)."""
        chord = self._chord(distance, turn)
        dx, dy = chord * np.cos(turn / 2.0), chord * np.sin(turn / 2.0)
        offset = self.config.rear_axle_offset
        if offset:
            # The turning point lies ``offset`` behind the centre: the centre ends ``offset`` ahead of
            # it along the new heading.
            dx, dy = dx - offset * (1.0 - np.cos(turn)), dy + offset * np.sin(turn)
        return dx, dy

    def two_arc_paths(self, length: float, spacing: float = 0.5, split: float = 1.0) -> FloatArray:
        """Box-centre poses along every path of two arcs of the actions' curvatures, in the start frame.

        A path drives one curvature for the first ``l1`` metres (0, ``split``, 2 ``split``, ...) and
        another for the rest of ``length``, sampled every ``spacing`` metres. Speed does not enter: a turn
        holds its curvature at any speed, and a straight piece may brake or accelerate. The single arcs
        come first.

        :return: poses (x, y, heading) relative to the start pose, (paths, samples, 3)
        """
        curvatures = np.unique(self.curvature)
        s = np.arange(1, round(length / spacing) + 1) * spacing
        singles = [(k, length, k) for k in curvatures]
        splits = np.arange(1, int(np.ceil(length / split))) * split
        pairs = [(k1, l1, k2) for k1 in curvatures for l1 in splits for k2 in curvatures if k1 != k2]
        paths = np.empty((len(singles) + len(pairs), len(s), 3))
        for i, (k1, l1, k2) in enumerate(singles + pairs):
            first = np.minimum(s, l1)
            turn1 = k1 * first
            dx1, dy1 = self._shift(first, turn1)
            second = np.maximum(s - l1, 0.0)
            turn2 = k2 * second
            dx2, dy2 = self._shift(second, turn2)
            c, sn = np.cos(turn1), np.sin(turn1)
            paths[i] = np.stack((dx1 + c * dx2 - sn * dy2, dy1 + sn * dx2 + c * dy2, turn1 + turn2), -1)
        return paths

    def all_next_poses(self, state: EgoState) -> FloatArray:
        """World poses (x, y, heading) after one step of each action, (N_a, 3)."""
        poses = np.empty((len(self.curvature), 3))
        for action in range(len(self.curvature)):
            nxt = self.step(state, action)
            poses[action] = (nxt.x, nxt.y, nxt.heading)
        return poses

    def rollout(self, state: EgoState, action: int, steps: int) -> FloatArray:
        """World poses (x, y, heading) of ``steps`` steps holding ``action``, (steps, 3)."""
        poses = np.empty((steps, 3))
        for k in range(steps):
            state = self.step(state, action)
            poses[k] = (state.x, state.y, state.heading)
        return poses

    def _next_speeds(self, speeds: FloatArray, braking: np.ndarray, keeping: np.ndarray) -> FloatArray:
        """:meth:`next_speed` for many speeds at once: ``braking`` and ``keeping`` mark 'slow down' and
        'keep direction'; the turns hold their speed."""
        cfg = self.config
        braked = np.maximum(speeds - cfg.deceleration * DT, 0.0)
        kept = np.maximum(np.minimum(speeds + cfg.acceleration * DT, cfg.cruise_speed), braked)
        return np.where(braking, braked, np.where(keeping, kept, speeds))

    def rollout_many(self, states: FloatArray, actions: np.ndarray, steps: int) -> FloatArray:
        """:meth:`rollout` for many states at once, the same to the last bit: the same operations in the
        same order, on arrays (:meth:`step_many`'s chord form gives other last bits).

        :param states: (n, 4) x, y, heading, speed
        :param actions: (n,) the action each state holds
        :param steps: steps of each rollout
        :return: world poses (x, y, heading), (n, steps, 3)
        """
        x, y, heading, speed = (np.array(states[:, k], dtype=float) for k in range(4))
        actions = np.asarray(actions)
        curvature = self.curvature[actions]
        braking, keeping = actions == EgoAction.SLOW_DOWN, actions == EgoAction.KEEP_DIRECTION
        poses = np.empty((len(states), steps, 3))
        for k in range(steps):
            new_speed = self._next_speeds(speed, braking, keeping)
            distance = 0.5 * (speed + new_speed) * DT
            turn = curvature * distance
            dx, dy = self._shift(distance, turn)
            c, s = np.cos(heading), np.sin(heading)
            x, y = x + c * dx - s * dy, y + s * dx + c * dy
            heading, speed = wrap_angle(heading + turn), new_speed
            poses[:, k, 0], poses[:, k, 1], poses[:, k, 2] = x, y, heading
        return poses

    def step_many(
        self, poses: FloatArray, speeds: FloatArray, actions: np.ndarray
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`step` for many states at once: poses (n, 3) (x, y, heading; the heading is not
        wrapped), speeds (n,) and one action each (n,); returns the new poses and speeds."""
        new_speeds = self._next_speeds(
            speeds, actions == EgoAction.SLOW_DOWN, actions == EgoAction.KEEP_DIRECTION
        )
        distance = 0.5 * (speeds + new_speeds) * DT
        turn = self.curvature[actions] * distance
        # The chord along the middle heading, as :meth:`_shift` in the world frame. Written so, not by
        # rotating _shift's (dx, dy): the search planner's rollouts, and with them the planner stage's
        # expert data, stay the same to the last bit as before the rear-axle offset existed.
        chord = self._chord(distance, turn)
        middle = poses[:, 2] + turn / 2.0
        x, y = poses[:, 0] + chord * np.cos(middle), poses[:, 1] + chord * np.sin(middle)
        offset = self.config.rear_axle_offset
        if offset:  # the centre ends ``offset`` ahead of the turning point along the new heading
            x = x + offset * (np.cos(poses[:, 2] + turn) - np.cos(poses[:, 2]))
            y = y + offset * (np.sin(poses[:, 2] + turn) - np.sin(poses[:, 2]))
        return np.stack((x, y, poses[:, 2] + turn), -1), new_speeds

    def step(self, state: EgoState, action: int) -> EgoState:
        """The ego state after one step of ``action``."""
        (dx, dy, dheading), speed = self.pose_change(state.speed, action)
        c, s = np.cos(state.heading), np.sin(state.heading)
        return EgoState(
            state.x + c * dx - s * dy,
            state.y + s * dx + c * dy,
            float(wrap_angle(state.heading + dheading)),
            speed,
        )
