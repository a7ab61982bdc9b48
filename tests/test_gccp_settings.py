"""The GCCP settings: the collision check's defaults, validation, YAML form and mask; the gccp map."""

from __future__ import annotations

import re

import pytest

from gccp_envs.config import IntersectionConfig
from sb3_gccp.gccp.predictor import ConstantVelocityPredictor
from sb3_gccp.gccp.settings import GCCPCheck, GCCPSettings

OURS = IntersectionConfig()


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"n_episode": 5}, "unknown gccp settings key(s): 'n_episode' (did you mean 'n_episodes'?)"),
        (
            {"mask_standing_escape": True},
            "gccp settings key 'mask_standing_escape' was removed; a run that set it to True cannot load "
            "(only False, its value that changed nothing)",
        ),
        ({"predictor": "magic"}, "gccp.predictor must be one of learned, no_goal, cv, none, got 'magic'"),
        ({"n_episodes": 0}, "gccp.n_episodes must be a positive integer, got 0"),
        ({"mask_after_episodes": -1}, "gccp.mask_after_episodes must be a non-negative integer, got -1"),
        ({"mask_margin": -0.5}, "gccp.mask_margin must be a non-negative number, got -0.5"),
        (
            {"mask_extrapolate_steps": 1.5},
            "gccp.mask_extrapolate_steps must be a non-negative integer, got 1.5",
        ),
        ({"mask_ego_deceleration": 0}, "gccp.mask_ego_deceleration must be a positive number, got 0"),
        (
            {"mask_vehicle_sizes": "smarts"},
            "gccp.mask_vehicle_sizes must be one of simulator, builtin, got 'smarts'",
        ),
        (
            {"predictor_kwargs": {"decoder_width": 3}},
            "unknown predictor config key(s): 'decoder_width' (did you mean 'decoder_hidden'?)",
        ),
    ],
)
def test_bad_settings_name_the_problem(values, message):
    with pytest.raises(ValueError, match="^" + re.escape(message) + "$"):
        GCCPSettings.from_dict(values)


def test_a_removed_check_key_at_its_neutral_value_is_dropped():
    assert GCCPSettings.from_dict({"mask_standing_escape": False}) == GCCPSettings.from_dict({})
    assert GCCPCheck.from_dict({"mask_standing_escape": False, "mask_margin": 1.0}) == GCCPCheck(margin=1.0)


def test_a_check_builds_the_mask_with_its_margin_and_extrapolation():
    mask = GCCPCheck(margin=1.0, extrapolate_steps=5).make_mask(ConstantVelocityPredictor(), OURS)
    assert mask.checker.margin == 1.0 and mask.checker.ego_size == (6.0, 3.0)
    assert mask.extrapolate_steps == 5
    paper = GCCPCheck().make_mask(ConstantVelocityPredictor(), OURS)
    assert paper.checker.margin == 0.0 and paper.extrapolate_steps == 0
    assert paper.ego_deceleration is None and mask.ego_deceleration is None
    braking = GCCPCheck(extrapolate_steps=5, ego_deceleration=4.0)
    assert braking.make_mask(ConstantVelocityPredictor(), OURS).ego_deceleration == 4.0
    held = GCCPCheck(margin=1.0, yield_margin=0.5).make_mask(ConstantVelocityPredictor(), OURS)
    assert held.yield_checker is not None and held.yield_checker.margin == 0.5
    assert held.yield_checker.ego_size == (5.5, 2.5)


def test_the_boxes_have_the_simulators_sizes_unless_told_ours():
    smarts = IntersectionConfig(simulator="smarts")
    mask = GCCPCheck(margin=1.0).make_mask(ConstantVelocityPredictor(), smarts)
    assert mask.checker.ego_size == pytest.approx((4.68, 2.47))
    assert mask.checker.neighbour_size == pytest.approx((4.68, 2.47))
    ours = GCCPCheck(margin=1.0, vehicle_sizes="builtin").make_mask(ConstantVelocityPredictor(), smarts)
    assert ours.checker.ego_size == ours.checker.neighbour_size == (6.0, 3.0)
    assert GCCPCheck.from_dict({"mask_vehicle_sizes": "builtin"}).vehicle_sizes == "builtin"
    assert GCCPCheck().to_dict()["mask_vehicle_sizes"] == "simulator"


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"margin": -1.0}, "mask_margin must be a non-negative number, got -1.0"),
        ({"extrapolate_steps": -1}, "mask_extrapolate_steps must be a non-negative integer, got -1"),
        ({"ego_deceleration": 0.0}, "mask_ego_deceleration must be a positive number, got 0.0"),
        ({"yield_margin": "wide"}, "mask_yield_margin must be a non-negative number, got 'wide'"),
        ({"fallback_margin": -0.5}, "mask_fallback_margin must be a non-negative number, got -0.5"),
        ({"vehicle_sizes": "smarts"}, "mask_vehicle_sizes must be one of simulator, builtin, got 'smarts'"),
    ],
)
def test_a_check_built_in_code_rejects_bad_values_by_their_yaml_key(values, message):
    with pytest.raises(ValueError, match="^" + re.escape(message) + "$"):
        GCCPCheck(**values)


def test_the_yaml_form_of_a_check_round_trips_and_names_the_file_in_errors():
    check = GCCPCheck.from_dict({"mask_margin": 1, "mask_extrapolate_steps": 10})
    assert check == GCCPCheck(margin=1.0, extrapolate_steps=10) and isinstance(check.margin, float)
    assert check.to_dict() == {
        "mask_margin": 1.0,
        "mask_extrapolate_steps": 10,
        "mask_ego_deceleration": None,
        "mask_yield_margin": None,
        "mask_fallback_margin": None,
        "mask_vehicle_sizes": "simulator",
    }
    assert GCCPCheck.from_dict(check.to_dict()) == check
    assert check.replace({"mask_yield_margin": 0.5}).yield_margin == 0.5
    with pytest.raises(ValueError, match=r"^hierarchy\.yml: mask_margin must be a non-negative number"):
        GCCPCheck.from_dict({"mask_margin": -1}, "hierarchy.yml: ")
    with pytest.raises(ValueError, match=r"^unknown GCCP check key\(s\) margin: expected mask_margin, "):
        check.replace({"margin": 1.0})


def test_gccp_settings_read_the_check_from_their_mask_keys_and_write_them_back():
    values = {"n_episodes": 10, "mask_margin": 1.0, "mask_yield_margin": 0.5}
    settings = GCCPSettings.from_dict(values)
    assert settings.check == GCCPCheck(margin=1.0, yield_margin=0.5)
    written = settings.to_dict()
    assert list(written)[-6:] == list(GCCPCheck().to_dict()) and "check" not in written
    assert GCCPSettings.from_dict(written) == settings
    with pytest.raises(ValueError, match=r"^unknown gccp settings key\(s\): 'check'"):
        GCCPSettings.from_dict({"check": {}})
