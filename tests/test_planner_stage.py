"""The planner training stage through the CLI: run folder, resume, bad input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from helpers import TINY_PLANNER_HYPERPARAMS, run_cli

TINY = TINY_PLANNER_HYPERPARAMS


@pytest.fixture
def tiny_config(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yml"
    path.write_text(yaml.safe_dump(TINY))
    return path


def test_train_planner_writes_a_complete_run_folder_and_resumes(tmp_path, tiny_config, cli):
    result = run_cli(
        "train",
        "--stage",
        "planner",
        "--config",
        str(tiny_config),
        "--log-folder",
        "runs",
        "--save-freq",
        "16",
        "--seed",
        "3",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "planner").iterdir()
    assert run.name.startswith("GCCPPlanner-v0_3_")
    for name in ("planner.zip", "config.yml", "args.yml", "command.txt"):
        assert (run / name).is_file(), name
    assert yaml.safe_load((run / "config.yml").read_text()) == TINY["GCCPPlanner-v0"]
    assert "--seed 3" in (run / "command.txt").read_text()
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["planner_16_steps", "planner_32_steps"]
    assert sorted(p.name for p in (run / "checkpoints" / "planner_16_steps").iterdir()) == [
        "complete.json",
        "planner.zip",
    ]
    assert yaml.safe_load((run / "args.yml").read_text())["save_freq"] == 16
    assert list((run / "monitor").glob("*.monitor.csv"))
    assert list((run / "tb").rglob("events.out.tfevents.*"))

    # The newest checkpoint damaged: resume continues from the one before, with the recorded
    # --save-freq and a new verbosity, and trains the rest of the budget.
    model = run / "checkpoints" / "planner_32_steps" / "planner.zip"
    model.write_bytes(model.read_bytes()[:1000])
    (run / "planner.zip").unlink()
    result = run_cli(
        "train", "--stage", "planner", "--log-folder", "runs", "--resume", "-v", "1", cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[0] == (
        f"resuming {Path('runs') / 'planner' / run.name} from checkpoints/planner_16_steps (16 steps, "
        "0 episodes); passed over checkpoints/planner_32_steps: planner.zip does not match its checksum"
    )
    assert "total_timesteps" in result.stdout  # -v 1: SB3's training table
    assert yaml.safe_load((run / "args.yml").read_text())["verbose"] == 1
    assert (run / "command.txt").read_text().splitlines()[1].endswith("--resume -v 1")
    assert (run / "checkpoints" / "planner_32_steps" / "complete.json").is_file()
    monitor = {p.name: p.read_bytes() for p in (run / "monitor").iterdir()}
    assert all(data.count(b"t_start") == 1 for data in monitor.values())  # appended to, one header

    # A resume that fails (a planner run is no decider run) leaves the run as it was.
    result = cli("train", "--stage", "decider", "--resume", str(run), cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "sb3_gccp: error: checkpoints/planner_32_steps holds no predictor.pt: not a checkpoint of this stage"
    ]
    assert {p.name: p.read_bytes() for p in (run / "monitor").iterdir()} == monitor
    assert len((run / "command.txt").read_text().splitlines()) == 2
    check = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sb3_gccp; from sb3_contrib import MaskablePPO; "
            f"print(MaskablePPO.load({str(run / 'planner.zip')!r}).num_timesteps)",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert check.stdout.strip() == "32", check.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--config", "missing.yml"], "hyperparameter file not found: missing.yml"),
        (["--config", "bad.yml"], "unknown hyperparameter(s): 'n_step' (did you mean 'n_steps'?)"),
        (
            ["--config", "badworld.yml"],
            "unknown intersection config key(s): 'spawn_prob' (did you mean 'spawn_probability'?)",
        ),
        (["--resume"], "nothing to resume in runs/planner"),
        (["-n", "0"], "-n/--n-timesteps must be positive"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, cli_error, args, message):
    (tmp_path / "bad.yml").write_text("GCCPPlanner-v0:\n  n_step: 8\n")
    (tmp_path / "badworld.yml").write_text("GCCPPlanner-v0:\n  env_kwargs: {spawn_prob: 0.1}\n")
    lines = cli_error(tmp_path, "train", "--stage", "planner", "--log-folder", "runs", *args)
    assert lines == [f"sb3_gccp: error: {message}"]
    assert not (tmp_path / "runs" / "planner").exists() or not any((tmp_path / "runs" / "planner").iterdir())
