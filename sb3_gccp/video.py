"""Videos of one episode of a hierarchy: the decision-maker, the frozen motion-planner and the GCCP masks.

Every 0.1 s step is a frame: the 12 subgoal candidates of the current decision (red where the GCCP
module masks them), the chosen subgoal, and the GCCP module's predicted 1 s futures of the ego under
the chosen subgoal and of the neighbours, all as they were when the decision was made, so the ego can
be seen driving along (or away from) what was predicted for it. Frames follow the world inside each
option through :meth:`~gccp_envs.option_env.GCCPDeciderEnv.set_planner_step_callback`.

GIFs are written with Pillow; MP4s need an ffmpeg encoder (``pip install imageio-ffmpeg``, or the
``video`` extra).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gccp_envs.geometry import FloatArray, from_frame
from gccp_envs.option_env import GCCPDeciderEnv
from gccp_envs.rendering import IntersectionRenderer
from sb3_gccp.evaluation import Policy
from sb3_gccp.gccp.mask import GCCPMask

VIDEO_SUFFIXES = (".gif", ".mp4")
"""File types :func:`write_video` writes, chosen by the file's extension."""
STOPPED = "stopped"
"""The outcome of an episode cut short by ``max_steps``."""
VIEW_CENTRE = (0.0, 10.0)
"""World point [m] at the middle of the frames: 10 m south of the junction's centre, so that the ego's
start (up to 53 m south of it with the default world) is in the 100 m view."""


@dataclass(frozen=True)
class DecisionOverlay:
    """What one decision draws over the frames of its option, in world coordinates."""

    candidates: FloatArray
    """(N, 3) the subgoal candidates the decision chose from."""
    masked: np.ndarray
    """(N,) bool, candidates the decision-maker was not allowed to choose (the env's ``action_masks()``)."""
    chosen: FloatArray
    """(3,) the chosen subgoal."""
    ego_prediction: FloatArray | None
    """(T_f, 2) the ego's predicted future under the chosen subgoal; ``None`` without a GCCP predictor."""
    neighbour_predictions: FloatArray | None
    """(S, T_f, 2) the present neighbours' predicted futures under the chosen subgoal."""


@dataclass(frozen=True)
class Recording:
    """The frames of one episode and how it ended."""

    frames: list[np.ndarray]
    """(H, W, 3) uint8 frames: the start, then one after every 0.1 s step."""
    outcome: str
    """success, collision, off-road, wrong exit, timeout, or ``STOPPED`` (``max_steps`` came first)."""
    steps: int
    """0.1 s steps recorded."""
    decisions: int
    """Decisions made."""


def decision_overlay(
    env: GCCPDeciderEnv, obs: dict[str, np.ndarray], allowed: np.ndarray, action: int
) -> DecisionOverlay:
    """The candidates, mask, chosen subgoal and (with a :class:`GCCPMask`) predicted futures of a decision.

    :param env: the option env, before the decision's step
    :param obs: the decider observation the decision was made from
    :param allowed: the action mask the decision-maker was given
    :param action: the chosen subgoal index
    :return: the overlay, in world coordinates
    """
    candidates = env.world.subgoal_candidates().copy()
    ego_prediction = neighbour_predictions = None
    if isinstance(env.mask_fn, GCCPMask):
        ego = env.world.ego
        future = env.mask_fn.predict(obs)[action]  # (V, T_f, 3) in the decision's ego frame
        world = from_frame(future[..., :2].astype(np.float64), np.array([ego.x, ego.y]), ego.heading)
        ego_prediction = world[0]
        neighbour_predictions = world[1:][env.mask_fn.present(obs)]
    return DecisionOverlay(
        candidates, ~np.asarray(allowed, bool), candidates[action], ego_prediction, neighbour_predictions
    )


def episode_outcome(info: dict[str, Any]) -> str:
    """The name of how an episode ended, from the final step's ``info``."""
    for key, name in (
        ("is_success", "success"),
        ("crashed", "collision"),
        ("offroad", "off-road"),
        ("wrong_exit", "wrong exit"),
        ("timeout", "timeout"),
    ):
        if info.get(key):
            return name
    return STOPPED


def record_episode(
    env: GCCPDeciderEnv,
    decider: Policy,
    task: str,
    seed: int,
    max_steps: int | None = None,
    size: int = 600,
    legend: bool = True,
) -> Recording:
    """Play one episode of ``task`` on the traffic of ``seed`` and draw every 0.1 s step.

    The decision-maker gets the env's action mask (the GCCP mask, if the env has one); with a
    :class:`GCCPMask` the predicted futures are drawn too.

    :param env: the option env of the hierarchy
    :param decider: (decider observation, action mask) -> subgoal index
    :param task: left, straight or right
    :param seed: the traffic seed
    :param max_steps: stop after this many 0.1 s steps (default: the whole episode)
    :param size: frame width and height [px]
    :param legend: write the colour key under the caption
    :return: the frames, the outcome and the number of steps and decisions
    """
    if max_steps is not None and max_steps < 1:
        raise ValueError(f"max_steps must be at least 1, got {max_steps}")
    limit = max_steps if max_steps is not None else np.inf
    renderer = IntersectionRenderer(env.world.layout, size=size, centre=VIEW_CENTRE)
    frames: list[np.ndarray] = []
    decisions = 0
    overlay: DecisionOverlay | None = None

    def draw(outcome: str | None = None) -> np.ndarray:
        assert overlay is not None
        world = env.world
        caption = (
            f"{task}, t = {world.time:.1f} s{f': {outcome}' if outcome else ''}\n"
            f"decision {decisions}, masked {int(overlay.masked.sum())}/{len(overlay.masked)}"
        )
        return renderer.frame(
            world,
            candidates=overlay.candidates,
            chosen=overlay.chosen,
            masked=overlay.masked,
            ego_prediction=overlay.ego_prediction,
            neighbour_predictions=overlay.neighbour_predictions,
            caption=caption,
            legend=legend,
        )

    def on_planner_step(_: GCCPDeciderEnv) -> None:
        if len(frames) <= limit:
            frames.append(draw())

    obs, _ = env.reset(seed=seed, options={"task": task})
    env.set_planner_step_callback(on_planner_step)
    try:
        while True:
            allowed = env.action_masks()
            action = int(decider(obs, allowed))
            overlay = decision_overlay(env, obs, allowed, action)
            decisions += 1
            if not frames:
                frames.append(draw())
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated or len(frames) > limit:
                break
    finally:
        env.set_planner_step_callback(None)
    steps = len(frames) - 1
    if steps < env.world.steps:  # the world drove on to the end of the option: leave the frame as drawn
        return Recording(frames, STOPPED, steps, decisions)
    outcome = episode_outcome(info)
    frames[-1] = draw(outcome)
    return Recording(frames, outcome, steps, decisions)


def check_video_path(path: str | Path) -> None:
    """Fail early, with a one-line reason, if :func:`write_video` could not write ``path``.

    :raises ValueError: an unsupported extension, MP4 without an encoder, a missing or read-only folder
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"cannot write {path}: the extension must be one of {', '.join(VIDEO_SUFFIXES)}")
    if suffix == ".mp4":
        _ffmpeg_writer()
    if not path.parent.is_dir():
        raise ValueError(f"cannot write {path}: no folder {path.parent}")
    if not os.access(path.parent, os.W_OK) or path.is_dir():
        raise ValueError(f"cannot write {path}: not writable")


def write_video(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0, hold: float = 1.0) -> None:
    """Write frames as an animated GIF (Pillow) or an MP4 (H.264 through imageio-ffmpeg).

    :param frames: (H, W, 3) uint8 frames, all of one size
    :param path: the file; its extension (``.gif`` or ``.mp4``) picks the format
    :param fps: frames per second (10 is real time for one frame per 0.1 s step)
    :param hold: seconds to keep the last frame on screen, so a looping GIF shows how the episode ended
    :raises ValueError: see :func:`check_video_path`, or no frames or a non-positive ``fps``
    """
    check_video_path(path)
    if not frames:
        raise ValueError("no frames to write")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if Path(path).suffix.lower() == ".gif":
        _write_gif(frames, Path(path), fps, hold)
    else:
        _write_mp4(frames, Path(path), fps, hold)


def _write_gif(frames: Sequence[np.ndarray], path: Path, fps: float, hold: float) -> None:
    from PIL import Image

    images = [Image.fromarray(frame) for frame in frames]
    durations = [round(1000 / fps)] * len(images)
    durations[-1] += round(1000 * hold)
    images[0].save(path, save_all=True, append_images=images[1:], duration=durations, loop=0)


def _write_mp4(frames: Sequence[np.ndarray], path: Path, fps: float, hold: float) -> None:
    height, width = frames[0].shape[:2]
    writer = _ffmpeg_writer()(
        str(path), (width, height), fps=fps, codec="libx264", pix_fmt_out="yuv420p", macro_block_size=2
    )
    writer.send(None)  # start ffmpeg
    try:
        for frame in [*frames, *[frames[-1]] * round(hold * fps)]:
            writer.send(np.ascontiguousarray(frame))
    finally:
        writer.close()


def _ffmpeg_writer() -> Callable[..., Any]:
    """imageio-ffmpeg's ``write_frames``, or ``ValueError`` saying how to get it."""
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as err:
        raise ValueError(
            "writing .mp4 needs imageio-ffmpeg: use a .gif, or pip install imageio-ffmpeg"
        ) from err
    return imageio_ffmpeg.write_frames
