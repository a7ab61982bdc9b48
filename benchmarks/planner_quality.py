"""How well a frozen motion-planner reaches subgoals and completes tasks.

1. ``GCCPPlanner-v0`` with default traffic, subgoals drawn uniformly from the candidates ahead and
   held for ``--hold-steps`` (3 s by default, so that even the farthest candidate is within reach): the
   share of subgoals reached, over the subgoals whose hold was not cut short by a collision, the time
   limit or the task's exit (see ``CUT_SHORT``), and the share of episodes that end off the road.
2. Stopping: on empty roads the planner is given only "hold" subgoals (the candidate nearest the ego,
   redrawn every T_m steps) for 4 s: the share of episodes where it stands (below 0.5 m/s) at the end and did
   not leave the road. A decision-maker can only yield with a planner that stops.
3. The planner under the scripted decision-maker (always the farthest candidate) in ``GCCPDecider-v0``
   on roads without traffic: the share of episodes that complete their task.
4. Restarting: the same, but at a random point of the route (after 0 to 4 decisions) the decision-maker
   holds (the nearest candidate) until the ego stands, then sends it to the farthest candidate again, as a
   decision-maker does after yielding: the share of those stops after which the ego drives off (moves
   1 m within 3 s) and the share that then complete the task. A planner that stands still for a far
   subgoal stalls the hierarchy until the time limit (``restart_rate``).
5. Restarting in traffic: part 4 with default traffic, which a decision-maker stops the ego for and
   which the planner sees in its observation: the share of those stops after which the episode runs
   into the time limit (``stall_in_traffic``; a clone can restart on every empty road and still stand
   beside traffic), and, apart, after which it collides (nothing checks the farthest candidate here).

With ``--oracle``, part 1 also prints ``oracle_reach``: the share of the drawn subgoals that some
forward path within the ego's turn radius and driving range reaches (Dubins paths; road edge and
traffic ignored), an upper bound on any planner's subgoal reach over the same draws.

Run: python benchmarks/planner_quality.py --model pretrained/planner.zip [--episodes 100] [--seed 0]
[--oracle] [--set KEY=VALUE ...]; ``--model scripted`` measures the scripted pure-pursuit planner,
``--model search`` the search planner (``gccp_envs.scripted.SearchPlanner``): the experts the planner
stage can clone.
A planner ``.zip`` named by a ``hierarchy.yml`` in its folder (a decider run, ``pretrained/``) is measured in
that hierarchy's world, the one the decision-maker runs it in (``pretrained/``: ``mask_drive_on: 10``, as the
planner entry trains it); ``--set`` keys apply on top, and ``--default-world`` measures it in the default
world instead. The experts and any other planner run in the default world.
Last line: ``task_completion_empty_road <rate>``. The shipped planner's goals: reach >= 0.95, off-road
<= 0.005, stop rate >= 0.90 and no lower than the best expert's, completion >= 0.99.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from tqdm import tqdm

import sb3_gccp  # noqa: F401  (registers the environments)
from gccp_envs.action import EgoState
from gccp_envs.config import DT, TASKS, IntersectionConfig
from gccp_envs.geometry import dubins_length
from gccp_envs.option_env import GCCPDeciderEnv, Planner
from gccp_envs.planner_env import GCCPPlannerEnv
from gccp_envs.scripted import FarthestSubgoalDecider
from sb3_gccp.commands.common import CLIError, parse_assignments
from sb3_gccp.constants import HIERARCHY_FILE
from sb3_gccp.evaluation import evaluate
from sb3_gccp.frozen import load_planner
from sb3_gccp.hierarchy import Hierarchy
from sb3_gccp.training.imitation import EXPERTS

LANE_CHANGE_OFFSET = 3.0
"""A subgoal at least this far [m] to the side of the ego when drawn needs a lane change."""
LANE_CHANGE_LENGTH = 9.0
"""Lane-change subgoals drawn less than this far ahead [m] are counted apart: a 4 m shift back to the
lane's heading with the quickest turn (radius 6 m, two opposite arcs of 48 degrees) takes about 9 m."""
CUT_SHORT = ("crashed", "timeout", "is_success")
"""Episode ends that leave a hold out of the reach rate unless its subgoal was reached: a collision
(the planner ignores traffic), the time limit, and the task's exit (candidates lie up to 20 m along the
route, so some lie beyond the exit line, where the episode has already ended). Leaving the road and
a wrong exit are the planner's failures and count as misses."""
TARGET_SPACING = 0.1
"""Spacing [m] of the positions ``reach_bound`` samples within a subgoal's reach radius."""
TARGET_TURN_SPACING = 0.01
"""Spacing [rad] of the headings ``reach_bound`` samples within a subgoal's heading tolerance."""


def longest_drive(config: IntersectionConfig, speed: float, steps: int) -> float:
    """Farthest [m] the ego can drive in ``steps`` steps from ``speed`` (accelerating to cruise speed)."""
    total = 0.0
    for _ in range(steps):
        new_speed = max(speed, min(speed + config.acceleration * DT, config.cruise_speed))
        total += 0.5 * (speed + new_speed) * DT
        speed = new_speed
    return total


def reach_bound(config: IntersectionConfig, start: EgoState, goal: np.ndarray, steps: int) -> bool:
    """Whether the subgoal ``goal`` could be reached within ``steps`` steps from ``start`` by any forward
    path no tighter than the quickest turn and no longer than the ego can drive: a relaxation of the six
    actions (which drive exactly such paths) that ignores the road edge and the traffic, so no planner
    reaches a subgoal this rejects. Samples the poses within the reach radius and heading tolerance."""
    r, h = config.subgoal_reach_radius, config.subgoal_reach_heading
    offsets = np.arange(-r, r + 1e-9, TARGET_SPACING)
    ox, oy = np.meshgrid(offsets, offsets)
    inside = np.hypot(ox, oy) <= r
    turns = np.arange(-h, h + 1e-9, TARGET_TURN_SPACING)
    ends = np.stack(
        [
            np.repeat(goal[0] + ox[inside], len(turns)),
            np.repeat(goal[1] + oy[inside], len(turns)),
            np.tile(goal[2] + turns, int(inside.sum())),
        ],
        axis=-1,
    )
    start_pose = np.array([start.x, start.y, start.heading])
    shortest = dubins_length(start_pose, ends, 1.0 / config.quick_turn_curvature).min()
    return bool(shortest <= longest_drive(config, start.speed, steps))


def subgoal_reaching(
    planner: Planner,
    episodes: int,
    seed: int,
    hold_steps: int,
    oracle: bool = False,
    world: dict[str, Any] | None = None,
) -> dict[str, float]:
    """Reach and off-road rates with uniformly drawn subgoals, over all tasks, how many of the drawn
    subgoals were short lane changes (see ``LANE_CHANGE_LENGTH``) and, with ``oracle``, how many
    no planner can miss for want of a path (see ``reach_bound``). ``world``: config keys of the env."""
    env = GCCPPlannerEnv(
        **{
            **(world or {}),
            "decision_period": hold_steps,
            "prediction_horizon": min(10, hold_steps),
            "hold_probability": 0.0,
        }
    )
    reached = counted = offroad = total = short = short_reached = feasible = short_feasible = 0
    cut_short = dict.fromkeys(CUT_SHORT, 0)

    def count(goal: np.ndarray, hit: bool, start: EgoState, world_goal: np.ndarray) -> None:
        nonlocal reached, counted, short, short_reached, feasible, short_feasible
        reached, counted = reached + hit, counted + 1
        can = oracle and (hit or reach_bound(env.config, start, world_goal, hold_steps))
        feasible += can
        if abs(goal[1]) >= LANE_CHANGE_OFFSET and goal[0] < LANE_CHANGE_LENGTH:
            short, short_reached, short_feasible = short + 1, short_reached + hit, short_feasible + can

    for task in TASKS:
        for k in tqdm(range(episodes), desc=f"subgoals {task}", leave=False):
            obs, _ = env.reset(seed=seed + k, options={"task": task})
            goal, hit, steps_held = obs["goal"].copy(), False, 0
            start, world_goal = replace(env.world.ego), env.subgoal.copy()
            while True:
                obs, _, terminated, truncated, info = env.step(planner(obs, env.action_masks()))
                hit |= info["goal_reached"]
                steps_held += 1
                if terminated or truncated:
                    # A hold cut short by an end the planner did not cause says nothing about it: a
                    # collision (it ignores traffic), the time limit, or the task's exit, which ends the
                    # episode before a candidate drawn beyond it can be reached.
                    cut = next((end for end in CUT_SHORT if info[end]), None)
                    if hit or cut is None:
                        count(goal, hit, start, world_goal)
                    else:
                        cut_short[cut] += 1
                    offroad += info["offroad"]
                    total += 1
                    break
                if steps_held == hold_steps:
                    count(goal, hit, start, world_goal)
                    goal, hit, steps_held = obs["goal"].copy(), False, 0
                    start, world_goal = replace(env.world.ego), env.subgoal.copy()
    return {
        "subgoal_reach": reached / max(counted, 1),
        "subgoals": counted,
        "offroad": offroad / total,
        "short_lane_changes": short,
        "short_lane_changes_reached": short_reached,
        "oracle_reach": feasible / max(counted, 1),
        "short_lane_changes_feasible": short_feasible,
        **{f"cut_short_{end}": n for end, n in cut_short.items()},
    }


def stopping(
    planner: Planner, episodes: int, seed: int, steps: int = 40, world: dict[str, Any] | None = None
) -> float:
    """Share of empty-road episodes in which the planner, given only hold subgoals, stands still on the
    road after ``steps`` steps."""
    env = GCCPPlannerEnv(
        **{**(world or {}), "spawn_probability": 0.0, "hold_probability": 1.0, "hold_continue": 1.0}
    )
    stopped = 0
    for task in TASKS:
        for k in tqdm(range(episodes), desc=f"stops {task}", leave=False):
            obs, _ = env.reset(seed=seed + k, options={"task": task})
            for _ in range(steps):
                obs, _, terminated, truncated, _ = env.step(planner(obs, env.action_masks()))
                if terminated or truncated:
                    break
            stopped += not (terminated or truncated) and env.world.ego.speed < 0.5
    return stopped / (len(TASKS) * episodes)


def restarting(
    planner: Planner,
    episodes: int,
    seed: int,
    hold_decisions: int = 5,
    restart_decisions: int = 3,
    traffic: bool = False,
    world: dict[str, Any] | None = None,
) -> dict[str, float]:
    """Stop the ego by hold subgoals at a random point of its route on an empty road (with ``traffic``:
    on default traffic), then send it to the farthest candidate: how often it drives off and completes,
    and how often the episode then ends in a time-out or a collision. Episodes that end before the
    hold, or whose ego does not stand within ``hold_decisions`` decisions, are counted apart."""
    env = GCCPDeciderEnv(
        planner=planner, **{**(world or {}), **({} if traffic else {"spawn_probability": 0.0})}
    )
    farthest = FarthestSubgoalDecider()
    rng = np.random.default_rng(seed)
    stops = moved = completed = not_stopped = timed_out = crashed = 0
    label = "restarts in traffic" if traffic else "restarts"
    for task in TASKS:
        for k in tqdm(range(episodes), desc=f"{label} {task}", leave=False):
            obs, _ = env.reset(seed=seed + k, options={"task": task})
            ended, sim = False, env.world
            for _ in range(int(rng.integers(5))):
                obs, _, terminated, truncated, _ = env.step(farthest(obs, env.action_masks()))
                if terminated or truncated:
                    ended = True
                    break
            for _ in range(hold_decisions):
                if ended or sim.ego.speed < 0.1:
                    break
                nearest = int(np.argmin(np.hypot(*obs["subgoals"][:, :2].T)))
                obs, _, terminated, truncated, _ = env.step(nearest)
                ended = terminated or truncated
            if ended:
                continue
            if sim.ego.speed >= 0.1:
                not_stopped += 1
                continue
            stops += 1
            start = np.array([sim.ego.x, sim.ego.y])
            drove_off, decisions, terminated, truncated = False, 0, False, False
            while not (terminated or truncated):
                obs, _, terminated, truncated, info = env.step(farthest(obs, env.action_masks()))
                decisions += 1
                if decisions <= restart_decisions:
                    drove_off |= bool(np.hypot(sim.ego.x - start[0], sim.ego.y - start[1]) >= 1.0)
            moved += drove_off or bool(info["is_success"])
            completed += bool(info["is_success"])
            timed_out += bool(info["timeout"])
            crashed += bool(info["crashed"])
    return {
        "restart_rate": moved / max(stops, 1),
        "completion_after_stop": completed / max(stops, 1),
        "timeout_after_stop": timed_out / max(stops, 1),
        "crash_after_stop": crashed / max(stops, 1),
        "stops": stops,
        "not_stopped": not_stopped,
    }


def hierarchy_world(model: str) -> tuple[dict[str, Any], Path | None]:
    """The world keys a planner ``.zip`` runs with inside the hierarchy of its folder, and that
    hierarchy's file; ``({}, None)`` when no ``hierarchy.yml`` there names it.

    :raises ValueError: one line, when that ``hierarchy.yml`` cannot be read
    """
    path = Path(model)
    spec = path.parent / HIERARCHY_FILE
    if not (path.suffix == ".zip" and spec.is_file()):
        return {}, None
    hierarchy = Hierarchy.read(path.parent)
    if hierarchy.planner is None or hierarchy.planner.resolve() != path.resolve():
        return {}, None
    return dict(hierarchy.world), spec


def _apart_from_defaults(world: dict[str, Any]) -> dict[str, Any]:
    """The keys of a world config map whose values differ from the defaults."""
    changed, default = IntersectionConfig.from_dict(world), IntersectionConfig()
    return {key: value for key, value in world.items() if getattr(changed, key) != getattr(default, key)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="the planner's SB3 .zip, 'scripted' or 'search'")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per task in each part")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hold-steps", type=int, default=30, help="steps each drawn subgoal is held")
    parser.add_argument(
        "--oracle",
        action="store_true",
        help="also search every drawn subgoal's action sequences: the reach no planner can beat",
    )
    parser.add_argument(
        "--max-lateral-acceleration",
        type=float,
        default=None,
        help="with --model search: the search planner's lateral acceleration limit [m/s²] (the planner "
        "stage's imitation.expert_kwargs)",
    )
    parser.add_argument(
        "--limit-from-goal-heading",
        type=float,
        default=None,
        help="with --max-lateral-acceleration: the limit holds only for goals whose heading differs from "
        "the ego's by at least this [rad]",
    )
    parser.add_argument(
        "--brake-behind",
        action="store_true",
        help="with --model search: brake for a goal behind the ego on its lane however far behind (the "
        "search planner's brake_behind)",
    )
    parser.add_argument(
        "--brake-behind-heading",
        type=float,
        default=None,
        help="with --brake-behind: only for a goal whose heading is within this [rad] of the ego's",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="world config key (repeatable) of every env the benchmark runs, e.g. rear_axle_offset=1.5",
    )
    parser.add_argument(
        "--default-world",
        action="store_true",
        help="measure a planner named by the hierarchy.yml beside it in the default world, not that "
        "hierarchy's",
    )
    args = parser.parse_args()
    try:
        trained, spec = ({}, None) if args.default_world else hierarchy_world(args.model)
        assigned = parse_assignments(args.set)
        world = {**trained, **assigned}
        config = IntersectionConfig.from_dict(world)
    except (CLIError, ValueError, TypeError) as err:
        parser.error(str(err))
    if args.max_lateral_acceleration is not None and args.model != "search":
        parser.error("--max-lateral-acceleration applies to --model search only")
    if args.brake_behind and args.model != "search":
        parser.error("--brake-behind applies to --model search only")
    if args.brake_behind_heading is not None and not args.brake_behind:
        parser.error("--brake-behind-heading needs --brake-behind")
    if args.limit_from_goal_heading is not None and args.max_lateral_acceleration is None:
        parser.error("--limit-from-goal-heading needs --max-lateral-acceleration")
    th.set_num_threads(1)
    kwargs: dict[str, float | bool] = {}
    if args.brake_behind:
        kwargs["brake_behind"] = True
    if args.brake_behind_heading is not None:
        kwargs["brake_behind_heading"] = args.brake_behind_heading
    if args.max_lateral_acceleration is not None:
        kwargs["max_lateral_acceleration"] = args.max_lateral_acceleration
    if args.limit_from_goal_heading is not None:
        kwargs["limit_from_goal_heading"] = args.limit_from_goal_heading
    try:
        planner: Planner = (
            EXPERTS[args.model](config, **kwargs)
            if args.model in EXPERTS
            else load_planner(args.model, config)
        )
    except (ValueError, OSError) as err:  # a bad expert setting, or no motion-planner at that path
        parser.error(str(err))
    reaching = subgoal_reaching(planner, args.episodes, args.seed, args.hold_steps, args.oracle, world)
    stop_rate = stopping(planner, args.episodes, args.seed, world=world)
    restart = restarting(planner, args.episodes, args.seed, world=world)
    in_traffic = restarting(planner, args.episodes, args.seed, traffic=True, world=world)
    env = GCCPDeciderEnv(planner=planner, **{**world, "spawn_probability": 0.0})
    results = evaluate(env, FarthestSubgoalDecider(), TASKS, args.episodes, args.seed)
    completion = sum(r.success for r in results) / len(results)
    limit = "" if not kwargs else " (" + ", ".join(f"{key} {value}" for key, value in kwargs.items()) + ")"
    shown = {**_apart_from_defaults(trained), **assigned}  # every --set key, even one at its default
    settings = "".join(f", {key}={value}" for key, value in shown.items())
    source = "" if spec is None else f" (world of {spec})"
    print(f"model {args.model}{limit}, {args.episodes} episodes per task, seed {args.seed}{settings}{source}")
    print(
        f"subgoal_reach {reaching['subgoal_reach']:.3f} over {reaching['subgoals']} subgoals held "
        f"{args.hold_steps} steps (default traffic)"
    )
    print(
        f"  left out, cut short before reached by a collision {reaching['cut_short_crashed']}, the time "
        f"limit {reaching['cut_short_timeout']}, the task's exit {reaching['cut_short_is_success']}"
    )
    print(
        f"  of them {reaching['short_lane_changes']} lane changes (>= {LANE_CHANGE_OFFSET:.0f} m to the "
        f"side) less than {LANE_CHANGE_LENGTH:.0f} m ahead: {reaching['short_lane_changes_reached']} reached"
    )
    if args.oracle:
        print(
            f"oracle_reach {reaching['oracle_reach']:.3f} (some action sequence reaches the subgoal in "
            f"{args.hold_steps} steps, road edge and traffic ignored); short lane changes: "
            f"{reaching['short_lane_changes_feasible']} of {reaching['short_lane_changes']}"
        )
    print(f"offroad {reaching['offroad']:.3f} of episodes (default traffic)")
    print(f"stop_rate {stop_rate:.3f} (hold subgoals only for 4 s, empty road)")
    print(
        f"restart_rate {restart['restart_rate']:.3f} over {restart['stops']} stops along the route "
        f"(drove off within 3 s when sent on, empty road); completion after the stop "
        f"{restart['completion_after_stop']:.3f}; {restart['not_stopped']} holds did not stop"
    )
    print(
        f"stall_in_traffic {in_traffic['timeout_after_stop']:.3f} of {in_traffic['stops']} stops along the "
        f"route ended in the time limit (default traffic); completion after the stop "
        f"{in_traffic['completion_after_stop']:.3f}, collisions {in_traffic['crash_after_stop']:.3f} "
        f"(nothing checks the farthest candidate)"
    )
    for task in TASKS:
        rows = [r for r in results if r.task == task]
        print(f"  {task:<9} completion {sum(r.success for r in rows) / len(rows):.3f} (empty road)")
    print(f"task_completion_empty_road {completion:.3f}")


if __name__ == "__main__":
    main()
