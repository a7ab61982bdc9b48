"""The methods of the paper's Tables I and II, and the paper's own figures for them."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Method:
    """A row of the paper's tables."""

    name: str
    """Name on the command line and of the run folder."""
    label: str
    """Name in the tables and figures (the paper's)."""
    predictor: str | None = None
    """``gccp.predictor`` of a hierarchy variant; None for a baseline on the flat env."""
    baseline: str | None = None
    """A baseline's algorithm and zoo file (``dqn``, ``ppo``, ``sac_discrete``); None: ``name``."""
    paper_style: bool = False
    """A baseline as the paper ran it: no action masks and no wrong-exit penalty (the zoo entry's
    ``action_masks`` and the world's ``wrong_exit_penalty`` set to false)."""

    @property
    def is_hierarchy(self) -> bool:
        """Whether this is a variant of the hierarchy (else a flat baseline)."""
        return self.predictor is not None

    @property
    def algorithm(self) -> str:
        """A baseline's name in :data:`sb3_gccp.training.baselines.BASELINES` (its zoo file's stem)."""
        return self.baseline or self.name


METHODS = {
    m.name: m
    for m in (
        Method("ours", "ours", "learned"),
        Method("with_cv", "w/ CV", "cv"),
        Method("without_gccp", "w/o GCCP", "none"),
        Method("without_goal", "w/o goal condition", "no_goal"),
        Method("dqn", "DQN"),
        Method("ppo", "PPO"),
        Method("sac_discrete", "SAC-Discrete"),
        Method("dqn_paper", "DQN (paper-style)", baseline="dqn", paper_style=True),
        Method("ppo_paper", "PPO (paper-style)", baseline="ppo", paper_style=True),
        Method("sac_discrete_paper", "SAC-Discrete (paper-style)", baseline="sac_discrete", paper_style=True),
    )
}
"""Every method, in training order (ours first)."""
TABLE_1 = ("dqn_paper", "ppo_paper", "sac_discrete_paper", "dqn", "ppo", "sac_discrete", "ours")
TABLE_2 = ("with_cv", "without_gccp", "without_goal", "ours")
PAPER_RESULTS: dict[str, tuple[tuple[float, float], ...]] = {
    "dqn": ((0, 28), (66, 32), (0, 26), (22.0, 28.7)),
    "ppo": ((34, 32), (54, 42), (54, 20), (47.3, 31.3)),
    "sac_discrete": ((64, 4), (74, 18), (84, 8), (74.0, 10.0)),
    "with_cv": ((86, 10), (88, 12), (90, 4), (88.0, 8.7)),
    "without_gccp": ((82, 10), (82, 16), (80, 8), (81.3, 11.3)),
    "without_goal": ((94, 2), (86, 8), (94, 4), (91.3, 4.7)),
    "ours": ((98, 2), (92, 6), (94, 2), (94.7, 3.3)),
}
"""The paper's (success %, collision %) for left, straight, right and overall (SMARTS, 50 flows)."""
