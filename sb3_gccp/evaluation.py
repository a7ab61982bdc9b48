"""Seeded evaluation episodes and the paper's results table (success / collision per task)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import gymnasium as gym
import numpy as np

from gccp_envs.config import TASKS
from sb3_gccp.progress import new_bar

Policy = Callable[[dict[str, np.ndarray], np.ndarray], int]
"""(observation, action mask) -> action."""


@dataclass(frozen=True)
class EpisodeResult:
    """Outcome of one evaluation episode."""

    task: str
    seed: int
    success: bool
    crashed: bool
    offroad: bool
    wrong_exit: bool
    timeout: bool
    steps: int
    episode_return: float


def run_episode(
    env: gym.Env,
    policy: Policy,
    task: str,
    seed: int,
    on_step: Callable[[gym.Env], None] | None = None,
) -> EpisodeResult:
    """Play one episode of ``task`` on the traffic of ``seed``.

    :param on_step: called after reset and after every step (for example to record frames)
    """
    obs, _ = env.reset(seed=seed, options={"task": task})
    if on_step:
        on_step(env)
    unwrapped = env.unwrapped
    total, steps = 0.0, 0
    while True:
        action = policy(obs, unwrapped.action_masks())  # type: ignore[attr-defined]
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        steps += 1
        if on_step:
            on_step(env)
        if terminated or truncated:
            return EpisodeResult(
                task,
                seed,
                bool(info["is_success"]),
                bool(info["crashed"]),
                bool(info["offroad"]),
                bool(info["wrong_exit"]),
                bool(info["timeout"]),
                steps,
                total,
            )


def evaluate(
    env: gym.Env,
    policy: Policy,
    tasks: Iterable[str],
    episodes_per_task: int,
    seed: int,
    progress: bool = True,
) -> list[EpisodeResult]:
    """Episodes ``seed .. seed + episodes_per_task - 1`` of every task: the same traffic flows per task."""
    tasks = list(tasks)
    results = []
    with new_bar(total=len(tasks) * episodes_per_task, enabled=progress, desc="episodes") as bar:
        for task in tasks:
            for k in range(episodes_per_task):
                results.append(run_episode(env, policy, task, seed + k))
                bar.update()
    return results


def summarize(results: list[EpisodeResult]) -> dict[str, dict[str, float]]:
    """Rates [%] of success, collision, off-road, wrong exit and timeout per task and overall.

    'overall' is the mean over tasks, as in the paper's tables.
    """
    tasks = sorted({r.task for r in results}, key=TASKS.index)
    table: dict[str, dict[str, float]] = {}
    keys = ("success", "crashed", "offroad", "wrong_exit", "timeout")
    for task in tasks:
        rows = [asdict(r) for r in results if r.task == task]
        table[task] = {k: 100.0 * float(np.mean([row[k] for row in rows])) for k in keys}
        table[task]["episodes"] = float(len(rows))
    table["overall"] = {k: float(np.mean([table[t][k] for t in tasks])) for k in keys}
    table["overall"]["episodes"] = float(sum(table[t]["episodes"] for t in tasks))
    return table


def format_table(table: dict[str, dict[str, float]]) -> str:
    """The summary as a Markdown table in the paper's layout, plus off-road, wrong exit and timeout."""
    lines = [
        "| task | episodes | success % | collision % | off-road % | wrong exit % | timeout % |",
        "|---|---|---|---|---|---|---|",
    ]
    for task, row in table.items():
        lines.append(
            f"| {task} | {row['episodes']:.0f} | {row['success']:.1f} | {row['crashed']:.1f} | "
            f"{row['offroad']:.1f} | {row['wrong_exit']:.1f} | {row['timeout']:.1f} |"
        )
    return "\n".join(lines)
