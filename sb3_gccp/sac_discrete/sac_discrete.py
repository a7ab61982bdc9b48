"""SAC-Discrete: soft actor-critic for discrete actions (Christodoulou 2019)."""

from __future__ import annotations

import math
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import (
    GymEnv,
    MaybeCallback,
    PyTorchObs,
    ReplayBufferSamples,
    Schedule,
)
from stable_baselines3.common.utils import get_parameters_by_name, polyak_update

from sb3_gccp.action_masks import MaskedRandomActions
from sb3_gccp.sac_discrete.policies import (
    Actor,
    CnnPolicy,
    DiscreteCritic,
    MlpPolicy,
    MultiInputPolicy,
    SACDiscretePolicy,
)

SelfSACDiscrete = TypeVar("SelfSACDiscrete", bound="SACDiscrete")

TARGET_ENTROPY_RATIO = 0.6
"""``target_entropy="auto"``: this fraction of the uniform policy's entropy log(n_actions). The paper's
0.98 keeps the policy near uniform, so with few actions it never commits (a known problem)."""


class SACDiscrete(MaskedRandomActions, OffPolicyAlgorithm):
    """Soft Actor-Critic for discrete action spaces (SAC-Discrete).

    Paper: https://arxiv.org/abs/1910.07207 (Christodoulou 2019, "Soft Actor-Critic for Discrete Action
    Settings"). The actor gives pi(.|s) over all actions and the critics Q(s, .) for all actions, so
    every expectation over actions is an exact sum instead of a sample:

    - critic target: y = r + gamma (1 - done) V(s'), with the soft state value
      V(s') = sum_a pi(a|s') [min_i Q'_i(s', a) - alpha log pi(a|s')] of the target critics Q'_i;
    - actor loss: sum_a pi(a|s) [alpha log pi(a|s) - min_i Q_i(s, a)];
    - temperature loss: log(alpha) (H(pi(.|s)) - target entropy), alpha learned through its log.

    The target critics follow the critics by Polyak averaging (``tau``) every ``target_update_interval``
    gradient steps.

    With action masks in the observations (:mod:`sb3_gccp.action_masks`), pi is a masked softmax: the
    masked actions have probability zero in every sum above, and warm-up actions are drawn from the
    allowed ones.

    :param policy: the policy (``MlpPolicy``, ``CnnPolicy``, ``MultiInputPolicy`` or a class)
    :param env: the environment (or its registered id); its action space must be ``Discrete``
    :param learning_rate: learning rate of the actor, the critics and the temperature, or a schedule of
        the remaining progress (1 to 0)
    :param buffer_size: replay buffer capacity
    :param learning_starts: transitions collected with uniformly random actions before learning starts
    :param batch_size: minibatch size of each gradient step
    :param tau: soft update coefficient of the target critics (1: hard copy)
    :param gamma: discount factor
    :param train_freq: update the model every ``train_freq`` steps, or a tuple like ``(2, "episode")``
    :param gradient_steps: gradient steps after each rollout; -1: as many as transitions collected
    :param replay_buffer_class: replay buffer class (default: selected from the observation space)
    :param replay_buffer_kwargs: its keyword arguments
    :param optimize_memory_usage: SB3's memory-efficient replay buffer variant
    :param n_steps: n-step returns for the critic target (SB3's ``NStepReplayBuffer``; not for Dict
        observations)
    :param ent_coef: the temperature alpha: a float keeps it fixed; ``"auto"`` learns it from 1.0,
        ``"auto_0.1"`` from 0.1
    :param target_update_interval: update the target critics every this many gradient steps
    :param target_entropy: the policy entropy (in nats) the learned temperature aims at: a float;
        ``"auto"`` for :data:`TARGET_ENTROPY_RATIO` times log(n_actions); ``"auto_0.3"`` for another
        fraction of log(n_actions)
    :param max_grad_norm: clip the actor's and the critics' gradient norms to this; ``None``: no clipping
    :param stats_window_size: episodes averaged in the rollout logs
    :param tensorboard_log: tensorboard log folder (``None``: no tensorboard)
    :param policy_kwargs: keyword arguments of the policy (see :class:`SACDiscretePolicy`)
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: seed of the random generators
    :param device: torch device ("cpu", "cuda", "auto")
    :param _init_setup_model: whether to build the networks now
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: SACDiscretePolicy
    actor: Actor
    critic: DiscreteCritic
    critic_target: DiscreteCritic

    def __init__(
        self,
        policy: str | type[SACDiscretePolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        max_grad_norm: float | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            support_multi_env=True,
        )
        self.ent_coef = ent_coef
        self.target_entropy = target_entropy
        self.target_update_interval = target_update_interval
        self.max_grad_norm = max_grad_norm
        self.log_ent_coef: th.Tensor | None = None
        self.ent_coef_optimizer: th.optim.Adam | None = None
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        # Checked here rather than through SB3's ``supported_action_spaces``, whose failure is an assert.
        if not isinstance(self.action_space, spaces.Discrete) or self.action_space.start != 0:
            raise ValueError(
                f"SACDiscrete needs a Discrete action space starting at 0, got {self.action_space}"
            )
        super()._setup_model()
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target
        self.batch_norm_stats = get_parameters_by_name(self.critic, ["running_"])
        self.batch_norm_stats_target = get_parameters_by_name(self.critic_target, ["running_"])
        self.target_entropy = resolve_target_entropy(self.target_entropy, int(self.action_space.n))
        if isinstance(self.ent_coef, str):
            init_value = _auto_value(self.ent_coef, "ent_coef", default=1.0)
            if init_value <= 0.0:
                raise ValueError(f"the initial ent_coef must be positive, got {self.ent_coef!r}")
            self.log_ent_coef = th.full((1,), math.log(init_value), device=self.device, requires_grad=True)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=self.lr_schedule(1))
        else:
            self.ent_coef_tensor = th.tensor(float(self.ent_coef), device=self.device)

    def current_ent_coef(self) -> th.Tensor:
        """The temperature alpha, detached from the graph of its loss."""
        if self.log_ent_coef is not None:
            return th.exp(self.log_ent_coef.detach())
        return self.ent_coef_tensor

    def critic_target_values(self, replay_data: ReplayBufferSamples, ent_coef: th.Tensor) -> th.Tensor:
        """TD targets y = r + gamma (1 - done) V(s'), V(s') the exact soft state value of the target critics.

        :param replay_data: a replay minibatch
        :param ent_coef: the temperature alpha
        :return: (B, 1) targets, without gradient
        """
        with th.no_grad():
            log_probs = self.actor.action_log_probs(replay_data.next_observations)
            next_q = self.critic_target(replay_data.next_observations).min(dim=0).values
            soft_value = (log_probs.exp() * (next_q - ent_coef * log_probs)).sum(dim=-1, keepdim=True)
            # n-step replay buffers discount each sample by gamma ** (its steps).
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
            return replay_data.rewards + (1 - replay_data.dones) * discounts * soft_value

    def critic_loss(self, replay_data: ReplayBufferSamples, targets: th.Tensor) -> th.Tensor:
        """Half the sum over the critics of the mean squared TD error of the taken actions.

        :param replay_data: a replay minibatch
        :param targets: (B, 1) TD targets
        :return: the loss (scalar)
        """
        q_values = self.critic(replay_data.observations)
        actions = replay_data.actions.long().expand(q_values.shape[0], -1, -1)
        taken = q_values.gather(dim=-1, index=actions)
        return 0.5 * ((taken - targets) ** 2).mean(dim=(1, 2)).sum()

    def actor_loss(self, observations: PyTorchObs, ent_coef: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """The expected soft policy loss sum_a pi(a|s) [alpha log pi(a|s) - min_i Q_i(s, a)], and the entropy.

        :param observations: a batch of observations
        :param ent_coef: the temperature alpha
        :return: the loss (scalar) and the (B,) entropies H(pi(.|s)), detached
        """
        log_probs = self.actor.action_log_probs(observations)
        with th.no_grad():
            q_values = self.critic(observations).min(dim=0).values
        probs = log_probs.exp()
        loss = (probs * (ent_coef * log_probs - q_values)).sum(dim=-1).mean()
        return loss, -(probs * log_probs).sum(dim=-1).detach()

    def ent_coef_loss(self, entropy: th.Tensor) -> th.Tensor:
        """Temperature loss log(alpha) (H - target entropy): alpha falls while the policy is more random.

        :param entropy: (B,) entropies of the current policy
        :return: the loss (scalar)
        """
        assert self.log_ent_coef is not None and isinstance(self.target_entropy, float)
        return (self.log_ent_coef * (entropy - self.target_entropy)).mean()

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """Update the critics, the actor and the temperature, in this order, on replay minibatches.

        :param gradient_steps: number of gradient steps
        :param batch_size: minibatch size
        """
        assert self.replay_buffer is not None
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        logs: dict[str, list[float]] = {"actor_loss": [], "critic_loss": [], "ent_coef": [], "entropy": []}
        for _ in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            ent_coef = self.current_ent_coef()
            critic_loss = self.critic_loss(replay_data, self.critic_target_values(replay_data, ent_coef))
            self._step(self.critic.optimizer, critic_loss)
            actor_loss, entropy = self.actor_loss(replay_data.observations, ent_coef)
            self._step(self.actor.optimizer, actor_loss)
            if self.ent_coef_optimizer is not None:
                ent_coef_loss = self.ent_coef_loss(entropy)
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()
                logs.setdefault("ent_coef_loss", []).append(ent_coef_loss.item())
            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
            for key, value in (
                ("actor_loss", actor_loss),
                ("critic_loss", critic_loss),
                ("ent_coef", ent_coef),
                ("entropy", entropy.mean()),
            ):
                logs[key].append(value.item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(f"train/{key}", np.mean(values))

    def _step(self, optimizer: th.optim.Optimizer, loss: th.Tensor) -> None:
        """One optimiser step on ``loss``, with the gradient norm clipped to ``max_grad_norm`` if set."""
        optimizer.zero_grad()
        loss.backward()
        if self.max_grad_norm is not None:
            parameters = [p for group in optimizer.param_groups for p in group["params"]]
            th.nn.utils.clip_grad_norm_(parameters, self.max_grad_norm)
        optimizer.step()

    def learn(
        self: SelfSACDiscrete,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "SACDiscrete",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfSACDiscrete:
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "actor", "critic", "critic_target"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        if self.ent_coef_optimizer is not None:
            return [*state_dicts, "ent_coef_optimizer"], ["log_ent_coef"]
        return state_dicts, ["ent_coef_tensor"]


def resolve_target_entropy(target_entropy: str | float, n_actions: int) -> float:
    """The target entropy in nats: a number as given, or ``"auto"`` / ``"auto_<ratio>"`` as a fraction of
    log(n_actions) (``"auto"``: :data:`TARGET_ENTROPY_RATIO`).

    :param target_entropy: the ``target_entropy`` argument of :class:`SACDiscrete`
    :param n_actions: number of discrete actions
    :return: the target entropy
    """
    if not isinstance(target_entropy, str):
        return float(target_entropy)
    ratio = _auto_value(target_entropy, "target_entropy", default=TARGET_ENTROPY_RATIO)
    if not 0.0 < ratio <= 1.0:
        raise ValueError(f"the target entropy ratio must be in (0, 1], got {target_entropy!r}")
    return ratio * math.log(n_actions)


def _auto_value(value: str, name: str, default: float) -> float:
    """The number of ``"auto_<number>"``, or ``default`` for ``"auto"``."""
    head, _, number = value.partition("_")
    if head != "auto":
        raise ValueError(f"{name} must be a number, 'auto' or 'auto_<number>', got {value!r}")
    try:
        return float(number) if number else default
    except ValueError as err:
        raise ValueError(f"{name} must be a number, 'auto' or 'auto_<number>', got {value!r}") from err
