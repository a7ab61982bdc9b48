"""Bad input is refused before any work, in one line with exit status 2, and nothing is written; no
code pickled in a model file runs unless the user trusts it."""

from __future__ import annotations

import base64
import multiprocessing
import shutil
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import pytest
import yaml
from helpers import (
    TINY_ENCODER,
    TINY_PLANNER_HYPERPARAMS,
    TINY_WORLD,
    rewrite_zip_data,
    save_tiny_models,
)

from sb3_gccp.cli import main

PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with an untrained tiny ``decider.zip`` and ``planner.zip`` (ours, on ``TINY_WORLD``)."""
    folder = tmp_path_factory.mktemp("models")
    save_tiny_models(folder)
    return folder


def hierarchy(models: Path, folder: Path, **spec: Any) -> Path:
    """A hierarchy folder in ``folder``: copies of the tiny models and a ``hierarchy.yml`` (the scripted
    planner and the constant-velocity GCCP module unless ``spec`` says otherwise)."""
    folder.mkdir()
    for model in models.iterdir():
        shutil.copy(model, folder)
    full = {"planner": "scripted", "decider": "decider.zip", "predictor": "cv", "world": TINY_WORLD, **spec}
    (folder / "hierarchy.yml").write_text(yaml.safe_dump(full))
    return folder


def one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], quiet: bool = False) -> str:
    """The one stderr line of a command that must fail with status 2, whether argparse or the command
    itself rejects the input (``quiet``: and that prints nothing on stdout)."""
    try:
        status = main(argv)
    except SystemExit as stop:
        status = stop.code
    assert status == 2
    out, err = capsys.readouterr()
    (line,) = err.splitlines()
    assert line.startswith("sb3_gccp: error: ")
    assert not quiet or out == ""
    return line


def refused(capsys: pytest.CaptureFixture[str], args: list[str], message: str) -> None:
    """``sb3_gccp ARGS`` exits with 2 and one line on stderr holding ``message``, printing nothing else."""
    assert message in one_line_error(capsys, args, quiet=True)


class TouchOnLoad:
    """A payload that creates ``marker`` when unpickled (as a hostile file would run a command)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (self.marker,))


def poison(path: Path, marker: Path, *entries: str) -> None:
    """Replace the pickled value of ``entries`` in the ``data`` of an SB3 ``.zip`` by a payload that creates
    ``marker`` when unpickled; their plain fields stay as they were."""
    from sb3_gccp.safe_loading import SavedModel

    payload = base64.b64encode(cloudpickle.dumps(TouchOnLoad(marker))).decode()
    data = SavedModel.read(path).data
    rewrite_zip_data(path, **{entry: {**data[entry], ":serialized:": payload} for entry in entries})


def test_evaluate_runs_no_code_pickled_in_a_model_file(models, tmp_path, capsys):
    folder = hierarchy(models, tmp_path / "downloaded")
    marker = tmp_path / "payload_ran"
    poison(folder / "decider.zip", marker, "policy_class", "observation_space", "action_space")
    args = ["evaluate", "--model", str(folder), "--tasks", "left", "--episodes-per-task", "1"]
    assert main([*args, "--no-progress"]) == 0
    assert "| left | 1 |" in capsys.readouterr().out
    assert not marker.exists()
    main([*args, "--no-progress", "--trust-pickle"])  # SB3's own load unpickles: the payload is live
    assert marker.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--set", "task=[left"], "--set 'task=[left': the value is not valid YAML"),
        (["--set", "duration=.inf"], "duration must be finite, got inf"),
        (["--set", "duration=.nan"], "duration must be finite, got nan"),
        (["--set", "r_time=-.inf"], "r_time must be finite, got -inf"),
        (["--set", "r_near=abc"], "r_near must be a number, got 'abc'"),
        (["--set", "npc_speed_range=[7, .inf]"], "npc_speed_range must be finite"),
        (["--json", "missing/out.json"], "--json missing/out.json: no folder missing"),
        (["--gif", "missing/out.gif"], "--gif missing/out.gif: no folder missing"),
    ],
)
def test_rollout_refuses_bad_input_before_playing(tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    refused(capsys, ["rollout", "--episodes-per-task", "1000", "--json", "out.json", *args], message)
    assert list(tmp_path.iterdir()) == []


def test_a_config_file_that_is_not_utf8_is_named(tmp_path, capsys):
    config = tmp_path / "world.yml"
    config.write_bytes(b"task: left\nduration: 2\xff\n")
    refused(capsys, ["config", "--config", str(config)], f"config file {config} is not UTF-8 text")


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"predictor": "learned"}, "a learned predictor needs predictor_weights"),
        ({"world": None}, "world must be a map"),
        ({"predictor": "learned", "predictor_weights": "predictor.pt"}, "predictor.pt is not a predictor"),
        ({"planner": "decider.zip"}, "decider.zip is not a motion-planner of this world"),
        ({"decider": "planner.zip"}, "planner.zip is not a decision-maker of this world"),
        ({"predictor": "learned", "predictor_weights": "/etc/hostname"}, "must name a file inside"),
    ],
)
def test_evaluate_refuses_a_bad_hierarchy_before_playing(models, tmp_path, capsys, spec, message):
    folder = hierarchy(models, tmp_path / "model", **spec)
    (folder / "predictor.pt").write_bytes((PRETRAINED / "predictor.pt").read_bytes()[:1000])  # cut short
    out = tmp_path / "table.json"
    refused(capsys, ["evaluate", "--model", str(folder), "--json", str(out)], message)
    assert not out.exists()


@pytest.mark.parametrize(
    ("planner", "setting", "message"),
    [
        (
            "scripted",
            "num_subgoals=5",
            "decider.zip (decision-maker) was trained on subgoals of shape (12, 3)",
        ),
        ("scripted", "bev_size=32", "decider.zip (decision-maker) was trained on bev of shape (1, 64, 64)"),
        (
            "planner.zip",
            "bev_size=32",
            "planner.zip (motion-planner) was trained on bev of shape (1, 64, 64)",
        ),
    ],
)
def test_evaluate_refuses_a_world_the_models_were_not_trained_for(
    models, tmp_path, capsys, planner, setting, message
):
    folder = hierarchy(models, tmp_path / "model", planner=planner)
    refused(capsys, ["evaluate", "--model", str(folder), "--set", setting], message)


def test_evaluate_checks_the_json_folder_before_playing(tmp_path, capsys):
    args = ["evaluate", "--model", str(PRETRAINED), "--episodes-per-task", "1000"]
    refused(capsys, [*args, "--json", str(tmp_path / "missing" / "table.json")], "no folder")


def test_a_baseline_naming_a_model_outside_its_folder_is_refused(tmp_path, capsys):
    folder = tmp_path / "baseline"
    shutil.copytree(PRETRAINED / "baselines" / "ppo", folder)
    (folder / "baseline.yml").write_text(yaml.safe_dump({"algorithm": "ppo", "model": "../model.zip"}))
    refused(capsys, ["evaluate", "--model", str(folder)], "model must name a file inside")


def test_export_of_a_truncated_zip_leaves_nothing_and_a_retry_works(models, tmp_path, capsys):
    folder = hierarchy(models, tmp_path / "run")
    whole = (folder / "decider.zip").read_bytes()
    (folder / "decider.zip").write_bytes(whole[: len(whole) // 2])
    refused(capsys, ["export", str(folder), str(tmp_path / "out")], "decider.zip is not a readable SB3 .zip")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    (folder / "decider.zip").write_bytes(whole)
    assert main(["export", str(folder), str(tmp_path / "out")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "run"]
    assert (tmp_path / "out" / "hierarchy.yml").is_file()


def test_export_refuses_a_world_the_models_were_not_trained_for(models, tmp_path, capsys):
    folder = hierarchy(models, tmp_path / "run")
    args = ["export", str(folder), str(tmp_path / "out"), "--set", "num_subgoals=5"]
    refused(capsys, args, "was trained on subgoals of shape (12, 3)")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--stage", "decider", "--planner", "models/decider.zip"], "decider.zip is not a motion-planner"),
        (["--stage", "predictor", "--planner", "models/decider.zip"], "decider.zip is not a motion-planner"),
        (
            ["--stage", "predictor", "--planner", "scripted", "--subgoals", "models/planner.zip"],
            "planner.zip is not a decision-maker",
        ),
    ],
)
def test_a_training_stage_refuses_a_model_of_the_wrong_kind_before_making_its_run_folder(
    models, tmp_path, capsys, monkeypatch, args, message
):
    monkeypatch.chdir(tmp_path)
    shutil.copytree(models, "models")
    decider = {
        "n_timesteps": 8,
        "policy": "DecisionMakerPolicy",
        "n_steps": 4,
        "batch_size": 4,
        "policy_kwargs": {"encoder": TINY_ENCODER, "net_arch": {"pi": [8], "vf": [8, 8]}},
        "env_kwargs": TINY_WORLD,
        "gccp": {"n_episodes": 1, "predictor": "none"},
    }
    Path("tiny.yml").write_text(yaml.safe_dump({"GCCPDecider-v0": decider}))
    refused(capsys, ["train", "--config", "tiny.yml", "--log-folder", "runs", *args], message)
    assert not Path("runs").exists()


def test_reproduce_refuses_a_planner_of_the_wrong_kind_before_writing(models, tmp_path, capsys):
    args = ["reproduce", "--preset", "quick", "--planner", str(models / "decider.zip")]
    out, runs = tmp_path / "results", tmp_path / "runs"
    refused(
        capsys, [*args, "--out", str(out), "--log-folder", str(runs)], "decider.zip is not a motion-planner"
    )
    assert not out.exists() and not runs.exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["rollout", "--seed", "-1"],
        ["evaluate", "--model", str(PRETRAINED), "--seed", "-1"],
        ["video", "--model", str(PRETRAINED), "--out", "x.gif", "--seed", "x"],
        ["train", "--stage", "planner", "--seed", "-1"],
        ["reproduce", "--seeds", "0", "-2"],
        ["reproduce", "--eval-seed", "-5"],
        ["tune", "--method", "ppo", "--episodes-per-trial", "1", "--seed", "-1"],
    ],
)
def test_a_seed_below_zero_is_refused_before_any_work(capsys, tmp_path, monkeypatch, argv):
    monkeypatch.chdir(tmp_path)
    line = one_line_error(capsys, argv)
    assert "a seed is a whole number >= 0" in line
    assert list(tmp_path.iterdir()) == []


def test_a_usage_error_is_one_line_that_points_to_help(capsys):
    line = one_line_error(capsys, ["rollout", "--episodes-per-task", "abc"])
    assert "invalid int value: 'abc'" in line and "see `sb3_gccp rollout --help`" in line


@pytest.mark.parametrize(
    "assignment, message",
    [
        ("npc_speed_range=5", "npc_speed_range must be a (low, high) pair with 0 <= low <= high, got 5"),
        ("npc_speed_range=[1, x]", "npc_speed_range must be a (low, high) pair"),
    ],
)
def test_a_pair_key_given_something_else_is_named(capsys, assignment, message):
    assert message in one_line_error(capsys, ["config", "--set", assignment])


def test_a_world_file_with_a_key_that_is_no_name_is_named(capsys, tmp_path):
    config = tmp_path / "world.yml"
    config.write_text("1: 2\n")
    assert "intersection config keys are names, got 1" in one_line_error(
        capsys, ["config", "--config", str(config)]
    )


@pytest.mark.parametrize(
    "change, message",
    [
        ({"policy": "NoSuchPolicy"}, "unknown class name 'NoSuchPolicy'"),
        ({"batch_size": 0}, "batch_size must be an integer of at least 2, got 0"),
        ({"n_epochs": 0}, "n_epochs must be an integer of at least 1, got 0"),
    ],
)
def test_settings_only_the_model_rejects_leave_no_run_folder(capsys, tmp_path, change, message):
    entry = {**TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"], **change}
    config = tmp_path / "planner.yml"
    config.write_text(yaml.safe_dump({"GCCPPlanner-v0": entry}))
    argv = ["train", "--stage", "planner", "--config", str(config), "--log-folder", str(tmp_path / "runs")]
    assert message in one_line_error(capsys, [*argv, "--no-progress"])
    assert not list((tmp_path / "runs").rglob("*.yml"))  # no run folder that --resume would take


def test_a_decider_whose_model_cannot_be_built_leaves_no_worker_process(capsys, tmp_path):
    decider = {
        "n_timesteps": 8,
        "n_envs": 2,  # one worker process each
        "policy": "NoSuchPolicy",
        "env_kwargs": TINY_WORLD,
        "gccp": {"n_episodes": 1, "predictor": "none"},
    }
    config = tmp_path / "decider.yml"
    config.write_text(yaml.safe_dump({"GCCPDecider-v0": decider}))
    argv = ["train", "--stage", "decider", "--planner", "scripted", "--config", str(config)]
    before = set(multiprocessing.active_children())
    line = one_line_error(capsys, [*argv, "--log-folder", str(tmp_path / "runs"), "--no-progress"])
    assert "unknown class name 'NoSuchPolicy'" in line
    assert set(multiprocessing.active_children()) <= before
    assert not list((tmp_path / "runs").rglob("*.yml"))


@pytest.mark.parametrize("arrays", [{"future": np.zeros(3)}, None])
def test_a_file_that_is_no_replay_buffer_leaves_no_predictor_run(capsys, tmp_path, arrays):
    buffer = tmp_path / "buffer.npz"
    if arrays is None:
        buffer.write_bytes(b"not a numpy file")
    else:
        np.savez(buffer, **arrays)  # a valid .npz without the buffer's capacity
    argv = ["train", "--stage", "predictor", "--buffer", str(buffer), "--log-folder", str(tmp_path / "runs")]
    assert "is not a replay buffer saved by sb3_gccp" in one_line_error(capsys, argv)
    assert not (tmp_path / "runs").exists()


def test_a_predictor_setting_of_the_wrong_kind_is_named(capsys, tmp_path):
    argv = ["train", "--stage", "predictor", "--planner", "scripted", "--predictor-set", "encoder=5"]
    line = one_line_error(capsys, [*argv, "--log-folder", str(tmp_path / "runs")])
    assert "the encoder config is a map of its keys, got 5" in line
    assert not (tmp_path / "runs").exists()


def test_a_tune_storage_that_cannot_be_opened_leaves_no_output_folder(capsys, tmp_path):
    argv = ["tune", "--method", "ppo", "--episodes-per-trial", "1", "--storage", "bogus://x"]
    one_line_error(capsys, [*argv, "--out", str(tmp_path / "tune")])
    assert not (tmp_path / "tune").exists()


def test_reproduce_into_a_file_writes_nothing(capsys, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    argv = ["reproduce", "--preset", "quick", "--methods", "ppo", "--out", str(afile)]
    line = one_line_error(capsys, [*argv, "--log-folder", str(tmp_path / "runs")])
    assert "a file, not a folder" in line
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["video", "--model", str(PRETRAINED), "--out", "x.gif", "--fps", "nan"],
            "--fps must be a number in",
        ),
        (
            ["video", "--model", str(PRETRAINED), "--out", "x.gif", "--fps", "inf"],
            "--fps must be a number in",
        ),
        (["rollout", "--gif", "out.txt"], "--gif out.txt: the file name must end in .gif"),
    ],
)
def test_an_output_option_that_could_only_fail_at_the_end_fails_first(
    capsys, tmp_path, monkeypatch, argv, message
):
    monkeypatch.chdir(tmp_path)
    assert message in one_line_error(capsys, argv)
    assert list(tmp_path.iterdir()) == []
