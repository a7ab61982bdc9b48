"""Two hierarchies compared flow by flow: is B's success rate better than A's, or within the noise?

Reads the ``--json`` files of ``sb3_gccp evaluate`` run on the same flows (the same tasks, seeds and
episodes per task) and pairs the episodes by (task, traffic seed). Two models that differ by a point or
two over 300 flows may differ by the flows alone; pairing removes the flows' share of that noise, because
only the flows that one model wins and the other loses (the discordant ones) say which is better.

For each pair it prints the success rates, the difference B - A in points, the discordant counts (B wins
where A fails, and the reverse), the exact two-sided sign test on them (McNemar's exact test) and a 95 %
bootstrap interval of the difference, resampling flows within each task. Several pairs (the same change
trained on several seeds, each beside the draw of the same seed without it) are also pooled: the
discordant flows of every pair counted together.

The sign test asks whether these trained models differ on flows like these; it does not count the spread
between training runs, which only more pairs (more seeds) measure.

    sb3_gccp evaluate --model A --episodes-per-task 100 --seed 1000 --json a.json
    sb3_gccp evaluate --model B --episodes-per-task 100 --seed 1000 --json b.json
    python benchmarks/paired.py a.json b.json [a2.json b2.json ...]
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass
from math import comb
from pathlib import Path

import numpy as np

BOOTSTRAP_SAMPLES = 10_000
"""Resamples of the flows for the interval of the difference."""


@dataclass(frozen=True)
class Pairing:
    """The episodes of two evaluations paired by flow: 1 where the episode succeeded, per task."""

    a: dict[str, np.ndarray]
    b: dict[str, np.ndarray]

    @property
    def b_only(self) -> int:
        """Flows B wins and A does not."""
        return sum(int((~a & b).sum()) for a, b in self._pairs())

    @property
    def a_only(self) -> int:
        """Flows A wins and B does not."""
        return sum(int((a & ~b).sum()) for a, b in self._pairs())

    @property
    def flows(self) -> int:
        return sum(len(a) for a in self.a.values())

    def success(self, side: str) -> float:
        """Success rate [%] of ``side`` ('a' or 'b') over all paired flows."""
        runs = self.a if side == "a" else self.b
        return 100.0 * sum(int(r.sum()) for r in runs.values()) / self.flows

    def _pairs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return [(self.a[task], self.b[task]) for task in self.a]


def load_episodes(path: str | Path) -> dict[tuple[str, int], bool]:
    """Success of every episode of an evaluation's ``--json`` file, by (task, traffic seed).

    :raises ValueError: the file is not such a file, or holds a flow twice
    """
    try:
        episodes = json.loads(Path(path).read_text())["episodes"]
        outcomes = [((str(e["task"]), int(e["seed"])), bool(e["success"])) for e in episodes]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not the --json file of sb3_gccp evaluate ({err})") from None
    result = dict(outcomes)
    if len(result) != len(outcomes):
        raise ValueError(f"{path}: a (task, seed) flow appears twice")
    return result


def pair(a: dict[tuple[str, int], bool], b: dict[tuple[str, int], bool], names: str = "A and B") -> Pairing:
    """Pair two evaluations flow by flow.

    :raises ValueError: they were not run on the same flows
    """
    if a.keys() != b.keys():
        raise ValueError(f"{names} were not evaluated on the same flows ({len(a.keys() ^ b.keys())} differ)")
    tasks = sorted({task for task, _ in a})
    keys = {task: sorted(k for k in a if k[0] == task) for task in tasks}
    return Pairing(
        {t: np.array([a[k] for k in keys[t]]) for t in tasks},
        {t: np.array([b[k] for k in keys[t]]) for t in tasks},
    )


def sign_test(wins: int, losses: int) -> float:
    """Exact two-sided sign test: the probability of a split at least this uneven if neither side is
    better (McNemar's exact test on the discordant flows)."""
    n = wins + losses
    if n == 0:
        return 1.0
    tail = sum(comb(n, k) for k in range(min(wins, losses) + 1)) / 2**n
    return min(1.0, 2.0 * tail)


def bootstrap_interval(pairings: Sequence[Pairing], rng: np.random.Generator) -> tuple[float, float]:
    """95 % interval of the mean difference B - A [points] over the pairings, resampling the flows of
    each task (the same resample for every pairing, as they share the flows)."""
    first = pairings[0]
    totals = np.zeros(BOOTSTRAP_SAMPLES)
    for task, runs in first.a.items():
        picks = rng.integers(0, len(runs), size=(BOOTSTRAP_SAMPLES, len(runs)))
        for p in pairings:
            diff = p.b[task].astype(np.int64) - p.a[task].astype(np.int64)
            totals += diff[picks].sum(1)
    low, high = np.percentile(100.0 * totals / (first.flows * len(pairings)), [2.5, 97.5])
    return float(low), float(high)


def report(name: str, pairings: Sequence[Pairing], rng: np.random.Generator) -> str:
    """One line: success rates, difference, discordant flows, sign test and interval."""
    a = np.mean([p.success("a") for p in pairings])
    b = np.mean([p.success("b") for p in pairings])
    wins, losses = sum(p.b_only for p in pairings), sum(p.a_only for p in pairings)
    low, high = bootstrap_interval(pairings, rng)
    return (
        f"{name}: A {a:.1f} %  B {b:.1f} %  B-A {b - a:+.1f} points  "
        f"B only {wins}  A only {losses}  sign test p {sign_test(wins, losses):.3f}  "
        f"95 % interval [{low:+.1f}, {high:+.1f}]"
    )


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="+", metavar="A.json B.json", help="evaluations, in pairs: A then B")
    parser.add_argument("--seed", type=int, default=0, help="seed of the bootstrap")
    args = parser.parse_args(argv)
    if len(args.files) % 2:
        parser.error(f"the files come in pairs (A then B), got {len(args.files)}")
    try:
        runs = [load_episodes(path) for path in args.files]
        if len(runs) > 2 and any(run.keys() != runs[0].keys() for run in runs):
            raise ValueError("pooled pairs must all be evaluated on the same flows")
        names = [(args.files[i], args.files[i + 1]) for i in range(0, len(runs), 2)]
        pairings = [pair(runs[2 * i], runs[2 * i + 1], f"{a} and {b}") for i, (a, b) in enumerate(names)]
    except ValueError as err:
        parser.error(str(err))
    rng = np.random.default_rng(args.seed)
    for (a_path, b_path), p in zip(names, pairings, strict=True):
        print(report(f"{Path(a_path).name} vs {Path(b_path).name} ({p.flows} flows)", [p], rng))
    if len(pairings) > 1:
        print(report(f"pooled over {len(pairings)} pairs", pairings, rng))


if __name__ == "__main__":
    main()
