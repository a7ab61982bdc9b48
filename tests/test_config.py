"""IntersectionConfig: the paper's constants, derived sizes and validation with helpful messages."""

from __future__ import annotations

import pytest

from gccp_envs.config import DT, TASKS, IntersectionConfig, parse_tasks, require_int, require_positive


def test_paper_constants():
    cfg = IntersectionConfig()
    assert DT == 0.1
    assert TASKS == ("left", "straight", "right")
    assert (cfg.num_subgoals, cfg.num_neighbours, cfg.num_routes, cfg.route_points) == (12, 5, 3, 50)
    assert (cfg.route_spacing, cfg.bev_size, cfg.bev_extent) == (1.0, 64, 50.0)
    assert (cfg.subgoal_spacing, cfg.subgoal_range, cfg.decision_period) == (5.0, 20.0, 10)
    assert (cfg.r_time, cfg.r_arr, cfg.r_col, cfg.r_off, cfg.eps_d, cfg.eps_h) == (
        -0.05,
        1.0,
        -1.0,
        -1.0,
        0.05,
        0.5,
    )
    assert (cfg.r_goal, cfg.r_subgoal, cfg.r_near, cfg.eps_s) == (3.0, 0.5, -0.5, 0.05)


def test_derived_sizes():
    cfg = IntersectionConfig(lanes_per_approach=3, lane_width=3.5, corner_radius=4.0)
    assert cfg.road_half_width == pytest.approx(10.5)
    assert cfg.junction_half_size == pytest.approx(14.5)


def test_from_dict_accepts_yaml_lists_and_overrides():
    cfg = IntersectionConfig.from_dict({"task": "left", "ego_start_speed": [1.0, 2.0]}, task="right")
    assert cfg.task == "right"
    assert cfg.ego_start_speed == (1.0, 2.0)
    assert isinstance(cfg.ego_start_speed, tuple)
    assert IntersectionConfig.from_dict(None) == IntersectionConfig()


def test_from_dict_names_unknown_keys_with_close_matches():
    with pytest.raises(ValueError, match=r"'spawn_probabilty' \(did you mean 'spawn_probability'\?\)"):
        IntersectionConfig.from_dict({"spawn_probabilty": 0.1})
    with pytest.raises(ValueError, match=r"'zzz_unrelated'") as info:
        IntersectionConfig.from_dict(num_subgoal=3, zzz_unrelated=1)
    assert "did you mean 'num_subgoals'" in str(info.value)


def test_a_removed_key_loads_only_at_the_value_that_changed_nothing():
    loaded = {"r_fail": 0.0, "r_junction_stand": 0, "lane_change_distance": 0.0, "duration": 20.0}
    assert IntersectionConfig.from_dict(loaded) == IntersectionConfig(duration=20.0)
    with pytest.raises(
        ValueError, match=r"^intersection config key 'r_fail' was removed; a run that set it to -3\.0"
    ):
        IntersectionConfig.from_dict({"r_fail": -3.0})
    with pytest.raises(ValueError, match=r"^intersection config key 'lane_change_distance' was removed"):
        IntersectionConfig.from_dict({"lane_change_distance": 15.0})


def test_replace_rejects_unknown_keys_like_from_dict():
    with pytest.raises(ValueError, match="did you mean 'spawn_probability'"):
        IntersectionConfig().replace(spawn_probabilty=0.1)


def test_replace_validates():
    assert IntersectionConfig().replace(task="left").task == "left"
    with pytest.raises(ValueError, match="task"):
        IntersectionConfig().replace(task="diagonal")


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"task": "diagonal"}, "unknown task 'diagonal'"),
        ({"ego_lane": "middle"}, "ego_lane"),
        ({"lanes_per_approach": 0}, "lanes_per_approach must be a positive integer"),
        ({"num_subgoals": 2.5}, "num_subgoals must be a positive integer"),
        ({"history_length": True}, "history_length must be a positive integer"),
        ({"lane_width": 0.0}, "lane_width must be a positive number"),
        ({"cruise_speed": -1.0}, "cruise_speed must be a positive number"),
        ({"npc_patience": 0.0}, "npc_patience must be a positive number"),
        ({"npc_patience": "8"}, "npc_patience must be a positive number"),
        ({"scripted_stop_aligned": "yes"}, "scripted_stop_aligned must be true or false"),
        ({"scripted_turn_speed": 0.0}, "scripted_turn_speed must be a positive number"),
        ({"r_near": "-0.5"}, "r_near must be a number, got '-0.5'"),
        ({"eps_s": True}, "eps_s must be a number, got True"),
        ({"r_subgoal_needs_travel": 1}, "r_subgoal_needs_travel must be true or false"),
        ({"smarts_grid_map": "no"}, "smarts_grid_map must be true or false"),
        ({"fallback_go_on_skips_hold": "maybe"}, "fallback_go_on_skips_hold must be true or false"),
        ({"standing_turn_drives": "maybe"}, "standing_turn_drives must be true or false"),
        ({"smarts_routes": "lanes"}, "unknown smarts_routes 'lanes': expected one of layout, waypoints"),
        ({"wrong_exit_penalty": 0}, "wrong_exit_penalty must be true or false"),
        ({"spawn_probability": 1.5}, "spawn_probability"),
        ({"spawn_probability": -0.1}, "spawn_probability"),
        ({"ego_start_speed": (8.0, 4.0)}, "ego_start_speed"),
        ({"npc_speed_range": (1.0,)}, "npc_speed_range"),
        ({"ego_start_distance": (25.0, 65.0)}, "ego_start_distance"),
        ({"exit_distance": 65.0}, "exit_distance"),
        ({"prediction_horizon": 11}, "prediction_horizon"),
        ({"quick_turn_curvature": 0.05}, "quick_turn_curvature"),
    ],
)
def test_validation_names_the_bad_field(changes, message):
    with pytest.raises(ValueError, match=message):
        IntersectionConfig(**changes)
    with pytest.raises(ValueError, match=message):
        IntersectionConfig.from_dict(changes)


def test_config_is_frozen():
    cfg = IntersectionConfig()
    with pytest.raises(AttributeError):
        cfg.task = "left"  # type: ignore[misc]


@pytest.mark.parametrize(
    ("value", "minimum", "message"),
    [
        (0, 1, "x must be a positive integer, got 0"),
        (True, 1, "x must be a positive integer, got True"),
        (2.0, 1, "x must be a positive integer, got 2.0"),
        (-1, 0, "x must be a non-negative integer, got -1"),
    ],
)
def test_require_int_rejects_in_one_line(value, minimum, message):
    with pytest.raises(ValueError) as err:
        require_int("x", value, minimum)
    assert str(err.value) == message


def test_require_int_and_positive_accept_good_values():
    require_int("x", 0, minimum=0)
    require_int("x", 3)
    require_positive("x", 1e-9)
    require_positive("x", 2)


@pytest.mark.parametrize("value", [0, -0.5, False, "1", None])
def test_require_positive_rejects(value):
    with pytest.raises(ValueError, match=f"^x must be a positive number, got {value!r}$"):
        require_positive("x", value)


def test_parse_tasks_reads_a_comma_separated_subset_in_one_line_errors():
    assert parse_tasks(" left, right") == ["left", "right"]
    assert parse_tasks(",".join(TASKS)) == list(TASKS)
    with pytest.raises(ValueError, match=r"^unknown task\(s\) 'up': expected a comma-separated subset"):
        parse_tasks("left,up")
    with pytest.raises(ValueError, match=r"^unknown task\(s\) \(none\)"):
        parse_tasks(" , ")
