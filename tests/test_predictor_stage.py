"""The predictor stage through the CLI: collect, train, report, plots; then train from the saved buffer."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import pytest
from helpers import run_cli
from sb3_contrib import MaskablePPO
from test_policies import TINY_POLICY

from sb3_gccp.gccp.predictor import load_predictor
from sb3_gccp.gccp.replay import EpisodeReplayBuffer
from sb3_gccp.policies import MotionPlannerPolicy


@pytest.fixture(scope="module")
def planner(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("planner") / "planner.zip"
    env = gym.make("GCCPPlanner-v0")
    MaskablePPO(MotionPlannerPolicy, env, policy_kwargs=TINY_POLICY, n_steps=16, seed=0).save(path)
    return path


def test_predictor_stage_end_to_end(tmp_path, planner):
    tiny = ("--episodes", "2", "--heldout-episodes", "1", "--gradient-steps", "4", "--eval-every", "2")
    result = run_cli(
        "train",
        "--stage",
        "predictor",
        "--planner",
        str(planner),
        *tiny,
        "--log-folder",
        "runs",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "predictor").iterdir()
    for name in ("buffer.npz", "heldout.npz", "predictor.pt", "predictor_no_goal.pt", "fig7.png", "fig8.png"):
        assert (run / name).is_file(), name
    metrics = json.loads((run / "metrics.json").read_text())
    assert set(metrics) == {"learned", "no_goal", "cv"}
    assert all(metrics[name]["ade"] >= 0 for name in metrics)
    assert "| constant velocity |" in result.stdout
    assert load_predictor(run / "predictor.pt").config.goal_condition
    assert not load_predictor(run / "predictor_no_goal.pt").config.goal_condition
    curves = (run / "curves.csv").read_text().splitlines()
    assert len(curves) == 1 + 2 * 2  # header, two evaluations per predictor
    assert len(EpisodeReplayBuffer.load(run / "buffer.npz")) > 0

    assert not load_predictor(run / "predictor.pt").config.cv_residual  # the paper's decoder by default

    # The saved buffer trains again, with a share of it held out, here with residual decoders.
    again = run_cli(
        "train",
        "--stage",
        "predictor",
        "--buffer",
        str(run / "buffer.npz"),
        "--predictor-set",
        "cv_residual=true",
        *tiny,
        "--log-folder",
        "again",
        cwd=tmp_path,
    )
    assert again.returncode == 0, again.stderr
    assert "held out" in again.stdout
    (rerun,) = (tmp_path / "again" / "predictor").iterdir()
    for name in ("predictor.pt", "predictor_no_goal.pt"):
        assert load_predictor(rerun / name).config.cv_residual


def test_predictor_stage_collects_with_the_scripted_planner(tmp_path):
    tiny = ("--episodes", "1", "--heldout-episodes", "1", "--gradient-steps", "2", "--eval-every", "2")
    result = run_cli("train", "--stage", "predictor", "--planner", "scripted", *tiny, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "predictor").iterdir()
    assert len(EpisodeReplayBuffer.load(run / "heldout.npz")) > 0 and (run / "fig8.png").is_file()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((), "give --planner"),
        (("--planner", "missing.zip"), "--planner: no such file"),
        (("--buffer", "missing.npz"), "--buffer: no such file"),
        (("--planner", "PLANNER", "--subgoals", "nearest"), "--subgoals must be"),
        (("--planner", "PLANNER", "--set", "spawn_probabilty=0"), "did you mean 'spawn_probability'"),
        (("--planner", "PLANNER", "--predictor-set", "cv_residul=true"), "did you mean 'cv_residual'"),
        (
            ("--planner", "PLANNER", "--predictor-set", "cv_residual=yes please"),
            "cv_residual must be a boolean",
        ),
        (("--planner", "PLANNER", "--predictor-set", "goal_condition=false"), "the stage trains both"),
        (("--planner", "PLANNER", "--predictor-set", "cv_residual"), "--predictor-set expects KEY=VALUE"),
    ],
)
def test_bad_predictor_stage_input_is_one_line(tmp_path, cli_error, planner, args, message):
    args = tuple(str(planner) if a == "PLANNER" else a for a in args)
    (line,) = cli_error(tmp_path, "train", "--stage", "predictor", *args, "--episodes", "1")
    assert message in line
    assert not (tmp_path / "runs").exists()  # nothing half-made left behind
