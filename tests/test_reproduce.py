"""``sb3_gccp reproduce``: every method end to end on a tiny budget, resuming, bad input, the tables."""

from __future__ import annotations

import csv
import json
import re
import subprocess
from pathlib import Path

import pytest
import torch as th
import yaml
from helpers import reproduce, run_cli

from sb3_gccp.cli import main
from sb3_gccp.hyperparams import default_config_file, load_hyperparams
from sb3_gccp.reproduce.methods import METHODS, TABLE_1, TABLE_2
from sb3_gccp.reproduce.plan import (
    PRESETS,
    check_settings,
    mask_after_episodes,
    method_settings,
    planner_settings,
)
from sb3_gccp.reproduce.report import aggregate, format_results_table
from sb3_gccp.training.baselines import MASKS_KEY

FIGURES = ("fig5_baselines", "fig6_ablations", "fig7_predictor_errors", "fig8_predictions")


@pytest.fixture(scope="module")
def reproduced(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    folder = tmp_path_factory.mktemp("reproduce")
    return folder, reproduce(folder)


def test_quick_preset_trains_evaluates_and_writes_tables_data_and_figures(reproduced):
    folder, result = reproduced
    assert result.returncode == 0, result.stderr
    out, root = folder / "results", folder / "runs" / "reproduce" / "quick"
    assert "[1/12] seed 0 planner: training for 32 steps" in result.stdout
    assert "[11/12] seed 0 sac_discrete_paper: training for 2 episodes" in result.stdout
    assert "[12/12] seed 0 predictor_errors: finished in" in result.stdout

    for stem, names in (("table1", TABLE_1), ("table2", TABLE_2)):
        table = (out / f"{stem}.md").read_text()
        for name in names:
            assert f"\n| {METHODS[name].label} | " in table, (stem, name)
        assert "| method | left S/C | straight S/C | right S/C | overall S/C | timeout % |" in table
    for figure in FIGURES:
        assert (out / f"{figure}.png").stat().st_size > 10_000, figure

    with (out / "results.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert {(r["method"], r["task"]) for r in rows} == {
        (m, t) for m in METHODS for t in ("left", "straight", "right", "overall")
    }
    results = json.loads((out / "results.json").read_text())
    assert results["budget"]["episodes_per_method"] == 2
    assert results["budget"]["planner_pretraining"]["0"]["timesteps"] == 32
    assert set(results["predictor_errors"]["0"]["errors"]) == {"learned", "no_goal", "cv"}
    # Every run's records, copied beside the tables.
    for name in METHODS:
        for record in ("training.json", "evaluation.json", "episodes.csv"):
            copy = out / "records" / "seed0" / name / record
            assert copy.read_bytes() == (root / "seed0" / name / record).read_bytes(), (name, record)
    assert (out / "records" / "seed0" / "predictor_errors.json").is_file()

    # The same budget for every method, the same traffic flows for every method's evaluation.
    flows = set()
    for name in METHODS:
        run = root / "seed0" / name
        assert json.loads((run / "training.json").read_text())["episodes"] == 2, name
        with (run / "episodes.csv").open() as file:
            assert len(list(csv.DictReader(file))) == 2, name
        episodes = json.loads((run / "evaluation.json").read_text())["episodes"]
        flows.add(tuple((e["task"], e["seed"]) for e in episodes))
    assert flows == {(("left", 0), ("straight", 0), ("right", 0))}
    # The four hierarchy variants differ in their GCCP predictor and share one planner.
    for name in ("ours", "with_cv", "without_gccp", "without_goal"):
        run = root / "seed0" / name
        assert yaml.safe_load((run / "hierarchy.yml").read_text())["predictor"] == METHODS[name].predictor
        assert (run / "planner.zip").read_bytes() == (root / "seed0" / "planner" / "planner.zip").read_bytes()


@pytest.mark.slow  # 13 s; the quick preset test covers a whole run in the fast tier
def test_a_second_run_skips_finished_methods_and_restarts_an_unfinished_one(reproduced):
    folder, first = reproduced
    assert first.returncode == 0, first.stderr
    root = folder / "runs" / "reproduce" / "quick" / "seed0"
    ours_model = (root / "ours" / "decider.zip").stat().st_mtime_ns
    (root / "dqn" / "training.json").unlink()  # as if interrupted while training

    result = reproduce(folder)
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("finished before, skipped") == 8  # all but dqn
    assert "seed 0 dqn: training for 2 episodes" in result.stdout
    assert "seed 0 dqn: an unfinished run without a checkpoint starts over" in result.stdout
    assert (root / "ours" / "decider.zip").stat().st_mtime_ns == ours_model
    assert (root / "dqn" / "training.json").is_file()


@pytest.mark.slow  # 30 s; tests/test_export.py covers export in the fast tier
def test_export_gives_small_folders_that_evaluate_like_their_runs(reproduced, tmp_path):
    folder, result = reproduced
    assert result.returncode == 0, result.stderr
    root = folder / "runs" / "reproduce" / "quick" / "seed0"
    evaluate = ("evaluate", "--tasks", "left", "--episodes-per-task", "2", "--set", "duration=2.0")
    for name, kind, models in (
        ("ours", "hierarchy", ("decider", "planner")),
        ("ppo", "baseline ppo", ("model",)),
    ):
        run, out = root / name, tmp_path / name
        exported = run_cli("export", str(run), str(out), cwd=tmp_path)
        assert exported.returncode == 0, exported.stderr
        for model in models:
            assert (out / f"{model}.zip").stat().st_size < (run / f"{model}.zip").stat().st_size, model
        assert (out / "episodes.csv").read_bytes() == (run / "episodes.csv").read_bytes()
        tables = [run_cli(*evaluate, "--model", str(path), cwd=tmp_path) for path in (run, out)]
        assert all(t.returncode == 0 for t in tables), [t.stderr for t in tables]
        assert tables[0].stdout.startswith(f"{kind} {run}")
        assert tables[0].stdout.splitlines()[1:] == tables[1].stdout.splitlines()[1:]

    again = run_cli("export", str(root / "ours"), str(tmp_path / "ours"), cwd=tmp_path)
    assert again.returncode == 2
    assert again.stderr.strip().endswith("exists and is not empty: export into a new folder")
    assert run_cli("export", str(tmp_path), str(tmp_path / "x"), cwd=tmp_path).returncode == 2
    stochastic = run_cli(*evaluate, "--model", str(tmp_path / "ppo"), "--stochastic", cwd=tmp_path)
    assert stochastic.returncode == 2 and "--stochastic" in stochastic.stderr


def test_exported_model_keeps_weights_and_optimizer_settings_not_its_tensorboard_folder(reproduced, tmp_path):
    from sb3_contrib import MaskablePPO

    from sb3_gccp.export import portable_copy

    folder, _ = reproduced
    source = folder / "runs" / "reproduce" / "quick" / "seed0" / "planner" / "planner.zip"  # 2 updates
    portable_copy(source, tmp_path / "planner.zip")
    full, stripped = MaskablePPO.load(source), MaskablePPO.load(tmp_path / "planner.zip")
    for key, value in full.policy.state_dict().items():
        assert th.equal(value, stripped.policy.state_dict()[key]), key
    assert full.policy.optimizer.state_dict()["state"] and not stripped.policy.optimizer.state_dict()["state"]
    groups = stripped.policy.optimizer.state_dict()["param_groups"]
    assert groups == full.policy.optimizer.state_dict()["param_groups"]
    assert full.tensorboard_log and stripped.tensorboard_log is None
    kept = ("n_steps", "gamma", "num_timesteps")
    assert [getattr(stripped, name) for name in kept] == [getattr(full, name) for name in kept]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--preset", "fast"], "unknown preset 'fast': expected quick or paper"),
        (["--methods", "ours", "dqm"], "unknown method(s) 'dqm' (did you mean 'dqn'?)"),
        (["--seeds", "0", "0"], "--seeds must be distinct non-negative integers"),
        (["--planner", "none.zip"], "planner not found: none.zip"),
        (["--set", "episods=3"], "unknown preset key(s): 'episods' (did you mean 'episodes'?)"),
        (["--set", "episodes=0"], "preset episodes must be a positive integer, got 0"),
        (["--set", "world.spawn_probabilty=0.1"], "unknown intersection config key(s)"),
        (["--set", "hyperparams.dqn.buffer_sise=5"], "unknown hyperparameter(s): 'buffer_sise'"),
        (["--set", "hyperparams.td3.tau=1"], "preset hyperparams: unknown group(s) 'td3'"),
        (["--set", "hyperparams.ppo.batch_size=0"], "batch_size must be an integer of at least 2, got 0"),
        (["--set", "hyperparams.hierarchy.n_epochs=0"], "n_epochs must be an integer of at least 1, got 0"),
        (["--jobs", "0"], "--jobs must be at least 1, got 0"),
        (["--launcher-set", "timeout_min=5"], "--launcher-set is for --launcher submitit"),
        (["--collect", "out"], "no runs to collect: runs/reproduce/quick/preset.yml not found"),
    ],
)
def test_bad_input_is_one_line_and_exit_2_before_anything_is_written(
    tmp_path, monkeypatch, capsys, args, message
):
    monkeypatch.chdir(tmp_path)
    assert main(["reproduce", "--preset", "quick", *args]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"sb3_gccp: error: {message}")
    assert not list(tmp_path.iterdir())


@pytest.fixture
def quick_folder(tmp_path, monkeypatch):
    """A reproduction folder of the quick preset with no run in it, in the current directory."""
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "runs" / "reproduce" / "quick"
    root.mkdir(parents=True)
    (root / "preset.yml").write_text(yaml.safe_dump(PRESETS["quick"].to_dict()))
    return tmp_path


def test_a_changed_training_budget_does_not_reuse_finished_runs(quick_folder, capsys):
    assert main(["reproduce", "--preset", "quick", "--methods", "ours", "--set", "episodes=7"]) == 2
    assert "(episodes differ): give the same settings or another --log-folder" in capsys.readouterr().err


def test_collecting_unfinished_runs_writes_nothing(quick_folder, capsys):
    assert main(["reproduce", "--preset", "quick", "--methods", "ppo", "--collect", "out"]) == 2
    assert "unfinished in runs/reproduce/quick: seed0/ppo" in capsys.readouterr().err
    assert not (quick_folder / "out").exists()


def test_results_json_writes_errors_over_no_neighbour_as_null():
    from sb3_gccp.reproduce.collect import strict_json

    text = strict_json({"errors": {"0": [0.5, float("nan")], "1": (float("inf"), 2)}, "n": 3})
    assert json.loads(text) == {"errors": {"0": [0.5, None], "1": [None, 2]}, "n": 3}
    assert "NaN" not in text and "Infinity" not in text


def test_paper_preset_configs_change_only_the_budget_and_the_gccp_variant():
    paper = PRESETS["paper"]
    decider = load_hyperparams(default_config_file("ppo_mask.yml"), "GCCPDecider-v0")
    for name in ("ours", "with_cv", "without_gccp", "without_goal"):
        entry = method_settings(METHODS[name], paper)
        gccp = entry.pop("gccp")
        assert entry == {k: v for k, v in decider.items() if k != "gccp"}
        assert gccp == {
            **decider["gccp"],
            "predictor": METHODS[name].predictor,
            "n_episodes": 2000,
        }
    assert mask_after_episodes(paper) == decider["gccp"]["mask_after_episodes"]
    assert mask_after_episodes(paper.with_overrides({"mask_after_episodes": 800})) == 800
    for name in ("dqn", "ppo", "sac_discrete"):
        entry = method_settings(METHODS[name], paper)
        shipped = load_hyperparams(default_config_file(f"{name}.yml"), "GCCPFlat-v0")
        assert entry == {**shipped, "n_timesteps": 2000 * 300}  # the cap: 2000 episodes of 30 s
        assert (
            entry["policy_kwargs"]["features_extractor_class"] == "sb3_gccp.policies.PlannerFeaturesExtractor"
        )
    assert planner_settings(paper)["n_timesteps"] == 100_000


def test_tuned_baseline_entries_are_masked_and_change_only_their_tuned_keys():
    paper = PRESETS["paper"]
    for file in sorted((default_config_file("dqn.yml").parent / "tuned").glob("*.yml")):
        method = METHODS[file.stem]
        entry = method_settings(method, paper, file)
        check_settings(method, entry)  # what `reproduce --config` checks before any training
        header = " ".join(line[2:] for line in file.read_text().splitlines() if line.startswith("# "))
        tuned_keys = re.search(r"Tuned keys: (.*?)\. Used", header)
        assert tuned_keys is not None, file
        tuned = {key.strip().split(".")[0] for key in tuned_keys.group(1).split(",")}
        shipped = method_settings(method, paper)
        assert entry[MASKS_KEY] is True and entry["n_timesteps"] == shipped["n_timesteps"]
        assert {key for key in {*entry, *shipped} if entry.get(key) != shipped.get(key)} <= tuned, file


def test_shipped_masked_baselines_were_trained_with_the_tuned_entries():
    # pretrained/baselines/<method>/ is a tuned row of Table I; its run config is that entry.
    paper = PRESETS["paper"]
    pretrained = Path(__file__).resolve().parents[1] / "pretrained" / "baselines"
    for file in sorted((default_config_file("dqn.yml").parent / "tuned").glob("*.yml")):
        shipped = pretrained / file.stem
        if not shipped.is_dir():  # a tuned entry not trained yet ships nothing
            continue
        run_config = yaml.safe_load((shipped / "config.yml").read_text())
        assert run_config == method_settings(METHODS[file.stem], paper, file), shipped
        assert yaml.safe_load((shipped / "baseline.yml").read_text())["algorithm"] == file.stem


def test_quick_preset_shrinks_every_network_and_merges_dotted_overrides():
    quick = PRESETS["quick"].with_overrides({"hyperparams.dqn.batch_size": 8, "world.duration": 5.0})
    dqn = method_settings(METHODS["dqn"], quick)
    assert dqn["batch_size"] == 8 and dqn["buffer_size"] == 2000  # merged into the preset's own map
    assert dqn["policy_kwargs"]["features_extractor_kwargs"]["encoder"] == quick.encoder
    assert dqn["n_timesteps"] == 6 * 50
    ours = method_settings(METHODS["ours"], quick)
    assert ours["policy_kwargs"]["encoder"] == ours["gccp"]["predictor_kwargs"]["encoder"] == quick.encoder
    entry = load_hyperparams(default_config_file("ppo_mask.yml"), "GCCPDecider-v0")
    assert ours["env_kwargs"] == {**entry["env_kwargs"], "duration": 5.0}


def test_tables_give_the_mean_and_min_max_over_seeds():
    def table(left: float, crashed: float, timeout: float) -> dict[str, dict[str, float]]:
        rates = {"offroad": 0.0, "wrong_exit": 0.0, "episodes": 50.0}
        row = {"success": left, "crashed": crashed, "timeout": timeout, **rates}
        return {task: dict(row) for task in ("left", "straight", "right", "overall")}

    seeds = [table(50.0, 10.0, 0.0), table(70.0, 20.0, 4.0), table(66.0, 12.0, 2.0)]
    text = format_results_table([("ours", seeds), ("DQN", [table(22.0, 28.7, 1.0)])])
    lines = text.splitlines()
    assert lines[0] == "| method | left S/C | straight S/C | right S/C | overall S/C | timeout % |"
    cells = " | ".join(["62.0 (50.0-70.0) / 14.0 (10.0-20.0)"] * 4)
    assert lines[2] == f"| ours | {cells} | 2.0 (0.0-4.0) |"
    assert lines[3] == "| DQN | " + " | ".join(["22.0 / 28.7"] * 4) + " | 1.0 |"
    spread = aggregate(seeds)["overall"]["success"]
    assert spread["mean"] == pytest.approx(62.0) and spread["std"] == pytest.approx(10.583, abs=1e-3)
    assert (spread["min"], spread["max"]) == (50.0, 70.0)


@pytest.mark.slow  # 19 s; the quick preset test runs every variant over a trained planner in the fast tier
def test_hierarchy_variants_over_the_scripted_planner(tmp_path):
    result = reproduce(tmp_path, "--planner", "scripted", "--methods", "ours", "without_gccp")
    assert result.returncode == 0, result.stderr
    assert "planner: training" not in result.stdout
    root = tmp_path / "runs" / "reproduce" / "quick" / "seed0"
    for name in ("ours", "without_gccp"):
        assert yaml.safe_load((root / name / "hierarchy.yml").read_text())["planner"] == "scripted"
        assert not (root / name / "planner.zip").exists()
    results = json.loads((tmp_path / "results" / "results.json").read_text())
    assert results["budget"]["planner_pretraining"]["0"]["planner"] == "scripted"
    # Not a planner: one line. A trained planner over runs made with the scripted one: refused.
    bad = reproduce(tmp_path, "--planner", str(tmp_path / "results" / "results.json"), "--methods", "ours")
    assert bad.returncode == 2 and "results.json is not a readable SB3 .zip" in bad.stderr
    planner = Path(__file__).resolve().parents[1] / "pretrained" / "planner.zip"
    again = reproduce(tmp_path, "--planner", str(planner), "--methods", "ours")
    assert again.returncode == 2 and "was trained over another planner" in again.stderr
