"""The GCCP callback: replay buffer from the training envs, predictor on the side, masks pushed at N_m."""

from __future__ import annotations

import numpy as np
import torch as th
from helpers import TINY_ENCODER
from sb3_contrib import MaskablePPO
from stable_baselines3.common.vec_env import DummyVecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from gccp_envs.option_env import GCCPDeciderEnv
from sb3_gccp.gccp.callback import GCCPCallback, StepOverlap
from sb3_gccp.gccp.mask import GCCPMask
from sb3_gccp.gccp.predictor import (
    PredictorConfig,
    TrajectoryPredictor,
    current_poses,
)
from sb3_gccp.gccp.replay import EpisodeReplayBuffer
from sb3_gccp.gccp.settings import GCCPSettings
from sb3_gccp.policies import DecisionMakerPolicy

TINY_PREDICTOR = {"encoder": TINY_ENCODER, "decoder_hidden": 8}


def tiny_predictor() -> TrajectoryPredictor:
    return TrajectoryPredictor(PredictorConfig.from_dict(TINY_PREDICTOR))


def decider_vec_env(n_envs: int = 2, **config: object) -> DummyVecEnv:
    # The scripted planner drives; 2 s episodes have 2 decisions each.
    return DummyVecEnv([lambda: GCCPDeciderEnv(duration=2.0, **config) for _ in range(n_envs)])


def tiny_model(env: DummyVecEnv) -> MaskablePPO:
    return MaskablePPO(
        DecisionMakerPolicy,
        env,
        n_steps=4,
        batch_size=4,
        n_epochs=1,
        policy_kwargs={"encoder": TINY_ENCODER, "net_arch": {"pi": [8, 8], "vf": [8, 8]}},
        seed=0,
    )


def test_callback_fills_the_buffer_trains_the_predictor_and_switches_masks_on_at_n_m():
    env = decider_vec_env()
    settings = GCCPSettings(n_episodes=6, mask_after_episodes=3, predictor_kwargs=TINY_PREDICTOR)
    predictor = tiny_predictor()
    before = [p.detach().clone() for p in predictor.parameters()]
    buffer = EpisodeReplayBuffer(100)
    callback = GCCPCallback(settings, predictor, buffer)
    model = tiny_model(env)
    model.learn(1000, callback=callback)

    assert callback.episodes == 6  # stopped at N_e, long before the step budget
    assert [row["masks_on"] for row in callback.history] == [0, 0, 0, 1, 1, 1]
    assert {row["task"] for row in callback.history} <= {"left", "straight", "right"}
    # Every decision of every finished episode is in the buffer: 2 per 2 s episode.
    assert len(buffer) == 2 * 6
    assert callback.trainer is not None and callback.trainer.gradient_steps == 5 * 6
    assert any(not th.equal(a, b) for a, b in zip(before, predictor.parameters(), strict=True))
    for worker in env.envs:
        mask_fn = worker.unwrapped.mask_fn
        assert isinstance(mask_fn, GCCPMask)
        assert mask_fn.predictor is not predictor  # a copy, as a subprocess worker would get
        # Pushed after a rollout past N_m: trained weights, not the initial ones.
        pushed = list(mask_fn.predictor.parameters())
        assert any(not th.equal(a, b) for a, b in zip(before, pushed, strict=True))


def trained_callback(overlap: bool) -> GCCPCallback:
    env = decider_vec_env()
    th.manual_seed(0)
    settings = GCCPSettings(n_episodes=6, mask_after_episodes=3, predictor_kwargs=TINY_PREDICTOR)
    callback = GCCPCallback(settings, tiny_predictor(), EpisodeReplayBuffer(100))
    tiny_model(StepOverlap(env, callback.run_next) if overlap else env).learn(1000, callback=callback)
    return callback


def test_predictor_updates_overlapped_with_the_steps_give_the_same_run():
    plain, overlapped = trained_callback(overlap=False), trained_callback(overlap=True)
    assert overlapped.trainer is not None and overlapped.trainer.gradient_steps == 5 * 6
    for a, b in zip(plain.predictor.parameters(), overlapped.predictor.parameters(), strict=True):
        assert th.equal(a, b)
    assert [row["success"] for row in plain.history] == [row["success"] for row in overlapped.history]
    assert np.array_equal(plain.buffer.stored()["future"], overlapped.buffer.stored()["future"])


class RecordingVecEnv(DummyVecEnv):
    def __init__(self, log: list[str]) -> None:
        super().__init__([lambda: GCCPDeciderEnv(duration=2.0)])
        self.log = log

    def step_async(self, actions: np.ndarray) -> None:
        self.log.append("send")
        super().step_async(actions)

    def step_wait(self) -> VecEnvStepReturn:
        self.log.append("collect")
        return super().step_wait()


def test_step_overlap_runs_the_work_after_sending_the_actions_and_before_collecting():
    log: list[str] = []
    env = StepOverlap(RecordingVecEnv(log), lambda: log.append("work"))
    env.reset()
    env.step(np.array([0]))
    env.step(np.array([0]))
    assert log == ["send", "work", "collect"] * 2


def test_without_gccp_nothing_is_masked_or_stored():
    env = decider_vec_env()
    buffer = EpisodeReplayBuffer(100)
    callback = GCCPCallback(GCCPSettings(n_episodes=2, mask_after_episodes=0, predictor="none"), None, buffer)
    tiny_model(env).learn(1000, callback=callback)
    assert callback.episodes == 2 and not callback.masks_on and len(buffer) == 0
    assert all(worker.unwrapped.mask_fn is None for worker in env.envs)


def crossing_scene(env: DummyVecEnv) -> dict[str, np.ndarray]:
    """Reset until the first worker sees a neighbour crossing the ego's heading; its observation."""
    for seed in range(200):
        env.seed(seed)
        obs = env.reset()
        first = {key: value[:1] for key, value in obs.items()}
        pose, _ = current_poses({key: th.as_tensor(value) for key, value in first.items()})
        present = first["history_mask"][0, 1].any()
        if present and 0.5 < abs(float(pose[0, 1, 2])) < 2.6:
            return {key: value[0] for key, value in first.items()}
    raise AssertionError("no crossing neighbour in 200 seeds")


def colliding_predictor(obs: dict[str, np.ndarray]) -> TrajectoryPredictor:
    """A predictor whose every vehicle moves by the same offset (f, l) in its own frame, chosen so
    that the ego lands on the first neighbour: (I - R(h)) (f, l) = (x, y)."""
    predictor = tiny_predictor()
    pose, _ = current_poses({key: th.as_tensor(value)[None] for key, value in obs.items()})
    x, y, h = (float(v) for v in pose[0, 1])
    rotation = np.array([[np.cos(h), -np.sin(h)], [np.sin(h), np.cos(h)]])
    forward, left = np.linalg.solve(np.eye(2) - rotation, [x, y])
    last = predictor.decoder[-1]
    scale = float(predictor.output_scale[0])
    with th.no_grad():
        last.weight.zero_()
        last.bias.copy_(th.tensor([forward / scale, left / scale, 0.0] * predictor.horizon))
    return predictor


def test_pushed_weights_change_the_workers_masks():
    env = decider_vec_env(n_envs=1, spawn_probability=0.2)
    obs = crossing_scene(env)
    callback = GCCPCallback(
        GCCPSettings(predictor_kwargs=TINY_PREDICTOR), tiny_predictor(), EpisodeReplayBuffer(10)
    )
    callback.init_callback(tiny_model(env))

    with th.no_grad():  # everybody stands still: nothing collides
        callback.predictor.decoder[-1].weight.zero_()
        callback.predictor.decoder[-1].bias.zero_()
    callback.push_masks()
    (still,) = env.env_method("action_masks")
    assert still.all()

    callback.predictor.load_state_dict(colliding_predictor(obs).state_dict())
    callback.push_masks()
    (colliding,) = env.env_method("action_masks")
    nearest = np.argmin(np.hypot(*obs["subgoals"][:, :2].T))
    # Every subgoal is predicted to collide: the env's fallback allows only the nearest candidate.
    assert colliding.sum() == 1 and colliding[nearest]
