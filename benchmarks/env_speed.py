"""Median step time of GCCPPlanner-v0 vs highway-env's intersection-v2, both at 10 Hz, same traffic.

Run: python benchmarks/env_speed.py [--steps 3000] [--spawn-probability 0.06]
Last line: ``ratio <ours/stock>`` (goal: at most 0.5).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import highway_env  # noqa: F401  (registers intersection-v2)
import numpy as np

import sb3_gccp  # noqa: F401  (registers GCCPPlanner-v0)
from gccp_envs.config import IntersectionConfig


def median_step_ms(env: gym.Env, steps: int, seed: int) -> float:
    """Median wall time of ``env.step`` with uniformly random actions; resets are not timed."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    times = []
    for _ in range(steps):
        action = env.action_space.sample()
        start = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        times.append(time.perf_counter() - start)
        if terminated or truncated:
            env.reset()
    return float(np.median(times) * 1e3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--spawn-probability", type=float, default=IntersectionConfig().spawn_probability)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    ours_env = gym.make("GCCPPlanner-v0", spawn_probability=args.spawn_probability)
    stock_env = gym.make(
        "intersection-v2",
        config={
            "policy_frequency": 10,
            "simulation_frequency": 10,
            "spawn_probability": args.spawn_probability,
        },
    )
    ours_env.reset(seed=args.seed)  # builds the cached layout outside the timing
    ours = median_step_ms(ours_env, args.steps, args.seed)
    stock = median_step_ms(stock_env, args.steps, args.seed)
    print(f"spawn_probability {args.spawn_probability} at 10 Hz, {args.steps} random-action steps each")
    print(f"GCCPPlanner-v0  median {ours:.2f} ms/step")
    print(f"intersection-v2 median {stock:.2f} ms/step")
    print(f"ratio {ours / stock:.3f}")


if __name__ == "__main__":
    main()
