"""``sb3_gccp export``: a trained run as a small folder that evaluates on its own (as in ``pretrained/``).

A hierarchy run (``hierarchy.yml``) gives its decider, planner (unless scripted) and predictor weights
with a ``hierarchy.yml`` naming the copies; a baseline run (``baseline.yml``) its model and config.
SB3 ``.zip`` files lose their optimisers' moment estimates on the way (Adam's ``exp_avg`` and
``exp_avg_sq`` are two thirds of a decider ``.zip``): they load and predict exactly as before, and
training resumed from an exported model restarts those estimates (a run's ``checkpoints/`` keep them).
The run's records come along when present: command, config, episodes, evaluation, training curve.
World config keys and GCCP check settings can be replaced on the way (``--set``, ``--mask``), so that the
exported hierarchy runs, for example, another GCCP check than it was trained with; ``hierarchy.yml`` then
lists them under ``overrides`` (settings the decider was not trained with), and evaluating it needs
``--allow-overrides``.
"""

from __future__ import annotations

import dataclasses
import io
import shutil
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch as th
import yaml

from sb3_gccp.constants import (
    ARGS_FILE,
    BASELINE_FILE,
    COMMAND_FILE,
    CONFIG_FILE,
    DECIDER_FILE,
    EPISODES_FILE,
    EVALUATION_FILE,
    HIERARCHY_FILE,
    METRICS_FILE,
    MODEL_FILE,
    PLANNER_FILE,
    PREDICTOR_FILE,
    SCRIPTED,
    TRAINING_CURVE_FILE,
    TRAINING_FILE,
)
from sb3_gccp.hierarchy import Hierarchy
from sb3_gccp.training.baselines import read_baseline_spec

RECORDS = (
    COMMAND_FILE,
    ARGS_FILE,
    CONFIG_FILE,
    EPISODES_FILE,
    METRICS_FILE,
    TRAINING_FILE,
    EVALUATION_FILE,
    TRAINING_CURVE_FILE,
)
"""Files of a run folder copied along when present."""


def strip_optimizer_state(source: str | Path, target: str | Path) -> None:
    """Copy an SB3 ``.zip`` without the per-parameter state of its optimisers (their settings stay).

    :param source: the saved model
    :param target: where the smaller copy goes
    """
    with zipfile.ZipFile(source) as zin, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            data = zin.read(item)
            if item.filename.endswith("optimizer.pth"):
                state = th.load(io.BytesIO(data), map_location="cpu", weights_only=True)
                buffer = io.BytesIO()
                th.save({"state": {}, "param_groups": state["param_groups"]}, buffer)
                data = buffer.getvalue()
            zout.writestr(item, data)


def export_run(
    run_dir: str | Path,
    out_dir: str | Path,
    world: Mapping[str, Any] | None = None,
    mask: Mapping[str, Any] | None = None,
) -> list[Path]:
    """Export a hierarchy or baseline run folder into a new folder; return the files written.

    :param world: world config keys replacing those of a hierarchy's ``hierarchy.yml``
    :param mask: GCCP check settings (``mask_*`` keys) replacing those of a hierarchy's ``hierarchy.yml``
    :raises ValueError: not a run folder, ``out_dir`` exists and is not empty (nothing is overwritten), a
        bad replacement, or replacements for a baseline
    """
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    if not run_dir.is_dir():
        raise ValueError(f"not a run folder: {run_dir}")
    if out_dir.exists() and any(out_dir.iterdir()):
        raise ValueError(f"{out_dir} exists and is not empty: export into a new folder")
    if (run_dir / HIERARCHY_FILE).is_file():
        plan = _hierarchy_files(run_dir, world or {}, mask or {})
    elif (run_dir / BASELINE_FILE).is_file():
        if world or mask:
            raise ValueError("--set and --mask change hierarchy runs only, not a baseline")
        plan = _baseline_files(run_dir)
    else:
        raise ValueError(f"{run_dir} holds neither {HIERARCHY_FILE} nor {BASELINE_FILE}")
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, source in plan.items():
        target = out_dir / name
        if isinstance(source, str):
            target.write_text(source)
        elif name.endswith(".zip"):
            strip_optimizer_state(source, target)
        else:
            shutil.copyfile(source, target)
        written.append(target)
    for name in RECORDS:
        if (run_dir / name).is_file() and name not in plan:
            shutil.copyfile(run_dir / name, out_dir / name)
            written.append(out_dir / name)
    return written


def _baseline_files(run_dir: Path) -> dict[str, Path | str]:
    """Target name -> source file (or text) of a baseline's export, with the rewritten baseline.yml."""
    name, model = read_baseline_spec(run_dir)
    return {MODEL_FILE: model, BASELINE_FILE: yaml.safe_dump({"algorithm": name, "model": MODEL_FILE})}


def _hierarchy_files(
    run_dir: Path, world: Mapping[str, Any], mask: Mapping[str, Any]
) -> dict[str, Path | str]:
    """Target name -> source file (or text) of a hierarchy's export, with the rewritten hierarchy.yml."""
    hierarchy = Hierarchy.read(run_dir).with_overrides(world, mask)
    files: dict[str, Path | str] = {DECIDER_FILE: hierarchy.decider}
    if hierarchy.planner is not None:
        files[PLANNER_FILE] = hierarchy.planner
    if hierarchy.predictor_weights is not None:
        files[PREDICTOR_FILE] = hierarchy.predictor_weights
    exported = dataclasses.replace(
        hierarchy,
        decider_file=DECIDER_FILE,
        planner_file=SCRIPTED if hierarchy.planner is None else PLANNER_FILE,
        predictor_weights_file=None if hierarchy.predictor_weights is None else PREDICTOR_FILE,
    )
    files[HIERARCHY_FILE] = exported.to_yaml()
    return files
