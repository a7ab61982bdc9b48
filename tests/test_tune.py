"""``sb3_gccp tune``: search-space errors, a tiny study, joining and resuming it, the best entry."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest
import yaml
from helpers import TINY_FLAT_POLICY_KWARGS
from optuna.trial import TrialState

from sb3_gccp.cli import main
from sb3_gccp.hyperparams import check_keys, default_config_file, load_hyperparams
from sb3_gccp.reproduce.plan import ReproduceRequest, prepare
from sb3_gccp.training.baselines import baseline_algorithm
from sb3_gccp.tune.objective import TUNE_METHODS, SuccessReporter
from sb3_gccp.tune.space import SearchSpace

TINY_PPO = {
    "GCCPFlat-v0": {
        "n_timesteps": 5000,
        "n_envs": 1,
        "policy": "MultiInputPolicy",
        "n_steps": 16,
        "batch_size": 16,
        "n_epochs": 1,
        "policy_kwargs": TINY_FLAT_POLICY_KWARGS,
        "env_kwargs": {"task": "mixed", "duration": 1.0},
    }
}
"""Flat PPO of seconds: a tiny encoder, 1 s episodes (10 steps)."""
TINY_SPACE = {
    "hyperparams": {
        "learning_rate": {"type": "float", "low": 1e-5, "high": 1e-3, "log": True},
        "n_epochs": {"type": "int", "low": 1, "high": 2},
        "policy_kwargs.net_arch": {"type": "categorical", "choices": {"a": [8], "b": [16, 16]}},
    },
    "pruner": {"type": "median", "n_startup_trials": 1, "report_every": 2},
}


@pytest.fixture()
def files(tmp_path: Path) -> tuple[Path, Path]:
    config, space = tmp_path / "tiny_ppo.yml", tmp_path / "space.yml"
    config.write_text(yaml.safe_dump(TINY_PPO))
    space.write_text(yaml.safe_dump(TINY_SPACE))
    return config, space


def tune_args(files: tuple[Path, Path], out: Path, n_trials: int, *extra: str) -> list[str]:
    config, space = files
    return [
        *("tune", "--method", "ppo", "--n-trials", str(n_trials), "--episodes-per-trial", "4"),
        *("--config", str(config), "--space", str(space), "--out", str(out), "--no-progress", *extra),
    ]


def stored(out: Path, name: str = "ppo") -> optuna.Study:
    return optuna.load_study(study_name=name, storage=f"sqlite:///{out / 'study.db'}")


@pytest.mark.parametrize(
    ("space", "message"),
    [
        ({"hyperparams": {}, "sampler": "tpe"}, "unknown key(s) 'sampler': expected hyperparams, pruner"),
        ({"hyperparams": {}}, "hyperparams must be a non-empty map of zoo keys"),
        (
            {"hyperparams": {"lerning_rate": {"type": "float", "low": 0.1, "high": 1}}},
            "lerning_rate: MaskablePPO takes no hyperparameter 'lerning_rate' "
            "(did you mean 'learning_rate'?)",
        ),
        (
            {"hyperparams": {"gamma": {"type": "float", "low": 0.99, "high": 0.9}}},
            "gamma: low must be below high, got low 0.99, high 0.9",
        ),
        (
            {"hyperparams": {"ent_coef": {"type": "float", "low": 0, "high": 0.1, "log": True}}},
            "ent_coef: a log scale needs low above 0, got 0",
        ),
        (
            {"hyperparams": {"gamma": {"type": "float", "low": 0.9, "high": 0.99, "scale": "log"}}},
            "gamma: unknown key(s) 'scale': expected type, low, high, log, step, choices",
        ),
        ({"hyperparams": {"gamma": {"type": "real"}}}, "gamma: type must be one of float, int, categorical"),
        (
            {"hyperparams": {"n_epochs": {"type": "int", "low": 1.5, "high": 4}}},
            "n_epochs: low must be an integer, got 1.5",
        ),
        (
            {"hyperparams": {"n_epochs": {"type": "float", "low": 1, "high": 4}}},
            "n_epochs: MaskablePPO takes an integer (default 10), the space samples floats: use type int",
        ),
        (
            {"hyperparams": {"clip_range": {"type": "categorical", "choices": [0.1], "low": 0}}},
            "clip_range: a categorical takes only choices, not low",
        ),
        (
            {"hyperparams": {"policy_kwargs.net_arch": {"type": "categorical", "choices": [[8], [16]]}}},
            "policy_kwargs.net_arch: choices must be numbers, strings or null; label others in a map",
        ),
        (
            {"hyperparams": {"policy_kwargs.depth": {"type": "int", "low": 1, "high": 3}}},
            "policy_kwargs.depth: MaskableMultiInputActorCriticPolicy takes no policy_kwargs key 'depth'",
        ),
        (
            {"hyperparams": {"n_timesteps": {"type": "int", "low": 1, "high": 3}}},
            "n_timesteps: not a tuned key",
        ),
        (
            {"hyperparams": {"gamma": {"type": "float", "low": 0.9, "high": 0.99}}, "pruner": {"every": 2}},
            "unknown pruner key(s) 'every'",
        ),
    ],
)
def test_a_bad_search_space_is_one_line_and_exit_2_before_any_trial(tmp_path, files, capsys, space, message):
    files[1].write_text(yaml.safe_dump(space))
    assert main(tune_args(files, tmp_path / "out", 1)) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"sb3_gccp: error: search space {files[1]}: {message}"), line
    assert not (tmp_path / "out").exists()


def test_the_shipped_search_spaces_fit_their_methods():
    for method in TUNE_METHODS.values():
        entry = method.base_entry(None)
        space = SearchSpace.from_file(
            default_config_file(f"tune/{method.name}.yml"), lambda key, e=entry, m=method: m.check_key(key, e)
        )
        method.check_space(space, entry, 50)
        assert space.hyperparams and space.pruner.type == "median"


def test_a_tiny_study_writes_a_best_entry_that_loads_and_a_second_call_adds_trials(tmp_path, files, capsys):
    out = tmp_path / "out"
    assert main(tune_args(files, out, 2)) == 0
    assert "saved" in capsys.readouterr().out
    study = stored(out)
    assert [t.state for t in study.trials] == [TrialState.COMPLETE, TrialState.COMPLETE]
    assert sorted(p.name for p in (out / "ppo").glob("trial_*")) == ["trial_0000", "trial_0001"]

    best = out / "ppo" / "best.yml"
    text = best.read_text()
    assert f"Optuna study 'ppo'\n# in sqlite:///{out / 'study.db'}:" in text
    assert f"trial {study.best_trial.number}, rolling success" in text
    entry = load_hyperparams(best, "GCCPFlat-v0")
    check_keys(entry, baseline_algorithm("ppo"))
    params = study.best_trial.params
    assert entry["learning_rate"] == params["learning_rate"] and entry["n_epochs"] == params["n_epochs"]
    assert entry["policy_kwargs"]["net_arch"] == {"a": [8], "b": [16, 16]}[params["policy_kwargs.net_arch"]]
    assert entry["n_timesteps"] == 5000 and entry["env_kwargs"] == TINY_PPO["GCCPFlat-v0"]["env_kwargs"]
    # reproduce takes it as is.
    plan = prepare(
        ReproduceRequest(preset="quick", methods=("ppo",), zoo_files={"ppo": best}, out=tmp_path / "r")
    )
    written = load_hyperparams(plan.configs["ppo"], "GCCPFlat-v0")
    assert written["learning_rate"] == params["learning_rate"]

    # The same command with a larger budget joins the study and adds a trial; other settings are refused.
    assert main(tune_args(files, out, 3)) == 0
    trials = stored(out).get_trials(states=(TrialState.COMPLETE,))
    assert len(trials) == 3
    assert trials[2].params["learning_rate"] not in (
        trials[0].params["learning_rate"],
        trials[1].params["learning_rate"],
    )
    args = tune_args(files, out, 5)
    args[args.index("--episodes-per-trial") + 1] = "6"
    assert main(args) == 2
    assert "was made with another episodes_per_trial" in capsys.readouterr().err


def test_a_trial_left_running_by_a_dead_worker_runs_again(tmp_path, files):
    out = tmp_path / "out"
    assert main(tune_args(files, out, 1)) == 0
    # A worker that died in its trial: the trial stays RUNNING, naming a process that has ended.
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    study = stored(out)
    trial = study.ask()
    space = SearchSpace.from_file(files[1], lambda key: None)
    space.sample(trial)
    trial.set_user_attr("worker", {"host": socket.gethostname(), "pid": int(dead.stdout), "pid_start": "0"})
    assert main(tune_args(files, out, 2)) == 0
    trials = stored(out).trials
    assert trials[1].state == TrialState.FAIL
    (retried,) = [t for t in trials if t.system_attrs.get("failed_trial") == 1]
    assert retried.state == TrialState.COMPLETE and retried.params == trials[1].params
    assert len([t for t in trials if t.state == TrialState.COMPLETE]) == 2


def test_the_reporter_stops_training_when_the_trial_is_pruned():
    class Trial:
        def __init__(self) -> None:
            self.reports: list[tuple[float, int]] = []

        def report(self, value: float, step: int) -> None:
            self.reports.append((value, step))

        def should_prune(self) -> bool:
            return len(self.reports) == 2

    trial = Trial()
    reporter = SuccessReporter(trial, every=2, window=3)  # type: ignore[arg-type]
    going = []
    for success in (True, False, True, True):  # two envs, one episode ending per step
        reporter.locals = {"infos": [{"is_success": success}, {}], "dones": [True, False]}
        going.append(reporter._on_step())
    assert trial.reports == [(0.5, 2), (2 / 3, 4)]
    assert going == [True, True, True, False] and reporter.pruned


def test_an_interrupted_trial_is_queued_again_with_its_hyperparameters(tmp_path, files, monkeypatch):
    def interrupted(trial, settings):
        settings.space.sample(trial)
        raise KeyboardInterrupt  # Ctrl-C in the middle of the trial's training

    monkeypatch.setattr("sb3_gccp.tune.study.run_trial", interrupted)
    out = tmp_path / "out"
    assert main(tune_args(files, out, 1)) == 130
    failed, queued = stored(out).trials
    assert failed.state == TrialState.FAIL and queued.state == TrialState.WAITING
    assert queued.params == failed.params and queued.system_attrs["failed_trial"] == failed.number


def running(out: Path) -> bool:
    if not (out / "study.db").is_file():
        return False
    try:
        return bool(stored(out).get_trials(states=(TrialState.RUNNING,)))
    except KeyError:  # no study yet
        return False


@pytest.mark.slow
def test_two_worker_processes_share_the_budget_and_a_killed_study_resumes(tmp_path, files):
    out = tmp_path / "out"
    command = [sys.executable, "-m", "sb3_gccp.cli", *tune_args(files, out, 4, "--n-jobs", "2")]
    worker = subprocess.Popen(command, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not running(out):  # then kill the whole process group
        time.sleep(0.5)
    os.killpg(worker.pid, signal.SIGKILL)
    worker.wait()
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    trials = stored(out).trials
    assert len([t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]) >= 4
    killed = [t for t in trials if t.state == TrialState.FAIL]
    assert killed and all(any(r.system_attrs.get("failed_trial") == k.number for r in trials) for k in killed)
    assert len({t.user_attrs["worker"]["pid"] for t in trials if t.state == TrialState.COMPLETE}) >= 2


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ("dqn=best.yml", "--config for method(s) not reproduced: dqn"),
        ("ppo", "--config expects METHOD=FILE, got 'ppo'"),
        ("ppo=missing.yml", "hyperparameter file not found: missing.yml"),
    ],
)
def test_reproduce_rejects_a_bad_zoo_file_option_in_one_line(tmp_path, monkeypatch, capsys, config, message):
    monkeypatch.chdir(tmp_path)
    assert main(["reproduce", "--preset", "quick", "--methods", "ppo", "--config", config]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line == f"sb3_gccp: error: {message}"
