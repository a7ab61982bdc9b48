"""``sb3_gccp rollout``: the scripted hierarchy from the command line, with and without a progress bar."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sb3_gccp.cli import main


@pytest.mark.parametrize("progress", [[], ["--no-progress"]])
def test_rollout_writes_its_table(tmp_path, capsys, progress):
    out = tmp_path / "rollout.json"
    args = ["rollout", "--tasks", "right", "--episodes-per-task", "1", "--json", str(out), *progress]
    assert main([*args, "--set", "spawn_probability=0", "--set", "duration=8"]) == 0
    written = json.loads(out.read_text())
    assert "| right | 1 |" in capsys.readouterr().out
    assert set(written["table"]) == {"right", "overall"}
    (episode,) = written["episodes"]
    assert (episode["task"], episode["seed"], episode["steps"]) == ("right", 0, 8)  # 8 s: 8 decisions
    assert episode["timeout"]


PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"


def test_evaluate_runs_the_shipped_hierarchy_under_another_gccp_check(capsys):
    args = ["evaluate", "--model", str(PRETRAINED), "--tasks", "right", "--episodes-per-task", "1"]
    assert main([*args, "--no-progress", "--mask", "mask_margin=0.5", "--set", "duration=2"]) == 0
    out = capsys.readouterr().out
    assert "(GCCP: learned, mask_margin=0.5)" in out and "| right | 1 |" in out


@pytest.mark.parametrize(
    "model, mask, message",
    [
        (PRETRAINED, "mask_extrapolate_steps=-1", "mask_extrapolate_steps must be a non-negative integer"),
        (PRETRAINED, "margin=1", "unknown GCCP check key(s) margin"),
        (PRETRAINED, "mask_margin", "--mask expects KEY=VALUE"),
        (PRETRAINED / "baselines" / "dqn", "mask_margin=1", "--mask: baselines have no GCCP check"),
    ],
)
def test_evaluate_rejects_a_bad_mask_setting_in_one_line(capsys, model, mask, message):
    assert main(["evaluate", "--model", str(model), "--mask", mask]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_decider_run_reports_where_its_rolling_success_passed_70_and_90_percent(tmp_path):
    from sb3_gccp.commands.train import sample_efficiency

    metrics = {"window": 100, "final_success_rate": 0.9, "final_collision_rate": 0.06}
    (tmp_path / "metrics.json").write_text(
        json.dumps({**metrics, "first_episode_success_70": 100, "first_episode_success_90": None})
    )
    assert sample_efficiency(tmp_path) == (
        "rolling success over 100 episodes first passed 70 % at episode 100, 90 % never; "
        "at the end 90.0 % success, 6.0 % collisions"
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--stage", "planner", "--save-freq", "0"], "--save-freq must be a positive integer, got 0"),
        (["--stage", "planner", "--save-freq", "-100"], "--save-freq must be a positive integer, got -100"),
        (
            ["--stage", "decider", "--planner", "scripted", "--torch-threads", "0"],
            "--torch-threads must be a positive integer, got 0",
        ),
        (
            ["--stage", "predictor", "--planner", "scripted", "--torch-threads", "0"],
            "--torch-threads must be a positive integer, got 0",
        ),
        (["--stage", "planner", "-v", "-1"], "-v/--verbose must be a non-negative integer, got -1"),
    ],
)
def test_train_rejects_a_run_option_out_of_range_in_one_line_before_writing(tmp_path, capsys, args, message):
    assert main(["train", *args, "--log-folder", str(tmp_path / "runs")]) == 2
    assert capsys.readouterr().err == f"sb3_gccp: error: {message}\n"
    assert not (tmp_path / "runs").exists()


def test_a_resume_with_an_option_out_of_range_changes_nothing_in_the_run(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yml").write_text("n_timesteps: 32\n")
    (run / "args.yml").write_text("seed: 0\nsave_freq: 16\n")
    assert main(["train", "--stage", "planner", "--resume", str(run), "--save-freq", "0"]) == 2
    assert capsys.readouterr().err == "sb3_gccp: error: --save-freq must be a positive integer, got 0\n"
    assert sorted(p.name for p in run.iterdir()) == ["args.yml", "config.yml"]
    assert (run / "args.yml").read_text() == "seed: 0\nsave_freq: 16\n"
