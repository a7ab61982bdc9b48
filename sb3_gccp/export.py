"""``sb3_gccp export``: a trained run as a small folder that evaluates on its own (as in ``pretrained/``).

A hierarchy run (``hierarchy.yml``) gives its decider, planner (unless scripted) and predictor weights
with a ``hierarchy.yml`` naming the copies; a baseline run (``baseline.yml``) its model and config.
SB3 ``.zip`` files lose their optimisers' moment estimates on the way (Adam's ``exp_avg`` and
``exp_avg_sq`` are two thirds of a decider ``.zip``): they load and predict exactly as before, and
training resumed from an exported model restarts those estimates (a run's ``checkpoints/`` keep them).
They also lose the training machine's TensorBoard folder, where SB3's ``learn()`` on a loaded model would
otherwise write (or fail, without tensorboard).
The run's records come along when present: command, config, episodes, evaluation, training curve, the
choice of the run's model on validation flows.
World config keys and GCCP check settings can be replaced on the way (``--set``, ``--mask``), so that the
exported hierarchy runs, for example, another GCCP check than it was trained with; ``hierarchy.yml`` then
lists them under ``overrides`` (settings the decider was not trained with), and evaluating it needs
``--allow-overrides``.

Every model is loaded first as ``evaluate`` would load it (without unpickling, its spaces checked
against the world): a file that would not run is refused before anything is written. The folder is
written under a temporary name beside ``out_dir`` and renamed at the end, so that a failure leaves
nothing behind and a retry starts afresh.
"""

from __future__ import annotations

import dataclasses
import io
import json
import shutil
import uuid
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch as th

from sb3_gccp.constants import (
    ARGS_FILE,
    BASELINE_FILE,
    CHOICE_FILE,
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
from sb3_gccp.safe_loading import first_line
from sb3_gccp.training.baselines import baseline_spec, load_baseline, read_baseline_spec

RECORDS = (
    COMMAND_FILE,
    ARGS_FILE,
    CONFIG_FILE,
    EPISODES_FILE,
    METRICS_FILE,
    TRAINING_FILE,
    EVALUATION_FILE,
    TRAINING_CURVE_FILE,
    CHOICE_FILE,
)
"""Files of a run folder copied along when present."""


def portable_copy(source: str | Path, target: str | Path) -> None:
    """Copy an SB3 ``.zip`` for use on another machine: without the per-parameter state of its optimisers
    (their settings stay) and without its TensorBoard folder.

    :param source: the saved model
    :param target: where the smaller copy goes
    :raises ValueError: one line, when ``source`` is damaged
    """
    try:
        with zipfile.ZipFile(source) as zin, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as zout:
            for item in zin.infolist():
                data = zin.read(item)
                if item.filename.endswith("optimizer.pth"):
                    state = th.load(io.BytesIO(data), map_location="cpu", weights_only=True)
                    buffer = io.BytesIO()
                    th.save({"state": {}, "param_groups": state["param_groups"]}, buffer)
                    data = buffer.getvalue()
                elif item.filename == "data":
                    data = _without_tensorboard_log(data)
                zout.writestr(item, data)
    except OSError:
        raise
    except Exception as err:  # a damaged file: zipfile, zlib, torch and its unpickler raise many kinds
        raise ValueError(f"{source} is damaged: {first_line(err)}") from err


def _without_tensorboard_log(data: bytes) -> bytes:
    """SB3's ``data`` entry with ``tensorboard_log`` set to null, every other byte as it was."""
    folder = json.loads(data).get("tensorboard_log")
    if folder is None:
        return data
    pair = f'"tensorboard_log": {json.dumps(folder)}'.encode()
    if data.count(pair) != 1:
        raise ValueError("its data entry names its TensorBoard folder in an unexpected form")
    return data.replace(pair, b'"tensorboard_log": null')


def export_run(
    run_dir: str | Path,
    out_dir: str | Path,
    world: Mapping[str, Any] | None = None,
    mask: Mapping[str, Any] | None = None,
    trusted: bool = False,
) -> list[Path]:
    """Export a hierarchy or baseline run folder into a new folder; return the files written.

    :param world: world config keys replacing those of a hierarchy's ``hierarchy.yml``
    :param mask: GCCP check settings (``mask_*`` keys) replacing those of a hierarchy's ``hierarchy.yml``
    :param trusted: check the models by loading them through SB3's ``load`` (which runs code pickled in
        them); the copies are made byte for byte either way
    :raises ValueError: not a run folder, ``out_dir`` exists and is not empty (nothing is overwritten), a
        bad replacement, replacements for a baseline, or a model that would not run
    """
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    if not run_dir.is_dir():
        raise ValueError(f"not a run folder: {run_dir}")
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise ValueError(f"{out_dir} exists and is not an empty folder: export into a new folder")
    if (run_dir / HIERARCHY_FILE).is_file():
        plan = _hierarchy_files(run_dir, world or {}, mask or {}, trusted)
    elif (run_dir / BASELINE_FILE).is_file():
        if world or mask:
            raise ValueError("--set and --mask change hierarchy runs only, not a baseline")
        plan = _baseline_files(run_dir, trusted)
    else:
        raise ValueError(f"{run_dir} holds neither {HIERARCHY_FILE} nor {BASELINE_FILE}")
    plan.update({name: run_dir / name for name in RECORDS if (run_dir / name).is_file() and name not in plan})
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = out_dir.parent / f".{out_dir.name}.{uuid.uuid4().hex[:8]}.partial"
    staging.mkdir()
    try:
        for name, source in plan.items():
            _write(staging / name, name, source)
        staging.replace(out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return [out_dir / name for name in plan]


def _write(target: Path, name: str, source: Path | str) -> None:
    """One file of an export: text as given, an SB3 ``.zip`` without its optimisers' state, else a copy."""
    if isinstance(source, str):
        target.write_text(source)
    elif name.endswith(".zip"):
        portable_copy(source, target)
    else:
        shutil.copyfile(source, target)


def _baseline_files(run_dir: Path, trusted: bool) -> dict[str, Path | str]:
    """Target name -> source file (or text) of a baseline's export, with the rewritten baseline.yml; the
    model loaded first as ``evaluate`` would."""
    name, masked, model = read_baseline_spec(run_dir)
    load_baseline(run_dir, trusted=trusted)
    return {MODEL_FILE: model, BASELINE_FILE: baseline_spec(name, masked)}


def _hierarchy_files(
    run_dir: Path, world: Mapping[str, Any], mask: Mapping[str, Any], trusted: bool
) -> dict[str, Path | str]:
    """Target name -> source file (or text) of a hierarchy's export, with the rewritten hierarchy.yml;
    the models loaded first on the exported world as ``evaluate`` would."""
    hierarchy = Hierarchy.read(run_dir).with_overrides(world, mask)
    hierarchy.decider_policy(hierarchy.make_env(trusted=trusted).config, trusted=trusted)
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
