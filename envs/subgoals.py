"""Subgoal candidates along the ego's routes (paper III-B-2).

Per route, candidates sit on a lattice every ``subgoal_spacing`` metres anchored at the stop line,
in a window of ``subgoal_range`` metres that starts half a spacing behind the ego. Anchoring at the
stop line keeps a candidate exactly on the stop line while the ego approaches it, and the window keeps
the lattice point nearest to the ego selectable: choosing it holds the ego where it is, which is how
the decision-maker waits for priority traffic (paper Fig. 8 A/B). Routes contribute
``ceil(N / N_r)`` candidates each, nearest first; missing ones are padded with the candidate closest to
the task goal, as in the paper.
"""

from __future__ import annotations

import math

import numpy as np

from gccp_envs.config import IntersectionConfig
from gccp_envs.geometry import FloatArray
from gccp_envs.scenario import IntersectionLayout


class SubgoalSampler:
    """Computes the N subgoal candidates (x, y, heading) of the ego in world coordinates."""

    def __init__(self, layout: IntersectionLayout, config: IntersectionConfig) -> None:
        self.layout = layout
        self.config = config
        self.per_route = math.ceil(config.num_subgoals / config.num_routes)

    def sample(self, routes: list[int], route_s: FloatArray, task_goal: FloatArray) -> FloatArray:
        """Candidates for an ego at arc lengths ``route_s`` on its ``routes``.

        :param routes: path indices of the ego's routes, best first
        :param route_s: the ego's arc length on each route
        :param task_goal: the task goal (x, y, heading)
        :return: (N, 3) world poses
        """
        cfg, paths = self.config, self.layout.paths
        poses = []
        for path, s in zip(routes, route_s, strict=True):
            first = math.ceil((s - cfg.subgoal_spacing / 2.0 - self.layout.stop_s) / cfg.subgoal_spacing)
            lattice = self.layout.stop_s + cfg.subgoal_spacing * (first + np.arange(self.per_route))
            lattice = lattice[
                (lattice < s - cfg.subgoal_spacing / 2.0 + cfg.subgoal_range)
                & (lattice <= paths.lengths[path])
            ]
            poses.append(paths.pose_at(np.full(len(lattice), path), lattice))
        candidates = np.concatenate([*poses, np.empty((0, 3))])[: cfg.num_subgoals]
        if not len(candidates):
            candidates = task_goal[None]
        missing = cfg.num_subgoals - len(candidates)
        if missing:
            closest = candidates[np.argmin(np.hypot(*(candidates[:, :2] - task_goal[:2]).T))]
            candidates = np.concatenate([candidates, np.repeat(closest[None], missing, axis=0)])
        return candidates
