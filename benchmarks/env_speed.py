"""Median step time of GCCPPlanner-v0 vs highway-env's intersection-v2, both at 10 Hz, same traffic.

Ours is timed as MaskablePPO calls it: ``action_masks()`` and then ``step``, an action drawn from the mask
(the stock env has no mask). ``--no-masks`` times ``step`` alone, as before.

Run: python benchmarks/env_speed.py [--steps 3000] [--spawn-probability 0.06]
Last line: ``ratio <ours/stock>`` (goal: at most 0.5). Ours is also timed on SUMO traffic (``traffic: sumo``,
the ``sumo`` extra), in the line ``sumo_ratio <sumo/builtin>`` (goal: at most 1.5), and, with the ``smarts``
extra, in SMARTS (``simulator: smarts``): ``smarts_ratio <smarts/builtin>``, then where a SMARTS step goes and
``smarts_observation_share <our observation / SMARTS's step>`` (goal: at most 0.2); ``--smarts-routes
waypoints`` times SMARTS with the routes from its waypoint paths.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from importlib.util import find_spec
from typing import Any

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


def print_backend_speed(
    args: argparse.Namespace,
    key: str,
    value: str,
    steps: int,
    blocks: int = 10,
    more: dict[str, Any] | None = None,
) -> dict[str, gym.Env]:
    """Time GCCPPlanner-v0 on our world and with config ``key=value`` (SUMO's traffic, SMARTS; and the keys
    ``more``) as ours is timed above, in alternating blocks of steps so that a change of load on a shared
    machine hits both alike; print the medians over the blocks and their ratio, ``<value>_ratio``. Return
    the envs, open."""
    envs = {
        name: gym.make("GCCPPlanner-v0", spawn_probability=args.spawn_probability, **overrides)
        for name, overrides in (("builtin", {}), (value, {key: value, **(more or {})}))
    }
    times: dict[str, list[float]] = {name: [] for name in envs}
    for block in range(blocks):
        for name, env in envs.items():
            times[name].append(
                median_step_ms(env, steps // blocks, args.seed + block, masks=not args.no_masks)
            )
    builtin, other = (float(np.median(times[name])) for name in envs)
    print(f"GCCPPlanner-v0 builtin / {value} {key}, interleaved: median {builtin:.2f} / {other:.2f} ms/step")
    print(f"{value}_ratio {other / builtin:.3f}")
    return envs


def print_smarts_split(env: gym.Env, steps: int, seed: int) -> None:
    """Where a SMARTS step goes, from cProfile over ``steps`` steps (``action_masks()`` and ``step``, not the
    resets): SMARTS's own step, our observation building, our action mask, and the rest (our reward, info,
    the ego's kinematics)."""
    profile = cProfile.Profile()
    env.reset(seed=seed)
    env.action_space.seed(seed)
    for _ in range(steps):  # resets (SMARTS steps through the warm-up) are not profiled
        profile.enable()
        mask = env.unwrapped.action_masks()  # type: ignore[attr-defined]
        _, _, terminated, truncated, _ = env.step(env.action_space.sample(mask=mask.astype(np.int8)))
        profile.disable()
        if terminated or truncated:
            env.reset()
    stats = pstats.Stats(profile).stats  # type: ignore[attr-defined]
    from smarts.core.smarts import SMARTS

    from gccp_envs.observation import SceneObserver
    from gccp_envs.planner_env import GCCPPlannerEnv

    parts = {
        "SMARTS.step": SMARTS.step,
        "SceneObserver.observe": SceneObserver.observe,
        "action_masks": GCCPPlannerEnv.action_masks,
        "env.step": GCCPPlannerEnv.step,
    }
    total = {}
    for label, function in parts.items():
        code = function.__code__
        total[label] = stats[(code.co_filename, code.co_firstlineno, code.co_name)][3]
    whole = total["env.step"] + total["action_masks"]
    shares = ", ".join(f"{label} {100 * total[label] / whole:.0f} %" for label in list(parts)[:3])
    print(f"SMARTS step + mask under cProfile, {steps} steps: {shares} of {1e3 * whole / steps:.1f} ms/step")
    print(f"smarts_observation_share {total['SceneObserver.observe'] / total['SMARTS.step']:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--spawn-probability", type=float, default=IntersectionConfig().spawn_probability)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-masks", action="store_true", help="time ours without action_masks()")
    parser.add_argument("--smarts-steps", type=int, default=1000, help="SMARTS steps (0: skip)")
    parser.add_argument(
        "--smarts-routes",
        choices=("layout", "waypoints"),
        default=IntersectionConfig().smarts_routes,
        help="the SMARTS env's smarts_routes (waypoints: asks SMARTS for its waypoint paths every step)",
    )
    args = parser.parse_args()
    if args.steps < 1 or args.smarts_steps < 0:
        parser.error("--steps must be at least 1 and --smarts-steps at least 0")
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
    for env in print_backend_speed(args, "traffic", "sumo", args.steps).values():
        env.close()
    if args.smarts_steps and find_spec("smarts") is not None:
        envs = print_backend_speed(
            args, "simulator", "smarts", args.smarts_steps, more={"smarts_routes": args.smarts_routes}
        )
        print_smarts_split(envs["smarts"], args.smarts_steps, args.seed)
        for env in envs.values():
            env.close()
    print(f"ratio {ours / stock:.3f}")


if __name__ == "__main__":
    main()
