"""Behaviour cloning of the scripted planner: data collection, cloning, the planner stage's key."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from helpers import TINY_ENCODER, TINY_PLANNER_HYPERPARAMS, run_cli
from sb3_contrib import MaskablePPO

from gccp_envs.config import IntersectionConfig
from gccp_envs.scripted import ScriptedPlanner, SearchPlanner
from sb3_gccp.policies import MotionPlannerPolicy
from sb3_gccp.training.imitation import (
    BehaviourCloningCallback,
    ExpertData,
    ImitationSettings,
    clone,
    collect_expert,
    discounted_returns,
    policy_driver,
)

WORLD = IntersectionConfig(spawn_probability=0.0, warmup_time=0.0, duration=4.0)
TINY_POLICY = {"encoder": TINY_ENCODER, "net_arch": {"pi": [8], "vf": [8]}}


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


def test_the_expert_takes_its_keyword_arguments():
    strict = {"max_lateral_acceleration": 0.5}
    data = collect_expert(WORLD, 30, seed=5, expert="search", expert_kwargs=strict)
    states = [{key: value[k] for key, value in data.obs.items()} for k in range(30)]
    limited, free = SearchPlanner(WORLD, **strict), SearchPlanner(WORLD)
    assert [limited(obs, data.masks[k]) for k, obs in enumerate(states)] == list(data.actions)
    assert [free(obs, data.masks[k]) for k, obs in enumerate(states)] != list(data.actions)


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


def test_returns_are_discounted_to_the_end_of_each_episode():
    rewards = np.array([1.0, 1.0, 1.0, 2.0, 2.0])
    ends = np.array([False, False, True, False, False])
    np.testing.assert_allclose(discounted_returns(rewards, ends, 0.5), [1.75, 1.5, 1.0, 3.0, 2.0], rtol=1e-6)


def test_expert_data_carry_the_driven_episodes_returns_and_survive_a_save(tmp_path):
    data = collect_expert(WORLD, 50, seed=3, gamma=0.9)
    rewards_sum_bound = 50 * (1.0 + 0.05 + 0.5 * np.pi)
    assert data.returns.shape == (50,) and np.all(np.abs(data.returns) < rewards_sum_bound)
    assert len(np.unique(data.returns)) > 10
    data.save(tmp_path / "data.npz")
    loaded = ExpertData.load(tmp_path / "data.npz")
    for key, value in data.obs.items():
        np.testing.assert_array_equal(loaded.obs[key], value)
    np.testing.assert_array_equal(loaded.returns, data.returns)
    assert (loaded.episodes, loaded.agreement) == (data.episodes, data.agreement)


def test_cloning_with_a_value_weight_fits_the_value_head_to_the_returns():
    data = collect_expert(WORLD, 200, seed=0)
    env = gym.make("GCCPPlanner-v0", config=WORLD)
    th.manual_seed(0)
    model = MaskablePPO("MultiInputPolicy", env, policy_kwargs={"net_arch": [64]}, seed=0)
    settings = ImitationSettings(epochs=30, batch_size=50, learning_rate=1e-3, value_coef=0.5)
    history = clone(model, data, settings, seed=0)
    assert history[-1]["value_mse"] < 0.2 * history[0]["value_mse"]


def _nll(model: MaskablePPO, data: ExpertData) -> float:
    obs = {key: th.as_tensor(value) for key, value in data.obs.items()}
    with th.no_grad():
        distribution = model.policy.get_distribution(obs, action_masks=data.masks)
        return float(-distribution.log_prob(th.as_tensor(data.actions)).mean())


def _ppo_with_cloning_term(data: ExpertData, bc_steps: int) -> tuple[MaskablePPO, list[tuple[int, int]]]:
    env = gym.make("GCCPPlanner-v0", config=WORLD)
    model = MaskablePPO(
        "MultiInputPolicy",
        env,
        n_steps=32,
        batch_size=32,
        n_epochs=1,
        policy_kwargs={"net_arch": [32]},
        seed=0,
    )
    callback = BehaviourCloningCallback(data, ImitationSettings(batch_size=50, bc_steps=bc_steps), seed=0)
    seen = []
    original = callback._on_rollout_start

    def spied() -> None:
        original()
        seen.append((model._n_updates, callback.updates_seen))

    callback._on_rollout_start = spied  # type: ignore[method-assign]
    model.learn(96, callback=callback)
    return model, seen


def test_the_cloning_term_steps_after_each_ppo_update_and_pulls_towards_the_expert():
    data = collect_expert(WORLD, 100, seed=0)
    cloned, seen = _ppo_with_cloning_term(data, bc_steps=20)
    # three rollouts: the first before any update, then one after each update
    assert seen == [(0, 0), (1, 1), (2, 2)]
    plain, _ = _ppo_with_cloning_term(data, bc_steps=0)
    assert _nll(cloned, data) < _nll(plain, data) - 0.1


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"epochs": 0}, "imitation.epochs must be a positive integer"),
        ({"value_coef": -0.1}, "imitation.value_coef must be a non-negative number"),
        ({"bc_steps": -1}, "imitation.bc_steps must be a non-negative integer, got -1"),
        ({"learning_rate": -1.0}, "imitation.learning_rate must be a positive number"),
        ({"expert_step": 10}, "expert_step"),
        ({"expert": "human"}, "imitation.expert must be one of scripted, search, got 'human'"),
        ({"expert": "search", "expert_kwargs": {"speed": 1}}, "expert_kwargs for expert 'search'.*'speed'"),
        ({"expert": "search", "expert_kwargs": [1]}, "imitation.expert_kwargs must be a map"),
        (
            {"expert": "search", "expert_kwargs": {"max_lateral_acceleration": 0}},
            "max_lateral_acceleration must be positive, got 0",
        ),
        ({"dagger_rounds": -1}, "imitation.dagger_rounds must be a non-negative integer, got -1"),
        ({"dagger_steps": 0}, "imitation.dagger_steps must be a positive integer, got 0"),
        ({"dagger_epochs": 0}, "imitation.dagger_epochs must be a positive integer, got 0"),
        ([1, 2], "imitation must be a map"),
    ],
)
def test_bad_imitation_settings_name_the_problem(values, message):
    with pytest.raises(ValueError, match=message):
        ImitationSettings.from_dict(values)


def _train_args(tmp_path: Path, entry: dict) -> list[str]:
    """The planner stage's command line over a config file holding ``entry``."""
    config = tmp_path / "imitation.yml"
    config.write_text(yaml.safe_dump({"GCCPPlanner-v0": entry}))
    return ["train", "--stage", "planner", "--config", str(config), "--log-folder", "runs", "--no-progress"]


def _train(tmp_path: Path, entry: dict) -> subprocess.CompletedProcess[str]:
    return run_cli(*_train_args(tmp_path, entry), cwd=tmp_path)


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
            "dagger_epochs": 3,
        },
    }
    result = _train(tmp_path, entry)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "planner").iterdir()
    record = json.loads((run / "imitation.json").read_text())
    assert [r["data_steps"] for r in record["dagger"]] == [50, 70]
    assert all(0.0 <= r["policy_agreed"] <= 1.0 and len(r["epochs"]) == 3 for r in record["dagger"])


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


def test_two_labelling_processes_give_the_same_data_as_one():
    env = gym.make("GCCPPlanner-v0", config=WORLD)
    model = MaskablePPO(MotionPlannerPolicy, env, policy_kwargs=TINY_POLICY, seed=0)
    settings = ImitationSettings(epochs=1, batch_size=16)
    clone(model, collect_expert(WORLD, 16, seed=0), settings, seed=0)  # as DAgger's driver after a fit
    driver = policy_driver(model)  # the DAgger case: the policy must reach the processes too
    # two processes first: right after a fit, as in the planner stage, before any drive in this process
    two, one = (collect_expert(WORLD, 90, seed=7, driver=driver, workers=n) for n in (2, 1))
    assert one.episodes == two.episodes >= 2  # 4 s episodes: the processes share them
    for key, value in one.obs.items():
        np.testing.assert_array_equal(two.obs[key], value)
    np.testing.assert_array_equal(two.masks, one.masks)
    np.testing.assert_array_equal(two.actions, one.actions)
    np.testing.assert_array_equal(two.returns, one.returns)
    assert two.agreement == one.agreement < 1.0  # the untrained policy drove, not the expert


LABELLING_UNTIL_INTERRUPTED = """
import signal
signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal: Ctrl-C is not ignored
from gccp_envs.config import IntersectionConfig
from sb3_gccp.training.imitation import collect_expert
if __name__ == "__main__":
    try:
        collect_expert(IntersectionConfig(spawn_probability=0.0, duration=4.0), 20_000, seed=0, workers=2)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
"""


def _processes_in_group(group: int) -> int:
    count = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended while listed
            continue
        count += int(fields[2]) == group  # the fields after the name: state, ppid, pgrp
    return count


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="counts processes in /proc")
def test_ctrl_c_while_two_processes_label_ends_every_process(tmp_path):
    script = tmp_path / "label.py"
    script.write_text(LABELLING_UNTIL_INTERRUPTED)
    process = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while _processes_in_group(process.pid) < 4:  # the process, the fork server and its two workers
            assert process.poll() is None and time.monotonic() < deadline, "the workers never started"
            time.sleep(0.1)
        time.sleep(1.0)  # inside the episodes
        os.killpg(process.pid, signal.SIGINT)  # Ctrl-C reaches the whole group
        out, _ = process.communicate(timeout=30)  # a multiprocessing.Pool waited here for good
        assert out.decode().strip() == "interrupted"
        deadline = time.monotonic() + 10
        while _processes_in_group(process.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _processes_in_group(process.pid) == 0, "a worker was left behind"
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)


def test_expert_data_written_into_given_rows_are_the_same_and_leave_the_other_rows_alone():
    fresh = collect_expert(WORLD, 30, seed=4, expert="search")
    env = gym.make("GCCPPlanner-v0", config=WORLD)
    room = ExpertData.empty(env.observation_space, env.action_space, 50)
    room.actions[:] = -1
    filled = collect_expert(WORLD, 30, seed=4, expert="search", out=room.rows(10, 40))
    for key, value in fresh.obs.items():
        np.testing.assert_array_equal(room.obs[key][10:40], value)
        assert room.obs[key].dtype == value.dtype
    np.testing.assert_array_equal(room.masks[10:40], fresh.masks)
    np.testing.assert_array_equal(room.returns[10:40], fresh.returns)
    assert room.actions[10:40].tolist() == fresh.actions.tolist()
    assert (room.actions[:10] == -1).all() and (room.actions[40:] == -1).all()
    assert (filled.episodes, filled.agreement) == (fresh.episodes, fresh.agreement)
    with pytest.raises(ValueError, match="out holds 30 steps, not 20"):
        collect_expert(WORLD, 20, seed=4, out=room.rows(10, 40))


def test_zero_ppo_steps_without_imitation_and_a_bad_imitation_key_are_one_line_errors(tmp_path, cli_error):
    entry = {**TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"], "n_timesteps": 0}
    lines = cli_error(tmp_path, *_train_args(tmp_path, entry))
    assert lines == ["sb3_gccp: error: n_timesteps must be positive and n_envs positive"]
    (line,) = cli_error(tmp_path, *_train_args(tmp_path, {**entry, "imitation": {"epoch": 1}}))
    assert "epoch" in line


def test_the_default_planner_recipe_clones_then_trains_ppo_with_a_cloning_term():
    from sb3_gccp.hyperparams import default_config_file, load_hyperparams

    entry = load_hyperparams(default_config_file("ppo_mask.yml"), "GCCPPlanner-v0")
    settings = ImitationSettings.from_dict(entry["imitation"])
    assert entry["n_timesteps"] >= 100_000 and settings.expert == "search"
    assert settings.bc_steps > 0 and settings.value_coef > 0


def test_planner_stage_saves_the_clone_and_ppo_moves_away_from_it(tmp_path):
    entry = {
        **TINY_PLANNER_HYPERPARAMS["GCCPPlanner-v0"],
        "imitation": {"expert_steps": 40, "epochs": 1, "batch_size": 20, "value_coef": 0.5, "bc_steps": 2},
    }
    result = _train(tmp_path, entry)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs" / "planner").iterdir()
    cloned, trained = MaskablePPO.load(run / "planner_cloned.zip"), MaskablePPO.load(run / "planner.zip")
    assert cloned.num_timesteps == 0 and trained.num_timesteps >= 32
    before, after = cloned.policy.state_dict(), trained.policy.state_dict()
    assert any(not th.equal(before[name], after[name]) for name in before)
    assert len(ExpertData.load(run / "imitation_data.npz").actions) == 40
