"""``hierarchy.yml``: reading it (files, GCCP variant and check, overrides), writing it, running it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from sb3_gccp.gccp.settings import RETIRED_CHECK_KEYS, GCCPCheck
from sb3_gccp.hierarchy import Hierarchy, load_hierarchy


def test_a_hierarchy_written_reads_back_the_same(tmp_path):
    (tmp_path / "decider.zip").write_bytes(b"not read here")
    (tmp_path / "predictor.pt").write_bytes(b"not read here")
    hierarchy = Hierarchy(
        tmp_path,
        planner_file="scripted",
        predictor="learned",
        predictor_weights_file="predictor.pt",
        trained_check=GCCPCheck(margin=1.0, extrapolate_steps=10),
        trained_world={"duration": 20.0, "ego_start_speed": (4.0, 8.0)},
    )
    spec = yaml.safe_load(hierarchy.write().read_text())
    assert list(spec) == [
        "planner",
        "decider",
        "predictor",
        "predictor_weights",
        "mask_margin",
        "mask_extrapolate_steps",
        "mask_ego_deceleration",
        "mask_yield_margin",
        "mask_fallback_margin",
        "mask_vehicle_sizes",
        "world",
    ]
    assert spec["world"]["ego_start_speed"] == [4.0, 8.0]
    read = Hierarchy.read(tmp_path)
    assert read.to_dict() == hierarchy.to_dict() and read.planner is None
    assert read.predictor_weights == tmp_path / "predictor.pt" and read.decider == tmp_path / "decider.zip"


def test_a_write_that_fails_leaves_the_file_before_it(tmp_path, monkeypatch):
    import sb3_gccp.training.checkpoints as checkpoints

    (tmp_path / "decider.zip").write_bytes(b"not read here")
    hierarchy = Hierarchy(
        tmp_path, planner_file="scripted", predictor="none", trained_world={"duration": 20.0}
    )
    before = hierarchy.write().read_text()
    changed = Hierarchy(tmp_path, planner_file="scripted", predictor="none", trained_world={"duration": 25.0})

    def fail(source, target):
        raise OSError("disk full")

    monkeypatch.setattr(checkpoints.os, "replace", fail)
    with pytest.raises(OSError):
        changed.write()
    assert (tmp_path / "hierarchy.yml").read_text() == before


def test_overrides_are_written_apart_from_what_was_trained(tmp_path):
    (tmp_path / "decider.zip").write_bytes(b"not read here")
    trained = Hierarchy(tmp_path, planner_file="scripted", predictor="cv", trained_world={"duration": 20.0})
    changed = trained.with_overrides({"duration": 10.0}, {"mask_margin": 0.5})
    assert changed.world == {"duration": 10.0} and changed.check.margin == 0.5
    assert changed.trained_check == trained.trained_check == GCCPCheck()
    spec = changed.to_dict()
    assert spec["world"] == {"duration": 20.0} and spec["mask_margin"] == 0.0
    assert spec["overrides"] == {"world": {"duration": 10.0}, "mask": {"mask_margin": 0.5}}
    changed.write()
    with pytest.raises(ValueError, match=r"not trained with \(overrides: world.duration, mask.mask_margin\)"):
        load_hierarchy(tmp_path)
    assert load_hierarchy(tmp_path, allow_overrides=True).to_dict() == spec
    with pytest.raises(ValueError, match="duration must be a positive number"):
        trained.with_overrides({"duration": 0.0})


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"predictor": "magic"}, "predictor must be one of learned, no_goal, cv, none, got 'magic'"),
        ({"predictor": "learned"}, "a learned predictor needs predictor_weights"),
        ({"planner_file": "x"}, "unknown key(s) planner_file: expected planner,"),
        ({"world": [1, 2]}, "world must be a map of world config keys"),
        ({"overrides": {"mask": {"margin": 1}}}, "unknown GCCP check key(s) in overrides.mask: margin"),
        ({"overrides": {"reward": {}}}, "overrides must be a map with the keys world and mask"),
        ({"predictor": "none", "overrides": {"mask": {"mask_margin": 1}}}, "has no GCCP module"),
    ],
)
def test_a_bad_hierarchy_file_is_named_in_one_line(tmp_path, spec, message):
    _cv_hierarchy(tmp_path, **spec)
    with pytest.raises(ValueError) as raised:
        load_hierarchy(tmp_path, allow_overrides=True)
    assert message in str(raised.value) and "\n" not in str(raised.value)


@pytest.mark.parametrize("key", ["planner", "decider", "predictor", "world"])
def test_a_hierarchy_file_without_a_required_key_is_named_in_one_line(tmp_path, key):
    _cv_hierarchy(tmp_path)
    spec = yaml.safe_load((tmp_path / "hierarchy.yml").read_text())
    del spec[key]
    (tmp_path / "hierarchy.yml").write_text(yaml.safe_dump(spec))
    with pytest.raises(ValueError, match=f"hierarchy.yml: missing key\\(s\\) {key}$"):
        load_hierarchy(tmp_path)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("/etc/hostname", "decider must name a file inside"),
        ("../decider.zip", "decider must name a file inside"),
        ("sub/../../decider.zip", "decider must name a file inside"),
        ("link.zip", "decider leads out of"),
    ],
)
def test_a_hierarchy_file_naming_a_file_outside_its_folder_is_refused(tmp_path, name, message):
    folder = tmp_path / "model"
    folder.mkdir()
    (tmp_path / "decider.zip").write_bytes(b"outside the folder")
    (folder / "link.zip").symlink_to(tmp_path / "decider.zip")
    _cv_hierarchy(folder, decider=name)
    with pytest.raises(ValueError, match=message) as raised:
        load_hierarchy(folder)
    assert "\n" not in str(raised.value)


def test_hierarchy_file_sets_the_mask_margin_and_extrapolation(tmp_path):
    (tmp_path / "decider.zip").write_bytes(b"not read here")
    spec = {"planner": "scripted", "decider": "decider.zip", "predictor": "cv", "world": {}}
    (tmp_path / "hierarchy.yml").write_text(yaml.safe_dump(spec))
    paper = load_hierarchy(tmp_path).mask_fn()
    assert paper is not None and paper.checker.margin == 0.0 and paper.extrapolate_steps == 0
    spec.update(mask_margin=1.0, mask_extrapolate_steps=10)
    (tmp_path / "hierarchy.yml").write_text(yaml.safe_dump(spec))
    longer = load_hierarchy(tmp_path).mask_fn()
    assert longer is not None and longer.checker.margin == 1.0 and longer.extrapolate_steps == 10
    assert longer.ego_deceleration is None
    spec.update(mask_ego_deceleration=4.0)
    (tmp_path / "hierarchy.yml").write_text(yaml.safe_dump(spec))
    braking = load_hierarchy(tmp_path).mask_fn()
    assert braking is not None and braking.ego_deceleration == 4.0 and braking.yield_checker is None
    spec.update(mask_yield_margin=0.5)
    (tmp_path / "hierarchy.yml").write_text(yaml.safe_dump(spec))
    held = load_hierarchy(tmp_path).mask_fn()
    assert held is not None and held.yield_checker is not None and held.yield_checker.margin == 0.5
    assert held.yield_checker.ego_size == (5.5, 2.5) and held.checker.ego_size == (6.0, 3.0)


def _cv_hierarchy(folder: Path, **settings: object) -> None:
    (folder / "decider.zip").write_bytes(b"not read here")
    spec = {"planner": "scripted", "decider": "decider.zip", "predictor": "cv", "world": {}, **settings}
    (folder / "hierarchy.yml").write_text(yaml.safe_dump(spec))


def test_a_run_folder_with_a_removed_key_at_its_neutral_value_still_loads(tmp_path):
    world = {"r_fail": 0.0, "lane_change_distance": 0.0}
    _cv_hierarchy(tmp_path, mask_margin=1.0, **RETIRED_CHECK_KEYS, world=world)
    hierarchy = load_hierarchy(tmp_path)
    assert hierarchy.check.margin == 1.0 and not set(RETIRED_CHECK_KEYS) & set(hierarchy.to_dict())


@pytest.mark.parametrize(
    ("key", "value"),
    [("mask_standing_escape", True), ("mask_extrapolate_ego", "route"), ("mask_unyielded", True)],
)
def test_a_run_folder_with_a_removed_key_at_another_value_is_refused(tmp_path, key, value):
    _cv_hierarchy(tmp_path, **{key: value})
    message = f"GCCP check key '{key}' was removed; a run that set it to {value!r} cannot load"
    with pytest.raises(ValueError, match=re.escape(message)):
        load_hierarchy(tmp_path)


def test_mask_settings_given_at_load_replace_the_hierarchy_files(tmp_path):
    _cv_hierarchy(tmp_path, mask_margin=1.0, mask_extrapolate_steps=10)
    hierarchy = load_hierarchy(tmp_path, {"mask_margin": 0.5, "mask_ego_deceleration": 4})
    mask = hierarchy.mask_fn()
    assert mask is not None and mask.checker.margin == 0.5 and mask.extrapolate_steps == 10
    assert mask.ego_deceleration == 4.0
    assert load_hierarchy(tmp_path, {}).check.margin == 1.0


@pytest.mark.parametrize(
    "settings, message",
    [
        ({"mask_margni": 1.0}, "unknown GCCP check key(s) mask_margni"),
        ({"mask_margin": -1.0}, "mask_margin must be a non-negative number"),
        ({"mask_margin": "wide"}, "mask_margin must be a non-negative number"),
        ({"mask_extrapolate_steps": 2.5}, "mask_extrapolate_steps must be a non-negative integer"),
        ({"mask_extrapolate_steps": True}, "mask_extrapolate_steps must be a non-negative integer"),
        ({"mask_ego_deceleration": 0}, "mask_ego_deceleration must be a positive number"),
        ({"mask_yield_margin": -0.5}, "mask_yield_margin must be a non-negative number"),
    ],
)
def test_bad_mask_settings_are_rejected_in_one_line(tmp_path, settings, message):
    _cv_hierarchy(tmp_path)
    with pytest.raises(ValueError, match=r"^GCCP check: |^unknown") as given:
        load_hierarchy(tmp_path, settings)
    assert message in str(given.value) and "\n" not in str(given.value)
    if "mask_margni" not in settings:  # the same value written in the file names the file
        _cv_hierarchy(tmp_path, **settings)
        with pytest.raises(ValueError, match="hierarchy.yml: " + message.split()[0]):
            load_hierarchy(tmp_path)


def test_mask_settings_need_a_gccp_module(tmp_path):
    (tmp_path / "decider.zip").write_bytes(b"not read here")
    spec = {"planner": "scripted", "decider": "decider.zip", "predictor": "none", "world": {}}
    (tmp_path / "hierarchy.yml").write_text(yaml.safe_dump(spec))
    assert load_hierarchy(tmp_path).mask_fn() is None
    with pytest.raises(ValueError, match="no GCCP module"):
        load_hierarchy(tmp_path, {"mask_margin": 0.5})
