"""Baselines on the flat env: checkpoints every few episodes, and a run that continues from them."""

from __future__ import annotations

import pytest
import yaml
from helpers import TINY_ENCODER

from sb3_gccp.constants import MODEL_FILE
from sb3_gccp.training.baselines import REPLAY_BUFFER_FILE, baseline_algorithm, train_baseline
from sb3_gccp.training.episodes import read_episodes


@pytest.fixture()
def zoo_file(tmp_path):
    entry = {
        "n_timesteps": 5000,
        "n_envs": 1,
        "policy": "MultiInputPolicy",
        "learning_starts": 5,
        "buffer_size": 200,
        "batch_size": 8,
        "train_freq": 4,
        "gradient_steps": 1,
        "policy_kwargs": {
            "features_extractor_class": "sb3_gccp.policies.PlannerFeaturesExtractor",
            "features_extractor_kwargs": {"encoder": TINY_ENCODER},
            "net_arch": [16],
        },
        "env_kwargs": {"task": "mixed", "duration": 1.0},
    }
    path = tmp_path / "dqn.yml"
    path.write_text(yaml.safe_dump({"GCCPFlat-v0": entry}))
    return path


def test_an_interrupted_baseline_continues_from_its_checkpoint(tmp_path, zoo_file):
    run = tmp_path / "dqn"
    train_baseline("dqn", zoo_file, run, seed=0, episodes=6, save_every_episodes=2)
    checkpoint = read_episodes(run / "checkpoints" / "episodes.csv")
    assert [row["episode"] for row in checkpoint] == [1, 2, 3, 4]  # the last checkpoint before the end
    saved = baseline_algorithm("dqn").load(run / "checkpoints" / MODEL_FILE)
    saved.load_replay_buffer(run / "checkpoints" / REPLAY_BUFFER_FILE)
    assert saved.replay_buffer is not None and saved.replay_buffer.size() == saved.num_timesteps
    # As if the run had been killed after that checkpoint: its final files are not there.
    (run / MODEL_FILE).unlink()
    (run / "episodes.csv").unlink()

    train_baseline("dqn", zoo_file, run, seed=0, episodes=6, save_every_episodes=2, resume=True)
    rows = read_episodes(run / "episodes.csv")
    assert [row["episode"] for row in rows] == [1, 2, 3, 4, 5, 6] and rows[:4] == checkpoint
    assert rows[4]["timesteps"] > saved.num_timesteps  # the step count went on from the checkpoint
    assert baseline_algorithm("dqn").load(run / MODEL_FILE).num_timesteps == rows[-1]["timesteps"]
    clock = [row["wall_clock_s"] for row in rows]  # the resumed run's clock goes on from the checkpoint's
    assert clock[0] > 0 and clock == sorted(clock) and clock[4] >= checkpoint[-1]["wall_clock_s"]


def test_resume_without_a_checkpoint_is_refused(tmp_path, zoo_file):
    with pytest.raises(ValueError, match="no checkpoint to resume"):
        train_baseline("dqn", zoo_file, tmp_path / "dqn", seed=0, episodes=2, resume=True)
