"""Names shared across the package: the environment ids and the files of run folders.

The world (``gccp_envs``) registers the environments, so their ids are defined there; the agent's
modules import them from here with the file names, so that every name has one spelling.
"""

from gccp_envs import DECIDER_ENV_ID, FLAT_ENV_ID, PLANNER_ENV_ID

__all__ = [
    "ARGS_FILE",
    "BASELINE_FILE",
    "CHOICE_FILE",
    "COMMAND_FILE",
    "CONFIG_FILE",
    "DECIDER_ENV_ID",
    "DECIDER_FILE",
    "EPISODES_FILE",
    "EVALUATION_FILE",
    "FLAT_ENV_ID",
    "HIERARCHY_FILE",
    "METRICS_FILE",
    "MODEL_FILE",
    "PLANNER_ENV_ID",
    "PLANNER_FILE",
    "PREDICTOR_FILE",
    "SCRIPTED",
    "TRAINING_CURVE_FILE",
    "TRAINING_FILE",
]

SCRIPTED = "scripted"
"""The planner name that stands for the scripted pure-pursuit planner (``gccp_envs.scripted``)
instead of a trained ``.zip``: in ``hierarchy.yml``, ``--planner`` and ``reproduce --planner``."""

CONFIG_FILE = "config.yml"
"""A run's resolved zoo entry (hyperparameters and world config)."""
ARGS_FILE = "args.yml"
"""A run's command arguments."""
COMMAND_FILE = "command.txt"
"""A run's command line."""
EPISODES_FILE = "episodes.csv"
"""One row per training episode (:mod:`sb3_gccp.training.episodes`)."""
METRICS_FILE = "metrics.json"
"""A run's summary numbers (the decider's success rates, the predictor stage's ADE/FDE)."""
TRAINING_CURVE_FILE = "training_curve.png"
"""Success and collision rate per training episode."""
TRAINING_FILE = "training.json"
"""Written by ``reproduce`` when a method's training finished: its budget and wall clock."""
EVALUATION_FILE = "evaluation.json"
"""Written by ``reproduce``: a method's evaluation table and episodes."""
CHOICE_FILE = "choice.json"
"""Written by the decider stage when it chooses its model on validation flows: every candidate's table."""

HIERARCHY_FILE = "hierarchy.yml"
"""The files, GCCP variant and check and world of a trained hierarchy (:mod:`sb3_gccp.hierarchy`)."""
PLANNER_FILE = "planner.zip"
"""The motion-planner of a planner run, copied into the decider runs that use it."""
DECIDER_FILE = "decider.zip"
"""The decision-maker of a decider run."""
PREDICTOR_FILE = "predictor.pt"
"""The GCCP trajectory predictor's weights (``sb3_gccp.gccp.predictor.load_predictor``)."""

BASELINE_FILE = "baseline.yml"
"""A baseline run's algorithm and model file (:mod:`sb3_gccp.training.baselines`)."""
MODEL_FILE = "model.zip"
"""A baseline run's model."""
