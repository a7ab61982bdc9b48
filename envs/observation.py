"""The paper's environment state (III-B-1) as numpy arrays in the ego frame.

- ``history`` (N_s+1, T_h, 9): VectorNet vectors [x, y, heading, speed at j-1, the same at j, i] of
  the ego (i = 0) and its N_s nearest neighbours (i = 1..N_s), oldest first; ``history_mask`` flags
  real vectors (a vehicle seen for less than T_h steps has fewer).
- ``routes`` (N_s+1, N_r, N_p, 8): vectors [x, y, heading at k, the same at k+1, i, j] of route j
  of vehicle i, waypoints every ``route_spacing`` metres from the vehicle's projection on the route.
  The ego's routes lead to its task goal; a neighbour's are the movements still open to it from its
  lane (its intention is not revealed). ``routes_mask`` flags real vectors.
- ``bev`` (1, S, S) uint8: drivable area (1) around the ego, ego at the centre, forward up.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from gccp_envs.config import IntersectionConfig
from gccp_envs.geometry import FloatArray, poses_to_frame
from gccp_envs.world import IntersectionWorld

HISTORY_FEATURES = 9
ROUTE_FEATURES = 8
BOUND = 1000.0
"""Bound of every coordinate-like feature: far beyond any distance on the map."""


def state_spaces(config: IntersectionConfig) -> dict[str, spaces.Box]:
    """Gymnasium spaces of the state arrays."""
    vehicles, routes = config.num_neighbours + 1, config.num_routes
    return {
        "history": spaces.Box(-BOUND, BOUND, (vehicles, config.history_length, HISTORY_FEATURES), np.float32),
        "history_mask": spaces.Box(0.0, 1.0, (vehicles, config.history_length), np.float32),
        "routes": spaces.Box(
            -BOUND, BOUND, (vehicles, routes, config.route_points, ROUTE_FEATURES), np.float32
        ),
        "routes_mask": spaces.Box(0.0, 1.0, (vehicles, routes, config.route_points), np.float32),
        "bev": spaces.Box(0, 1, (1, config.bev_size, config.bev_size), np.uint8),
    }


def pose_space(*shape: int) -> spaces.Box:
    """Space of poses (x, y, heading) in the ego frame."""
    return spaces.Box(-BOUND, BOUND, (*shape, 3), np.float32)


class SceneObserver:
    """Builds the state of a world at its current step."""

    def __init__(self, world: IntersectionWorld) -> None:
        self.world = world
        cfg = world.config
        self.config = cfg
        res = cfg.bev_extent / cfg.bev_size
        centres = (np.arange(cfg.bev_size) + 0.5 - cfg.bev_size / 2.0) * res
        # Row 0 is the farthest ahead, columns run from the ego's left to its right.
        self._bev_forward = -centres[:, None] * np.ones((1, cfg.bev_size))
        self._bev_right = np.ones((cfg.bev_size, 1)) * centres[None, :]
        vehicle, route = np.meshgrid(
            np.arange(cfg.num_neighbours + 1), np.arange(cfg.num_routes), indexing="ij"
        )
        self._route_ids = np.repeat(np.stack((vehicle, route), -1)[:, :, None], cfg.route_points, axis=2)
        layout = world.layout
        self._entry_routes = np.full((4 * layout.lanes, cfg.num_routes), -1, np.int64)
        for entry in range(4 * layout.lanes):
            paths = np.flatnonzero(layout.path_entry == entry)[: cfg.num_routes]
            self._entry_routes[entry, : len(paths)] = paths

    def to_ego(self, poses: FloatArray) -> FloatArray:
        """World poses (..., 3+) in the ego frame, as float32."""
        ego = self.world.ego
        return poses_to_frame(poses, np.array([ego.x, ego.y]), ego.heading).astype(np.float32)

    def observe(self) -> dict[str, np.ndarray]:
        """The state arrays of the current step."""
        world = self.world
        slots = np.concatenate([[world.ego_slot], world.neighbours()]).astype(np.int64)
        history, history_mask = self._history(slots)
        routes, routes_mask = self._routes(slots)
        return {
            "history": history,
            "history_mask": history_mask,
            "routes": routes,
            "routes_mask": routes_mask,
            "bev": self._bev(),
        }

    def _history(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg, world = self.config, self.world
        steps = cfg.history_length
        poses, valid = world.poses_between(world.steps - steps, world.steps, slots, world.slot_uids(slots))
        local = self.to_ego(poses)  # (T_h + 1, n, 4)
        n = len(slots)
        history = np.zeros((cfg.num_neighbours + 1, steps, 9), np.float32)
        mask = np.zeros((cfg.num_neighbours + 1, steps), np.float32)
        vec = np.concatenate(
            [
                local[:-1],
                local[1:],
                np.broadcast_to(np.arange(n, dtype=np.float32)[None, :, None], (steps, n, 1)),
            ],
            -1,
        )
        ok = valid[:-1] & valid[1:]
        history[:n] = np.where(ok[..., None], vec, 0.0).transpose(1, 0, 2)
        mask[:n] = ok.T
        return history, mask

    def _route_paths(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Route path indices (n, N_r), -1 where absent, and the vehicles' arc lengths on them."""
        cfg, world = self.config, self.world
        layout, traffic = world.layout, world.traffic
        n = len(slots)
        paths = np.full((n, cfg.num_routes), -1, np.int64)
        arc = np.zeros((n, cfg.num_routes))
        ego_routes, ego_s = world.ego_routes()
        paths[0, : len(ego_routes)] = ego_routes
        arc[0, : len(ego_routes)] = ego_s
        if n > 1:
            npc = slots[1:]
            entry = layout.path_entry[traffic.path[npc]]
            options = self._entry_routes[entry]
            s, d = layout.paths.lookup(np.maximum(options, 0), traffic.pose[npc, None, :2])
            # Past the stop line, only the movements the vehicle is still on stay open.
            open_ = (options >= 0) & (
                (traffic.s[npc, None] < layout.stop_s)
                | (np.abs(d) < 1.0)
                | (options == traffic.path[npc, None])
            )
            paths[1:] = np.where(open_, options, -1)
            arc[1:] = np.where(options == traffic.path[npc, None], traffic.s[npc, None], s)
        return paths, arc

    def _routes(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg, layout = self.config, self.world.layout
        paths, arc = self._route_paths(slots)
        n, points = len(slots), cfg.route_points
        offsets = np.arange(points + 1) * cfg.route_spacing
        s = arc[..., None] + offsets  # (n, N_r, N_p + 1)
        safe = np.maximum(paths, 0)[..., None]
        world_poses = layout.paths.pose_at(np.broadcast_to(safe, s.shape), s)
        local = self.to_ego(world_poses)
        ok = (paths[..., None] >= 0) & (s[..., 1:] <= layout.paths.lengths[safe])
        routes = np.zeros((cfg.num_neighbours + 1, cfg.num_routes, points, ROUTE_FEATURES), np.float32)
        routes[:n, ..., 0:3] = local[:, :, :-1]
        routes[:n, ..., 3:6] = local[:, :, 1:]
        routes[:n, ..., 6:8] = self._route_ids[:n]
        routes[:n] *= ok[..., None]
        mask = np.zeros((cfg.num_neighbours + 1, cfg.num_routes, points), np.float32)
        mask[:n] = ok
        return routes, mask

    def _bev(self) -> np.ndarray:
        sensed = self.world.sensed_bev()
        if sensed is not None:
            return sensed[None]
        ego = self.world.ego
        c, s = np.cos(ego.heading), np.sin(ego.heading)
        x = ego.x + c * self._bev_forward - s * self._bev_right
        y = ego.y + s * self._bev_forward + c * self._bev_right
        return self.world.layout.is_drivable(x, y).astype(np.uint8)[None]
