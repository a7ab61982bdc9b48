"""The decision-maker stage and ``sb3_gccp evaluate`` through the CLI, on a tiny budget."""

from __future__ import annotations

import copy
import csv
import json
from pathlib import Path

import pytest
import torch as th
import yaml
from helpers import TINY_ENCODER, TINY_PLANNER_HYPERPARAMS, run_cli
from sb3_contrib import MaskablePPO

from gccp_envs.planner_env import GCCPPlannerEnv
from sb3_gccp.gccp.settings import GCCPSettings
from sb3_gccp.training.decider import training_metrics
from sb3_gccp.training.episodes import read_episodes

TINY_DECIDER = {
    "GCCPDecider-v0": {
        "n_timesteps": 1000,
        "n_envs": 2,
        "policy": "DecisionMakerPolicy",
        "n_steps": 4,
        "batch_size": 8,
        "n_epochs": 1,
        "policy_kwargs": {"encoder": TINY_ENCODER, "net_arch": {"pi": [8, 8], "vf": [8, 8]}},
        "env_kwargs": {"duration": 2.0, "spawn_probability": 0.2},
        "gccp": {
            "n_episodes": 3,
            "mask_after_episodes": 2,
            "predictor_kwargs": {"encoder": TINY_ENCODER, "decoder_hidden": 8},
            "save_every_episodes": 2,
        },
    }
}
"""A decider run of seconds: 2 s episodes (2 decisions each), masks on after 2 episodes."""


@pytest.fixture(scope="module")
def tiny_planner(tmp_path_factory: pytest.TempPathFactory) -> Path:
    settings = TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"]
    env = GCCPPlannerEnv(**settings["env_kwargs"])
    model = MaskablePPO("MultiInputPolicy", env, n_steps=16, batch_size=16, n_epochs=1, seed=0)
    model.learn(16)
    path = tmp_path_factory.mktemp("planner") / "planner.zip"
    model.save(path)
    return path


def _train_decider(tmp_path: Path, entry: dict, planner: Path, log_folder: str = "runs") -> tuple[Path, str]:
    """The run folder and the output of a decider stage with zoo ``entry``, seed 2, in ``tmp_path``."""
    config = tmp_path / "tiny.yml"
    config.write_text(yaml.safe_dump(entry))
    args = ("train", "--stage", "decider", "--config", str(config), "--log-folder", log_folder)
    result = run_cli(*args, "--planner", str(planner), "--seed", "2", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / log_folder / "decider").iterdir()
    return run, result.stdout


def test_decider_stage_trains_the_same_run_for_a_seed_evaluates_and_resumes(tmp_path, tiny_planner, cli):
    run, _ = _train_decider(tmp_path, TINY_DECIDER, tiny_planner)
    assert run.name.startswith("GCCPDecider-v0_2_")
    for name in (
        "planner.zip",
        "decider.zip",
        "predictor.pt",
        "hierarchy.yml",
        "episodes.csv",
        "metrics.json",
    ):
        assert (run / name).is_file(), name
    assert (run / "training_curve.png").stat().st_size > 1000
    assert list((run / "tb").rglob("events.out.tfevents.*"))
    with (run / "episodes.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert [row["masks_on"] for row in rows] == ["0", "0", "1"]
    assert json.loads((run / "metrics.json").read_text())["episodes"] == 3
    hierarchy = yaml.safe_load((run / "hierarchy.yml").read_text())
    assert hierarchy["predictor"] == "learned" and hierarchy["world"]["duration"] == 2.0
    assert hierarchy["mask_margin"] == 0.0 and hierarchy["mask_extrapolate_steps"] == 0

    # The same seed trains the same decider and predictor: the predictor starts from the run's seed,
    # and its updates run beside the env workers' steps in the order the episodes ended.
    rerun, _ = _train_decider(tmp_path, TINY_DECIDER, tiny_planner, "again")
    first, second = (
        th.load(folder / "predictor.pt", weights_only=True)["state_dict"] for folder in (run, rerun)
    )
    assert first.keys() == second.keys()
    for key in first:
        assert th.equal(first[key], second[key]), key
    first_rows, second_rows = (read_episodes(folder / "episodes.csv") for folder in (run, rerun))
    for row in first_rows + second_rows:
        assert row.pop("wall_clock_s") > 0  # the one column that may differ
    assert first_rows == second_rows

    # The same seed gives the same table; a decider .zip inside the run folder works as well.
    evaluate = ("evaluate", "--episodes-per-task", "1", "--tasks", "left,right", "--seed", "5")
    first = cli(*evaluate, "--model", str(run), "--json", "table.json", cwd=tmp_path)
    second = cli(*evaluate, "--model", str(run / "decider.zip"), cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    assert "| overall | 2 |" in first.stdout
    assert first.stdout.splitlines()[1:] == second.stdout.splitlines()[1:]
    assert set(json.loads((tmp_path / "table.json").read_text())["table"]) == {"left", "right", "overall"}
    # Sampled decisions are seeded too.
    sampled = [cli(*evaluate, "--model", str(run), "--stochastic", cwd=tmp_path) for _ in range(2)]
    assert sampled[0].returncode == 0, sampled[0].stderr
    assert "stochastic decisions" in sampled[0].stdout and sampled[0].stdout == sampled[1].stdout

    # A longer budget in the run's config plays the part of an interrupted run: resume continues from
    # the checkpoint with the predictor, its optimiser and the replay buffer.
    settings = yaml.safe_load((run / "config.yml").read_text())
    settings["gccp"]["n_episodes"] = 5
    (run / "config.yml").write_text(yaml.safe_dump(settings))
    result = run_cli("train", "--stage", "decider", "--log-folder", "runs", "--resume", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    with (run / "episodes.csv").open() as file:
        resumed = list(csv.DictReader(file))
    assert resumed[:3] == rows and len(resumed) == 5
    assert float(resumed[3]["wall_clock_s"]) >= float(rows[2]["wall_clock_s"])  # the clock goes on
    assert [row["masks_on"] for row in resumed[3:]] == ["1", "1"]
    newest = max((run / "checkpoints").glob("*/complete.json"), key=lambda p: p.stat().st_mtime).parent
    state = th.load(newest / "gccp_state.pt", weights_only=True)
    assert (state["episodes"], state["gradient_steps"]) == (5, 25)  # K_p = 5 steps per episode


def test_the_run_model_is_the_candidate_best_on_the_validation_flows(tmp_path, tiny_planner, cli):
    entry = copy.deepcopy(TINY_DECIDER)
    entry["GCCPDecider-v0"]["gccp"].update(  # about 4 episodes a rollout: candidates at its starts
        n_episodes=9,
        choose_on_flows=7,
        choose_episodes_per_task=1,
        choose_every_episodes=2,
        choose_from_episodes=2,
    )
    run, stdout = _train_decider(tmp_path, entry, tiny_planner)
    names = sorted((p.name for p in (run / "candidates").iterdir()), key=int)
    assert names and all(2 <= int(name) < 9 for name in names)
    choice = json.loads((run / "choice.json").read_text())
    assert list(choice["tables"]) == [*names, "final"]
    ranked = [
        (table["overall"]["success"], -table["overall"]["crashed"], i)
        for i, table in enumerate(choice["tables"].values())
    ]
    chosen = choice["chosen"]
    assert chosen == [*names, "final"][max(ranked)[2]]
    assert f"after {chosen} episodes" in stdout
    source = run / "final" if chosen == "final" else run / "candidates" / chosen
    if chosen != "final":
        assert (run / "decider.zip").read_bytes() == (source / "decider.zip").read_bytes()
        assert (run / "final" / "decider.zip").read_bytes() != (run / "decider.zip").read_bytes()
    assert (run / "predictor.pt").read_bytes() == (
        (run / "predictor.pt") if chosen == "final" else source / "predictor.pt"
    ).read_bytes()
    # The choice's table is what ``sb3_gccp evaluate`` gives for the run's model on those flows.
    evaluate = ("evaluate", "--episodes-per-task", "1", "--seed", "7", "--json", "table.json")
    assert cli(*evaluate, "--model", str(run), cwd=tmp_path).returncode == 0
    assert json.loads((tmp_path / "table.json").read_text())["table"] == choice["tables"][chosen]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["train", "--stage", "decider"],
            "the decider stage needs --planner PATH.zip (a trained motion-planner)",
        ),
        (["train", "--stage", "decider", "--planner", "none.zip"], "planner not found: none.zip"),
        (["train", "--stage", "all", "--resume"], "--resume works per stage"),
        (
            ["train", "--stage", "decider", "--planner", "scripted", "--set", "nonsense=1"],
            "unknown intersection config key(s): 'nonsense'",
        ),
        (
            ["train", "--stage", "decider", "--planner", "scripted", "--gccp", "predictor=bogus"],
            "gccp.predictor must be one of learned, no_goal, cv, none, got 'bogus'",
        ),
        (["train", "--stage", "planner", "--gccp", "predictor=none"], "--gccp sets the decider's gccp map"),
        (
            ["train", "--stage", "decider", "--planner", "scripted", "--gccp", "choose_on_flows=-1"],
            "gccp.choose_on_flows must be a non-negative integer, got -1",
        ),
        (["evaluate", "--model", "nowhere"], "model not found: nowhere"),
        (["evaluate", "--model", "."], "no hierarchy.yml in ."),
        (["evaluate", "--model", ".", "--episodes-per-task", "0"], "--episodes-per-task must be at least 1"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, cli_error, args, message):
    (line,) = cli_error(tmp_path, *args)
    assert line.startswith(f"sb3_gccp: error: {message}")
    assert not (tmp_path / "runs").exists()


def test_stage_all_trains_the_planner_for_n_g_episodes_then_the_decider(tmp_path):
    planner = dict(TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"], n_timesteps=2000)
    decider = yaml.safe_load(yaml.safe_dump(TINY_DECIDER["GCCPDecider-v0"]))
    decider["n_envs"] = 1
    decider["gccp"].update(n_episodes=2, planner_episodes=2)
    config = tmp_path / "both.yml"
    config.write_text(yaml.safe_dump({"GCCPPlanner-v0": planner, "GCCPDecider-v0": decider}))
    result = run_cli("train", "--stage", "all", "--config", str(config), "--log-folder", "runs", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    saved = [line for line in result.stdout.splitlines() if line.startswith("saved ")]
    planner_zip, run = (Path(line.split(" ", 1)[1]) for line in saved)
    assert f"sb3_gccp evaluate --model {run}" in result.stdout  # it says what to do with the run
    assert "rolling success over 100 episodes first passed 70 %" in result.stdout
    # 2 episodes of at most 2 s (20 steps) each, far below the planner's 2000-step budget.
    assert MaskablePPO.load(tmp_path / planner_zip).num_timesteps <= 40
    assert (tmp_path / run / "planner.zip").read_bytes() == (tmp_path / planner_zip).read_bytes()
    assert yaml.safe_load((tmp_path / run / "hierarchy.yml").read_text())["decider"] == "decider.zip"


def test_decider_stage_with_the_scripted_planner(tmp_path, cli):
    decider = yaml.safe_load(yaml.safe_dump(TINY_DECIDER["GCCPDecider-v0"]))
    decider.update(n_envs=1)
    decider["gccp"].update(n_episodes=1, predictor="learned")
    config = tmp_path / "tiny.yml"
    config.write_text(yaml.safe_dump({"GCCPDecider-v0": decider}))
    args = (
        "train",
        "--stage",
        "decider",
        "--planner",
        "scripted",
        "--config",
        str(config),
        "--log-folder",
        "runs",
        "--set",
        "duration=1.5",
        "--gccp",
        "predictor=cv",
    )
    result = run_cli(*args, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "decider").iterdir()
    assert not (run / "planner.zip").exists() and not (run / "predictor.pt").exists()
    written = yaml.safe_load((run / "hierarchy.yml").read_text())
    assert written["planner"] == "scripted"
    # --set replaced the entry's world key, for training and in what the run records.
    assert written["world"]["duration"] == 1.5
    assert yaml.safe_load((run / "config.yml").read_text())["env_kwargs"]["duration"] == 1.5
    # --gccp replaced the entry's predictor (learned) the same way.
    assert yaml.safe_load((run / "config.yml").read_text())["gccp"]["predictor"] == "cv"
    result = cli("evaluate", "--model", str(run), "--episodes-per-task", "1", "--tasks", "left", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "(GCCP: cv)" in result.stdout


def test_training_metrics_find_the_episode_where_success_passes_70_percent():
    history = [{"success": int(k >= 150), "crashed": int(k < 150)} for k in range(300)]
    metrics = training_metrics(history, GCCPSettings(), window=100)
    # The rolling rate over the last 100 episodes reaches 0.7 when 70 of them succeeded: episode 220.
    assert metrics["first_episode_success_70"] == 220
    assert metrics["first_episode_success_90"] == 240
    assert metrics["final_success_rate"] == 1.0 and metrics["final_collision_rate"] == 0.0
