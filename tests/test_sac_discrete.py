"""SAC-Discrete: exact expectations in its losses, SB3 integration, Dict observations, the zoo launcher."""

from __future__ import annotations

import math
import subprocess
import sys
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from helpers import TINY_ENCODER, run_zoo
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from torch import nn

from sb3_gccp.action_masks import ActionMaskObservation
from sb3_gccp.hyperparams import (
    check_keys,
    default_config_file,
    load_hyperparams,
    resolve_policy_kwargs,
)
from sb3_gccp.policies import PlannerFeaturesExtractor
from sb3_gccp.sac_discrete import SACDiscrete
from sb3_gccp.sac_discrete.sac_discrete import TARGET_ENTROPY_RATIO, resolve_target_entropy

TINY_MLP = {"net_arch": [16]}
TINY_WORLD = {"spawn_probability": 0.0, "warmup_time": 0.0, "duration": 3.0}
"""An empty road and 3 s episodes: a flat-env run of a few hundred steps takes seconds."""


def tiny_cartpole(**kwargs: Any) -> SACDiscrete:
    settings: dict[str, Any] = {"policy_kwargs": TINY_MLP, "learning_starts": 32, "batch_size": 8, "seed": 0}
    return SACDiscrete("MlpPolicy", "CartPole-v1", **{**settings, **kwargs})


def from_shipped_config(env_id: str, **overrides: Any) -> tuple[SACDiscrete, int]:
    """The model of an entry of ``zoo_configs/sac_discrete.yml`` and its budget."""
    settings = load_hyperparams(default_config_file("sac_discrete.yml"), env_id)
    masked = settings.pop("action_masks", False)
    check_keys(settings, SACDiscrete)
    settings.update(overrides)
    n_timesteps = int(settings.pop("n_timesteps"))
    policy = settings.pop("policy")
    settings.pop("n_envs", None)
    env = gym.make(env_id, **settings.pop("env_kwargs", {}))
    env = ActionMaskObservation(env) if masked else env
    policy_kwargs = resolve_policy_kwargs(settings.pop("policy_kwargs", {}))
    return SACDiscrete(policy, env, policy_kwargs=policy_kwargs, **settings), n_timesteps


def set_output(net: nn.Sequential, values: list[float]) -> None:
    """Make an MLP output ``values`` whatever its input: zero weights and a bias in its last layer."""
    last = net[-1]
    assert isinstance(last, nn.Linear)
    with th.no_grad():
        last.weight.zero_()
        last.bias.copy_(th.tensor(values))


def batch(rewards: list[float], dones: list[float], actions: list[int]) -> ReplayBufferSamples:
    """A CartPole minibatch with the given rewards, dones and actions (the observations do not matter)."""
    size = len(rewards)
    observations = th.randn(size, 4)
    return ReplayBufferSamples(
        observations=observations,
        actions=th.tensor(actions).reshape(-1, 1),
        next_observations=observations + 0.1,
        dones=th.tensor(dones).reshape(-1, 1),
        rewards=th.tensor(rewards).reshape(-1, 1),
    )


@pytest.fixture
def known_model() -> SACDiscrete:
    """pi = (0.25, 0.75) everywhere; the critics (and their targets) give Q1 = (1, 2), Q2 = (3, 0)."""
    model = tiny_cartpole(ent_coef=0.5, gamma=0.9)
    set_output(model.actor.logits_net, [math.log(0.25), math.log(0.75)])
    for critic in (model.critic, model.critic_target):
        for q_net, values in zip(critic.q_networks, ([1.0, 2.0], [3.0, 0.0]), strict=True):
            assert isinstance(q_net, nn.Sequential)
            set_output(q_net, values)
    return model


# Hand computations for alpha = 0.5, pi = (0.25, 0.75), min(Q1, Q2) = (1, 0):
# V = 0.25 (1 - 0.5 ln 0.25) + 0.75 (0 - 0.5 ln 0.75); H = -(0.25 ln 0.25 + 0.75 ln 0.75).
SOFT_VALUE = 0.25 * (1 + 0.5 * 1.3862944) + 0.75 * (0.5 * 0.2876821)
ENTROPY = 0.25 * 1.3862944 + 0.75 * 0.2876821


def test_a_box_action_space_is_rejected():
    with pytest.raises(ValueError, match="SACDiscrete needs a Discrete action space"):
        SACDiscrete("MlpPolicy", "Pendulum-v1")


def test_critic_target_is_the_exact_soft_state_value(known_model):
    data = batch(rewards=[1.0, -2.0], dones=[0.0, 1.0], actions=[0, 1])
    targets = known_model.critic_target_values(data, known_model.current_ent_coef())
    # A sampled next action would give 1 + 0.9 (1 - 0.5 ln 0.25) or 1 + 0.9 (0 - 0.5 ln 0.75), never this.
    th.testing.assert_close(targets, th.tensor([[1.0 + 0.9 * SOFT_VALUE], [-2.0]]))


def test_critic_loss_regresses_each_critic_on_the_taken_action(known_model):
    data = batch(rewards=[0.0, 0.0], dones=[0.0, 0.0], actions=[0, 1])
    targets = th.tensor([[2.0], [1.0]])
    # Critic 1 took Q = (1, 2) -> errors (-1, 1); critic 2 took Q = (3, 0) -> errors (1, -1).
    th.testing.assert_close(known_model.critic_loss(data, targets), th.tensor(0.5 * (1.0 + 1.0)))


def test_actor_loss_and_entropy_are_expectations_over_all_actions(known_model):
    loss, entropy = known_model.actor_loss(th.randn(3, 4), known_model.current_ent_coef())
    th.testing.assert_close(loss, th.tensor(-SOFT_VALUE))
    th.testing.assert_close(entropy, th.full((3,), ENTROPY))


def test_temperature_falls_above_the_target_entropy_and_rises_below():
    for entropy, direction in ((0.6, -1.0), (0.1, 1.0)):
        model = tiny_cartpole(target_entropy=0.3)  # a fresh optimiser: no momentum from the other case
        assert model.ent_coef_optimizer is not None
        before = model.current_ent_coef().item()
        model.ent_coef_optimizer.zero_grad()
        model.ent_coef_loss(th.full((4,), entropy)).backward()
        model.ent_coef_optimizer.step()
        assert direction * (model.current_ent_coef().item() - before) > 0


def test_target_entropy_options():
    assert resolve_target_entropy("auto", 6) == pytest.approx(TARGET_ENTROPY_RATIO * math.log(6))
    assert resolve_target_entropy("auto_0.98", 2) == pytest.approx(0.98 * math.log(2))
    assert resolve_target_entropy(0.25, 6) == 0.25
    for bad in ("auto_1.5", "max", "auto_x"):
        with pytest.raises(ValueError, match="target"):
            resolve_target_entropy(bad, 6)
    assert tiny_cartpole().target_entropy == pytest.approx(TARGET_ENTROPY_RATIO * math.log(2))


def test_target_critics_follow_every_target_update_interval_gradient_steps():
    model = tiny_cartpole(tau=1.0, target_update_interval=2, learning_starts=0)
    model.learn(16)  # fills the buffer: 16 gradient steps, the last one updates the targets

    def synced() -> bool:
        pairs = zip(model.critic.parameters(), model.critic_target.parameters(), strict=True)
        return all(th.equal(a, b) for a, b in pairs)

    assert synced()
    model.train(gradient_steps=1, batch_size=8)
    assert not synced()
    model.train(gradient_steps=1, batch_size=8)
    assert synced()


def test_gradients_are_clipped_to_max_grad_norm():
    model = tiny_cartpole(max_grad_norm=1e-3)
    data = batch(rewards=[100.0] * 4, dones=[0.0] * 4, actions=[0, 1, 0, 1])
    model._step(model.critic.optimizer, model.critic_loss(data, th.full((4, 1), 100.0)))
    grads = [p.grad for p in model.critic.parameters() if p.grad is not None]
    assert grads and th.linalg.vector_norm(th.stack([g.norm() for g in grads])) <= 1e-3 + 1e-9


def test_deterministic_predict_is_the_most_probable_action():
    model = tiny_cartpole()
    env = gym.make("CartPole-v1")
    obs = np.stack([env.observation_space.sample() for _ in range(64)])
    actions, _ = model.predict(obs, deterministic=True)
    with th.no_grad():
        log_probs = model.actor.action_log_probs(th.as_tensor(obs))
    np.testing.assert_array_equal(actions, log_probs.argmax(-1).numpy())
    set_output(model.actor.logits_net, [0.0, 0.0])  # uniform: sampling must give both actions
    sampled, _ = model.predict(obs, deterministic=False)
    assert set(sampled.tolist()) == {0, 1}


def test_training_logs_losses_temperature_and_entropy():
    model = tiny_cartpole()
    model.learn(64, log_interval=None)
    logged = model.logger.name_to_value
    for key in (
        "train/actor_loss",
        "train/critic_loss",
        "train/ent_coef",
        "train/entropy",
        "train/ent_coef_loss",
    ):
        assert key in logged, key
    assert 0.0 < logged["train/entropy"] <= math.log(2) + 1e-6
    assert logged["train/n_updates"] == 64 - 32


def test_saved_model_predicts_identically_in_a_fresh_process(tmp_path):
    model = tiny_cartpole()
    model.learn(64)
    model.save(tmp_path / "sac.zip")
    obs = np.stack([gym.make("CartPole-v1").observation_space.sample() for _ in range(16)])
    with th.no_grad():
        log_probs = model.actor.action_log_probs(th.as_tensor(obs)).numpy()
    np.save(tmp_path / "obs.npy", obs)
    code = (
        "import sys, numpy as np, torch as th, sb3_gccp\n"
        "from sb3_gccp.sac_discrete import SACDiscrete\n"
        "model = SACDiscrete.load(sys.argv[1] + '/sac.zip')\n"
        "obs = np.load(sys.argv[1] + '/obs.npy')\n"
        "with th.no_grad():\n"
        "    log_probs = model.actor.action_log_probs(th.as_tensor(obs)).numpy()\n"
        "np.save(sys.argv[1] + '/log_probs.npy', log_probs)\n"
        "print(model.num_timesteps, model.current_ent_coef().item())\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]
    np.testing.assert_array_equal(np.load(tmp_path / "log_probs.npy"), log_probs)
    steps, ent_coef = result.stdout.split()
    assert int(steps) == 64 and float(ent_coef) == pytest.approx(model.current_ent_coef().item())
    assert float(ent_coef) != 1.0  # the temperature was learned, and its value saved


@pytest.mark.parametrize("share", [False, True])
def test_dict_observations_train_with_the_planner_features_extractor(share):
    env = gym.make("GCCPFlat-v0", **TINY_WORLD)
    model = SACDiscrete(
        "MultiInputPolicy",
        env,
        policy_kwargs={
            "features_extractor_class": PlannerFeaturesExtractor,
            "features_extractor_kwargs": {"encoder": TINY_ENCODER},
            "net_arch": [16],
            "share_features_extractor": share,
        },
        buffer_size=200,
        learning_starts=40,
        batch_size=8,
        seed=0,
    )
    extractor = model.critic.features_extractor
    assert isinstance(extractor, PlannerFeaturesExtractor)
    assert (model.actor.features_extractor is extractor) is share
    assert model.critic_target.features_extractor is not extractor
    actor_optimized = {id(p) for group in model.actor.optimizer.param_groups for p in group["params"]}
    assert actor_optimized.isdisjoint(map(id, model.actor.features_extractor.parameters())) is share
    before = [p.detach().clone() for p in extractor.parameters()]
    model.learn(80)
    assert model._n_updates == 40
    assert any(not th.equal(a, b) for a, b in zip(before, extractor.parameters(), strict=True))
    action, _ = model.predict(env.observation_space.sample(), deterministic=True)
    assert env.action_space.contains(int(action))


def test_shipped_flat_config_builds_its_model():
    model, n_timesteps = from_shipped_config("GCCPFlat-v0", buffer_size=100)
    assert isinstance(model.critic.features_extractor, PlannerFeaturesExtractor)
    assert n_timesteps > 0


def test_zoo_launcher_trains_cartpole_and_evaluates(tmp_path):
    pytest.importorskip("rl_zoo3")
    tiny = {
        "CartPole-v1": {
            "n_timesteps": 200,
            "policy": "MlpPolicy",
            "learning_starts": 100,
            "batch_size": 16,
            "learning_rate": {"initial": 1e-3, "final": 1e-4, "after_gradient_steps": 50},
            "policy_kwargs": {"net_arch": [16], "activation_fn": "torch.nn.Tanh"},
        }
    }
    (tmp_path / "tiny.yml").write_text(yaml.safe_dump(tiny))
    args = ["--algo", "sac_discrete", "--env", "CartPole-v1", "--conf-file", "tiny.yml", "-f", "logs"]
    args += ["--eval-freq", "100", "--eval-episodes", "1", "--seed", "0", "--vec-env", "dummy"]
    result = run_zoo(tmp_path, *args)
    assert result.returncode == 0, result.stderr[-2000:]
    run = tmp_path / "logs" / "sac_discrete" / "CartPole-v1_1"
    assert (run / "evaluations.npz").is_file()  # evaluated without action masks
    model = SACDiscrete.load(run / "CartPole-v1.zip")
    assert model.num_timesteps == 200 and model._n_updates == 100
    assert model.policy.activation_fn is nn.Tanh  # the dotted path in policy_kwargs was imported
    # One gradient step per env step: the step falls after 50 of the 200 steps, at 75 % remaining.
    assert (model.lr_schedule(0.76), model.lr_schedule(0.74)) == (1e-3, 1e-4)


def cartpole_return(model: SACDiscrete, episodes: int) -> float:
    """Mean return of deterministic CartPole episodes from fixed seeds."""
    env = gym.make("CartPole-v1")
    env.reset(seed=100)
    mean, _ = evaluate_policy(model, env, n_eval_episodes=episodes, deterministic=True, warn=False)
    return float(mean)


def test_two_thousand_steps_lift_cartpole_clearly_above_chance():
    # Seeds 0-5 measured 193-255 (10 episodes); random actions average about 22.
    model, _ = from_shipped_config("CartPole-v1", seed=0, learning_starts=500)
    assert cartpole_return(model, 10) < 60
    model.learn(2000)
    assert cartpole_return(model, 10) >= 120


@pytest.mark.slow
def test_learns_cartpole_with_the_shipped_hyperparameters():
    model, n_timesteps = from_shipped_config("CartPole-v1", seed=0)
    model.learn(n_timesteps)
    assert cartpole_return(model, 20) >= 475
