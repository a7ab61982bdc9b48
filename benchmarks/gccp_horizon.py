"""How far ahead the GCCP collision check must look: success and collisions of a fixed hierarchy
under masks that check the predicted 1 s (the paper), or further by extrapolation, with box margins.

The hierarchy is the scripted one (the farthest allowed candidate over the scripted pure-pursuit
planner, which stops on a near subgoal), so only the mask changes between rows. Every row plays the
same seeded traffic flows. Prints one row per mask and, last, ``best_collision_rate <rate>``.

    python benchmarks/gccp_horizon.py --predictor pretrained/predictor.pt
"""

from __future__ import annotations

import argparse
import time

import torch as th

from gccp_envs.config import TASKS
from gccp_envs.option_env import GCCPDeciderEnv
from gccp_envs.scripted import FarthestSubgoalDecider
from sb3_gccp.evaluation import evaluate, summarize
from sb3_gccp.gccp.mask import GCCPMask
from sb3_gccp.gccp.predictor import ConstantVelocityPredictor, load_predictor
from sb3_gccp.gccp.settings import GCCPCheck

# (predictor, extrapolated steps, margin [m])
MASKS = (
    ("cv", 0, 0.0),
    ("cv", 0, 1.0),
    ("cv", 5, 1.0),
    ("cv", 10, 0.0),
    ("cv", 10, 1.0),
    ("cv", 20, 1.0),
    ("learned", 0, 0.0),
    ("learned", 10, 1.0),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes-per-task", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--predictor", help="learned predictor weights (rows 'learned'; skipped without)")
    args = parser.parse_args()
    th.set_num_threads(1)
    print(f"scripted hierarchy, {args.episodes_per_task} flows per task from seed {args.seed}")
    print("| predictor | checked [s] | margin [m] | success % | collision % | timeout % | wall [s] |")
    print("|---|---|---|---|---|---|---|")
    collisions = []
    for name, steps, margin in MASKS:
        if name == "learned" and not args.predictor:
            continue
        predictor = ConstantVelocityPredictor() if name == "cv" else load_predictor(args.predictor)
        mask = GCCPMask(predictor, GCCPCheck(margin=margin, extrapolate_steps=steps))
        env = GCCPDeciderEnv(planner=None, mask_fn=mask)
        start = time.perf_counter()
        results = evaluate(env, FarthestSubgoalDecider(), TASKS, args.episodes_per_task, args.seed, False)
        row = summarize(results)["overall"]
        collisions.append(row["crashed"] / 100)
        horizon = (env.config.prediction_horizon + steps) * 0.1
        print(
            f"| {name} | {horizon:.1f} | {margin:.1f} | {row['success']:.1f} | {row['crashed']:.1f} | "
            f"{row['timeout']:.1f} | {time.perf_counter() - start:.0f} |",
            flush=True,
        )
    print(f"best_collision_rate {min(collisions):.3f}")


if __name__ == "__main__":
    main()
