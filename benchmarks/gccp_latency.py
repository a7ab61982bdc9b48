"""Latency of the GCCP mask for one decision on one torch thread: predictor forward + collision check.

Decider observations come from random rollouts of ``GCCPDecider-v0`` (scripted planner, uniform
random subgoals). Each observation is timed once per repetition after a warm-up; the median is over
all timings. The predictor is untrained unless ``--predictor`` names a file saved by
``sb3_gccp.gccp.predictor.save_predictor`` (its weights do not change the cost). Observations without
any neighbour skip the prediction (nothing can collide), so the medians are given over the
observations with at least one neighbour as well as over all of them.

Run: python benchmarks/gccp_latency.py [--observations 300] [--repeats 3] [--predictor FILE] [--cv]
Last line: ``mask_ms <median over all observations>`` (goal: at most 2 on one thread).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch as th
from torch import nn

import sb3_gccp  # noqa: F401  (registers the environments)
from sb3_gccp.gccp.mask import GCCPMask
from sb3_gccp.gccp.predictor import ConstantVelocityPredictor, TrajectoryPredictor, load_predictor

Obs = dict[str, np.ndarray]


def decider_observations(count: int, seed: int) -> list[Obs]:
    """Observations of decision points from random rollouts.

    :param count: how many to collect
    :param seed: seed of the first episode and of the subgoal choices
    :return: the observations
    """
    env = gym.make("GCCPDecider-v0")
    rng = np.random.default_rng(seed)
    observations: list[Obs] = []
    obs, _ = env.reset(seed=seed)
    while len(observations) < count:
        observations.append(obs)
        obs, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
    env.close()
    return observations


def median_ms(function: Callable[[Obs], object], observations: list[Obs], repeats: int) -> np.ndarray:
    """Per-observation median time [ms] of ``function`` over ``repeats`` passes (after one warm-up pass).

    :param function: what to time
    :param observations: its inputs
    :param repeats: timed passes over all inputs
    :return: (len(observations),) times
    """
    for obs in observations[:50]:
        function(obs)
    times = np.empty((repeats, len(observations)))
    for r in range(repeats):
        for i, obs in enumerate(observations):
            start = time.perf_counter()
            function(obs)
            times[r, i] = time.perf_counter() - start
    return np.median(times, axis=0) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--observations", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--predictor", help="a predictor saved by save_predictor (default: untrained)")
    parser.add_argument("--cv", action="store_true", help="time the constant-velocity predictor instead")
    args = parser.parse_args()
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    observations = decider_observations(args.observations, args.seed)
    predictor: nn.Module
    if args.cv:
        predictor = ConstantVelocityPredictor()
    elif args.predictor:
        predictor = load_predictor(args.predictor)
    else:
        predictor = TrajectoryPredictor()
    mask = GCCPMask(predictor)
    crowded = np.array([mask.present(obs).any() for obs in observations])
    futures = {id(obs): mask.predict(obs) for obs in observations}

    def check(obs: Obs) -> np.ndarray:
        future = futures[id(obs)]
        return mask.checker.action_mask(future[:, 0], future[:, 1:], mask.present(obs))

    predict = median_ms(mask.predict, observations, args.repeats)
    collide = median_ms(check, observations, args.repeats)
    total = median_ms(mask, observations, args.repeats)
    print(
        f"{len(observations)} decider observations, {int(crowded.sum())} with neighbours; "
        f"{type(predictor).__name__}, torch threads {th.get_num_threads()}"
    )
    print(f"predictor_forward_ms {np.median(predict):.3f}")
    print(f"collision_check_ms {np.median(collide):.3f}")
    p90 = np.quantile(total[crowded], 0.9)
    print(f"mask_ms_with_neighbours {np.median(total[crowded]):.3f} (p90 {p90:.3f})")
    print(f"mask_ms {np.median(total):.3f}")


if __name__ == "__main__":
    main()
