"""Median step time of GCCPPlanner-v0 vs highway-env's intersection-v2, both at 10 Hz, same traffic.

Ours is timed as MaskablePPO calls it: ``action_masks()`` and then ``step``, an action drawn from the mask
(the stock env has no mask). ``--no-masks`` times ``step`` alone, as before.

Run: python benchmarks/env_speed.py [--steps 3000] [--spawn-probability 0.06]
Last line: ``ratio <ours/stock>`` (goal: at most 0.5). Ours is also timed on SUMO traffic (``traffic: sumo``,
the ``sumo`` extra), in the line ``sumo_ratio <sumo/builtin>`` (goal: at most 1.5).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import highway_env  # noqa: F401  (registers intersection-v2)
import numpy as np

import sb3_gccp  # noqa: F401  (registers GCCPPlanner-v0)
from gccp_envs.config import IntersectionConfig


def median_step_ms(env: gym.Env, steps: int, seed: int, masks: bool = False) -> float:
    """Median wall time of ``env.step`` (with ``masks``, of ``action_masks()`` and ``step``, the action
    drawn under the mask, as MaskablePPO steps) with uniformly random actions; resets are not timed."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    times = []
    for _ in range(steps):
        start = time.perf_counter()
        mask = env.unwrapped.action_masks() if masks else None  # type: ignore[attr-defined]
        action = env.action_space.sample(mask=None if mask is None else mask.astype(np.int8))
        _, _, terminated, truncated, _ = env.step(action)
        times.append(time.perf_counter() - start)
        if terminated or truncated:
            env.reset()
    return float(np.median(times) * 1e3)


def print_sumo_speed(args: argparse.Namespace, blocks: int = 10) -> None:
    """Time GCCPPlanner-v0 on our traffic and on SUMO's (``traffic: sumo``) as ours is timed above, in
    alternating blocks of steps so that a change of load on a shared machine hits both alike; print the
    medians over the blocks and their ratio."""
    envs = {
        name: gym.make("GCCPPlanner-v0", spawn_probability=args.spawn_probability, traffic=name)
        for name in ("builtin", "sumo")
    }
    times: dict[str, list[float]] = {name: [] for name in envs}
    for block in range(blocks):
        for name, env in envs.items():
            times[name].append(
                median_step_ms(env, args.steps // blocks, args.seed + block, masks=not args.no_masks)
            )
    for env in envs.values():
        env.close()
    builtin, sumo = (float(np.median(times[name])) for name in envs)
    print(f"GCCPPlanner-v0 builtin / sumo traffic, interleaved: median {builtin:.2f} / {sumo:.2f} ms/step")
    print(f"sumo_ratio {sumo / builtin:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--spawn-probability", type=float, default=IntersectionConfig().spawn_probability)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-masks", action="store_true", help="time ours without action_masks()")
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
    ours = median_step_ms(ours_env, args.steps, args.seed, masks=not args.no_masks)
    stock = median_step_ms(stock_env, args.steps, args.seed)
    print(f"spawn_probability {args.spawn_probability} at 10 Hz, {args.steps} random-action steps each")
    with_masks = "" if args.no_masks else " (action_masks() + step)"
    print(f"GCCPPlanner-v0  median {ours:.2f} ms/step{with_masks}")
    print(f"intersection-v2 median {stock:.2f} ms/step")
    print_sumo_speed(args)
    print(f"ratio {ours / stock:.3f}")


if __name__ == "__main__":
    main()
