"""Planar geometry shared by the world: frames, oriented boxes and vectorised lane paths.

Frames follow highway-env: world x to the right, y down on screen, headings measured from +x towards +y
and always wrapped to [-pi, pi]. The ego frame is the world frame moved to the ego and rotated by its
heading: x forward, y to the ego's right on screen. A left turn decreases the heading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Size = tuple[FloatArray | float, FloatArray | float]
"""A box's (length, width): numbers, or arrays broadcast over the boxes."""


def wrap_angle(angle: FloatArray | float) -> FloatArray:
    """Wrap angles to [-pi, pi).

    :param angle: angles [rad]
    :return: the wrapped angles
    """
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def _mod2pi(angle: FloatArray) -> FloatArray:
    """Angle in [0, 2 pi), with round-off just below 2 pi taken as 0 (no spurious full circles)."""
    wrapped = np.mod(angle, 2.0 * np.pi)
    return np.where(wrapped > 2.0 * np.pi - 1e-6, 0.0, wrapped)


def _root(square: FloatArray) -> FloatArray:
    """Square root, NaN (no such word) for negative squares beyond round-off."""
    return np.sqrt(np.where(square > -1e-9, np.maximum(square, 0.0), np.nan))


def _arccos(cosine: FloatArray) -> FloatArray:
    """Arc cosine, NaN (no such word) outside [-1, 1] beyond round-off."""
    return np.arccos(np.where(np.abs(cosine) < 1 + 1e-9, np.clip(cosine, -1.0, 1.0), np.nan))


def dubins_length(start: FloatArray, ends: FloatArray, radius: float) -> FloatArray:
    """Length of the shortest forward path with turn radius at least ``radius`` from one pose to others.

    The minimum over Dubins' six words (Shkel and Lumelsky 2001, "Classification of the Dubins set"),
    vectorised over the end poses. Mirror-symmetric, so it holds in either handedness of frame.

    :param start: (3,) start pose (x, y, heading)
    :param ends: (K, 3) end poses
    :param radius: the smallest turn radius [m]
    :return: (K,) lengths [m]
    """
    dx, dy = ends[:, 0] - start[0], ends[:, 1] - start[1]
    d = np.hypot(dx, dy) / radius
    theta = _mod2pi(np.arctan2(dy, dx))
    alpha, beta = _mod2pi(start[2] - theta), _mod2pi(ends[:, 2] - theta)
    sa, sb, ca, cb = np.sin(alpha), np.sin(beta), np.cos(alpha), np.cos(beta)
    c_ab = np.cos(alpha - beta)
    words = []
    with np.errstate(invalid="ignore"):
        p_sq = 2 + d * d - 2 * c_ab + 2 * d * (sa - sb)  # LSL
        phi = np.arctan2(cb - ca, d + sa - sb)
        words.append(_mod2pi(phi - alpha) + _root(p_sq) + _mod2pi(beta - phi))
        p_sq = 2 + d * d - 2 * c_ab + 2 * d * (sb - sa)  # RSR
        phi = np.arctan2(ca - cb, d - sa + sb)
        words.append(_mod2pi(alpha - phi) + _root(p_sq) + _mod2pi(phi - beta))
        p = _root(-2 + d * d + 2 * c_ab + 2 * d * (sa + sb))  # LSR
        phi = np.arctan2(-ca - cb, d + sa + sb) - np.arctan2(-2.0, p)
        words.append(_mod2pi(phi - alpha) + p + _mod2pi(phi - beta))
        p = _root(-2 + d * d + 2 * c_ab - 2 * d * (sa + sb))  # RSL
        phi = np.arctan2(ca + cb, d - sa - sb) - np.arctan2(2.0, p)
        words.append(_mod2pi(alpha - phi) + p + _mod2pi(beta - phi))
        p = _mod2pi(2 * np.pi - _arccos((6 - d * d + 2 * c_ab + 2 * d * (sa - sb)) / 8))  # RLR
        t = _mod2pi(alpha - np.arctan2(ca - cb, d - sa + sb) + p / 2)
        words.append(t + p + _mod2pi(alpha - beta - t + p))
        p = _mod2pi(2 * np.pi - _arccos((6 - d * d + 2 * c_ab + 2 * d * (sb - sa)) / 8))  # LRL
        t = _mod2pi(-alpha - np.arctan2(ca - cb, d + sa - sb) + p / 2)
        words.append(t + p + _mod2pi(beta - alpha - t + p))
    return np.nanmin(np.stack(words), axis=0) * radius


def to_frame(points: FloatArray, origin: FloatArray, heading: float) -> FloatArray:
    """Express world points (..., 2) in the frame at ``origin`` rotated by ``heading``.

    :param points: world positions, last axis (x, y)
    :param origin: frame origin (x, y)
    :param heading: frame heading [rad]
    :return: the positions in the frame
    """
    c, s = np.cos(heading), np.sin(heading)
    dx = points[..., 0] - origin[0]
    dy = points[..., 1] - origin[1]
    return np.stack((c * dx + s * dy, -s * dx + c * dy), axis=-1)


def from_frame(
    points: FloatArray, origin: FloatArray | tuple[FloatArray, FloatArray], heading: FloatArray | float
) -> FloatArray:
    """Express points (..., 2) given in the frame at ``origin`` rotated by ``heading`` in the world.

    The inverse of :func:`to_frame`.

    :param points: positions in the frame, last axis (x, y)
    :param origin: frame origin (x, y); arrays that broadcast with the points give one frame each
    :param heading: frame heading [rad], a float or an array like the origin's
    :return: the world positions
    """
    c, s = np.cos(heading), np.sin(heading)
    x, y = points[..., 0], points[..., 1]
    return np.stack((origin[0] + c * x - s * y, origin[1] + s * x + c * y), axis=-1)


def poses_to_frame(poses: FloatArray, origin: FloatArray, heading: float) -> FloatArray:
    """Express world poses (..., >=3) with columns (x, y, heading, ...) in a frame; extra columns kept.

    :param poses: world poses
    :param origin: frame origin (x, y)
    :param heading: frame heading [rad]
    :return: the poses in the frame, headings wrapped
    """
    out = np.array(poses, dtype=np.float64, copy=True)
    out[..., :2] = to_frame(poses[..., :2], origin, heading)
    out[..., 2] = wrap_angle(poses[..., 2] - heading)
    return out


_CORNER_SIGNS = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])


def box_corners(
    x: FloatArray | float,
    y: FloatArray | float,
    heading: FloatArray | float,
    length: FloatArray | float,
    width: FloatArray | float,
) -> FloatArray:
    """Corners (..., 4, 2) of oriented boxes centred at (x, y).

    :return: corners in counter-clockwise order on the math plane
    """
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    lon = _CORNER_SIGNS[:, 0] * (np.asarray(length) / 2.0)[..., None]
    lat = _CORNER_SIGNS[:, 1] * (np.asarray(width) / 2.0)[..., None]
    cx = np.asarray(x)[..., None] + lon * c - lat * s
    cy = np.asarray(y)[..., None] + lon * s + lat * c
    return np.stack((cx, cy), axis=-1)


def boxes_overlap(a: FloatArray, b: FloatArray) -> NDArray[np.bool_]:
    """Separating Axis Theorem test of oriented boxes, broadcast over leading axes.

    Touching boxes (zero-width overlap) do not count as overlapping.

    :param a: corners (..., 4, 2) in the order of :func:`box_corners`
    :param b: corners (..., 4, 2)
    :return: whether each pair overlaps
    """
    a, b = np.broadcast_arrays(a, b)
    # Two edge directions per box are enough for rectangles.
    axes = np.stack(
        (
            a[..., 1, :] - a[..., 0, :],
            a[..., 3, :] - a[..., 0, :],
            b[..., 1, :] - b[..., 0, :],
            b[..., 3, :] - b[..., 0, :],
        ),
        axis=-2,
    )
    pa = np.einsum("...kd,...cd->...kc", axes, a)
    pb = np.einsum("...kd,...cd->...kc", axes, b)
    separated = (pa.max(-1) <= pb.min(-1)) | (pb.max(-1) <= pa.min(-1))
    return ~separated.any(-1)


def poses_overlap(
    a: FloatArray,
    a_size: Size,
    b: FloatArray,
    b_size: Size,
) -> NDArray[np.bool_]:
    """Separating Axis Theorem test of boxes given as poses, broadcast over leading axes.

    The same test as :func:`boxes_overlap` without building corners: on each of the four box axes,
    the boxes are separated when the centre distance along the axis is at least the sum of their
    half extents along it. Touching boxes do not count as overlapping.

    :param a: poses (..., 3) = (x, y, heading) of the first boxes
    :param a_size: their (length, width), broadcastable to the leading axes
    :param b: poses (..., 3) of the second boxes
    :param b_size: their (length, width)
    :return: whether each pair overlaps
    """
    ha, wa = a_size[0] * 0.5, a_size[1] * 0.5
    hb, wb = b_size[0] * 0.5, b_size[1] * 0.5
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    ca, sa = np.cos(a[..., 2]), np.sin(a[..., 2])
    cb, sb = np.cos(b[..., 2]), np.sin(b[..., 2])
    cos_d = np.abs(ca * cb + sa * sb)
    sin_d = np.abs(sa * cb - ca * sb)
    # Half extents along the other box's length and width axes, plus the box's own.
    reach_long = ha + hb * cos_d + wb * sin_d
    reach_lat = wa + hb * sin_d + wb * cos_d
    if _same_scalar_sizes(a_size, b_size):  # the common case: the sums on b's axes are the same
        reach_long_b, reach_lat_b = reach_long, reach_lat
    else:
        reach_long_b, reach_lat_b = hb + ha * cos_d + wa * sin_d, wb + ha * sin_d + wa * cos_d
    separated = np.abs(dx * ca + dy * sa) >= reach_long
    separated |= np.abs(dy * ca - dx * sa) >= reach_lat
    separated |= np.abs(dx * cb + dy * sb) >= reach_long_b
    separated |= np.abs(dy * cb - dx * sb) >= reach_lat_b
    return ~separated


def _same_scalar_sizes(a_size: Size, b_size: Size) -> bool:
    """Whether two (length, width) pairs are the same two numbers."""
    scalars = all(isinstance(v, (int, float)) for v in (*a_size, *b_size))  # np.float64 is a float
    return scalars and tuple(a_size) == tuple(b_size)


@dataclass(frozen=True)
class Segment:
    """A straight segment (``radius == 0``) or a circular arc of a lane path.

    A straight segment runs from ``start`` along unit ``direction``. An arc turns around ``center``
    from phase ``phase0`` with ``sense`` +1 (phase increasing, heading increasing) or -1.
    """

    length: float
    start: tuple[float, float] = (0.0, 0.0)
    direction: tuple[float, float] = (1.0, 0.0)
    center: tuple[float, float] = (0.0, 0.0)
    radius: float = 0.0
    phase0: float = 0.0
    sense: float = 1.0

    @staticmethod
    def line(start: FloatArray, end: FloatArray) -> Segment:
        """A straight segment between two points."""
        delta = np.asarray(end, float) - np.asarray(start, float)
        length = float(np.hypot(*delta))
        return Segment(length, tuple(map(float, start)), tuple(map(float, delta / length)))  # type: ignore[arg-type]

    @staticmethod
    def arc(center: FloatArray, radius: float, phase0: float, phase1: float) -> Segment:
        """A circular arc from ``phase0`` to ``phase1`` (the sign of their difference is the sense)."""
        sense = 1.0 if phase1 > phase0 else -1.0
        return Segment(
            abs(phase1 - phase0) * radius,
            center=(float(center[0]), float(center[1])),
            radius=float(radius),
            phase0=float(phase0),
            sense=sense,
        )

    def pose(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Positions and unwrapped headings at arc lengths ``s`` along the segment."""
        s = np.asarray(s, float)
        if self.radius == 0.0:
            heading = np.full_like(s, np.arctan2(self.direction[1], self.direction[0]))
            return (
                self.start[0] + s * self.direction[0],
                self.start[1] + s * self.direction[1],
                heading,
            )
        phase = self.phase0 + self.sense * s / self.radius
        x = self.center[0] + self.radius * np.cos(phase)
        y = self.center[1] + self.radius * np.sin(phase)
        return x, y, phase + self.sense * np.pi / 2.0


class PathSet:
    """Lane paths sampled for fast lookups, with vectorised projection of points onto them.

    Every path is a chain of segments. Poses at arc length ``s`` are read from samples every
    ``resolution`` metres; projection onto segments is exact.
    """

    def __init__(self, paths: list[list[Segment]], resolution: float = 0.1) -> None:
        self.resolution = resolution
        self.lengths = np.array([sum(seg.length for seg in path) for path in paths])
        n = int(np.ceil(self.lengths.max() / resolution)) + 2
        self.samples = np.zeros((len(paths), n, 3))
        self.curvature = np.zeros((len(paths), n))
        max_segments = max(len(path) for path in paths)
        shape = (len(paths), max_segments)
        self._seg_offset = np.full(shape, np.inf)
        self._seg_length = np.zeros(shape)
        self._seg_start = np.zeros((*shape, 2))
        self._seg_dir = np.zeros((*shape, 2))
        self._seg_center = np.zeros((*shape, 2))
        self._seg_radius = np.zeros(shape)
        self._seg_phase0 = np.zeros(shape)
        self._seg_sense = np.ones(shape)
        for p, path in enumerate(paths):
            self._sample(p, path, n)
            offset = 0.0
            for k, seg in enumerate(path):
                self._seg_offset[p, k] = offset
                self._seg_length[p, k] = seg.length
                self._seg_start[p, k] = seg.start
                self._seg_dir[p, k] = seg.direction
                self._seg_center[p, k] = seg.center
                self._seg_radius[p, k] = seg.radius
                self._seg_phase0[p, k] = seg.phase0
                self._seg_sense[p, k] = seg.sense
                offset += seg.length

    def _sample(self, p: int, path: list[Segment], n: int) -> None:
        s = np.arange(n) * self.resolution
        offsets = np.cumsum([0.0] + [seg.length for seg in path])
        for k, seg in enumerate(path):
            last = k == len(path) - 1
            sel = (s >= offsets[k]) & ((s < offsets[k + 1]) | last)
            # The last segment is sampled on past the path's end so interpolation stays exact there.
            local = s[sel] - offsets[k]
            x, y, h = seg.pose(local)
            self.samples[p, sel] = np.stack((x, y, h), -1)
            self.curvature[p, sel] = 0.0 if seg.radius == 0.0 else 1.0 / seg.radius
        self.samples[p, :, 2] = np.unwrap(self.samples[p, :, 2])

    def __len__(self) -> int:
        return len(self.lengths)

    def build_lookup(self, extent: float, cell: float = 0.5, band: float = 8.0) -> None:
        """Tabulate the projection of every grid cell centre within ``band`` of each path.

        After this, :meth:`lookup` answers many projections at once for the cost of one gather.

        :param extent: the grid covers [-extent, extent] in x and y [m]
        :param cell: cell size [m]
        :param band: cells farther than this from a path read as off the path
        """
        n = int(np.ceil(2 * extent / cell))
        centres = (np.arange(n) + 0.5) * cell - extent
        self._lookup_s = np.zeros((len(self), n, n), np.float32)
        self._lookup_d = np.full((len(self), n, n), np.inf, np.float32)
        for p in range(len(self)):
            # Only cells in the path's bounding box grown by the band can be near it.
            xy = self.samples[p, :, :2]
            lo = np.searchsorted(centres, xy.min(0) - band)
            hi = np.searchsorted(centres, xy.max(0) + band)
            gx, gy = np.meshgrid(centres[lo[0] : hi[0]], centres[lo[1] : hi[1]], indexing="ij")
            s, d = self.project(np.array(p), np.stack((gx, gy), -1))
            self._lookup_s[p, lo[0] : hi[0], lo[1] : hi[1]] = s
            self._lookup_d[p, lo[0] : hi[0], lo[1] : hi[1]] = np.where(np.abs(d) <= band, d, np.inf)
        self._lookup_extent, self._lookup_cell, self._lookup_n = extent, cell, n

    def lookup(self, path: NDArray[np.int64], points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Tabulated :meth:`project` (to half a cell); ``d`` is ``inf`` off the tabulated band."""
        ij = np.floor((points + self._lookup_extent) / self._lookup_cell).astype(np.int64)
        inside = ((ij >= 0) & (ij < self._lookup_n)).all(-1)
        ij = np.clip(ij, 0, self._lookup_n - 1)
        s = self._lookup_s[path, ij[..., 0], ij[..., 1]]
        d = self._lookup_d[path, ij[..., 0], ij[..., 1]]
        return s.astype(np.float64), np.where(inside, d, np.inf)

    def pose_at(self, path: NDArray[np.int64], s: FloatArray) -> FloatArray:
        """Poses (..., 3) = (x, y, wrapped heading) at arc lengths ``s`` on paths ``path``.

        Arc lengths beyond a path's ends are clamped to it.
        """
        u = np.clip(s, 0.0, self.lengths[path]) / self.resolution
        i = np.minimum(u.astype(np.int64), self.samples.shape[1] - 2)
        f = (u - i)[..., None]
        pose = self.samples[path, i] * (1.0 - f) + self.samples[path, i + 1] * f
        pose[..., 2] = wrap_angle(pose[..., 2])
        return pose

    def project(self, path: NDArray[np.int64], points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Project points onto paths, pairwise over the broadcast leading shape.

        :param path: path indices (...)
        :param points: positions (..., 2)
        :return: arc length ``s`` of the nearest path point and signed lateral offset ``d``
            (positive on the right of the path on screen), each (...)
        """
        path, px, py = np.broadcast_arrays(path, points[..., 0], points[..., 1])
        px, py = px[..., None], py[..., None]
        length = self._seg_length[path]
        radius = self._seg_radius[path]
        is_arc = radius > 0.0
        # Straight segments.
        start, direction = self._seg_start[path], self._seg_dir[path]
        rx, ry = px - start[..., 0], py - start[..., 1]
        t_line = np.clip(rx * direction[..., 0] + ry * direction[..., 1], 0.0, length)
        # Arcs: the angle from the start phase along the sense, clamped to the arc.
        center, sense = self._seg_center[path], self._seg_sense[path]
        cx, cy = px - center[..., 0], py - center[..., 1]
        safe_radius = np.where(is_arc, radius, 1.0)
        swept = (
            np.mod(sense * (np.arctan2(cy, cx) - self._seg_phase0[path]) + np.pi / 2, 2 * np.pi) - np.pi / 2
        )
        t_arc = np.clip(swept * safe_radius, 0.0, length)
        t = np.where(is_arc, t_arc, t_line)
        phase = self._seg_phase0[path] + sense * t / safe_radius
        qx = np.where(is_arc, center[..., 0] + radius * np.cos(phase), start[..., 0] + t * direction[..., 0])
        qy = np.where(is_arc, center[..., 1] + radius * np.sin(phase), start[..., 1] + t * direction[..., 1])
        hx = np.where(is_arc, -sense * np.sin(phase), direction[..., 0])
        hy = np.where(is_arc, sense * np.cos(phase), direction[..., 1])
        ex, ey = px - qx, py - qy
        dist = np.hypot(ex, ey)
        dist = np.where(np.isfinite(self._seg_offset[path]), dist, np.inf)
        k = np.argmin(dist, axis=-1)[..., None]
        s = np.take_along_axis(self._seg_offset[path] + t, k, -1)[..., 0]
        d = np.take_along_axis(hx * ey - hy * ex, k, -1)[..., 0]
        return s, d
