"""Videos of one hierarchy episode: a frame per 0.1 s step with subgoals, mask and predicted futures."""

from __future__ import annotations

import sys
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image
from sb3_contrib import MaskablePPO

from gccp_envs.option_env import GCCPDeciderEnv
from gccp_envs.rendering import (
    CANDIDATE_COLOR,
    CHOSEN_COLOR,
    MASKED_COLOR,
    PREDICTED_EGO_COLOR,
    PREDICTED_NEIGHBOUR_COLOR,
)
from gccp_envs.scripted import FarthestSubgoalDecider
from sb3_gccp.cli import main
from sb3_gccp.gccp.mask import GCCPMask
from sb3_gccp.gccp.predictor import ConstantVelocityPredictor
from sb3_gccp.video import STOPPED, decision_overlay, record_episode, write_video

TRAFFIC = {"spawn_probability": 0.15, "task": "left"}


class EvenSubgoalsOnly(GCCPMask):
    """The constant-velocity GCCP module's predictions with a fixed mask: odd candidates are masked."""

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.arange(len(obs["subgoals"])) % 2 == 0


def pixels(frames: list[np.ndarray], color: tuple[int, int, int]) -> int:
    return sum(int(np.all(frame == np.array(color, np.uint8), axis=-1).sum()) for frame in frames)


def test_a_frame_per_step_with_candidates_mask_choice_and_predictions():
    env = GCCPDeciderEnv(TRAFFIC, mask_fn=EvenSubgoalsOnly(ConstantVelocityPredictor()))
    recording = record_episode(env, FarthestSubgoalDecider(), "left", seed=0, max_steps=25, legend=False)
    assert (recording.steps, recording.decisions, recording.outcome) == (25, 3, STOPPED)
    assert len(recording.frames) == 26
    assert all(frame.shape == (600, 600, 3) and frame.dtype == np.uint8 for frame in recording.frames)
    for frames in (recording.frames[:1], recording.frames[-1:]):
        for color in (CANDIDATE_COLOR, MASKED_COLOR, CHOSEN_COLOR, PREDICTED_EGO_COLOR):
            assert pixels(frames, color) > 0, color
    assert pixels(recording.frames, PREDICTED_NEIGHBOUR_COLOR) > 0
    assert not np.array_equal(recording.frames[1], recording.frames[2])  # the world moves every 0.1 s


def test_whole_episode_ends_with_its_outcome_and_without_gccp_draws_no_predictions():
    env = GCCPDeciderEnv({**TRAFFIC, "duration": 2.0})
    recording = record_episode(env, FarthestSubgoalDecider(), "left", seed=1, size=200, legend=False)
    assert (recording.outcome, recording.steps, recording.decisions) == ("timeout", 20, 2)
    assert len(recording.frames) == 21 and recording.frames[0].shape == (200, 200, 3)
    assert pixels(recording.frames, MASKED_COLOR) == pixels(recording.frames, PREDICTED_EGO_COLOR) == 0
    env.reset(seed=1)
    env.step(0)  # the recorder no longer follows the env
    assert len(recording.frames) == 21


def test_predicted_futures_are_drawn_in_world_coordinates():
    env = GCCPDeciderEnv(TRAFFIC, mask_fn=GCCPMask(ConstantVelocityPredictor()))
    obs, _ = env.reset(seed=0, options={"task": "left"})
    allowed = env.action_masks()
    overlay = decision_overlay(env, obs, allowed, 4)
    ego = env.world.ego
    # Constant velocity: 1 s straight ahead along the ego's heading, from where it stands.
    ahead = np.array([ego.x, ego.y]) + ego.speed * 1.0 * np.array([np.cos(ego.heading), np.sin(ego.heading)])
    assert overlay.ego_prediction is not None and overlay.neighbour_predictions is not None
    np.testing.assert_allclose(overlay.ego_prediction[-1], ahead, atol=1e-3)
    assert len(overlay.neighbour_predictions) == int(obs["history_mask"][1:].any(-1).sum())
    np.testing.assert_array_equal(overlay.chosen, env.world.subgoal_candidates()[4])
    np.testing.assert_array_equal(overlay.masked, ~allowed)


@pytest.fixture(scope="module")
def tiny_hierarchy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder: an untrained tiny decider, the scripted planner, the constant-velocity GCCP module."""
    folder = tmp_path_factory.mktemp("hierarchy")
    env = GCCPDeciderEnv(TRAFFIC)
    MaskablePPO("MultiInputPolicy", env, n_steps=16, policy_kwargs={"net_arch": [8]}, seed=0).save(
        folder / "decider.zip"
    )
    spec = {"planner": "scripted", "decider": "decider.zip", "predictor": "cv", "world": TRAFFIC}
    (folder / "hierarchy.yml").write_text(yaml.safe_dump(spec))
    return folder


def test_cli_writes_a_gif_and_reports_the_outcome(tiny_hierarchy, tmp_path, capsys):
    out = tmp_path / "episode.gif"
    args = ["video", "--model", str(tiny_hierarchy), "--task", "left", "--seed", "0", "--out", str(out)]
    assert main([*args, "--max-steps", "15", "--fps", "20"]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and "stopped after 15 steps" in printed
    with Image.open(out) as gif:
        assert gif.n_frames == 16 and gif.size == (600, 600)
        assert gif.info["duration"] == 50


@pytest.mark.skipif(find_spec("smarts") is None, reason="SMARTS is not installed (the smarts extra)")
def test_cli_writes_a_gif_of_an_episode_in_smarts(tiny_hierarchy, tmp_path, capfd):
    out = tmp_path / "smarts.gif"
    args = ["video", "--model", str(tiny_hierarchy), "--task", "left", "--seed", "0", "--out", str(out)]
    # capfd: SMARTS silences SUMO's start through sys.stdout's file descriptor (suppress_output)
    assert main([*args, "--max-steps", "15", "--set", "simulator=smarts"]) == 0
    assert "stopped after 15 steps" in capfd.readouterr().out
    with Image.open(out) as gif:
        assert gif.n_frames == 16 and gif.size == (600, 600)
        gif.seek(15)
        last = np.asarray(gif.convert("RGB"))
        gif.seek(0)
        assert not np.array_equal(np.asarray(gif.convert("RGB")), last)  # SMARTS moved the world


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"--out": "episode.avi"}, "the extension must be one of .gif, .mp4"),
        ({"--out": "missing/episode.gif"}, "no folder"),
        ({"--task": "u-turn"}, "unknown task 'u-turn'"),
        ({"--model": "no_such_run"}, "model not found"),
        ({"--max-steps": "0"}, "--max-steps must be at least 1"),
    ],
)
def test_cli_rejects_bad_input_on_one_line(tiny_hierarchy, tmp_path, capsys, change, message):
    options = {"--model": str(tiny_hierarchy), "--task": "left", "--out": "episode.gif", **change}
    if not Path(options["--model"]).is_absolute():
        options["--model"] = str(tmp_path / options["--model"])
    options["--out"] = str(tmp_path / options["--out"])
    assert main(["video", *[item for pair in options.items() for item in pair]]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sb3_gccp: error: ") and message in err and "\n" not in err
    assert not list(tmp_path.iterdir())  # nothing written


def test_mp4_without_an_encoder_says_what_to_do(tiny_hierarchy, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails as if not installed
    out = tmp_path / "episode.mp4"
    assert main(["video", "--model", str(tiny_hierarchy), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "use a .gif, or pip install imageio-ffmpeg" in err and "\n" not in err
    assert not out.exists()


def test_mp4_holds_the_last_frame(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    frames = [np.full((64, 64, 3), 20 * k, np.uint8) for k in range(6)]
    write_video(frames, tmp_path / "clip.mp4", fps=10, hold=0.5)
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "clip.mp4"))
    meta = next(reader)
    assert meta["size"] == (64, 64) and meta["fps"] == 10
    assert sum(1 for _ in reader) == 6 + 5
