"""Imitation pre-training of the motion-planner: behaviour cloning (and DAgger) of a scripted planner.

PPO on ``GCCPPlanner-v0`` learns to drive to subgoals but never to brake for one it should stop on
(docs/experiments/2026-11-23-ppo-planner-never-stops.md): braking is a long chain of one action whose
pay-off comes at the end. The scripted planners do stop. This module drives one on the planner env,
records (observation, action mask, action) and fits a MaskablePPO policy to it by maximum likelihood
under the same masks, so that a learned ``MotionPlannerPolicy`` starts from a planner that stops. The
expert is the pure-pursuit planner (:class:`gccp_envs.scripted.ScriptedPlanner`) or the search planner
(:class:`gccp_envs.scripted.SearchPlanner`, which reaches more subgoals); DAgger rounds then let the
cloned policy drive and the expert label where it went. The planner stage runs it before PPO when the
zoo entry has an ``imitation`` map (see :class:`ImitationSettings`).

PPO alone undoes a plain clone's braking (docs/experiments/), so cloning also fits the value head to
the returns of the driven episodes (``value_coef``: PPO's first advantages are then not noise) and,
during PPO, :class:`BehaviourCloningCallback` takes ``bc_steps`` cloning steps on the data set after
every PPO update, in the spirit of DAPG (Rajeswaran et al. 2018, https://arxiv.org/abs/1709.10087),
which adds the demonstrations' likelihood to the policy gradient.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Generator, Mapping
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy
from stable_baselines3.common.callbacks import BaseCallback

from gccp_envs.config import (
    IntersectionConfig,
    reject_unknown_keys,
    require_int,
    require_non_negative,
    require_positive,
)
from gccp_envs.planner_env import GCCPPlannerEnv
from gccp_envs.scripted import ScriptedPlanner, SearchPlanner
from sb3_gccp.frozen import FrozenPolicy
from sb3_gccp.progress import new_bar
from sb3_gccp.training.workers import start_worker_server, worker_context

EXPERTS = {"scripted": ScriptedPlanner, "search": SearchPlanner}
"""The planners the planner stage can clone, by the name the ``imitation.expert`` key takes."""
DAGGER_SEED_STRIDE = 1_000_000
"""Offset between the episode seeds of consecutive DAgger rounds."""


@dataclass(frozen=True)
class ImitationSettings:
    """The ``imitation`` map of a planner entry (ours; the paper trains the planner by PPO only)."""

    expert: str = "scripted"
    """The planner to clone: 'scripted' (pure pursuit, :class:`ScriptedPlanner`) or 'search' (earliest
    arrival over an action-sequence library, :class:`SearchPlanner`)."""
    expert_kwargs: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments of the expert's class beside the world config (for the search planner, e.g.
    ``max_lateral_acceleration``)."""
    expert_steps: int = 40_000
    """Planner-env steps the expert drives to make the data set (one env, seeded episodes)."""
    epochs: int = 4
    """Passes over the data set."""
    batch_size: int = 256
    """Transitions per gradient step."""
    learning_rate: float = 3e-4
    """Adam's learning rate of the cloning (PPO's optimiser is not touched)."""
    dagger_rounds: int = 0
    """Rounds of DAgger (Ross et al. 2011) after the first fit: the cloned policy drives, the expert
    labels every state it visits, the labelled steps join the data set and the policy is fitted again
    (``epochs`` passes), so that it learns to recover from its own mistakes. 0: behaviour cloning only."""
    dagger_steps: int = 20_000
    """Planner-env steps the cloned policy drives in each DAgger round."""
    dagger_epochs: int | None = None
    """Passes over the aggregated data set in each DAgger round (the policy starts from the last fit,
    so fewer than ``epochs`` may do); None: ``epochs``."""
    value_coef: float = 0.0
    """Weight of the value head's squared error to the driven episodes' discounted returns (PPO's
    ``gamma``) in the cloning loss. 0: the value head is left as it is."""
    bc_steps: int = 0
    """Cloning gradient steps (``batch_size`` transitions each, PPO's optimiser and learning rate) on
    the data set after every PPO update, so that PPO cannot drift far from the expert. 0: none."""
    workers: int = 1
    """Processes that drive and label the expert's and the DAgger rounds' episodes side by side (ours; a
    speed setting only: the data set is the same for any number)."""

    def __post_init__(self) -> None:
        if self.expert not in EXPERTS:
            raise ValueError(f"imitation.expert must be one of {', '.join(EXPERTS)}, got {self.expert!r}")
        if not isinstance(self.expert_kwargs, Mapping):
            raise ValueError(f"imitation.expert_kwargs must be a map, got {self.expert_kwargs!r}")
        try:  # made once with the default world, so that a bad argument fails here and not mid-stage
            EXPERTS[self.expert](IntersectionConfig(), **self.expert_kwargs)
        except (TypeError, ValueError) as error:
            raise ValueError(f"imitation.expert_kwargs for expert {self.expert!r}: {error}") from None
        for name in ("expert_steps", "epochs", "batch_size", "dagger_steps", "workers"):
            require_int(f"imitation.{name}", getattr(self, name))
        if self.dagger_epochs is not None:
            require_int("imitation.dagger_epochs", self.dagger_epochs)
        require_int("imitation.dagger_rounds", self.dagger_rounds, minimum=0)
        require_int("imitation.bc_steps", self.bc_steps, minimum=0)
        require_positive("imitation.learning_rate", self.learning_rate)
        require_non_negative("imitation.value_coef", self.value_coef)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None) -> ImitationSettings:
        """Settings from a YAML map, rejecting unknown keys by name."""
        if not isinstance(values, Mapping):
            raise ValueError(
                f"imitation must be a map of {', '.join(cls.__dataclass_fields__)}, got {values!r}"
            )
        reject_unknown_keys(values, cls, "imitation")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Plain data."""
        return asdict(self)


@dataclass
class ExpertData:
    """Steps labelled by the expert: observations (one array per key), masks, the expert's actions and
    the discounted returns of the episodes as driven."""

    obs: dict[str, np.ndarray]
    masks: np.ndarray
    actions: np.ndarray
    returns: np.ndarray
    episodes: int
    agreement: float = 1.0
    """Share of the steps where the driver took the expert's action (1 when the expert drives)."""

    @classmethod
    def empty(cls, observation_space: spaces.Space, action_space: spaces.Space, rows: int) -> ExpertData:
        """Room for ``rows`` steps of a Dict-observation, discrete-action env, to be filled in place
        (:func:`collect_expert` with ``out``)."""
        if not isinstance(observation_space, spaces.Dict) or not isinstance(action_space, spaces.Discrete):
            raise TypeError(f"expected Dict observations and Discrete actions, got {observation_space}")
        obs = {
            key: np.empty((rows, *space.shape), space.dtype)  # type: ignore[misc]
            for key, space in observation_space.spaces.items()
        }
        masks = np.empty((rows, int(action_space.n)), bool)
        return cls(obs, masks, np.empty(rows, np.int64), np.empty(rows, np.float32), 0)

    def rows(self, start: int, stop: int) -> ExpertData:
        """Steps ``start`` to ``stop`` as views: writing to them writes here."""
        return ExpertData(
            {key: value[start:stop] for key, value in self.obs.items()},
            self.masks[start:stop],
            self.actions[start:stop],
            self.returns[start:stop],
            self.episodes,
            self.agreement,
        )

    def save(self, path: Path) -> None:
        """Write the data set to a compressed ``.npz`` file (observation keys prefixed ``obs/``)."""
        arrays: dict[str, Any] = {f"obs/{key}": value for key, value in self.obs.items()}
        arrays.update(
            masks=self.masks,
            actions=self.actions,
            returns=self.returns,
            episodes=self.episodes,
            agreement=self.agreement,
        )
        with path.open("wb") as file:
            np.savez_compressed(file, **arrays)

    @classmethod
    def load(cls, path: Path) -> ExpertData:
        """The data set written by :meth:`save`."""
        with np.load(path) as saved:
            obs = {key[4:]: saved[key] for key in saved.files if key.startswith("obs/")}
            return cls(
                obs,
                saved["masks"],
                saved["actions"],
                saved["returns"],
                int(saved["episodes"]),
                float(saved["agreement"]),
            )

    def __add__(self, other: ExpertData) -> ExpertData:
        """Both data sets in one (DAgger's aggregation)."""
        return ExpertData(
            {key: np.concatenate((value, other.obs[key])) for key, value in self.obs.items()},
            np.concatenate((self.masks, other.masks)),
            np.concatenate((self.actions, other.actions)),
            np.concatenate((self.returns, other.returns)),
            self.episodes + other.episodes,
            _mean_agreement(self, other),
        )


def _mean_agreement(first: ExpertData, second: ExpertData) -> float:
    """The agreement of two data sets taken together."""
    return (first.agreement * len(first.actions) + second.agreement * len(second.actions)) / (
        len(first.actions) + len(second.actions)
    )


Driver = Callable[[dict[str, np.ndarray], np.ndarray], int]
"""A planner as a function of (observation, action mask) to an action."""


class PolicyDriver:
    """A policy's most likely action under the mask, as the frozen planner drives
    (:class:`~sb3_gccp.frozen.FrozenPolicy`: ``predict``'s action, traced). An object rather than a
    closure, so that it pickles into the processes that label in parallel.

    :param policy: the policy of the model being cloned
    """

    def __init__(self, policy: MaskableActorCriticPolicy) -> None:
        self.policy = policy
        self._frozen = FrozenPolicy(policy)

    def __getstate__(self) -> dict[str, Any]:
        # The class, its constructor's arguments and the weights, as SB3's ``policy.save`` keeps them: a
        # policy that has just been fitted holds its last distribution, whose tensors do not pickle.
        kwargs = self.policy._get_constructor_parameters()
        kwargs["lr_schedule"] = _no_learning  # the schedule of the training run may not pickle; unused here
        return {"class": type(self.policy), "kwargs": kwargs, "weights": self.policy.state_dict()}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.policy = state["class"](**state["kwargs"])
        self.policy.load_state_dict(state["weights"])
        self._frozen = FrozenPolicy(self.policy)

    def __call__(self, obs: dict[str, np.ndarray], mask: np.ndarray) -> int:
        return self._frozen(obs, mask)


def _no_learning(progress_remaining: float) -> float:
    """The learning rate of a policy that only drives."""
    return 0.0


def policy_driver(model: MaskablePPO) -> PolicyDriver:
    """The model's most likely action under the mask."""
    return PolicyDriver(model.policy)


@dataclass
class _Episode:
    """One episode as driven and labelled: per step the observation, mask, expert's action, reward,
    whether the episode ended there and whether the driver took the expert's action."""

    obs: dict[str, np.ndarray]
    masks: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    ends: np.ndarray
    agreed: np.ndarray


class _Labeller:
    """Drives whole episodes of ``GCCPPlanner-v0`` and labels every step with the expert's action.

    :param driver: who drives; None: the expert itself
    """

    def __init__(
        self, world: IntersectionConfig, expert: str, expert_kwargs: Mapping[str, Any], driver: Driver | None
    ) -> None:
        self.env = GCCPPlannerEnv(world)
        self.label = EXPERTS[expert](self.env.config, **expert_kwargs)
        self.driver = driver

    def episode(self, seed: int) -> _Episode:
        """The episode of ``reset(seed=seed)``, to its end."""
        obs, _ = self.env.reset(seed=seed)
        steps: list[tuple[dict[str, np.ndarray], np.ndarray, int, float, bool, bool]] = []
        done = False
        while not done:
            mask = self.env.action_masks()
            action = self.label(obs, mask)
            driven = action if self.driver is None else self.driver(obs, mask)
            next_obs, reward, terminated, truncated, _ = self.env.step(driven)
            done = terminated or truncated
            steps.append((obs, mask, action, float(reward), done, driven == action))
            obs = next_obs
        return _Episode(
            {key: np.stack([step[0][key] for step in steps]) for key in obs},
            np.stack([step[1] for step in steps]),
            np.array([step[2] for step in steps], np.int64),
            np.array([step[3] for step in steps]),
            np.array([step[4] for step in steps]),
            np.array([step[5] for step in steps]),
        )

    def close(self) -> None:
        self.env.close()


_worker_labeller: _Labeller | None = None
"""The labeller of a labelling process (made once per process by :func:`_start_worker`)."""


def _start_worker(
    world: IntersectionConfig,
    expert: str,
    expert_kwargs: Mapping[str, Any],
    driver: Driver | None,
    torch_threads: int,
) -> None:
    global _worker_labeller
    th.set_num_threads(torch_threads)  # as the learner's process, so that the driver's floats are its own
    _worker_labeller = _Labeller(world, expert, expert_kwargs, driver)


def _worker_episode(seed: int) -> _Episode:
    assert _worker_labeller is not None
    return _worker_labeller.episode(seed)


def _episodes(
    world: IntersectionConfig,
    seed: int,
    expert: str,
    expert_kwargs: Mapping[str, Any],
    driver: Driver | None,
    workers: int,
) -> Generator[_Episode, None, None]:
    """The episodes seeded ``seed``, ``seed + 1``, ... in that order, driven in this process or, with
    ``workers`` > 1, by that many processes, a few episodes ahead of the consumer."""
    if workers == 1:
        labeller = _Labeller(world, expert, expert_kwargs, driver)
        try:
            yield from (labeller.episode(seed + k) for k in itertools.count())
        finally:
            labeller.close()
        return
    initargs = (world, expert, dict(expert_kwargs), driver, th.get_num_threads())
    start_worker_server(__name__)  # its processes import this module
    # An executor, not a multiprocessing.Pool: a Pool whose worker died (Ctrl-C reaches the workers too)
    # waits for the lost episode for ever in join(), and its terminate() can block on the lock that an
    # idle worker holds. The executor notices a dead worker and stops.
    executor = ProcessPoolExecutor(workers, worker_context(), _start_worker, initargs)
    finished = False
    try:
        ahead = 2 * workers  # episodes asked for beyond the one awaited: no process waits for work
        pending = deque(executor.submit(_worker_episode, seed + k) for k in range(ahead))
        for k in itertools.count(ahead):
            yield pending.popleft().result()
            pending.append(executor.submit(_worker_episode, seed + k))
    except GeneratorExit:
        finished = True  # the consumer has its episodes: let the workers end the ones they are on
        raise
    finally:
        executor.shutdown(wait=finished, cancel_futures=True)


def collect_expert(
    world: IntersectionConfig,
    steps: int,
    seed: int,
    progress: bool = False,
    expert: str = "scripted",
    driver: Driver | None = None,
    gamma: float = 0.99,
    out: ExpertData | None = None,
    expert_kwargs: Mapping[str, Any] | None = None,
    workers: int = 1,
) -> ExpertData:
    """Label ``steps`` steps of ``GCCPPlanner-v0`` (episodes seeded from ``seed`` on, the last cut off
    at ``steps``) with an expert planner's actions.

    :param expert: a key of ``EXPERTS``
    :param driver: who drives (DAgger: the cloned policy, a :class:`PolicyDriver`); default the expert
    :param gamma: discount of the returns (the episode cut off by ``steps`` counts as ended there)
    :param out: where to write the steps (``steps`` rows, see :meth:`ExpertData.rows`); default new arrays
    :param expert_kwargs: keyword arguments of the expert's class beside the world config
    :param workers: processes that drive the episodes (the driver must pickle); the data are the same
        for any number
    :return: the states visited, with the expert's actions
    """
    require_int("workers", workers)
    data = out
    if data is None:
        space = GCCPPlannerEnv(world)
        data = ExpertData.empty(space.observation_space, space.action_space, steps)
        space.close()
    if len(data.actions) != steps:
        raise ValueError(f"out holds {len(data.actions)} steps, not {steps}")
    rewards, ends, agreed = np.empty(steps), np.empty(steps, bool), np.empty(steps, bool)
    filled = 0
    episodes = _episodes(world, seed, expert, expert_kwargs or {}, driver, workers)
    with new_bar(
        total=steps, enabled=progress, desc="expert steps" if driver is None else "DAgger steps"
    ) as bar:
        try:
            for episode in episodes:
                rows = slice(filled, min(steps, filled + len(episode.actions)))
                taken = rows.stop - rows.start
                for key, value in episode.obs.items():
                    data.obs[key][rows] = value[:taken]
                data.masks[rows], data.actions[rows] = episode.masks[:taken], episode.actions[:taken]
                rewards[rows], ends[rows] = episode.rewards[:taken], episode.ends[:taken]
                agreed[rows] = episode.agreed[:taken]
                filled = rows.stop
                bar.update(taken)
                if filled == steps:
                    break
        finally:
            episodes.close()  # stops the labelling processes
    data.returns[:] = discounted_returns(rewards, ends, gamma)
    return replace(data, episodes=int(ends.sum()), agreement=float(agreed.mean()))


def discounted_returns(rewards: np.ndarray, ends: np.ndarray, gamma: float) -> np.ndarray:
    """Per step, the discounted sum of the rewards to the end of its episode (``ends`` marks each
    episode's last step; the last step of the arrays ends one too)."""
    returns = np.empty(len(rewards), np.float32)
    running = 0.0
    for k in range(len(rewards) - 1, -1, -1):
        running = rewards[k] + gamma * running * (not ends[k])
        returns[k] = running
    return returns


def clone(
    model: MaskablePPO, data: ExpertData, settings: ImitationSettings, seed: int, progress: bool = False
) -> list[dict[str, float]]:
    """Fit the model's policy to the expert's actions (masked log-likelihood) and, with
    ``settings.value_coef``, its value head to the returns.

    :return: per epoch, the mean negative log-likelihood, the share of actions the policy's most
        likely action matches and the value's mean squared error
    """
    policy = model.policy
    optimizer = th.optim.Adam(policy.parameters(), lr=settings.learning_rate)
    rng = np.random.default_rng(seed)
    n = len(data.actions)
    history = []
    policy.set_training_mode(True)
    with new_bar(total=settings.epochs * n, enabled=progress, desc="cloning") as bar:
        for _ in range(settings.epochs):
            order = rng.permutation(n)
            totals = np.zeros(3)
            for start in range(0, n, settings.batch_size):
                rows = order[start : start + settings.batch_size]
                totals += cloning_step(model, data, rows, optimizer, settings.value_coef) * len(rows)
                bar.update(len(rows))
            history.append(dict(zip(("nll", "accuracy", "value_mse"), (totals / n).tolist(), strict=True)))
    policy.set_training_mode(False)
    return history


def cloning_step(
    model: MaskablePPO, data: ExpertData, rows: np.ndarray, optimizer: th.optim.Optimizer, value_coef: float
) -> np.ndarray:
    """One gradient step of the cloning loss on the data set's ``rows``.

    :return: the batch's mean negative log-likelihood, action match and value squared error
    """
    policy = model.policy
    obs = {key: th.as_tensor(value[rows], device=policy.device) for key, value in data.obs.items()}
    actions = th.as_tensor(data.actions[rows], device=policy.device)
    # evaluate_actions' forward, keeping the distribution for the action match
    latent_pi, latent_vf = policy.mlp_extractor(policy.extract_features(obs))
    distribution = policy._get_action_dist_from_latent(latent_pi)
    distribution.apply_masking(data.masks[rows])
    values, log_prob = policy.value_net(latent_vf), distribution.log_prob(actions)
    value_error = th.nn.functional.mse_loss(
        values.flatten(), th.as_tensor(data.returns[rows], device=policy.device)
    )
    nll = -log_prob.mean()
    loss = nll + value_coef * value_error if value_coef > 0 else nll
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    matched = (distribution.mode() == actions).float().mean()
    return np.array([float(nll.detach()), float(matched), float(value_error.detach())])


class BehaviourCloningCallback(BaseCallback):
    """After every PPO update, ``settings.bc_steps`` cloning steps (:func:`cloning_step`) on the expert's
    data set with PPO's own optimiser, at PPO's current learning rate.

    :param data: the data set of the cloning (expert and DAgger steps)
    :param settings: the imitation settings (``bc_steps``, ``batch_size``, ``value_coef``)
    :param seed: seed of the batch draws
    """

    def __init__(self, data: ExpertData, settings: ImitationSettings, seed: int, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.data = data
        self.settings = settings
        self.rng = np.random.default_rng(seed)
        self.updates_seen = 0

    @property
    def ppo(self) -> MaskablePPO:
        """The model being trained."""
        assert isinstance(self.model, MaskablePPO)
        return self.model

    def _on_training_start(self) -> None:
        self.updates_seen = self.model._n_updates

    def _on_rollout_start(self) -> None:
        # Rollouts start right after the previous update (none before the first).
        if self.model._n_updates == self.updates_seen:
            return
        self.updates_seen = self.model._n_updates
        if self.settings.bc_steps == 0:
            return
        policy = self.model.policy
        policy.set_training_mode(True)
        totals = np.zeros(3)
        for _ in range(self.settings.bc_steps):
            rows = self.rng.integers(len(self.data.actions), size=self.settings.batch_size)
            totals += cloning_step(self.ppo, self.data, rows, policy.optimizer, self.settings.value_coef)
        policy.set_training_mode(False)
        means = totals / self.settings.bc_steps
        for name, value in zip(("bc_nll", "bc_accuracy", "bc_value_mse"), means, strict=True):
            self.logger.record(f"imitation/{name}", value)

    def _on_step(self) -> bool:
        return True


def imitate(
    model: MaskablePPO,
    world: IntersectionConfig,
    settings: ImitationSettings,
    seed: int,
    progress: bool = False,
) -> tuple[dict[str, Any], ExpertData]:
    """Clone the expert into ``model``'s policy, then run the DAgger rounds.

    Round k's episodes are seeded from ``seed + k * DAGGER_SEED_STRIDE``, apart from the expert's.

    :return: the record written to ``imitation.json`` (the settings, the expert's episodes, the first
        fit per epoch and, per DAgger round, the episodes driven, the share of the visited steps where
        the policy already chose the expert's action, the data set's size and the fit per epoch) and
        the data set
    """
    gamma = float(model.gamma)
    # The data set grows by every DAgger round: its arrays are made once, at full size (85,000 steps of
    # 39 kB at the shipped settings), and filled in place rather than copied at each round.
    filled = settings.expert_steps
    room = ExpertData.empty(
        model.observation_space, model.action_space, filled + settings.dagger_rounds * settings.dagger_steps
    )
    data = collect_expert(
        world,
        filled,
        seed,
        progress,
        settings.expert,
        gamma=gamma,
        out=room.rows(0, filled),
        expert_kwargs=settings.expert_kwargs,
        workers=settings.workers,
    )
    record: dict[str, Any] = {
        "settings": settings.to_dict(),
        "expert_episodes": data.episodes,
        "epochs": clone(model, data, settings, seed, progress),
        "dagger": [],
    }
    dagger_fit = replace(settings, epochs=settings.dagger_epochs or settings.epochs)
    for k in range(1, settings.dagger_rounds + 1):
        visited = collect_expert(
            world,
            settings.dagger_steps,
            seed + k * DAGGER_SEED_STRIDE,
            progress,
            settings.expert,
            driver=policy_driver(model),
            gamma=gamma,
            out=room.rows(filled, filled + settings.dagger_steps),
            expert_kwargs=settings.expert_kwargs,
            workers=settings.workers,
        )
        filled += settings.dagger_steps
        data = replace(
            room.rows(0, filled),
            episodes=data.episodes + visited.episodes,
            agreement=_mean_agreement(data, visited),
        )
        record["dagger"].append(
            {
                "episodes": visited.episodes,
                "policy_agreed": visited.agreement,
                "data_steps": len(data.actions),
                "epochs": clone(model, data, dagger_fit, seed + k, progress),
            }
        )
    return record, data
