"""rl-zoo3's own trainer through our launcher: ppo_mask, masked evaluation, our schedule."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml
from helpers import TINY_PLANNER_HYPERPARAMS, run_zoo

pytest.importorskip("rl_zoo3")

TINY = TINY_PLANNER_HYPERPARAMS


def test_zoo_launcher_trains_with_masked_evaluation(tmp_path):
    (tmp_path / "tiny.yml").write_text(yaml.safe_dump(TINY))
    args = [
        "--algo",
        "ppo_mask",
        "--env",
        "GCCPPlanner-v0",
        "--conf-file",
        "tiny.yml",
        "-f",
        "logs",
        "--eval-freq",
        "16",
        "--eval-episodes",
        "1",
        "--seed",
        "0",
        "--vec-env",
        "dummy",
    ]
    result = run_zoo(tmp_path, *args)
    assert result.returncode == 0, result.stderr[-2000:]
    run = tmp_path / "logs" / "ppo_mask" / "GCCPPlanner-v0_1"
    assert (run / "GCCPPlanner-v0.zip").is_file()
    assert (run / "evaluations.npz").is_file()  # the masked evaluation ran
    # rl-zoo writes its config as a python-tagged OrderedDict: check the text, do not load it.
    assert "MultiInputPolicy" in (run / "GCCPPlanner-v0" / "config.yml").read_text()
    check = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sb3_gccp; from sb3_contrib import MaskablePPO; "
            f"m = MaskablePPO.load({str(run / 'GCCPPlanner-v0.zip')!r}); "
            "print(m.num_timesteps, m.lr_schedule(1.0), m.lr_schedule(0.0))",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert check.stdout.split() == ["32", "0.0001", "1e-05"], check.stderr[-2000:]


def test_zoo_launcher_refuses_the_imitation_key(tmp_path):
    entry = {**TINY["GCCPPlanner-v0"], "imitation": {"expert_steps": 10}}
    (tmp_path / "imitation.yml").write_text(yaml.safe_dump({"GCCPPlanner-v0": entry}))
    args = ["--algo", "ppo_mask", "--env", "GCCPPlanner-v0", "--conf-file", "imitation.yml", "-f", "logs"]
    result = run_zoo(tmp_path, *args)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == (
        "sb3_gccp.zoo: error: imitation: cloning the scripted planner runs in "
        "`sb3_gccp train --stage planner` only"
    )
    assert not list((tmp_path / "logs").rglob("*.zip"))
