"""Training throughput of MaskablePPO + MotionPlannerPolicy on GCCPPlanner-v0 vs stock PPO + MlpPolicy.

The stock reference is SB3's PPO with its MlpPolicy on highway-env's intersection-v2 at 10 Hz
(``policy_frequency = simulation_frequency = 10``, the rest of its default config). Both runs use
2 envs in the same kind of VecEnv and the same PPO hyperparameters (by default the planner's
``zoo_configs/ppo_mask.yml``: n_steps 1024 per env, batch_size 256, n_epochs 5; pass
``--batch-size 64 --n-epochs 10`` for SB3's defaults); only ``learn()`` is timed, after one warm-up
reset that builds each process's cached road layout.

Torch threads: the main process keeps 2 (the gradient steps use both cores); the SubprocVecEnv
workers step numpy environments and are set to 1 thread, so they never oversubscribe the cores.

Run: python benchmarks/train_speed.py [--timesteps 8192] [--vec-env subproc|dummy]
Last line: ``ratio <ours/stock>`` (goal: above 1).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from sb3_contrib import MaskablePPO
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_gccp.policies import MotionPlannerPolicy, PlannerFeaturesExtractor

STOCK_CONFIG = {"policy_frequency": 10, "simulation_frequency": 10}
"""highway-env intersection-v2 at the planner's 10 Hz."""


def _one_thread(env_id: str, **kwargs: Any) -> gym.Env:
    """Make an env in a worker process limited to one torch thread."""
    th.set_num_threads(1)
    return gym.make(env_id, **kwargs)


def make_envs(env_id: str, n_envs: int, vec_env: str, seed: int, **env_kwargs: Any) -> VecEnv:
    """Monitor-wrapped vectorised envs, warmed up by one reset.

    :param env_id: gymnasium id, prefixed with the module that registers it ("module:id"), so that
        spawned workers import it
    :param n_envs: number of envs
    :param vec_env: 'subproc' or 'dummy'
    :param seed: seed of the first env
    :param env_kwargs: keyword arguments of ``gym.make``
    :return: the VecEnv
    """
    factory: Callable[..., gym.Env] = _one_thread if vec_env == "subproc" else gym.make
    envs = make_vec_env(
        lambda: factory(env_id, **env_kwargs),
        n_envs=n_envs,
        seed=seed,
        vec_env_cls=SubprocVecEnv if vec_env == "subproc" else DummyVecEnv,
    )
    envs.reset()
    return envs


def steps_per_second(model: BaseAlgorithm, timesteps: int) -> float:
    """Env steps per wall-clock second of ``model.learn(timesteps)``.

    :param model: the algorithm, built on warmed-up envs
    :param timesteps: training budget
    :return: steps per second
    """
    start = time.perf_counter()
    model.learn(timesteps)
    elapsed = time.perf_counter() - start
    model.get_env().close()  # type: ignore[union-attr]
    return model.num_timesteps / elapsed


def _best_ms(run: Callable[[], Any], repeats: int) -> float:
    """Best of 5 mean wall times [ms] of ``repeats`` calls, after 3 warm-up calls."""
    for _ in range(3):
        run()
    best = float("inf")
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeats):
            run()
        best = min(best, (time.perf_counter() - start) / repeats * 1e3)
    return best


def encoder_costs(seed: int) -> tuple[int, float, float]:
    """Parameters and per-sample costs of the default encoder's ego feature on real observations.

    :param seed: seed of the episode the observations come from (default traffic, random actions)
    :return: parameters, inference [us/sample] at batch 2 on 1 thread (``th.inference_mode``),
        forward + backward [us/sample] at batch 64 on 2 threads
    """
    env = gym.make("sb3_gccp:GCCPPlanner-v0")
    env.reset(seed=seed)
    env.action_space.seed(seed)
    samples = []
    while len(samples) < 64:
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        samples.append(obs)
        if terminated or truncated:
            env.reset()
    batch = {key: th.as_tensor(np.stack([o[key] for o in samples])).float() for key in samples[0]}
    pair = {key: value[:2] for key, value in batch.items()}
    extractor = PlannerFeaturesExtractor(env.observation_space)
    threads = th.get_num_threads()
    th.set_num_threads(1)
    with th.inference_mode():
        inference = _best_ms(lambda: extractor(pair), 200) / 2
    th.set_num_threads(2)
    training = _best_ms(lambda: extractor(batch).sum().backward(), 10) / 64
    th.set_num_threads(threads)
    return sum(p.numel() for p in extractor.parameters()), inference * 1e3, training * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=8192, help="env steps per algorithm")
    parser.add_argument("--n-envs", type=int, default=2)
    parser.add_argument("--n-steps", type=int, default=1024, help="rollout steps per env and update")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--n-epochs", type=int, default=5)
    parser.add_argument("--vec-env", choices=("subproc", "dummy"), default="dummy")
    parser.add_argument("--threads", type=int, default=2, help="torch threads of the main process")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    params, inference, training = encoder_costs(args.seed)
    print(
        f"encoder (default sizes): {params} parameters; {inference:.0f} us/sample inference at batch 2 "
        f"(1 thread), {training:.0f} us/sample forward+backward at batch 64 (2 threads)"
    )
    ppo_kwargs = {
        "n_steps": args.n_steps,
        "batch_size": args.batch_size,
        "n_epochs": args.n_epochs,
        "seed": args.seed,
        "device": "cpu",
        "verbose": 0,
    }
    ours_env = make_envs("sb3_gccp:GCCPPlanner-v0", args.n_envs, args.vec_env, args.seed)
    ours = steps_per_second(MaskablePPO(MotionPlannerPolicy, ours_env, **ppo_kwargs), args.timesteps)
    stock_env = make_envs(
        "highway_env:intersection-v2", args.n_envs, args.vec_env, args.seed, config=STOCK_CONFIG
    )
    stock = steps_per_second(PPO("MlpPolicy", stock_env, **ppo_kwargs), args.timesteps)
    print(
        f"{args.timesteps} steps each, {args.n_envs} envs ({args.vec_env}), n_steps {args.n_steps}, "
        f"batch_size {args.batch_size}, n_epochs {args.n_epochs}, {args.threads} torch threads"
    )
    print(f"MaskablePPO + MotionPlannerPolicy, GCCPPlanner-v0: {ours:.1f} steps/s")
    print(f"PPO + MlpPolicy, intersection-v2:                  {stock:.1f} steps/s")
    print(f"ratio {ours / stock:.3f}")


if __name__ == "__main__":
    main()
