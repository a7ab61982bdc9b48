"""Checkpoints of a training run, written so that a kill at any moment leaves one to resume from.

In a run folder::

    checkpoints/
        <stage>_<steps>_steps/      one checkpoint, taken between two PPO updates
            <the stage's files>     planner.zip; or decider.zip, predictor.pt, buffer.npz,
                                    gccp_state.pt, episodes.csv
            complete.json           written last: the step count, every file's size and SHA-256, and
                                    the length of every Monitor file of ``monitor/`` at that moment

Every file goes to a temporary name in its folder and is renamed over its own (``os.replace``), so a
file is whole or absent. A checkpoint without ``complete.json``, or whose files do not match it, is
damaged: a resume takes the newest undamaged one, deletes the damaged ones above it and cuts the
Monitor files back to the lengths it recorded (the episodes after it are played again). The two newest
complete checkpoints are kept.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback

CHECKPOINTS_DIR = "checkpoints"
"""The checkpoints' folder in a run folder."""
MARKER_FILE = "complete.json"
"""Written last into a checkpoint folder: what the checkpoint holds."""
MONITOR_DIR = "monitor"
"""The Monitor CSVs' folder in a run folder (one ``<worker>.monitor.csv`` per env worker)."""
KEPT = 2
"""Complete checkpoints kept: the newest and the one before, for when the newest is damaged."""
PAUSE_VARIABLE = "SB3_GCCP_CHECKPOINT_PAUSE"
"""Seconds to wait after each file of a checkpoint: lets a fault-injection test kill a run inside a write."""

Writer = Callable[[Path], object]
"""Writes one file of a checkpoint to the path it is given."""


def write_atomically(path: Path, write: Writer) -> None:
    """Write ``path`` through ``write`` on a temporary name beside it, flush it to disk, rename it into place.

    The temporary name keeps the suffix (``decider.tmp.zip``): SB3 and numpy add theirs otherwise.
    """
    temporary = path.with_name(f"{path.stem}.tmp{path.suffix}")
    try:
        write(temporary)
        with temporary.open("rb+") as file:
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        # A failed write (or rename, or Ctrl-C) leaves the old file as it was and no half-written one.
        temporary.unlink(missing_ok=True)
        raise
    _sync_folder(path.parent)


def _sync_folder(folder: Path) -> None:
    # The rename is on disk only once the folder's entry is.
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


@dataclass(frozen=True)
class Checkpoint:
    """A complete checkpoint of a run (its folder's ``complete.json``)."""

    folder: Path
    steps: int
    """Environment steps over all workers (the model's ``num_timesteps``)."""
    episodes: int
    """Episodes the Monitor files held, over all workers."""
    files: Mapping[str, Mapping[str, int | str]]
    """File name -> its ``bytes`` and ``sha256``."""
    monitor: Mapping[str, int]
    """Monitor file name -> its length in bytes."""

    @property
    def name(self) -> str:
        """``checkpoints/<folder>``, as messages name it."""
        return f"{CHECKPOINTS_DIR}/{self.folder.name}"

    def file(self, name: str) -> Path:
        """The path of one of the checkpoint's files.

        :raises ValueError: the checkpoint holds no such file (the run is of another stage)
        """
        if name not in self.files:
            raise ValueError(f"{self.name} holds no {name}: not a checkpoint of this stage")
        return self.folder / name


class DamagedCheckpoint(Exception):
    """A checkpoint folder that cannot be resumed from, with the reason."""


def save_checkpoint(run_dir: Path, stage: str, steps: int, files: Mapping[str, Writer]) -> Checkpoint:
    """Write a checkpoint of ``run_dir`` at ``steps``, file by file, then its marker; keep the two newest.

    A complete checkpoint at the same step count is the same state (a resume that had nothing left to
    train): it is kept as it is.

    :param stage: names the folder (``<stage>_<steps>_steps``)
    :param files: file name -> the function writing it
    """
    folder = run_dir / CHECKPOINTS_DIR / f"{stage}_{steps}_steps"
    if (folder / MARKER_FILE).is_file():
        return read_checkpoint(folder)
    if folder.exists():  # left by a kill during its write
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    monitor = monitor_lengths(run_dir)
    pause = float(os.environ.get(PAUSE_VARIABLE, 0))
    records: dict[str, dict[str, int | str]] = {}
    for name, write in files.items():
        write_atomically(folder / name, write)
        records[name] = {"bytes": (folder / name).stat().st_size, "sha256": _digest(folder / name)}
        time.sleep(pause)
    marker = {
        "steps": steps,
        "episodes": _count_rows(run_dir / MONITOR_DIR, monitor),
        "files": records,
        "monitor": monitor,
    }
    write_atomically(folder / MARKER_FILE, lambda path: path.write_text(json.dumps(marker, indent=2) + "\n"))
    _prune(run_dir, folder)
    return read_checkpoint(folder)


def save_model_checkpoint(model: BaseAlgorithm, run_dir: Path, stage: str, model_file: str) -> Checkpoint:
    """A checkpoint holding only the model, as ``model_file``, at the model's step count."""
    return save_checkpoint(run_dir, stage, model.num_timesteps, {model_file: model.save})


class ModelCheckpointCallback(BaseCallback):
    """Checkpoints the model after every ``save_freq`` environment steps, at the start of the next rollout.

    There the last PPO update is done and no step of the next rollout is taken, so that a resume
    collects the rollouts an uninterrupted run would; list it before callbacks that act at a rollout's
    start (the cloning steps of imitation), which a resume then repeats as the run would have.

    :param run_dir: the run folder
    :param stage: names the checkpoint folders
    :param save_freq: environment steps between checkpoints, over all workers
    :param model_file: the model's file name in a checkpoint
    """

    def __init__(self, run_dir: Path, stage: str, save_freq: int, model_file: str) -> None:
        super().__init__()
        self.run_dir = run_dir
        self.stage = stage
        self.save_freq = save_freq
        self.model_file = model_file
        self._saved_at = 0

    def _on_training_start(self) -> None:
        self._saved_at = self.model.num_timesteps

    def _on_rollout_start(self) -> None:
        steps = self.model.num_timesteps
        if steps // self.save_freq > self._saved_at // self.save_freq:
            save_model_checkpoint(self.model, self.run_dir, self.stage, self.model_file)
            self._saved_at = steps

    def _on_step(self) -> bool:
        return True


def read_checkpoint(folder: Path, verify: bool = False) -> Checkpoint:
    """The checkpoint in ``folder``; with ``verify``, only if every file matches its size and SHA-256.

    :raises DamagedCheckpoint: no marker, an unreadable one, or (with ``verify``) a missing or changed file
    """
    try:
        marker = json.loads((folder / MARKER_FILE).read_text())
        checkpoint = Checkpoint(
            folder, int(marker["steps"]), int(marker["episodes"]), marker["files"], marker["monitor"]
        )
    except FileNotFoundError as err:
        raise DamagedCheckpoint(f"no {MARKER_FILE} (interrupted while written)") from err
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DamagedCheckpoint(f"unreadable {MARKER_FILE}") from err
    if verify:
        for name, record in checkpoint.files.items():
            path = folder / name
            if not path.is_file():
                raise DamagedCheckpoint(f"{name} is missing")
            if path.stat().st_size != record["bytes"] or _digest(path) != record["sha256"]:
                raise DamagedCheckpoint(f"{name} does not match its checksum")
    return checkpoint


def find_checkpoint(run_dir: Path) -> tuple[Checkpoint | None, dict[Path, str]]:
    """The newest undamaged checkpoint of a run, and the newer checkpoint folders passed over, with why.

    :raises ValueError: the run's ``checkpoints/`` holds loose model files (the layout of an older
        version, which this one cannot check)
    """
    damaged: dict[Path, str] = {}
    for folder in reversed(_checkpoint_folders(run_dir)):
        try:
            return read_checkpoint(folder, verify=True), damaged
        except DamagedCheckpoint as err:
            damaged[folder] = str(err)
    loose = sorted(p.name for p in (run_dir / CHECKPOINTS_DIR).glob("*") if p.is_file())
    if loose:
        raise ValueError(
            f"{run_dir / CHECKPOINTS_DIR} holds checkpoint files of an older sb3_gccp ({', '.join(loose)}), "
            "no checkpoint folders: resume the run with the version that wrote it"
        )
    return None, damaged


def resume_message(run_dir: Path, checkpoint: Checkpoint | None, damaged: Mapping[Path, str]) -> str:
    """One line saying where a resume of ``run_dir`` continues from, and which checkpoints it passed over."""
    if checkpoint is None:
        line = f"resuming {run_dir}: no complete checkpoint, starting over"
    else:
        line = (
            f"resuming {run_dir} from {checkpoint.name} "
            f"({checkpoint.steps:,} steps, {checkpoint.episodes:,} episodes)"
        )
    passed = "; ".join(f"{CHECKPOINTS_DIR}/{folder.name}: {why}" for folder, why in damaged.items())
    return f"{line}; passed over {passed}" if passed else line


def rewind_run(run_dir: Path, checkpoint: Checkpoint | None) -> None:
    """Bring a run folder back to ``checkpoint`` (None: to its start) before training resumes from it.

    Deletes the checkpoint folders above it (damaged, or they would be mistaken for newer work) and
    cuts every Monitor file back to its length at the checkpoint; without a checkpoint the Monitor files
    go, and new ones are written from the start.
    """
    steps = -1 if checkpoint is None else checkpoint.steps
    for folder in _checkpoint_folders(run_dir):
        if _steps_of(folder) > steps:
            _delete(folder)
    lengths = {} if checkpoint is None else checkpoint.monitor
    for path in (run_dir / MONITOR_DIR).glob("*.monitor.csv"):
        if path.name in lengths:
            os.truncate(path, min(lengths[path.name], path.stat().st_size))
        else:
            path.unlink()


def monitor_lengths(run_dir: Path) -> dict[str, int]:
    """Monitor file name -> its length in bytes, for the files of ``run_dir/monitor``."""
    return {path.name: path.stat().st_size for path in sorted((run_dir / MONITOR_DIR).glob("*.monitor.csv"))}


def monitor_start_times(run_dir: Path) -> dict[str, float]:
    """Monitor file name -> the ``t_start`` of its header (what its rows' ``t`` count from)."""
    times = {}
    for path in sorted((run_dir / MONITOR_DIR).glob("*.monitor.csv")):
        with path.open() as file:
            times[path.name] = float(json.loads(file.readline().lstrip("#"))["t_start"])
    return times


def _count_rows(folder: Path, lengths: Mapping[str, int]) -> int:
    # Each file: a JSON header line, the CSV header, then one line per finished episode.
    rows = 0
    for name, length in lengths.items():
        with (folder / name).open("rb") as file:
            rows += max(file.read(length).count(b"\n") - 2, 0)
    return rows


def _digest(path: Path) -> str:
    with path.open("rb") as file:
        return hashlib.file_digest(file, "sha256").hexdigest()


def _steps_of(folder: Path) -> int:
    return int(folder.name.rsplit("_", 2)[-2])


def _checkpoint_folders(run_dir: Path) -> list[Path]:
    """The checkpoint folders of a run, complete or not, oldest first."""
    folders = []
    for path in (run_dir / CHECKPOINTS_DIR).glob("*_steps"):
        name = path.name.rsplit("_", 2)
        if path.is_dir() and len(name) == 3 and name[1].isdigit():
            folders.append(path)
    return sorted(folders, key=_steps_of)


def _prune(run_dir: Path, newest: Path) -> None:
    """Delete every checkpoint folder but ``newest`` and the complete ones before it, ``KEPT`` in all."""
    older = [f for f in _checkpoint_folders(run_dir) if f != newest]
    complete = [f for f in older if (f / MARKER_FILE).is_file() and _steps_of(f) < _steps_of(newest)]
    kept = complete[len(complete) - (KEPT - 1) :]
    for folder in older:
        if folder not in kept:
            _delete(folder)


def _delete(folder: Path) -> None:
    # The marker first: a kill halfway leaves an incomplete checkpoint, never a complete-looking one.
    (folder / MARKER_FILE).unlink(missing_ok=True)
    shutil.rmtree(folder)
