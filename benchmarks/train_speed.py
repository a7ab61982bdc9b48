"""Training throughput of the planner stage, as ``sb3_gccp train --stage planner`` runs it, vs stock SB3 PPO.

Ours is the command itself (:func:`sb3_gccp.cli.main`) on the planner entry of
``zoo_configs/ppo_mask.yml``: MaskablePPO + ``MotionPlannerPolicy`` on ``GCCPPlanner-v0`` with its action
masks, the VecEnv of :func:`~sb3_gccp.training.run_folder.make_run_env`, the cloning term between PPO
updates, checkpoints, Monitor files, TensorBoard logging, the progress bar and the command's default
torch threads. Only the imitation warm start before PPO is cut to a token one (``--expert-steps`` steps
of the expert, no DAgger rounds) and left out of the timing; the cloning term draws its batches from
those steps.

The stock reference is SB3's PPO with its MlpPolicy on highway-env's intersection-v2 at 10 Hz, with the
entry's PPO settings (``n_steps``, ``batch_size``, ``n_epochs``, ...), the same number of envs in the
same VecEnv class and the same torch threads, logging to TensorBoard too. It runs at our traffic
density:

- ``spawn_probability`` is ours (the entry's world, 0.06): highway-env tries one spawn per agent step
  with that chance, as our world does per 0.1 s step, so at 10 Hz both try 0.6 spawns a second;
- ``initial_vehicle_count`` 12 (its default 10): our world simulates ``warmup_time`` = 12 s of traffic
  before the ego appears (5.2 vehicles at the ego's start, mean of seeds 0-199), while intersection-v2
  tries ``initial_vehicle_count - 1`` spawns at a fixed chance of 0.6 plus one sure one and removes those
  within 20 m of the ego: 12 gives 5.1 (10 gives 4.6, 13 gives 5.5).

Both are timed the same way, in steady state, from the wall-clock stamps of SB3's log record after each
rollout (``time/fps`` in the TensorBoard log): env steps between the first and the last record over the
seconds between them. Each interval holds one PPO update, our cloning steps, and the next rollout.

Run: python benchmarks/train_speed.py [--timesteps 8192] [--expert-steps 512]
Last line: ``ratio <ours/stock>`` (goal: above 1).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import highway_env  # noqa: F401  (registers intersection-v2)
import numpy as np
import torch as th
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import sb3_gccp  # noqa: F401  (registers GCCPPlanner-v0)
from gccp_envs.config import IntersectionConfig
from sb3_gccp.cli import build_parser
from sb3_gccp.cli import main as sb3_gccp_main
from sb3_gccp.constants import PLANNER_ENV_ID
from sb3_gccp.hyperparams import default_config_file, load_hyperparams
from sb3_gccp.policies import PlannerFeaturesExtractor
from sb3_gccp.training.planner import IMITATION_KEY
from sb3_gccp.training.run_folder import algorithm_kwargs, latest_run

STOCK_ENV_ID = "intersection-v2"
STOCK_INITIAL_VEHICLES = 12
"""intersection-v2's ``initial_vehicle_count`` that matches our vehicles at the ego's start (above)."""


def steady_steps_per_second(tb_dir: Path) -> tuple[float, int]:
    """Env steps per second between the first and the last ``time/fps`` record of a TensorBoard log.

    :param tb_dir: the folder of one run's event file
    :return: steps per second, and the number of intervals (PPO updates) they span
    """
    accumulator = EventAccumulator(str(tb_dir))
    accumulator.Reload()
    records = accumulator.Scalars("time/fps")
    if len(records) < 2:
        raise SystemExit(f"{tb_dir}: fewer than two updates logged; raise --timesteps")
    first, last = records[0], records[-1]
    return (last.step - first.step) / (last.wall_time - first.wall_time), len(records) - 1


def token_imitation(settings: dict[str, Any], expert_steps: int) -> dict[str, Any]:
    """The planner entry with its imitation warm start cut to ``expert_steps`` expert steps and no DAgger
    rounds; the cloning term between updates (``bc_steps``) is kept."""
    imitation = settings.get(IMITATION_KEY)
    if imitation is None:
        return settings
    return {**settings, IMITATION_KEY: {**imitation, "expert_steps": expert_steps, "dagger_rounds": 0}}


def time_stage(argv: list[str], log_folder: Path) -> tuple[float, int]:
    """Run ``sb3_gccp`` with ``argv`` and time its planner run (see :func:`steady_steps_per_second`)."""
    if sb3_gccp_main(argv) != 0:
        raise SystemExit(f"sb3_gccp {' '.join(argv)} failed")
    run_dir = latest_run(log_folder / "planner")
    assert run_dir is not None
    return steady_steps_per_second(next((run_dir / "tb").iterdir()))


def stock_config(settings: dict[str, Any]) -> dict[str, Any]:
    """intersection-v2's config at 10 Hz and at the density of the entry's world (see above)."""
    world = IntersectionConfig.from_dict(settings.get("env_kwargs") or {})
    return {
        "policy_frequency": 10,
        "simulation_frequency": 10,
        "spawn_probability": world.spawn_probability,
        "initial_vehicle_count": STOCK_INITIAL_VEHICLES,
    }


def time_stock(settings: dict[str, Any], timesteps: int, seed: int, log_folder: Path) -> tuple[float, int]:
    """Train SB3's PPO + MlpPolicy on intersection-v2 at our density with the entry's PPO settings; time
    it as :func:`time_stage` does."""
    # make_run_env's VecEnv class.
    env = make_vec_env(
        STOCK_ENV_ID,
        n_envs=int(settings.get("n_envs", 1)),
        seed=seed,
        env_kwargs={"config": stock_config(settings)},
        vec_env_cls=DummyVecEnv,
    )
    ppo_settings = {k: v for k, v in settings.items() if k not in (IMITATION_KEY, "policy_kwargs")}
    kwargs = algorithm_kwargs({**ppo_settings, "policy": "MlpPolicy"}, timesteps, algorithm=PPO)
    model = PPO(env=env, seed=seed, device="cpu", tensorboard_log=str(log_folder), **kwargs)
    model.learn(timesteps, tb_log_name="stock")
    env.close()
    return steady_steps_per_second(log_folder / "stock_1")


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
    """Parameters and per-sample costs of the default encoder's ego feature on real observations, on the
    current torch threads.

    :param seed: seed of the episode the observations come from (default traffic, random actions)
    :return: parameters, inference [us/sample] at batch 2 (``th.inference_mode``), forward + backward
        [us/sample] at batch 64
    """
    env = gym.make(PLANNER_ENV_ID)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    samples: list[dict[str, np.ndarray]] = []
    while len(samples) < 64:
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        samples.append(obs)
        if terminated or truncated:
            env.reset()
    batch = {key: th.as_tensor(np.stack([o[key] for o in samples])).float() for key in samples[0]}
    pair = {key: value[:2] for key, value in batch.items()}
    assert isinstance(env.observation_space, gym.spaces.Dict)
    extractor = PlannerFeaturesExtractor(env.observation_space)
    with th.inference_mode():
        inference = _best_ms(lambda: extractor(pair), 200) / 2
    training = _best_ms(lambda: extractor(batch).sum().backward(), 10) / 64
    return sum(p.numel() for p in extractor.parameters()), inference * 1e3, training * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=8192, help="env steps per algorithm")
    parser.add_argument("--expert-steps", type=int, default=512, help="expert steps of the token warm start")
    parser.add_argument("--config", default=str(default_config_file("ppo_mask.yml")))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    settings = token_imitation(load_hyperparams(args.config, PLANNER_ENV_ID), args.expert_steps)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        config = folder / "planner.yml"
        config.write_text(yaml.safe_dump({PLANNER_ENV_ID: settings}))
        argv = ["train", "--stage", "planner", "--config", str(config), "--seed", str(args.seed)]
        argv += ["-n", str(args.timesteps), "--log-folder", str(folder / "runs")]
        threads = build_parser().parse_args(argv).torch_threads
        ours, updates = time_stage(argv, folder / "runs")
        th.set_num_threads(threads)
        stock, _ = time_stock(settings, args.timesteps, args.seed, folder / "stock")
    params, inference, training = encoder_costs(args.seed)
    bc_steps = (settings.get(IMITATION_KEY) or {}).get("bc_steps", 0)
    print(
        f"encoder (default sizes): {params} parameters; {inference:.0f} us/sample inference at batch 2, "
        f"{training:.0f} us/sample forward+backward at batch 64 (torch threads {threads})"
    )
    ppo = ", ".join(f"{key} {settings.get(key)}" for key in ("n_envs", "n_steps", "batch_size", "n_epochs"))
    print(
        f"{args.timesteps} steps each, timed over the last {updates} updates: {ppo}, torch threads {threads};"
        f" ours with {bc_steps} cloning steps per update"
    )
    print(f"sb3_gccp train --stage planner (MaskablePPO + MotionPlannerPolicy): {ours:.1f} steps/s")
    density = ", ".join(
        f"{k} {stock_config(settings)[k]}" for k in ("spawn_probability", "initial_vehicle_count")
    )
    print(f"PPO + MlpPolicy, {STOCK_ENV_ID} ({density}): {stock:.1f} steps/s")
    print(f"ratio {ours / stock:.3f}")


if __name__ == "__main__":
    main()
