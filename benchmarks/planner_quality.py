"""How well a frozen motion-planner reaches subgoals and completes tasks.

1. ``GCCPPlanner-v0`` with default traffic, subgoals drawn uniformly from the 12 candidates and held
   for ``--hold-steps`` (3 s by default, so that even the farthest candidate is within reach): the share
   of subgoals reached, over the subgoals whose hold was not cut short by a collision or the time
   limit, and the share of episodes that end off the road.
2. Stopping: on empty roads the planner is given only "hold" subgoals (the candidate nearest the ego,
   redrawn every T_m steps) for 4 s: the share of episodes where it stands (below 0.5 m/s) at the end and did
   not leave the road. A decision-maker can only yield with a planner that stops.
3. The planner under the scripted decision-maker (always the farthest candidate) in ``GCCPDecider-v0``
   on roads without traffic: the share of episodes that complete their task.

Run: python benchmarks/planner_quality.py --model pretrained/planner.zip [--episodes 100] [--seed 0]
Last line: ``task_completion_empty_road <rate>`` (goals: completion >= 0.98, reach >= 0.95,
off-road <= 0.01).
"""

from __future__ import annotations

import argparse

import numpy as np
from tqdm import tqdm

import sb3_gccp  # noqa: F401  (registers the environments)
from gccp_envs.config import TASKS
from gccp_envs.option_env import GCCPDeciderEnv
from gccp_envs.planner_env import GCCPPlannerEnv
from gccp_envs.scripted import FarthestSubgoalDecider
from sb3_gccp.evaluation import evaluate
from sb3_gccp.frozen import FrozenPolicy

LANE_CHANGE_OFFSET = 3.0
"""A subgoal at least this far [m] to the side of the ego when drawn needs a lane change."""
LANE_CHANGE_LENGTH = 9.0
"""Lane-change subgoals drawn less than this far ahead [m] are counted apart: a 4 m shift back to the
lane's heading with the quickest turn (radius 6 m, two opposite arcs of 48 degrees) takes about 9 m, so
these are at best marginally reachable within the 2 m / 0.5 rad tolerance."""


def subgoal_reaching(planner: FrozenPolicy, episodes: int, seed: int, hold_steps: int) -> dict[str, float]:
    """Reach and off-road rates with uniformly drawn subgoals, over all tasks, and how many of the
    drawn subgoals were lane changes too short to drive (see ``LANE_CHANGE_LENGTH``)."""
    env = GCCPPlannerEnv(
        decision_period=hold_steps, prediction_horizon=min(10, hold_steps), hold_probability=0.0
    )
    reached = counted = offroad = total = short = short_reached = 0

    def count(goal: np.ndarray, hit: bool) -> None:
        nonlocal reached, counted, short, short_reached
        reached, counted = reached + hit, counted + 1
        if abs(goal[1]) >= LANE_CHANGE_OFFSET and goal[0] < LANE_CHANGE_LENGTH:
            short, short_reached = short + 1, short_reached + hit

    for task in TASKS:
        for k in tqdm(range(episodes), desc=f"subgoals {task}", leave=False):
            obs, _ = env.reset(seed=seed + k, options={"task": task})
            goal, hit, steps_held = obs["goal"].copy(), False, 0
            while True:
                obs, _, terminated, truncated, info = env.step(planner(obs, env.action_masks()))
                hit |= info["goal_reached"]
                steps_held += 1
                if terminated or truncated:
                    # A hold cut short by a collision or the time limit says nothing about the planner.
                    if hit or not (info["crashed"] or info["timeout"]):
                        count(goal, hit)
                    offroad += info["offroad"]
                    total += 1
                    break
                if steps_held == hold_steps:
                    count(goal, hit)
                    goal, hit, steps_held = obs["goal"].copy(), False, 0
    return {
        "subgoal_reach": reached / max(counted, 1),
        "subgoals": counted,
        "offroad": offroad / total,
        "short_lane_changes": short,
        "short_lane_changes_reached": short_reached,
    }


def stopping(planner: FrozenPolicy, episodes: int, seed: int, steps: int = 40) -> float:
    """Share of empty-road episodes in which the planner, given only hold subgoals, stands still on the
    road after ``steps`` steps."""
    env = GCCPPlannerEnv(spawn_probability=0.0, hold_probability=1.0, hold_continue=1.0)
    stopped = 0
    for task in TASKS:
        for k in range(episodes):
            obs, _ = env.reset(seed=seed + k, options={"task": task})
            for _ in range(steps):
                obs, _, terminated, truncated, _ = env.step(planner(obs, env.action_masks()))
                if terminated or truncated:
                    break
            stopped += not (terminated or truncated) and env.world.ego.speed < 0.5
    return stopped / (len(TASKS) * episodes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="the planner's SB3 .zip")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per task in each part")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hold-steps", type=int, default=30, help="steps each drawn subgoal is held")
    args = parser.parse_args()
    planner = FrozenPolicy(args.model)
    reaching = subgoal_reaching(planner, args.episodes, args.seed, args.hold_steps)
    stop_rate = stopping(planner, args.episodes, args.seed)
    env = GCCPDeciderEnv(planner=planner, spawn_probability=0.0)
    results = evaluate(env, FarthestSubgoalDecider(), TASKS, args.episodes, args.seed)
    completion = sum(r.success for r in results) / len(results)
    print(f"model {args.model}, {args.episodes} episodes per task, seed {args.seed}")
    print(
        f"subgoal_reach {reaching['subgoal_reach']:.3f} over {reaching['subgoals']} subgoals held "
        f"{args.hold_steps} steps (default traffic)"
    )
    print(
        f"  of them {reaching['short_lane_changes']} lane changes (>= {LANE_CHANGE_OFFSET:.0f} m to the "
        f"side) less than {LANE_CHANGE_LENGTH:.0f} m ahead: {reaching['short_lane_changes_reached']} reached"
    )
    print(f"offroad {reaching['offroad']:.3f} of episodes (default traffic)")
    print(f"stop_rate {stop_rate:.3f} (hold subgoals only for 4 s, empty road)")
    for task in TASKS:
        rows = [r for r in results if r.task == task]
        print(f"  {task:<9} completion {sum(r.success for r in rows) / len(rows):.3f} (empty road)")
    print(f"task_completion_empty_road {completion:.3f}")


if __name__ == "__main__":
    main()
