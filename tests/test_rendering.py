"""RGB frames: size, colours of the ego, candidates, masked candidates and the chosen subgoal."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from helpers import place_ego

from gccp_envs.rendering import (
    CANDIDATE_COLOR,
    CHOSEN_COLOR,
    EGO_COLOR,
    MASKED_COLOR,
    OFF_ROAD_COLOR,
    PREDICTED_EGO_COLOR,
    PREDICTED_NEIGHBOUR_COLOR,
    TEXT_COLOR,
    IntersectionRenderer,
)

SIZE, VIEW = 600, 100.0


def pixel(x, y):
    """(row, column) of a world point in a frame: the junction centre in the middle, y down."""
    return int((y + VIEW / 2) * SIZE / VIEW), int((x + VIEW / 2) * SIZE / VIEW)


def where(frame, color):
    return np.argwhere(np.all(frame == np.array(color, np.uint8), axis=-1))


def make(env_id, **kwargs):
    env = gym.make(
        env_id, render_mode="rgb_array", **{"spawn_probability": 0.0, "task": "straight", **kwargs}
    ).unwrapped
    env.reset(seed=0)
    return env


@pytest.mark.parametrize("env_id", ["GCCPPlanner-v0", "GCCPDecider-v0", "GCCPFlat-v0"])
def test_frame_shape_and_background(env_id):
    env = make(env_id)
    frame = env.render()
    assert frame.shape == (SIZE, SIZE, 3) and frame.dtype == np.uint8
    assert frame.flags["C_CONTIGUOUS"]
    # Off-road shading between the arms, not on the road.
    np.testing.assert_array_equal(frame[pixel(-40, -40)], OFF_ROAD_COLOR)
    np.testing.assert_array_equal(frame[pixel(40, 30)], OFF_ROAD_COLOR)
    assert not np.array_equal(frame[pixel(0, 0)], OFF_ROAD_COLOR)
    assert not np.array_equal(frame[pixel(-40, 4)], OFF_ROAD_COLOR)  # the west arm
    # The ego is drawn in green where it is.
    ego = env.world.ego
    green = where(frame, EGO_COLOR)
    assert len(green) > 20
    np.testing.assert_allclose(green.mean(0), pixel(ego.x, ego.y), atol=3)
    env.close()


def test_decider_draws_the_chosen_subgoal_after_a_step():
    env = make("GCCPDecider-v0")
    frame = env.render()
    assert len(where(frame, CHOSEN_COLOR)) == 0  # nothing chosen yet
    assert len(where(frame, CANDIDATE_COLOR)) > 0
    env.step(3)
    frame = env.render()
    gold = where(frame, CHOSEN_COLOR)
    assert len(gold) > 30
    x, y, _ = env._subgoal
    # The large dot is centred on the subgoal; the heading tick points north (up) from it.
    assert np.min(np.hypot(*(gold - pixel(x, y)).T)) < 1.5
    assert gold[:, 0].min() < pixel(x, y)[0] - 8


def test_decider_draws_masked_candidates_red():
    env = make("GCCPDecider-v0")
    assert len(where(env.render(), MASKED_COLOR)) == 0
    env.set_mask_fn(lambda obs: np.arange(12) % 2 == 0)
    env.action_masks()
    assert len(where(env.render(), MASKED_COLOR)) > 0


def test_planner_draws_its_goal_and_the_flat_env_no_candidates():
    planner = make("GCCPPlanner-v0")
    frame = planner.render()
    assert len(where(frame, CHOSEN_COLOR)) > 0
    assert len(where(frame, CANDIDATE_COLOR)) > 0
    flat = make("GCCPFlat-v0")
    frame = flat.render()
    assert len(where(frame, CANDIDATE_COLOR)) == 0
    gold = where(frame, CHOSEN_COLOR)
    goal = flat.world.task_goal
    assert np.min(np.hypot(*(gold - pixel(goal[0], goal[1])).T)) < 1.5


def test_frames_follow_the_world():
    env = make("GCCPPlanner-v0", spawn_probability=0.3)
    place_ego(env.world, 6.0, 35.0, -np.pi / 2, 8.0)  # well inside the view
    first = env.render()
    for _ in range(5):
        env.step(1)
    second = env.render()
    assert not np.array_equal(first, second)
    np.testing.assert_allclose(
        where(second, EGO_COLOR).mean(0), pixel(env.world.ego.x, env.world.ego.y), atol=3
    )
    # Other vehicles are drawn (grey) somewhere in the view after the warm-up.
    assert len(where(second, (200, 200, 200))) > 0


def test_renderer_frame_without_extras(layout):
    from helpers import EMPTY

    from gccp_envs.world import IntersectionWorld

    world = IntersectionWorld(EMPTY)
    world.reset(np.random.default_rng(0), "left")
    frame = IntersectionRenderer(layout, size=200, view=50.0).frame(world)
    assert frame.shape == (200, 200, 3)
    assert len(where(frame, CHOSEN_COLOR)) == len(where(frame, CANDIDATE_COLOR)) == 0


def test_predicted_trajectories_caption_and_legend(layout):
    from helpers import EMPTY

    from gccp_envs.world import IntersectionWorld

    world = IntersectionWorld(EMPTY)
    world.reset(np.random.default_rng(0), "left")
    renderer = IntersectionRenderer(layout)
    plain = renderer.frame(world)
    ego_path = np.stack([np.linspace(-30, -20, 10), np.full(10, 6.0)], -1)  # on the west arm
    others = np.stack([np.full((1, 10), 20.0), np.linspace(-6, -2, 10)[None]], -1)  # on the east arm
    frame = renderer.frame(world, ego_prediction=ego_path, neighbour_predictions=others)
    for color, path in ((PREDICTED_EGO_COLOR, ego_path), (PREDICTED_NEIGHBOUR_COLOR, others[0])):
        drawn = where(frame, color)
        assert len(where(plain, color)) == 0 and len(drawn) > 20
        np.testing.assert_allclose(drawn.min(0), np.min([pixel(x, y) for x, y in path], 0), atol=4)
        np.testing.assert_allclose(drawn.max(0), np.max([pixel(x, y) for x, y in path], 0), atol=4)
    labelled = renderer.frame(world, caption="left\nt = 0.0 s", legend=True)
    corner = labelled[:200, :200]  # the grass north-west of the junction (lane markings are white too)
    assert len(where(plain[:200, :200], TEXT_COLOR)) == 0
    rows = where(corner, TEXT_COLOR)[:, 0]
    assert rows.max() - rows.min() > renderer.font.get_linesize()  # one caption line under the other
    legend = (CANDIDATE_COLOR, MASKED_COLOR, CHOSEN_COLOR, PREDICTED_EGO_COLOR, PREDICTED_NEIGHBOUR_COLOR)
    for color in legend:
        assert len(where(corner, color)) > 0, color


def test_centre_moves_the_view(layout):
    from helpers import EMPTY

    from gccp_envs.world import IntersectionWorld

    world = IntersectionWorld(EMPTY)
    world.reset(np.random.default_rng(0), "left")
    ego = world.ego
    frame = IntersectionRenderer(layout, centre=(0.0, 10.0)).frame(world)
    np.testing.assert_allclose(where(frame, EGO_COLOR).mean(0), pixel(ego.x, ego.y - 10.0), atol=3)
