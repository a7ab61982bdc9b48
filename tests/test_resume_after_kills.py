"""Fault injection: a decider run killed with SIGKILL ten times at random moments (inside checkpoint
writes, while training, while a resume starts) and resumed each time ends as the uninterrupted run does."""

from __future__ import annotations

import csv
import json
import os
import random
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
import torch as th
import yaml
from helpers import TINY_ENCODER

from sb3_gccp.training.checkpoints import MARKER_FILE, PAUSE_VARIABLE

N_EPISODES = 100
STEPS_PER_EPISODE = 2
"""Without traffic every 2 s episode times out after its 2 decisions."""
K_P = 2
KILLS = 10
PAUSE = 0.2
"""Seconds after each file of a checkpoint (5 files): a write lasts a second or more."""

CONFIG = {
    "GCCPDecider-v0": {
        "n_timesteps": 100_000,
        "n_envs": 1,
        "policy": "DecisionMakerPolicy",
        "n_steps": 4,
        "batch_size": 4,
        "n_epochs": 1,
        "policy_kwargs": {"encoder": TINY_ENCODER, "net_arch": {"pi": [8, 8], "vf": [8, 8]}},
        "env_kwargs": {"duration": 2.0, "spawn_probability": 0.0},
        "gccp": {
            "n_episodes": N_EPISODES,
            "mask_after_episodes": 4,
            "save_every_episodes": 4,
            "predictor_steps_per_episode": K_P,
            "predictor_batch_size": 8,
            "predictor_kwargs": {"encoder": TINY_ENCODER, "decoder_hidden": 8},
        },
    }
}
"""Episodes of a fixed length, two per rollout: the uninterrupted run's PPO updates are then a fixed
number that a resumed run must match exactly."""


def launch(cwd: Path, log: Path, *args: str, pause: bool = True) -> subprocess.Popen[bytes]:
    env = dict(os.environ, **({PAUSE_VARIABLE: str(PAUSE)} if pause else {}))
    command = [sys.executable, "-m", "sb3_gccp.cli", "train", "--stage", "decider", "--log-folder", "runs"]
    with log.open("wb") as out, log.with_suffix(".err").open("wb") as err:
        return subprocess.Popen(
            [*command, "--no-progress", "--torch-threads", "1", *args],
            cwd=cwd,
            stdout=out,
            stderr=err,
            env=env,
            start_new_session=True,
        )


def kill(process: subprocess.Popen[bytes]) -> None:
    assert process.poll() is None, "the run ended before it was killed"
    os.killpg(process.pid, signal.SIGKILL)
    process.wait(timeout=30)


def incomplete_writes(cwd: Path) -> set[Path]:
    """Checkpoint folders being written: no marker, and newer than every complete one (not pruned ones)."""
    folders = list(cwd.glob("runs/decider/*/checkpoints/*_steps"))
    steps = {f: int(f.name.split("_")[-2]) for f in folders}
    done = [steps[f] for f in folders if (f / MARKER_FILE).exists()]
    return {f for f in folders if not (f / MARKER_FILE).exists() and steps[f] > max(done, default=-1)}


def wait_inside_write(process: subprocess.Popen[bytes], cwd: Path, writes: int) -> None:
    """Return while the run is inside the ``writes``-th checkpoint write it started."""
    stale = incomplete_writes(cwd)  # left by the previous kill, deleted when the resume starts
    seen: set[Path] = set()
    while len(seen) < writes:
        assert process.poll() is None, "the run ended before it was killed"
        stale = {f for f in stale if f.exists()}
        seen |= incomplete_writes(cwd) - stale
        time.sleep(0.01)


def wait_for_episodes(process: subprocess.Popen[bytes], cwd: Path, launched: float, episodes: int) -> None:
    """Return once the run logged ``episodes`` episodes since it was launched (Monitor rows are timed)."""
    while True:
        assert process.poll() is None, "the run ended before it was killed"
        for path in cwd.glob("runs/decider/*/monitor/0.monitor.csv"):
            header, *rows = path.read_text().split("\n")[:-1]  # whole lines only
            t_start = json.loads(header[1:])["t_start"]
            if sum(t_start + float(row.split(",")[2]) > launched for row in rows[1:]) >= episodes:
                return
        time.sleep(0.01)


def wait_for_output(process: subprocess.Popen[bytes], log: Path) -> None:
    while not log.read_text().strip():
        assert process.poll() is None, "the run ended before it was killed"
        time.sleep(0.01)


def read_rows(path: Path, skip: int = 0) -> list[dict[str, str]]:
    with path.open() as file:
        for _ in range(skip):
            file.readline()
        return list(csv.DictReader(file))


def finished_run(cwd: Path) -> tuple[Path, int, int]:
    """The run folder, the predictor's gradient steps and PPO's updates at the end."""
    (run,) = (cwd / "runs" / "decider").iterdir()
    newest = max(run.glob(f"checkpoints/*/{MARKER_FILE}"), key=lambda p: int(p.parent.name.split("_")[-2]))
    state = th.load(newest.parent / "gccp_state.pt", weights_only=True)
    with zipfile.ZipFile(run / "decider.zip") as model:
        updates = json.loads(model.read("data"))["_n_updates"]
    return run, int(state["gradient_steps"]), int(updates)


@pytest.mark.slow
def test_a_decider_run_killed_ten_times_ends_as_the_uninterrupted_run(tmp_path):
    config = tmp_path / "tiny.yml"
    config.write_text(yaml.safe_dump(CONFIG))
    new_run = ("--planner", "scripted", "--config", str(config), "--seed", "0")
    reference = tmp_path / "reference"
    reference.mkdir()
    assert launch(reference, tmp_path / "reference.log", *new_run, pause=False).wait(timeout=600) == 0

    interrupted = tmp_path / "interrupted"
    interrupted.mkdir()
    rng = random.Random(0)
    logs = [tmp_path / f"attempt{k}.log" for k in range(KILLS + 1)]
    kinds = [("write", "training", "start")[k % 3] for k in range(KILLS)]
    for k, kind in enumerate(kinds):
        launched = time.time()
        process = launch(interrupted, logs[k], *(new_run if k == 0 else ("--resume",)))
        if kind == "write":  # inside the first or second checkpoint write, after one file or more
            wait_inside_write(process, interrupted, writes=rng.choice([1, 2]))
            time.sleep(rng.uniform(0, 4 * PAUSE))
        elif kind == "training":  # between or inside the steps of an episode
            wait_for_episodes(process, interrupted, launched, episodes=rng.randint(1, 6))
            time.sleep(rng.uniform(0, 0.3))
        else:  # while the resume rewinds the run folder, loads the checkpoint, builds the envs
            wait_for_output(process, logs[k])
            time.sleep(rng.uniform(0, 2.0))
        kill(process)
    final = launch(interrupted, logs[KILLS], "--resume", pause=False)
    assert final.wait(timeout=600) == 0, logs[KILLS].with_suffix(".err").read_text()

    resumes = [log.read_text().splitlines()[0] for log in logs[1:]]
    assert all(line.startswith("resuming runs/decider/") for line in resumes), resumes
    # A kill inside a write leaves a checkpoint without its marker, which the next resume passes over.
    assert sum("passed over" in line for line in resumes) >= kinds.count("write"), resumes

    run, gradient_steps, updates = finished_run(interrupted)
    reference_run, reference_gradient_steps, reference_updates = finished_run(reference)
    episodes = read_rows(run / "episodes.csv")
    assert [int(row["episode"]) for row in episodes] == list(range(1, N_EPISODES + 1))
    assert [row["timesteps"] for row in episodes] == [
        row["timesteps"] for row in read_rows(reference_run / "episodes.csv")
    ]
    monitor = read_rows(run / "monitor" / "0.monitor.csv", skip=1)
    assert len(monitor) == N_EPISODES and {row["l"] for row in monitor} == {str(STEPS_PER_EPISODE)}
    times = [float(row["t"]) for row in monitor]
    assert times == sorted(times)  # appended, timed from the run's start
    assert gradient_steps == reference_gradient_steps == K_P * N_EPISODES
    assert updates == reference_updates
    assert [(p / MARKER_FILE).is_file() for p in (run / "checkpoints").iterdir()] == [True, True]
