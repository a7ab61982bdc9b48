"""Helpers shared by the tests: an empty-road config and hand placement of the ego."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import yaml

from gccp_envs.action import EgoAction, EgoState
from gccp_envs.config import IntersectionConfig
from gccp_envs.scenario import IntersectionLayout
from gccp_envs.world import IntersectionWorld

EMPTY = IntersectionConfig(spawn_probability=0.0, task="straight")
"""The default world without any traffic."""


def load_benchmark(name: str) -> ModuleType:
    """The script ``benchmarks/<name>.py`` as a module (benchmarks are scripts, not a package)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def always_brake(obs: object, action_mask: object = None) -> int:
    """A planner that only ever slows down."""
    return int(EgoAction.SLOW_DOWN)


def path_pose(layout: IntersectionLayout, path: int, s: float) -> np.ndarray:
    """(x, y, heading) of arc length ``s`` on ``path``."""
    return layout.paths.pose_at(np.array(path), np.array(float(s)))


def forget_ego_caches(world: IntersectionWorld) -> None:
    """Drop what the world cached about the ego for the current step (it was moved by hand)."""
    for cache in ("_candidates", "_routes"):
        if hasattr(world, cache):
            setattr(world, cache, None)


def place_ego(world: IntersectionWorld, x: float, y: float, heading: float, speed: float) -> None:
    """Put the ego at a pose, as if it had driven there straight at constant speed."""
    world.ego = EgoState(float(x), float(y), float(heading), float(speed))
    forget_ego_caches(world)
    world._record()
    world._backfill_history(np.array([world.ego_slot]))


def place_ego_on_path(world: IntersectionWorld, path: int, s: float, speed: float) -> np.ndarray:
    """Put the ego on ``path`` at arc length ``s``; return its pose."""
    pose = path_pose(world.layout, path, s)
    place_ego(world, pose[0], pose[1], pose[2], speed)
    return pose


def ego_frame(points: np.ndarray, x: float, y: float, heading: float) -> np.ndarray:
    """World points (..., 2) in the frame of a pose, computed independently of the package."""
    rot = np.array([[np.cos(heading), np.sin(heading)], [-np.sin(heading), np.cos(heading)]])
    return (np.asarray(points, float) - np.array([x, y])) @ rot.T


TINY_PLANNER_HYPERPARAMS = {
    "GCCPPlanner-v0": {
        "n_timesteps": 32,
        "n_envs": 1,
        "policy": "MultiInputPolicy",
        "n_steps": 16,
        "batch_size": 16,
        "n_epochs": 1,
        "learning_rate": {"initial": 1e-4, "final": 1e-5, "after_gradient_steps": 1},
        "policy_kwargs": {"net_arch": {"pi": [8], "vf": [8]}},
        "env_kwargs": {"spawn_probability": 0.0, "warmup_time": 0.0, "duration": 2.0},
    }
}
"""A planner run that takes seconds: tiny MLP, 32 steps, an empty road, 2 s episodes."""


TINY_ENCODER = {"hidden_size": 16, "num_heads": 2, "token_size": 8, "token_heads": 2, "bev_channels": [4, 4]}
"""Encoder config fields of a tiny scene encoder, for fast network tests."""
TINY_FLAT_POLICY_KWARGS = {
    "features_extractor_class": "sb3_gccp.policies.PlannerFeaturesExtractor",
    "features_extractor_kwargs": {"encoder": TINY_ENCODER},
    "net_arch": [8],
}
"""``policy_kwargs`` of a baseline on the flat env with the tiny scene encoder."""


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``sb3_gccp ARGS`` in a subprocess started in ``cwd``, as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "sb3_gccp.cli", *args], cwd=cwd, capture_output=True, text=True, timeout=300
    )


def run_zoo(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``python -m sb3_gccp.zoo ARGS`` in a subprocess (rl-zoo3's trainer through our launcher)."""
    return subprocess.run(
        [sys.executable, "-m", "sb3_gccp.zoo", *args], cwd=cwd, capture_output=True, text=True, timeout=300
    )


TINY_WORLD = {"duration": 2.0, "spawn_probability": 0.0, "warmup_time": 0.0}
"""A world of 2 s episodes (two decisions) on an empty road."""


def save_tiny_models(folder: Path) -> tuple[Path, Path]:
    """An untrained decision-maker and motion-planner of this project's policies with a tiny encoder,
    saved by SB3 on ``TINY_WORLD`` as ``folder/decider.zip`` and ``folder/planner.zip``."""
    from sb3_contrib import MaskablePPO

    from gccp_envs.option_env import GCCPDeciderEnv
    from gccp_envs.planner_env import GCCPPlannerEnv
    from sb3_gccp.policies import DecisionMakerPolicy, MotionPlannerPolicy

    decider = folder / "decider.zip"
    kwargs = {"encoder": TINY_ENCODER, "net_arch": {"pi": [8], "vf": [8, 8]}}
    MaskablePPO(DecisionMakerPolicy, GCCPDeciderEnv(TINY_WORLD), n_steps=16, policy_kwargs=kwargs).save(
        decider
    )
    planner = folder / "planner.zip"
    kwargs = {"encoder": TINY_ENCODER, "net_arch": {"pi": [8], "vf": [8]}}
    MaskablePPO(MotionPlannerPolicy, GCCPPlannerEnv(TINY_WORLD), n_steps=16, policy_kwargs=kwargs).save(
        planner
    )
    return decider, planner


def rewrite_zip_data(path: Path, **entries: object) -> None:
    """Replace entries of the ``data`` JSON of an SB3 ``.zip`` in place, as someone editing it would."""
    import json
    import zipfile

    with zipfile.ZipFile(path) as archive:
        files = {name: archive.read(name) for name in archive.namelist()}
    files["data"] = json.dumps({**json.loads(files["data"]), **entries}).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in files.items():
            archive.writestr(name, content)


TINY_REPRODUCE = [
    "episodes=2",
    "mask_after_episodes=1",
    "episodes_per_task=1",
    "heldout_episodes=1",
    "planner_timesteps=32",
    f"encoder={yaml.safe_dump(TINY_ENCODER, default_flow_style=True).strip()}",
    "world.duration=2.0",
    "hyperparams.planner.n_steps=16",
    "hyperparams.planner.batch_size=16",
    "hyperparams.planner.imitation.expert_steps=32",
    "hyperparams.planner.imitation.dagger_steps=16",
    "hyperparams.planner.imitation.workers=1",
    "hyperparams.hierarchy.n_steps=4",
    "hyperparams.hierarchy.batch_size=4",
    "hyperparams.ppo.n_steps=8",
    "hyperparams.ppo.batch_size=8",
    "hyperparams.dqn.learning_starts=5",
    "hyperparams.dqn.buffer_size=100",
    "hyperparams.dqn.batch_size=8",
    "hyperparams.sac_discrete.learning_starts=5",
    "hyperparams.sac_discrete.buffer_size=100",
    "hyperparams.sac_discrete.batch_size=8",
]
"""The quick preset shrunk to seconds: 2 episodes of 2 s per method, a planner cloned from 48 labelled
steps in one process and trained for 32 PPO steps, tiny networks."""


def reproduce(cwd: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """``sb3_gccp reproduce --preset quick`` shrunk by ``TINY_REPRODUCE``, in a subprocess in ``cwd``."""
    overrides = [*(arg for item in TINY_REPRODUCE for arg in ("--set", item)), *extra]
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "sb3_gccp.cli",
            "reproduce",
            "--preset",
            "quick",
            "--torch-threads",
            "1",
            *overrides,
        ],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


def sumo_children() -> list[int]:
    """Ids of this process's child processes running a SUMO binary (by the program's name: the
    command line of another child, such as multiprocessing's forkserver, may name SUMO's folders)."""
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            program = (stat.parent / "cmdline").read_bytes().split(b"\0")[0]
        except OSError:
            continue
        if int(fields[1]) == os.getpid() and b"sumo" in os.path.basename(program):
            children.append(int(stat.parent.name))
    return children
