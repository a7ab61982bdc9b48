"""The reproduction's tables (Markdown, as the paper's) and CSV, and the figures beside them."""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gccp_envs.config import TASKS, IntersectionConfig
from sb3_gccp.reproduce.figures import (
    plot_predictions,
    plot_predictor_errors,
    plot_success_curves,
    success_history,
)
from sb3_gccp.reproduce.methods import METHODS, PAPER_RESULTS, TABLE_1, TABLE_2
from sb3_gccp.reproduce.plan import Plan, mask_after_episodes

RATES = ("success", "crashed", "offroad", "wrong_exit", "timeout")


def aggregate(tables: Sequence[Mapping[str, Mapping[str, float]]]) -> dict[str, dict[str, dict[str, float]]]:
    """Mean, sample standard deviation, min and max over seeds of every rate of
    :func:`~sb3_gccp.evaluation.summarize` tables (std 0 with one seed)."""
    result: dict[str, dict[str, dict[str, float]]] = {}
    for task in tables[0]:
        result[task] = {}
        for rate in RATES:
            values = np.array([t[task][rate] for t in tables])
            std = float(values.std(ddof=1)) if len(values) > 1 else 0.0
            result[task][rate] = {
                "mean": float(values.mean()),
                "std": std,
                "min": float(values.min()),
                "max": float(values.max()),
            }
    return result


def _spread(values: Sequence[float]) -> str:
    if len(values) == 1:
        return f"{values[0]:.1f}"
    return f"{np.mean(values):.1f} ({min(values):.1f}-{max(values):.1f})"


def format_results_table(rows: Sequence[tuple[str, Sequence[Mapping[str, Mapping[str, float]]]]]) -> str:
    """The paper's table: per method (a label and its summary table per training seed), success /
    collision [%] per task and overall, and the overall timeout share; over several seeds the mean and, in
    brackets, the lowest and highest seed's."""
    lines = [
        "| method | left S/C | straight S/C | right S/C | overall S/C | timeout % |",
        "|---|---|---|---|---|---|",
    ]
    for label, tables in rows:
        cells = [
            " / ".join(_spread([t[task][rate] for t in tables]) for rate in ("success", "crashed"))
            for task in (*TASKS, "overall")
        ]
        cells.append(_spread([t["overall"]["timeout"] for t in tables]))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_paper_table(names: Sequence[str]) -> str:
    """The paper's own figures for these methods (those it has), in the same layout; the paper's baselines
    had no action masks, but they stand beside ours as the paper printed them."""
    lines = [
        "| method | left S/C | straight S/C | right S/C | overall S/C |",
        "|---|---|---|---|---|",
    ]
    for name in (n for n in names if n in PAPER_RESULTS):
        cells = [f"{s:g} / {c:g}" for s, c in PAPER_RESULTS[name]]
        lines.append(f"| {METHODS[name].label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


TABLE_TITLES = {
    "table1": ("Table I: the baselines and ours", TABLE_1),
    "table2": ("Table II: ablations of GCCP", TABLE_2),
}


def write_outputs(
    plan: Plan,
    runs: Mapping[str, Mapping[int, Mapping[str, Any]]],
    errors: Mapping[int, Mapping[str, Any]],
) -> None:
    """Tables, CSV and figures into ``<out>`` (results.json is written by the caller)."""
    out = plan.request.out
    for stem, (title, names) in TABLE_TITLES.items():
        present = [n for n in names if n in runs]
        if present:
            (out / f"{stem}.md").write_text(_table_document(plan, title, present, runs))
            print(f"wrote {out / f'{stem}.md'}", flush=True)
    _write_csv(runs, out / "results.csv")
    curves = {
        name: [success_history(Path(r["run_dir"])) for r in seed_runs.values()]
        for name, seed_runs in runs.items()
    }
    for stem, names, title in (
        ("fig5_baselines", TABLE_1, "Ours vs the baselines"),
        ("fig6_ablations", TABLE_2, "Ours vs the ablations"),
    ):
        present = [n for n in names if n in curves]
        if present:
            # Every hierarchy variant with a predictor switches its masks on at N_m.
            hierarchy = any(METHODS[n].predictor not in (None, "none") for n in present)
            plot_success_curves(
                {n: curves[n] for n in present},
                out / f"{stem}.png",
                title,
                mask_after_episodes(plan.preset) if hierarchy else None,
            )
    if errors:
        plot_predictor_errors([e["errors"] for e in errors.values()], out / "fig7_predictor_errors.png")
        ours = plan.root / f"seed{plan.request.seeds[0]}" / "ours"
        plot_predictions(ours, plan.request.eval_seed, out / "fig8_predictions.png")
    print(f"wrote {out / 'results.csv'} and the figures", flush=True)


def _table_document(
    plan: Plan, title: str, names: Sequence[str], runs: Mapping[str, Mapping[int, Mapping[str, Any]]]
) -> str:
    request, preset = plan.request, plan.preset
    seeds = ", ".join(map(str, request.seeds))
    several = len(request.seeds) > 1
    spread = " (the mean over the training seeds, their min-max in brackets)" if several else ""
    rows = [(METHODS[n].label, [r["table"] for r in runs[n].values()]) for n in names]
    world = IntersectionConfig.from_dict(dict(preset.world))
    return "\n".join(
        [
            f"# {title}",
            "",
            f"Preset `{request.preset}`: every method trained for {preset.episodes:,} episodes (training "
            f"seeds {seeds}), evaluated on {preset.episodes_per_task} seeded traffic flow(s) per task from "
            f"seed {request.eval_seed}. Cells: success / collision rate [%]{spread}; timeout: episodes that "
            f"reached the {world.duration:g} s limit [%], overall. The rest of each row are off-road and "
            "wrong-exit episodes (results.csv).",
            "",
            format_results_table(rows),
            "",
            "The paper's figures (SMARTS, 50 flows per task):",
            "",
            format_paper_table(names),
            "",
        ]
    )


def _write_csv(runs: Mapping[str, Mapping[int, Mapping[str, Any]]], path: Path) -> None:
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["method", "label", "seed", "task", "episodes", *RATES])
        for name, seed_runs in runs.items():
            for seed, run in seed_runs.items():
                for task, row in run["table"].items():
                    rates = [f"{row[r]:.2f}" for r in RATES]
                    writer.writerow([name, METHODS[name].label, seed, task, int(row["episodes"]), *rates])
