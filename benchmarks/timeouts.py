"""Why a trained hierarchy times out: each timed-out episode classified by what the ego stood still for.

At every decision where the ego stands (below 0.5 m/s) the scene is one of:

- queued: the ego has not entered the junction and a standing car ahead of it waits, uncommitted, at
  its stop line for a gap in the crossing streams (nothing the ego can do short of leaving its lane);
- standoff: a committed car within 10 m stands too, typically because the ego's box reaches its path,
  while the GCCP mask leaves the ego only the candidate under it (on SUMO's traffic and in SMARTS, whose
  drivers do not report a commitment, a car inside the junction box counts as committed);
- stall: neither, and the decider sent the ego to a subgoal beyond reach (``subgoal_reach_radius``)
  that the motion-planner does not drive to;
- other: anything else (the decider holds the ego on the candidate under it, for moving traffic).

A timed-out episode gets the kind it stood longest for if that was at least 10 s, else 'other' (for
example creeping through the junction too slowly).

Prints one line per timed-out episode and, last, ``timeouts <n> queued <q> standoff <s> stall <p> other <o>``.

    python benchmarks/timeouts.py --model pretrained --tasks left --episodes-per-task 50 --seed 0
    python benchmarks/timeouts.py --model pretrained/smarts --seed 1000 --set simulator=smarts
"""

from __future__ import annotations

import argparse
from functools import partial

import gymnasium as gym
import numpy as np
import torch as th

from gccp_envs.config import DT, parse_tasks
from gccp_envs.rewards import goal_errors
from gccp_envs.traffic import VEHICLE_LENGTH
from sb3_gccp.commands.common import CLIError, add_world_overrides, parse_assignments
from sb3_gccp.evaluation import run_episode
from sb3_gccp.hierarchy import load_hierarchy

STOPPED = 0.5
"""Speed [m/s] below which a car counts as standing."""
NEAR = 10.0
"""Distance [m] between centres within which a standing car is the one the ego waits behind or beside."""

LONG_WAIT = 10.0
"""Seconds of standing that explain a timeout."""


def waiting_reason(env: gym.Env) -> str | None:
    """Why the ego stands still at this step of a decider env: 'queued', 'standoff', 'stall', 'other', or
    None if it moves."""
    option_env = env.unwrapped
    world = option_env.world  # type: ignore[attr-defined]
    ego, traffic = world.ego, world.traffic
    if ego.speed >= STOPPED:
        return None
    idx = traffic.indices
    distance = np.hypot(traffic.pose[idx, 0] - ego.x, traffic.pose[idx, 1] - ego.y)
    standing = (distance < NEAR) & (traffic.speed[idx] < STOPPED)
    ego_out = max(abs(ego.x), abs(ego.y))
    out = np.maximum(np.abs(traffic.pose[idx, 0]), np.abs(traffic.pose[idx, 1]))
    ahead = out < ego_out
    outside = ego_out > world.layout.junction + VEHICLE_LENGTH / 2
    inside = out < world.layout.junction
    committed = getattr(traffic, "committed", np.zeros(len(traffic.pose), bool))[idx] | inside
    if outside and (standing & ahead & ~committed).any():
        return "queued"
    if (standing & committed).any():
        return "standoff"
    subgoal = option_env.subgoal  # type: ignore[attr-defined]
    if subgoal is not None and goal_errors(ego, subgoal)[0] > world.config.subgoal_reach_radius:
        return "stall"
    return "other"


def _record(reasons: list[str | None], env: gym.Env) -> None:
    reasons.append(waiting_reason(env))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="pretrained", help="a hierarchy run folder or pretrained/")
    parser.add_argument("--tasks", default="left", help="comma-separated: left,straight,right")
    parser.add_argument("--episodes-per-task", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0, help="first traffic seed")
    add_world_overrides(parser)
    args = parser.parse_args()
    try:
        tasks = parse_tasks(args.tasks)
        hierarchy = load_hierarchy(args.model)
        env = hierarchy.make_env(parse_assignments(args.set))
    except (ValueError, TypeError, OSError, CLIError) as err:
        parser.error(str(err))
    th.set_num_threads(1)
    policy = hierarchy.decider_policy(env.config)
    counts = {"queued": 0, "standoff": 0, "stall": 0, "other": 0}
    decision_s = env.unwrapped.config.decision_period * DT  # type: ignore[attr-defined]
    total = 0
    for task in tasks:
        for seed in range(args.seed, args.seed + args.episodes_per_task):
            total += 1
            reasons: list[str | None] = []
            result = run_episode(env, policy, task, seed, partial(_record, reasons))
            if not result.timeout:
                continue
            seconds = {k: reasons.count(k) * decision_s for k in counts}
            kind = max(seconds, key=lambda k: seconds[k])
            kind = kind if seconds[kind] >= LONG_WAIT else "other"
            counts[kind] += 1
            stood = ", ".join(f"{k} {v:.0f} s" for k, v in seconds.items())
            print(f"{task} seed {seed}: {kind} (standing {stood})")
    env.close()
    print(f"{total} episodes")
    print(f"timeouts {sum(counts.values())} " + " ".join(f"{k} {v}" for k, v in counts.items()))


if __name__ == "__main__":
    main()
