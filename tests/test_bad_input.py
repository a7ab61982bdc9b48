"""Bad input is refused before any work, in one line with exit status 2, and nothing is written; no
code pickled in a model file runs unless the user trusts it."""

from __future__ import annotations

import base64
import shutil
from pathlib import Path
from typing import Any

import cloudpickle
import pytest
import yaml
from helpers import TINY_ENCODER, TINY_WORLD, rewrite_zip_data, save_tiny_models

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


def refused(capsys: pytest.CaptureFixture[str], args: list[str], message: str) -> None:
    """``sb3_gccp ARGS`` exits with 2 and one line on stderr holding ``message``, printing nothing else."""
    assert main(args) == 2
    out, err = capsys.readouterr()
    assert err.startswith("sb3_gccp: error: ") and err.count("\n") == 1, err
    assert message in err
    assert out == ""


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
