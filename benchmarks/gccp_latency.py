"""Latency of the GCCP mask for one decision, on one torch thread, against the decision it guards.

Decision points come from episodes of the shipped hierarchy (``pretrained/`` by default, read by
:func:`sb3_gccp.hierarchy.load_hierarchy`): its decision-maker picks the subgoals under its own mask, its
frozen motion-planner drives them, in the option env its ``make_env`` builds. Every ``env.step`` of
those episodes is timed: one decision's wall clock, T_m planner steps with the frozen planner and the
next observation, without the mask (``action_masks()`` is a separate call). On the observations of
those decisions, with the hierarchy's predictor, two checks are timed: the paper's
(:class:`~sb3_gccp.gccp.settings.GCCPCheck` ``()``: no margin, no extrapolation) and the one the
hierarchy runs (its ``mask_*`` settings: margin, extrapolation, ego braking, yield rule). Each
observation is timed once per repetition after a warm-up; medians are over all timings. Observations
without any neighbour skip the prediction (nothing can collide), so the masks' medians are also given
over those with a neighbour.

Run: python benchmarks/gccp_latency.py [--model pretrained] [--decisions 300] [--repeats 3]
Last line: ``mask_share <shipped check ms / decision ms>`` (goal: at most 0.1).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Mapping

import numpy as np
import torch as th

from gccp_envs.config import IntersectionConfig
from sb3_gccp.gccp.mask import GCCPMask
from sb3_gccp.gccp.settings import GCCPCheck
from sb3_gccp.hierarchy import Hierarchy, load_hierarchy

Obs = dict[str, np.ndarray]


def timed_decisions(hierarchy: Hierarchy, count: int, seed: int) -> tuple[list[Obs], np.ndarray]:
    """Decision points of the hierarchy's own episodes, and the wall time of each decision.

    :param hierarchy: the hierarchy whose decider, planner, mask and world are run
    :param count: how many decisions
    :param seed: seed of the first episode (the next ones count up)
    :return: the observations the decisions were made from, and (count,) ``env.step`` times [ms]
    """
    env = hierarchy.make_env()
    decider = hierarchy.decider_policy(env.config)
    observations: list[Obs] = []
    times = np.empty(count)
    obs, _ = env.reset(seed=seed)
    while len(observations) < count:
        action = decider(obs, env.action_masks())
        start = time.perf_counter()
        next_obs, _, terminated, truncated, _ = env.step(action)
        times[len(observations)] = (time.perf_counter() - start) * 1e3
        observations.append(obs)
        obs = next_obs
        if terminated or truncated:
            seed += 1
            obs, _ = env.reset(seed=seed)
    env.close()
    return observations, times


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


class CachedPredictionMask(GCCPMask):
    """A mask that looks its predictions up instead of running the predictor, to time the check alone.

    :param mask: the mask whose predictor and check are used
    :param observations: the observations it will be called on
    """

    def __init__(self, mask: GCCPMask, observations: list[Obs]) -> None:
        super().__init__(mask.predictor, mask.check)
        self.futures = {id(obs): mask.predict(obs) for obs in observations}

    def predict(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        return self.futures[id(obs)]


def check_ms(mask: GCCPMask, observations: list[Obs], repeats: int) -> tuple[float, float, np.ndarray]:
    """Median times of a mask's predictor forward and of its check alone (on cached predictions), and
    the per-observation times of the whole mask [ms]."""
    forward = median_ms(mask.predict, observations, repeats)
    collision = median_ms(CachedPredictionMask(mask, observations), observations, repeats)
    return float(np.median(forward)), float(np.median(collision)), median_ms(mask, observations, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="pretrained", help="a hierarchy folder (with hierarchy.yml)")
    parser.add_argument("--decisions", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    hierarchy = load_hierarchy(args.model)
    shipped = hierarchy.mask_fn()
    if shipped is None:
        parser.error(f"{args.model} has no GCCP module (predictor: none)")
    observations, decision = timed_decisions(hierarchy, args.decisions, args.seed)
    crowded = np.array([shipped.present(obs).any() for obs in observations])
    print(
        f"{len(observations)} decisions of {args.model} (its decider, planner and mask), "
        f"{int(crowded.sum())} with neighbours; {type(shipped.predictor).__name__}, "
        f"torch threads {th.get_num_threads()}"
    )
    t_m = IntersectionConfig.from_dict(hierarchy.world).decision_period
    print(f"decision_ms {np.median(decision):.3f} (one env.step: T_m = {t_m} planner steps, no mask)")
    whole = {}
    for name, check in (("paper", GCCPCheck()), ("shipped", hierarchy.check)):
        mask = check.make_mask(shipped.predictor, IntersectionConfig.from_dict(hierarchy.world))
        forward, collision, whole[name] = check_ms(mask, observations, args.repeats)
        crowded_ms = whole[name][crowded]
        settings = ", ".join(f"{key} {value}" for key, value in check.to_dict().items())
        print(
            f"{name} check ({settings}): forward {forward:.3f} ms, check {collision:.3f} ms, "
            f"whole mask {np.median(whole[name]):.3f} ms (with neighbours {np.median(crowded_ms):.3f}, "
            f"p90 {np.quantile(crowded_ms, 0.9):.3f})"
        )
    print(f"mask_ms {np.median(whole['shipped']):.3f}")
    print(f"mask_share {np.median(whole['shipped']) / np.median(decision):.3f}")


if __name__ == "__main__":
    main()
