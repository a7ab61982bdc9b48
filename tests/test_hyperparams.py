"""Zoo-style hyperparameter files: loading, key checks, class names and the paper's step schedule."""

from __future__ import annotations

import pytest
from sb3_contrib import MaskablePPO
from torch import nn

from sb3_gccp.hyperparams import (
    HyperparamsError,
    StepSchedule,
    check_keys,
    default_config_file,
    load_hyperparams,
    off_policy_gradient_steps_per_timestep,
    resolve_class,
    resolve_policy_kwargs,
    resolve_schedule,
)


def test_shipped_planner_config_is_valid():
    settings = load_hyperparams(default_config_file("ppo_mask.yml"), "GCCPPlanner-v0")
    check_keys({k: v for k, v in settings.items() if k != "imitation"}, MaskablePPO)
    assert settings["policy"] == "MotionPlannerPolicy"
    assert settings["n_epochs"] == 5  # paper: K_m = 5
    # PPO refines a cloned planner: the paper's 1e-4 -> 1e-5 after 2000 gradient steps.
    assert settings["learning_rate"] == {"initial": 1e-4, "final": 1e-5, "after_gradient_steps": 2000}


def test_shipped_planner_is_trained_in_the_world_the_decider_runs_it_in():
    """The option env runs the frozen planner under the decider entry's road-keeping keys; the planner
    entry trains it under the same ones, with a teacher its expert class accepts."""
    from gccp_envs.config import IntersectionConfig
    from sb3_gccp.training.imitation import EXPERTS

    planner = load_hyperparams(default_config_file("ppo_mask.yml"), "GCCPPlanner-v0")
    decider = load_hyperparams(default_config_file("ppo_mask.yml"), "GCCPDecider-v0")
    for key in ("mask_drive_on", "mask_lookahead", "rear_axle_offset"):
        default = getattr(IntersectionConfig(), key)
        assert planner["env_kwargs"].get(key, default) == decider["env_kwargs"].get(key, default), key
    assert planner["env_kwargs"]["mask_drive_on"] == 10.0
    imitation = planner["imitation"]
    teacher = EXPERTS[imitation["expert"]](IntersectionConfig(), **imitation["expert_kwargs"])
    assert teacher.brake_behind and teacher.brake_behind_heading == pytest.approx(0.1)


def test_missing_entry_and_bad_yaml(tmp_path):
    file = tmp_path / "h.yml"
    file.write_text("CartPole-v1: {n_envs: 1}\n")
    with pytest.raises(HyperparamsError, match="no entry for GCCPPlanner-v0 \\(entries: CartPole-v1\\)"):
        load_hyperparams(file, "GCCPPlanner-v0")
    file.write_text("GCCPPlanner-v0: [unclosed\n")
    with pytest.raises(HyperparamsError, match="not valid YAML"):
        load_hyperparams(file, "GCCPPlanner-v0")
    with pytest.raises(HyperparamsError, match="not found"):
        load_hyperparams(tmp_path / "missing.yml", "GCCPPlanner-v0")


def test_unknown_key_names_it_with_a_hint():
    with pytest.raises(HyperparamsError, match="'n_step' \\(did you mean 'n_steps'\\?\\)"):
        check_keys({"n_step": 8, "gamma": 0.9}, MaskablePPO)
    with pytest.raises(HyperparamsError, match=r"unsupported .*normalize"):
        check_keys({"normalize": True}, MaskablePPO)


def test_yaml_is_never_evaluated(tmp_path):
    file = tmp_path / "h.yml"
    file.write_text('GCCPPlanner-v0:\n  policy_kwargs: "dict(net_arch=[8])"\n')
    settings = load_hyperparams(file, "GCCPPlanner-v0")
    assert settings["policy_kwargs"] == "dict(net_arch=[8])"  # a string, as written


def test_resolve_class_by_alias_and_dotted_path():
    assert (
        resolve_class("MultiInputPolicy", MaskablePPO.policy_aliases)
        is MaskablePPO.policy_aliases["MultiInputPolicy"]
    )
    assert resolve_class("sb3_contrib.MaskablePPO") is MaskablePPO
    with pytest.raises(HyperparamsError, match="unknown class name 'Nope'"):
        resolve_class("Nope")
    with pytest.raises(HyperparamsError, match="cannot import"):
        resolve_class("sb3_gccp.nothing.Here")


def test_step_schedule_switches_after_the_paper_gradient_steps():
    # PPO with n_epochs 5 and batch 256 takes 5/256 gradient steps per env step: 2000 gradient steps
    # happen after 102400 env steps, 34.13 % of a 300k budget.
    schedule = resolve_schedule(
        {"initial": 1e-4, "final": 1e-5, "after_gradient_steps": 2000}, "learning_rate", 5 / 256, 300_000
    )
    assert isinstance(schedule, StepSchedule)
    assert schedule.switch_remaining == pytest.approx(1 - 102_400 / 300_000)
    assert schedule(1.0) == 1e-4
    assert schedule(1 - 102_000 / 300_000) == 1e-4
    assert schedule(1 - 103_000 / 300_000) == 1e-5
    assert resolve_schedule(3e-4, "learning_rate", 1.0, 10) == 3e-4
    with pytest.raises(HyperparamsError, match="learning_rate must be a number"):
        resolve_schedule("lin_1e-4", "learning_rate", 1.0, 10)


def test_off_policy_gradient_steps_per_timestep():
    defaults = {"train_freq": 1, "gradient_steps": 1}
    assert off_policy_gradient_steps_per_timestep({}, defaults) == 1.0
    assert off_policy_gradient_steps_per_timestep({"train_freq": 4, "n_envs": 2}, defaults) == 1 / 8
    assert (
        off_policy_gradient_steps_per_timestep({"train_freq": [8, "step"], "gradient_steps": 2}, defaults)
        == 1 / 4
    )
    # -1: one gradient step per collected transition, whatever the number of envs.
    assert off_policy_gradient_steps_per_timestep({"gradient_steps": -1, "n_envs": 4}, defaults) == 1.0
    with pytest.raises(HyperparamsError, match="train_freq in steps"):
        off_policy_gradient_steps_per_timestep({"train_freq": [1, "episode"]}, defaults)


def test_policy_kwargs_classes_are_imported_from_dotted_paths():
    resolved = resolve_policy_kwargs(
        {"activation_fn": "torch.nn.Tanh", "net_arch": [8], "features_extractor_kwargs": {"name": "x.Y"}}
    )
    assert resolved == {
        "activation_fn": nn.Tanh,
        "net_arch": [8],
        "features_extractor_kwargs": {"name": "x.Y"},
    }
    with pytest.raises(HyperparamsError, match=r"cannot import 'sb3_gccp\.policies\.Nope'"):
        resolve_policy_kwargs({"features_extractor_class": "sb3_gccp.policies.Nope"})
