"""Which seeded traffic flows no policy can win: a car at the head of the ego's lane never gets its gap.

An evaluation flow (task, seed) is the world of ``env.reset(seed=seed, options={"task": task})``. The
task's turn is allowed from some lanes of the ego's arm only (left from the innermost, right from the
outermost, straight from both). At the ego's start, a car that stands or creeps within ``HEAD_OF_QUEUE``
metres of the stop line of such a lane, not yet committed to crossing, can be neither overtaken nor
cut in front of: the ego enters the junction on that lane only after that car has committed. The
script holds the ego back (it brakes to a stop where it starts, so it cannot change when cross traffic
lets those cars go), records when each such car commits, and adds the least time the ego needs from
standing at the stop line to the task's exit (full acceleration to cruise speed, no traffic). A lane
is open if that sum is within the episode's time limit; a flow is unwinnable if no task lane is open.
The bound is generous to the policy: it ignores the car length between the ego and the stop line and
any traffic after the head of the queue, so the true ceiling can only be lower.

On SUMO's traffic and in SMARTS (``--set traffic=sumo``, ``--set simulator=smarts``), whose drivers report
no commitment, a car commits when its front crosses its stop line.

Prints one line per unwinnable flow, then per task the best success any policy can reach on the
flows, and last ``max_success <rate>`` over all tasks.

    python benchmarks/winnable.py --episodes-per-task 50 --seed 0
    python benchmarks/winnable.py --episodes-per-task 50 --seed 0 --set simulator=smarts
"""

from __future__ import annotations

import argparse

import numpy as np
from gymnasium.utils import seeding
from tqdm import tqdm

from gccp_envs.action import EgoAction
from gccp_envs.config import DT, TASKS, IntersectionConfig, parse_tasks
from gccp_envs.traffic import VEHICLE_LENGTH
from gccp_envs.world import EGO_ARM, IntersectionWorld, make_world
from sb3_gccp.commands.common import CLIError, add_world_overrides, load_world_config

HEAD_OF_QUEUE = VEHICLE_LENGTH + 2.0
"""A car whose front is within this distance [m] of its stop line leaves no room for the ego ahead of it."""
STANDING = 4.0
"""Speed [m/s] below which a car at the head of its queue counts as waiting, not driving through."""


def least_exit_time(config: IntersectionConfig, distance: float) -> float:
    """Seconds the ego needs to drive ``distance`` metres from standing (accelerating to cruise speed)."""
    speed, travelled, steps = 0.0, 0.0, 0
    while travelled < distance:
        new_speed = min(speed + config.acceleration * DT, config.cruise_speed)
        travelled += 0.5 * (speed + new_speed) * DT
        speed, steps = new_speed, steps + 1
    return steps * DT


def committed(world: IntersectionWorld, slots: np.ndarray) -> np.ndarray:
    """Which of the vehicles in ``slots`` have committed to crossing: as our traffic reports it, or, for a
    backend that reports none, once the front has crossed the stop line."""
    traffic = world.traffic
    if hasattr(traffic, "committed"):
        return np.asarray(traffic.committed[slots])
    return np.asarray(traffic.s[slots] + traffic.length[slots] / 2.0 > world.layout.stop_s)


def lane_opening_times(world: IntersectionWorld, task: str) -> dict[int, float]:
    """Per task lane, the time [s] its head-of-queue cars have all committed (inf: not within the limit).

    Advances ``world`` to its time limit with the ego braking where it starts.
    """
    layout, traffic, config = world.layout, world.traffic, world.config
    lanes = sorted({layout.movements[p].lane for p in layout.paths_from(EGO_ARM, turn=task)})
    idx = traffic.indices
    front = layout.stop_s - (traffic.s[idx] + traffic.length[idx] / 2.0)
    waiting = (
        (layout.path_arm[traffic.path[idx]] == EGO_ARM)
        & ~committed(world, idx)
        & (front < HEAD_OF_QUEUE)
        & (traffic.speed[idx] < STANDING)
    )
    heads = {
        lane: set(traffic.uid[idx[waiting & (layout.path_lane[traffic.path[idx]] == lane)]].tolist())
        for lane in lanes
    }
    committed_at: dict[int, float] = {}
    for step in range(1, round(config.duration / DT) + 1):
        world.step(EgoAction.SLOW_DOWN)
        idx = traffic.indices
        for slot in idx[committed(world, idx)]:
            committed_at.setdefault(int(traffic.uid[slot]), step * DT)
    return {
        lane: max((committed_at.get(u, np.inf) for u in uids), default=0.0) for lane, uids in heads.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default=",".join(TASKS), help="comma-separated: left,straight,right")
    parser.add_argument("--episodes-per-task", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0, help="first traffic seed")
    add_world_overrides(parser)
    args = parser.parse_args()
    try:
        tasks = parse_tasks(args.tasks)
        config = load_world_config(None, args.set)
    except (ValueError, CLIError) as err:
        parser.error(str(err))
    if args.episodes_per_task < 1:
        parser.error("--episodes-per-task must be positive")
    try:
        world = make_world(config)
    except (ValueError, ImportError) as err:
        parser.error(str(err))
    winnable_total = 0
    for task in tasks:
        path = world.layout.paths_from(EGO_ARM, turn=task)[0]
        distance = world.layout.junction_end_s[path] - world.layout.stop_s + config.exit_distance
        drive = least_exit_time(config, float(distance))
        winnable = 0
        seeds = range(args.seed, args.seed + args.episodes_per_task)
        for seed in tqdm(seeds, desc=task, leave=False):
            world.reset(seeding.np_random(seed)[0], task)
            opening = lane_opening_times(world, task)
            if min(opening.values()) + drive <= config.duration:
                winnable += 1
                continue
            when = ", ".join(
                f"lane {lane} {'never' if np.isinf(t) else f'at {t:.1f} s'}" for lane, t in opening.items()
            )
            tqdm.write(
                f"{task} seed {seed}: unwinnable (head of queue commits: {when}; exit needs {drive:.1f} s)"
            )
        winnable_total += winnable
        print(f"{task}: {winnable} of {len(seeds)} flows winnable, max success {winnable / len(seeds):.3f}")
    world.close()
    print(f"max_success {winnable_total / (len(tasks) * args.episodes_per_task):.3f}")


if __name__ == "__main__":
    main()
