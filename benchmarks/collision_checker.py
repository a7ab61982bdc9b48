"""The SAT collision checker against python-fcl: agreement on random and near-touching box pairs,
and the time of one decision's 12 candidates x 5 neighbours x 10 steps = 600 box pairs.

Run: python benchmarks/collision_checker.py [--pairs 100000] [--seed 0]
Last line: ``speedup_vs_fcl <x>`` (goal: at least 30, with 0 disagreements).
"""

from __future__ import annotations

import argparse
import time

import fcl
import numpy as np

from gccp_envs.geometry import poses_overlap
from sb3_gccp.gccp.collision import CollisionChecker


def fcl_box(pose: np.ndarray, length: float, width: float) -> fcl.CollisionObject:
    """A flat fcl box at a planar pose."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return fcl.CollisionObject(fcl.Box(length, width, 1.0), fcl.Transform(rotation, [pose[0], pose[1], 0.0]))


def fcl_overlap(a: fcl.CollisionObject, b: fcl.CollisionObject) -> bool:
    """python-fcl's verdict for one pair."""
    return fcl.collide(a, b, fcl.CollisionRequest(), fcl.CollisionResult()) > 0


def touching_scale(a: np.ndarray, sa: np.ndarray, direction: np.ndarray, hb: float, sb: np.ndarray) -> float:
    """The centre distance along ``direction`` at which box b (heading ``hb``) just touches box a."""
    axes = [a[2], a[2] + np.pi / 2, hb, hb + np.pi / 2]
    cos_d, sin_d = abs(np.cos(hb - a[2])), abs(np.sin(hb - a[2]))
    la, wa, lb, wb = sa[0] / 2, sa[1] / 2, sb[0] / 2, sb[1] / 2
    reach = [
        la + lb * cos_d + wb * sin_d,
        wa + lb * sin_d + wb * cos_d,
        lb + la * cos_d + wa * sin_d,
        wb + la * sin_d + wa * cos_d,
    ]
    return min(
        r / max(abs(direction @ [np.cos(u), np.sin(u)]), 1e-12) for r, u in zip(reach, axes, strict=True)
    )


def random_pairs(n: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Half uniform pairs, half near-touching (0.1 % inside or outside contact), with random sizes."""
    a = np.column_stack([np.zeros((n, 2)), rng.uniform(-np.pi, np.pi, n)])
    b = np.column_stack([rng.uniform(-8, 8, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    size_a = np.column_stack([rng.uniform(2.0, 6.0, n), rng.uniform(1.0, 2.5, n)])
    size_b = np.column_stack([rng.uniform(2.0, 6.0, n), rng.uniform(1.0, 2.5, n)])
    for k in range(n // 2):
        direction = rng.normal(size=2)
        direction /= np.linalg.norm(direction)
        scale = touching_scale(a[k], size_a[k], direction, b[k, 2], size_b[k])
        b[k, :2] = direction * scale * (1.0 + (1e-3 if k % 2 else -1e-3))
    return a, size_a, b, size_b


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    a, size_a, b, size_b = random_pairs(args.pairs, rng)
    ours = poses_overlap(a, (size_a[:, 0], size_a[:, 1]), b, (size_b[:, 0], size_b[:, 1]))
    reference = np.array(
        [fcl_overlap(fcl_box(a[k], *size_a[k]), fcl_box(b[k], *size_b[k])) for k in range(args.pairs)]
    )
    disagree = np.flatnonzero(ours != reference)
    near = args.pairs // 2
    print(
        f"{args.pairs} pairs ({near} near-touching at 0.1 % of contact distance): "
        f"{int(reference.sum())} overlapping by fcl, disagreements {len(disagree)}"
    )
    for k in disagree[:10]:
        print(f"  pair {k}: ours {ours[k]} fcl {reference[k]} a {a[k]} {size_a[k]} b {b[k]} {size_b[k]}")

    # One decision: 12 candidates x 5 neighbours x 10 steps.
    ego = rng.uniform(-15, 15, (12, 10, 3))
    neighbours = rng.uniform(-15, 15, (12, 5, 10, 3))
    present = np.ones(5, bool)
    checker = CollisionChecker()
    repeats = 200
    start = time.perf_counter()
    for _ in range(repeats):
        mask = checker.collides(ego, neighbours, present)
    ours_s = (time.perf_counter() - start) / repeats
    start = time.perf_counter()
    for _ in range(10):
        ego_objects = [[fcl_box(p, *checker.ego_size) for p in row] for row in ego]
        fcl_mask = np.array(
            [
                any(
                    fcl_overlap(ego_objects[i][t], fcl_box(neighbours[i, j, t], *checker.neighbour_size))
                    for j in range(5)
                    for t in range(10)
                )
                for i in range(12)
            ]
        )
    fcl_s = (time.perf_counter() - start) / 10
    assert np.array_equal(mask, fcl_mask), "the decision masks differ"
    print(f"one decision (600 pairs): ours {ours_s * 1e6:.0f} us, fcl {fcl_s * 1e6:.0f} us")
    print(f"speedup_vs_fcl {fcl_s / ours_s:.1f}")


if __name__ == "__main__":
    main()
