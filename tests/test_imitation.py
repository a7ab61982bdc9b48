"""Behaviour cloning of the scripted planner: data collection, cloning, the planner stage's key."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from helpers import TINY_PLANNER_HYPERPARAMS
from sb3_contrib import MaskablePPO

from gccp_envs.config import IntersectionConfig
from gccp_envs.scripted import ScriptedPlanner, SearchPlanner
from sb3_gccp.imitation import ImitationSettings, clone, collect_expert

WORLD = IntersectionConfig(spawn_probability=0.0, warmup_time=0.0, duration=4.0)


def test_expert_data_are_the_scripted_planners_actions_under_the_envs_masks():
    data = collect_expert(WORLD, 60, seed=5)
    assert data.actions.shape == (60,) and data.masks.shape == (60, 6)
    assert data.episodes >= 1  # 4 s episodes: at least one reset in 6 s of driving
    assert data.masks[np.arange(60), data.actions].all()
    expert = ScriptedPlanner(WORLD)
    first = {key: value[0] for key, value in data.obs.items()}
    assert expert(first, data.masks[0]) == data.actions[0]


def test_search_expert_data_are_the_search_planners_actions():
    data = collect_expert(WORLD, 30, seed=5, expert="search")
    assert data.masks[np.arange(30), data.actions].all()
    first = {key: value[0] for key, value in data.obs.items()}
    assert SearchPlanner(WORLD)(first, data.masks[0]) == data.actions[0]


def test_cloning_makes_the_policy_choose_the_experts_actions():
    data = collect_expert(WORLD, 200, seed=0)
    env = gym.make("GCCPPlanner-v0", config=WORLD)
    th.manual_seed(0)
    model = MaskablePPO("MultiInputPolicy", env, policy_kwargs={"net_arch": [64]}, seed=0)
    settings = ImitationSettings(expert_steps=200, epochs=40, batch_size=50, learning_rate=1e-3)
    history = clone(model, data, settings, seed=0)
    assert len(history) == 40
    assert history[-1]["nll"] < 0.5 * history[0]["nll"]
    most_common = np.bincount(data.actions).max() / len(data.actions)  # always braking: about 0.5
    assert history[-1]["accuracy"] > most_common + 0.15 > history[0]["accuracy"] + 0.15


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"epochs": 0}, "imitation.epochs must be a positive integer"),
        ({"learning_rate": -1.0}, "imitation.learning_rate must be a positive number"),
        ({"expert_step": 10}, "expert_step"),
        ({"expert": "human"}, "imitation.expert must be one of scripted, search, got 'human'"),
        ({"dagger_rounds": -1}, "imitation.dagger_rounds must be a non-negative integer, got -1"),
        ({"dagger_steps": 0}, "imitation.dagger_steps must be a positive integer, got 0"),
        ([1, 2], "imitation must be a map"),
    ],
)
def test_bad_imitation_settings_name_the_problem(values, message):
    with pytest.raises(ValueError, match=message):
        ImitationSettings.from_dict(values)


def _train(tmp_path: Path, entry: dict) -> subprocess.CompletedProcess[str]:
    config = tmp_path / "imitation.yml"
    config.write_text(yaml.safe_dump({"GCCPPlanner-v0": entry}))
    args = ["train", "--stage", "planner", "--config", str(config), "--log-folder", "runs", "--no-progress"]
    return subprocess.run(
        [sys.executable, "-m", "sb3_gccp.cli", *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_planner_stage_clones_then_saves_without_ppo_steps(tmp_path):
    entry = {
        **TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"],
        "n_timesteps": 0,
        "imitation": {"expert_steps": 40, "epochs": 2, "batch_size": 20},
    }
    result = _train(tmp_path, entry)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "planner").iterdir()
    record = json.loads((run / "imitation.json").read_text())
    assert record["settings"]["expert_steps"] == 40 and len(record["epochs"]) == 2
    assert MaskablePPO.load(run / "planner.zip").num_timesteps == 0


def test_dagger_rounds_let_the_policy_drive_and_the_expert_label(tmp_path):
    entry = {
        **TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"],
        "n_timesteps": 0,
        "imitation": {
            "expert": "search",
            "expert_steps": 30,
            "epochs": 1,
            "batch_size": 20,
            "dagger_rounds": 2,
            "dagger_steps": 20,
        },
    }
    result = _train(tmp_path, entry)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "planner").iterdir()
    record = json.loads((run / "imitation.json").read_text())
    assert [r["data_steps"] for r in record["dagger"]] == [50, 70]
    assert all(0.0 <= r["policy_agreed"] <= 1.0 and len(r["epochs"]) == 1 for r in record["dagger"])


def test_dagger_data_are_the_drivers_states_with_the_experts_actions():
    always_right = lambda obs, mask: int(np.flatnonzero(mask)[-1])  # noqa: E731
    data = collect_expert(WORLD, 40, seed=1, driver=always_right)
    expert = ScriptedPlanner(WORLD)
    labels = [expert({k: v[i] for k, v in data.obs.items()}, data.masks[i]) for i in range(40)]
    assert data.actions.tolist() == labels
    drove = [always_right(None, m) for m in data.masks]
    assert data.agreement == np.mean(np.array(drove) == data.actions)
    merged = data + collect_expert(WORLD, 10, seed=2)
    assert len(merged.actions) == 50 and merged.obs["goal"].shape[0] == 50
    assert merged.agreement == (data.agreement * 40 + 10) / 50


def test_zero_ppo_steps_without_imitation_and_a_bad_imitation_key_are_one_line_errors(tmp_path):
    entry = {**TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"], "n_timesteps": 0}
    result = _train(tmp_path, entry)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "sb3_gccp: error: n_timesteps must be positive and n_envs positive"
    ]
    result = _train(tmp_path, {**entry, "imitation": {"epoch": 1}})
    assert result.returncode == 2
    assert "epoch" in result.stderr and len(result.stderr.strip().splitlines()) == 1
