"""``reproduce`` as jobs: the job graph, the scheduler, ``--jobs``, submitit, resuming and ``--collect``."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from helpers import reproduce

from sb3_gccp.reproduce import launchers
from sb3_gccp.reproduce.jobs import Job, job_graph
from sb3_gccp.reproduce.launchers import JobFailed, run_jobs
from sb3_gccp.reproduce.plan import ReproduceRequest, prepare

HIERARCHY = ("ours", "with_cv", "without_gccp", "without_goal")
BASELINES = ("dqn", "ppo", "sac_discrete", "dqn_paper", "ppo_paper", "sac_discrete_paper")
FAST = ("--planner", "scripted", "--no-progress")
"""No planner job: the runs of these tests take seconds."""


def test_a_seeds_planner_comes_before_its_hierarchy_variants_and_the_baselines_wait_for_nothing(tmp_path):
    request = ReproduceRequest(preset="quick", seeds=(0, 1), out=tmp_path / "out", log_folder=tmp_path)
    jobs = job_graph(prepare(request))
    keys = [job.key for job in jobs]
    assert keys[:12] == [
        "seed0/planner",
        *(f"seed0/{name}" for name in (*HIERARCHY, *BASELINES)),
        "seed0/predictor_errors",
    ]
    assert len(keys) == 24 and len(set(keys)) == 24
    needs = {job.key: job.needs for job in jobs}
    for seed in (0, 1):
        assert needs[f"seed{seed}/planner"] == ()
        for name in HIERARCHY:
            assert needs[f"seed{seed}/{name}"] == (f"seed{seed}/planner",)
        for name in BASELINES:
            assert needs[f"seed{seed}/{name}"] == ()
        assert needs[f"seed{seed}/predictor_errors"] == (f"seed{seed}/ours", f"seed{seed}/without_goal")
    for i, job in enumerate(jobs):  # the sequential order runs every job after what it needs
        assert set(job.needs) <= set(keys[:i]), job.key

    given = ReproduceRequest(
        preset="quick",
        methods=("ours", "dqn"),
        planner=Path("scripted"),
        out=tmp_path / "o",
        log_folder=tmp_path,
    )
    assert [(j.key, j.needs) for j in job_graph(prepare(given))] == [
        ("seed0/ours", ()),
        ("seed0/dqn", ()),
        ("seed0/predictor_errors", ("seed0/ours",)),
    ]


class FakeLauncher:
    """Jobs that end on the second time they are asked; records starts, ends and the most at once."""

    def __init__(self, slots: int, failing: tuple[str, ...] = ()) -> None:
        self.slots, self.failing = slots, failing
        self.events: list[tuple[str, str]] = []
        self.running: set[str] = set()
        self.most = 0

    def output(self, job: Job) -> Path:
        return Path("log")

    def submit(self, job: Job, label: str) -> FakeHandle:
        self.events.append(("start", job.key))
        self.running.add(job.key)
        self.most = max(self.most, len(self.running))
        return FakeHandle(self, job.key)


class FakeHandle:
    def __init__(self, launcher: FakeLauncher, key: str) -> None:
        self.launcher, self.key, self.asked = launcher, key, 0

    def done(self) -> bool:
        self.asked += 1
        return self.asked > 1

    def result(self) -> dict[str, int]:
        self.launcher.events.append(("end", self.key))
        self.launcher.running.discard(self.key)
        if self.key in self.launcher.failing:
            raise JobFailed("ValueError: broken; output in log")
        return {"timesteps": 1}

    def cancel(self) -> None:
        self.launcher.events.append(("cancel", self.key))


GRAPH = [
    Job(0, "planner"),
    Job(0, "ours", ("seed0/planner",)),
    Job(0, "with_cv", ("seed0/planner",)),
    Job(0, "dqn"),
    Job(0, "ppo"),
]


def test_jobs_start_after_what_they_need_and_never_more_than_the_slots(monkeypatch, capsys):
    monkeypatch.setattr(launchers, "POLL_SECONDS", 0.0)
    launcher = FakeLauncher(slots=2)
    run_jobs(GRAPH, launcher, lambda job: {"timesteps": 0} if job.name == "ppo" else None)
    events = launcher.events
    assert launcher.most == 2
    assert ("start", "seed0/ppo") not in events  # finished before
    assert events.index(("end", "seed0/planner")) < events.index(("start", "seed0/ours"))
    assert events.index(("end", "seed0/planner")) < events.index(("start", "seed0/with_cv"))
    assert events[:2] == [("start", "seed0/planner"), ("start", "seed0/dqn")]  # a baseline fills the slot
    out = capsys.readouterr().out
    assert "[5/5] seed 0 ppo: finished before, skipped" in out
    assert "[2/5] seed 0 ours: finished in 0 s, 1 steps (4/5 done)" in out


def test_after_a_failure_no_job_starts_and_the_error_is_one_line(monkeypatch, capsys):
    monkeypatch.setattr(launchers, "POLL_SECONDS", 0.0)
    launcher = FakeLauncher(slots=2, failing=("seed0/planner",))
    with pytest.raises(JobFailed) as error:
        run_jobs(GRAPH, launcher, lambda job: None)
    assert str(error.value) == (
        "1 job(s) failed: seed 0 planner: ValueError: broken; output in log; "
        "not started: seed 0 ours, seed 0 with_cv, seed 0 ppo"
    )
    assert ("start", "seed0/ours") not in launcher.events
    assert ("end", "seed0/dqn") in launcher.events  # the job in flight finished
    assert "[1/5] seed 0 planner: failed: ValueError: broken" in capsys.readouterr().out


TWO_WORKERS = (*FAST, "--set", "n_envs=2")
"""Every run with two env worker processes (SubprocVecEnv): a job's process must be able to start them."""


@pytest.fixture(scope="module")
def two_at_once(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("jobs")
    return folder, reproduce(folder, *TWO_WORKERS, "--methods", "ours", "dqn", "ppo", "--jobs", "2")


def run_files(root: Path) -> dict[Path, int]:
    """Every file of the finished runs, with its modification time."""
    return {path: path.stat().st_mtime_ns for path in sorted(root.rglob("*")) if path.is_file()}


@pytest.mark.slow  # reproduce end to end, several times (about 40 s each)
def test_two_jobs_at_once_write_the_tables_and_each_run_its_log(two_at_once):
    folder, result = two_at_once
    assert result.returncode == 0, result.stderr
    root = folder / "runs" / "reproduce" / "quick"
    for name in ("ours", "dqn", "ppo", "predictor_errors"):
        assert (
            f"seed 0 {name}: started, output in runs/reproduce/quick/logs/seed0_{name}.log" in result.stdout
        )
    assert "] seed 0 dqn: trained 2 episodes in" in (root / "logs" / "seed0_dqn.log").read_text()
    assert result.stdout.count(" done)") == 4
    table1 = (folder / "results" / "table1.md").read_text()
    assert all(f"\n| {label} | " in table1 for label in ("DQN", "PPO", "ours"))
    assert "\n| ours | " in (folder / "results" / "table2.md").read_text()


@pytest.mark.slow  # reproduce end to end, several times (about 40 s each)
def test_a_second_reproduce_reruns_no_finished_run(two_at_once):
    folder, first = two_at_once
    assert first.returncode == 0, first.stderr
    root = folder / "runs" / "reproduce" / "quick"
    finished = run_files(root / "seed0")

    # As if the first had been killed with sac_discrete still to run.
    again = reproduce(folder, *TWO_WORKERS, "--methods", "ours", "dqn", "ppo", "sac_discrete", "--jobs", "2")
    assert again.returncode == 0, again.stderr
    for name in ("ours", "dqn", "ppo", "predictor_errors"):
        assert f"seed 0 {name}: finished before, skipped" in again.stdout, name
    assert "seed 0 sac_discrete: started" in again.stdout
    now = run_files(root / "seed0")
    assert {path: now[path] for path in finished} == finished  # not a file of them rewritten
    assert (root / "seed0" / "sac_discrete" / "training.json").is_file()


@pytest.mark.slow  # reproduce end to end, several times (about 40 s each)
def test_collect_builds_the_tables_from_run_folders_alone(two_at_once, tmp_path):
    folder, first = two_at_once
    assert first.returncode == 0, first.stderr
    shutil.copytree(folder / "runs", tmp_path / "fetched")  # from wherever they ran
    collected = reproduce(
        tmp_path, *FAST, "--methods", "ours", "dqn", "ppo", "--log-folder", "fetched", "--collect", "tables"
    )
    assert collected.returncode == 0, collected.stderr
    assert "training" not in collected.stdout and "started" not in collected.stdout
    table1 = (tmp_path / "tables" / "table1.md").read_text()
    present = [label for label in ("DQN", "PPO", "SAC-Discrete", "ours") if f"\n| {label} | " in table1]
    assert present == ["DQN", "PPO", "ours"]  # the selection's runs, whatever else the folder holds
    assert "\n| ours | " in (tmp_path / "tables" / "table2.md").read_text()
    assert (tmp_path / "tables" / "fig5_baselines.png").is_file()

    missing = reproduce(
        tmp_path, *FAST, "--methods", "ours", "with_cv", "--log-folder", "fetched", "--collect", "t2"
    )
    assert missing.returncode == 2
    (line,) = missing.stderr.strip().splitlines()
    assert line.startswith(
        "sb3_gccp: error: unfinished in fetched/reproduce/quick: seed0/with_cv: run reproduce"
    )
    assert not (tmp_path / "t2").exists()  # not even the zoo files


@pytest.mark.slow  # each job starts its own interpreter through submitit's local executor
def test_submitit_local_executor_writes_the_tables(tmp_path):
    result = reproduce(tmp_path, *FAST, "--methods", "ours", "dqn", "--launcher", "submitit")
    assert result.returncode == 0, result.stderr
    assert result.stdout.count(" done)") == 3
    assert "\n| DQN | " in (tmp_path / "results" / "table1.md").read_text()
    logs = list((tmp_path / "runs" / "reproduce" / "quick" / "submitit").glob("*_log.out"))
    assert len(logs) == 3
