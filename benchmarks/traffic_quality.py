"""Share of other vehicles that crash with no ego: ours vs highway-env's intersection-v0 and -v2.

20 seeds x 60 s of simulated time at 10 Hz, the same spawn probability per step for all. Our world is run
with both traffic backends: ours and SUMO's (``traffic: sumo``, the ``sumo`` extra), crashes detected by
our box checker in both.
Run: python benchmarks/traffic_quality.py [--seeds 20] [--seconds 60] [--spawn-probability 0.06]
Last line: ``npc_crash_share <ours>`` (goal: at most 0.01).
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import highway_env  # noqa: F401  (registers the stock intersections)
import numpy as np
from tqdm import trange

from gccp_envs.config import DT, IntersectionConfig
from gccp_envs.scenario import layout_for
from gccp_envs.world import make_traffic


def ours(
    seeds: int, steps: int, spawn_probability: float, backend: str = "builtin"
) -> tuple[int, int, float]:
    """(vehicles, crashed vehicles, completed crossings per minute) of our world's traffic (config
    ``traffic``: ``backend``)."""
    config = IntersectionConfig(spawn_probability=spawn_probability, traffic=backend)
    layout = layout_for(config)
    total = crashed = left = 0
    traffic = make_traffic(layout, config, np.random.default_rng())
    for seed in trange(seeds, desc=f"ours, {backend}", leave=False):
        rng = np.random.default_rng(seed)
        traffic.reset(rng)
        for _ in range(steps):
            if rng.uniform() < spawn_probability:
                traffic.spawn_random()
            traffic.step()
            traffic.detect_crashes()
        total += traffic.spawned
        crashed += len(traffic.crashed_uids)
        left += traffic.spawned - int(traffic.active.sum())
    traffic.close()
    return total, crashed, left / seeds / (steps * DT / 60.0)


def stock(env_id: str, seeds: int, steps: int, spawn_probability: float) -> tuple[int, int, float]:
    """The same for a highway-env intersection, its ego taken off the road after reset."""
    env = gym.make(
        env_id,
        config={
            "policy_frequency": 10,
            "simulation_frequency": 10,
            "spawn_probability": spawn_probability,
        },
    ).unwrapped
    total = crashed = left = 0
    for seed in trange(seeds, desc=env_id, leave=False):
        env.reset(seed=seed)
        road = env.road
        road.vehicles = [v for v in road.vehicles if v not in env.controlled_vehicles]
        seen = {id(v): v for v in road.vehicles}
        for _ in range(steps):
            road.act()
            road.step(DT)
            env._clear_vehicles()
            env._spawn_vehicle(spawn_probability=spawn_probability)
            seen.update({id(v): v for v in road.vehicles})
        total += len(seen)
        crashed += sum(v.crashed for v in seen.values())
        left += len(seen) - len(road.vehicles)
    return total, crashed, left / seeds / (steps * DT / 60.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--spawn-probability", type=float, default=IntersectionConfig().spawn_probability)
    args = parser.parse_args()
    steps = round(args.seconds / DT)
    print(f"{args.seeds} seeds x {args.seconds:.0f} s at 10 Hz, spawn_probability {args.spawn_probability}")
    print(f"{'traffic':<16}{'vehicles':>9}{'crashed':>9}{'share':>8}{'through/min':>13}")
    results = {
        "intersection-v0": stock("intersection-v0", args.seeds, steps, args.spawn_probability),
        "intersection-v2": stock("intersection-v2", args.seeds, steps, args.spawn_probability),
        "ours": ours(args.seeds, steps, args.spawn_probability),
        "ours, sumo": ours(args.seeds, steps, args.spawn_probability, "sumo"),
    }
    for name, (total, crashed, rate) in results.items():
        print(f"{name:<16}{total:>9}{crashed:>9}{crashed / max(total, 1):>8.3f}{rate:>13.1f}")
    total, crashed, _ = results["ours"]
    print(f"npc_crash_share {crashed / max(total, 1):.4f}")


if __name__ == "__main__":
    main()
