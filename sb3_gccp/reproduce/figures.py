"""The paper's Figs. 5-8 from a reproduction's runs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from gccp_envs.config import TASKS, IntersectionConfig
from sb3_gccp.constants import EPISODES_FILE
from sb3_gccp.gccp.predictor import load_predictor
from sb3_gccp.hierarchy import load_hierarchy
from sb3_gccp.reproduce.methods import METHODS
from sb3_gccp.training.episodes import read_episodes, rolling_rate
from sb3_gccp.training.predictor import plot_scene

CURVE_COLORS = {
    "ours": "black",
    "with_cv": "tab:purple",
    "without_gccp": "tab:brown",
    "without_goal": "tab:pink",
    "dqn": "tab:blue",
    "ppo": "tab:orange",
    "sac_discrete": "tab:green",
}
"""One colour per method in Figs. 5 and 6 (ours the same in both); a baseline's paper-style row has its
algorithm's colour, dashed."""
CURVE_WINDOW = 100
"""Episodes of the rolling success rate in Figs. 5 and 6 (fewer at the start)."""


def success_history(run_dir: Path) -> list[int]:
    return [row["success"] for row in read_episodes(run_dir / EPISODES_FILE)]


def plot_success_curves(
    curves: Mapping[str, Sequence[Sequence[int]]], path: Path, title: str, mask_after: int | None
) -> None:
    """Figs. 5 and 6: the rolling success rate per training episode of each method (mean over seeds,
    the band from the lowest to the highest seed).

    :param curves: per method name, the per-episode success (0/1) of each training seed
    :param mask_after: where the GCCP masks came on (a dashed line), if any
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 4))
    for name, runs in curves.items():
        rates = [rolling_rate(list(run), CURVE_WINDOW) for run in runs if len(run)]
        if not rates:
            continue
        length = min(len(r) for r in rates)
        stack = np.stack([r[:length] for r in rates])
        episodes = np.arange(1, length + 1)
        method = METHODS[name]
        color = CURVE_COLORS[name if method.is_hierarchy else method.algorithm]
        ax.plot(
            episodes,
            stack.mean(0),
            color=color,
            label=method.label,
            lw=2 if name == "ours" else 1.2,
            ls="--" if method.paper_style else "-",
        )
        if len(rates) > 1:
            ax.fill_between(episodes, stack.min(0), stack.max(0), color=color, alpha=0.2)
    if mask_after is not None:
        ax.axvline(mask_after, color="black", lw=0.8, ls="--", label="GCCP masks on")
    ax.set_xlabel("training episode")
    ax.set_ylabel(f"success rate (last {CURVE_WINDOW} episodes)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


PREDICTOR_LABELS = {
    "learned": "goal-conditioned (ours)",
    "no_goal": "w/o goal condition",
    "cv": "constant velocity",
}


def plot_predictor_errors(per_seed: Sequence[Mapping[str, Mapping[str, float]]], path: Path) -> None:
    """Fig. 7: ADE and FDE at 1 s of each predictor over all vehicles, the ego and the neighbours
    (bars: mean over seeds; whiskers: std when there are several)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in PREDICTOR_LABELS if n in per_seed[0]]
    groups = (("", "all vehicles"), ("ego_", "ego"), ("neighbour_", "neighbours"))
    width = 0.8 / len(names)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, metric in zip(axes, ("ade", "fde"), strict=True):
        for i, name in enumerate(names):
            values = np.array([[seed[name][f"{g}{metric}"] for g, _ in groups] for seed in per_seed])
            std = np.nanstd(values, 0, ddof=1) if len(values) > 1 else None
            x = np.arange(len(groups)) + (i - (len(names) - 1) / 2) * width
            ax.bar(x, np.nanmean(values, 0), width, yerr=std, capsize=3, label=PREDICTOR_LABELS[name])
        ax.set_xticks(np.arange(len(groups)), [label for _, label in groups])
        ax.set_ylabel(f"{metric.upper()} at 1 s [m]")
        ax.grid(alpha=0.3, axis="y")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(names), fontsize=8)
    fig.suptitle("Trajectory prediction on held-out decisions of ours")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_predictions(run_dir: Path, seed: int, path: Path) -> None:
    """Fig. 8: a hierarchy's predictor in one scene per task, two subgoals each.

    :param run_dir: the hierarchy (ours, of the first training seed)
    :param seed: the first traffic seed searched for the scenes
    """
    hierarchy = load_hierarchy(run_dir)
    assert hierarchy.predictor_weights is not None
    world = IntersectionConfig.from_dict(dict(hierarchy.world))
    predictor = load_predictor(hierarchy.predictor_weights)
    decider = hierarchy.decider_policy(world)
    plot_scene(predictor, world, seed, path, hierarchy.planner, tasks=TASKS, decider=decider)
