"""Episodes and frames in parallel: same results on worker processes and on Ray as in one process.

The Ray test starts a local Ray instance with 2 CPUs; it runs when ``ray`` is importable (the
``distributed`` extra) and fails instead of skipping when ``VGPNAV_REQUIRE_RAY=1`` (CI installs it).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
from worker_tasks import (
    CountingSetup,
    affinity_task,
    failing_task,
    noting_task,
    ordered_task,
    share_task,
    tagged_task,
    threads_task,
)

from vgpnav_env.eval.perception_runs import QueryRun, perceive_queries
from vgpnav_env.eval.workers import Workers, note


@pytest.mark.parametrize("n", [1, 2])
def test_results_in_item_order_and_one_state_per_worker(n: int) -> None:
    with Workers(n, progress=False) as workers:
        out = workers.map(CountingSetup("a"), tagged_task, list(range(9)))
        again = workers.map(CountingSetup("a"), tagged_task, list(range(9)))
        other = workers.map(CountingSetup("b"), tagged_task, [4])
    assert [r[0] for r in out] == [i * i for i in range(9)]
    tokens = {pid: {tok for _, p, tok, _ in out if p == pid} for _, pid, _, _ in out}
    assert all(len(t) == 1 for t in tokens.values())  # setup ran once per worker process
    assert len(tokens) <= n and (n == 1) == (set(tokens) == {os.getpid()})
    # State kept between maps: a worker that ran the first map keeps its setup's state (one that
    # got none of its tasks, e.g. still starting while the other took all nine, sets up anew).
    kept = [(pid, tok) for _, pid, tok, _ in again if pid in tokens]
    assert kept and all(tok in tokens[pid] for pid, tok in kept)
    assert other[0][3] == "b"  # a new setup replaces the state
    assert (workers.cpu_seconds > 0) == (n > 1)


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux-only")
def test_each_worker_runs_on_its_share_of_the_cores() -> None:
    cores = sorted(os.sched_getaffinity(0))
    with Workers(2, progress=False) as workers:
        seen = workers.map(CountingSetup("a"), affinity_task, list(range(8)))
    # The last task may start once the other worker is idle, and then runs on every core.
    shares = [set(s) for _, s in seen]
    even = [s for s in shares if len(s) < len(cores)] if len(cores) >= 2 else shares
    assert len(even) >= len(shares) - 1
    assert all(s <= set(cores) and len(s) >= len(cores) // 2 for s in shares)
    by_pid = {pid: set(s) for pid, s in seen if len(s) < len(cores)}
    if len(cores) >= 2 and len(by_pid) == 2:  # disjoint halves: no core runs two workers' thread pools
        a, b = by_pid.values()
        assert not a & b and a | b == set(cores)
    assert sorted(os.sched_getaffinity(0)) == cores  # this process keeps all of them


def test_each_worker_sizes_its_thread_pools_to_its_share() -> None:
    """N workers on N cores: one thread per pool, idle OpenMP threads sleep."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    with Workers(2, progress=False) as workers:
        reports = workers.map(CountingSetup("a"), threads_task, list(range(6)))
    even = [r for r in reports if r["share"] == max(1, cores // 2)]
    assert len(even) >= len(reports) - 1  # the last task may take the idle worker's cores
    for r in reports:
        assert r["share"] == r["backbone_pool"] and r["opencv"] == 1
        assert r["environment"]["OMP_WAIT_POLICY"] == "PASSIVE"
        assert r["environment"]["OMP_NUM_THREADS"] == str(r["share"])
        assert r["environment"]["OPENBLAS_NUM_THREADS"] == "1"
        if isinstance(r["native"], dict):  # threadpoolctl installed: every loaded BLAS / OpenMP pool
            assert all(n == (1 if _is_blas(k) else r["share"]) for k, n in r["native"].items()), r["native"]


@pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2, reason="needs 2 cores"
)
def test_a_task_running_alone_takes_the_idle_workers_cores() -> None:
    """Fewer tasks than workers: the running ones share every core; the next map starts even."""
    cores = sorted(os.sched_getaffinity(0))
    with Workers(2, progress=False) as workers:
        workers.map(CountingSetup("a"), share_task, [0, 1])  # starts the worker processes
        alone = workers.map(CountingSetup("a"), share_task, [2])[0]
        after = workers.map(CountingSetup("a"), share_task, [3, 4, 5, 6])
    assert alone["share"] == alone["backbone_pool"] == len(cores) and alone["affinity"] == cores
    assert alone["environment"]["OMP_NUM_THREADS"] == str(len(cores))
    assert after[0]["share"] == len(cores) // 2 and len(after[0]["affinity"]) == len(cores) // 2
    assert sum(r["share"] == len(cores) // 2 for r in after) >= 3


def test_running_share() -> None:
    from vgpnav_env.eval.workers import running_share

    assert [running_share(2, 2, left) for left in (5, 2, 1, 0)] == [1, 1, 2, 1]
    assert [running_share(8, 4, left) for left in (4, 3, 2, 1)] == [2, 2, 4, 8]
    assert running_share(2, 4, 1) == 2 and running_share(2, 4, 3) == 1


def _is_blas(pool: str) -> bool:
    return pool.split(" ")[0] in {"openblas", "mkl", "blis"}


def test_blas_gets_one_thread_whatever_the_share() -> None:
    """BLAS pools spin between small calls: one thread even where the share is larger."""
    code = (
        "import json, numpy\n"
        "from vgpnav_env.perception.backbones.threads import configure_threads, thread_report\n"
        "configure_threads(threads=2)\n"
        "print(json.dumps(thread_report()))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    report = json.loads(out)
    assert report["share"] == report["backbone_pool"] == 2
    env = report["environment"]
    assert env["OPENBLAS_NUM_THREADS"] == "1" and env["OMP_NUM_THREADS"] == "2"
    if isinstance(report["native"], dict):
        blas = [n for k, n in report["native"].items() if _is_blas(k)]
        assert blas and all(n == 1 for n in blas), report["native"]


@pytest.mark.parametrize("n", [1, 2])
def test_costly_items_start_first_and_results_keep_their_order(n: int) -> None:
    cost = [1.0, 5.0, 3.0, 4.0, 2.0, 0.5]
    with Workers(n, progress=False) as workers:
        out = workers.map(CountingSetup("a"), ordered_task, list(range(6)), cost=cost)
    assert [item for item, _, _ in out] == list(range(6))
    for pid in {p for _, p, _ in out}:  # each worker started its items in decreasing cost
        mine = sorted((position, cost[item]) for item, p, position in out if p == pid)
        assert [c for _, c in mine] == sorted((c for _, c in mine), reverse=True)
    if n == 1:
        assert [position for _, _, position in out] == [4, 0, 2, 1, 3, 5]
    with pytest.raises(ValueError, match="costs"):
        Workers(1, progress=False).map(CountingSetup("a"), ordered_task, [1, 2], cost=[1.0])


def test_a_task_error_reaches_the_caller() -> None:
    with Workers(2, progress=False) as workers, pytest.raises(ValueError, match="bad item"):
        workers.map(CountingSetup("a"), failing_task, [1, 2])
    with pytest.raises(ValueError, match="workers must be >= 1"):
        Workers(0)


@pytest.mark.parametrize("n", [1, 2])
def test_a_running_tasks_note_shows_beside_the_bar(n: int, capsys: pytest.CaptureFixture[str]) -> None:
    note("outside any map")  # a no-op
    with Workers(n) as workers:
        out = workers.map(CountingSetup("a"), noting_task, [1, 2, 3], desc="noting")
    assert out == [1, 4, 9]  # notes do not change the results
    err = capsys.readouterr().err
    assert "noting" in err and "3/3" in err
    assert all(f"item {i} running" in err for i in (1, 2, 3)), err
    assert "outside any map" not in err


def _comparable(frames) -> list[dict]:
    """Frame records without wall/CPU timings; nan replaced so that equal records compare equal."""
    out = []
    for f in frames:
        r = asdict(f.record)
        r.pop("timings")
        out.append({k: "nan" if isinstance(v, float) and math.isnan(v) else v for k, v in r.items()})
    return out


@pytest.fixture(scope="module")
def build(tiny_build_dir: Path) -> Path:
    return tiny_build_dir


@pytest.mark.slow
def test_query_frames_on_two_processes_equal_one_process(build: Path) -> None:
    """The classical backbone (pixels only): chunks on two processes, anchor shipped to both."""
    run = QueryRun(build, "classical", n_queries=5)
    one = perceive_queries(run, progress=False)
    with Workers(2, progress=False) as workers:
        two = perceive_queries(run, workers=workers)
    assert [f.record.frame for f in two] == [f.record.frame for f in one]
    assert sum(f.record.status == "localized" for f in one) >= 2  # not a comparison of lost frames
    assert _comparable(two) == _comparable(one)


@pytest.mark.slow
def test_navigation_episodes_on_two_processes_equal_one_process(tmp_path: Path) -> None:
    from vgpnav_env.eval.navigation import evaluate_navigation

    kwargs = {"agent": "oracle", "episodes": 3, "seed": 3, "size": (64, 48), "progress": False}
    one = evaluate_navigation("home", out_dir=tmp_path / "one", **kwargs)
    with Workers(2, progress=False) as workers:
        two = evaluate_navigation("home", out_dir=tmp_path / "two", workers=workers, **kwargs)
    assert two["records"] == one["records"]
    assert two["settings"]["workers"] == "2 processes" and one["settings"]["workers"] == "this process"
    for name in ("one", "two"):
        assert len(list((tmp_path / name / "trajectories").glob("episode_*.png"))) == 3


needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None and os.environ.get("VGPNAV_REQUIRE_RAY") != "1",
    reason="ray is not installed (pip install 'vgpnav-env[distributed]')",
)


@pytest.mark.slow
@needs_ray
def test_ray_local_instance_with_two_workers_equals_sequential(build: Path) -> None:
    """Noisy simulated backbone: the per-frame seeds make Ray's scheduling irrelevant."""
    options = {"rotation_noise_deg": 0.5, "direction_noise_deg": 1.0, "outlier_fraction": 0.2}
    run = QueryRun(build, "simulated", options, n_queries=8, seed=4)
    sequential = perceive_queries(run, progress=False)
    with Workers(2, ray="local", progress=False) as workers:
        distributed = perceive_queries(run, workers=workers)
        assert workers.where == "Ray (local)"
    assert _comparable(distributed) == _comparable(sequential)
    assert workers.cpu_seconds > 0


@needs_ray
def test_ray_tasks_run_on_one_thread_each(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two local Ray workers, light tasks (a few seconds: Ray's start): each task's process sizes
    its pools to the one CPU the task holds, and costly items start first."""
    tests = str(Path(__file__).parent)  # Ray's worker processes import the tasks from here
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [tests, os.environ.get("PYTHONPATH")])))
    with Workers(2, ray="local", progress=False) as workers:
        reports = workers.map(CountingSetup("a"), threads_task, list(range(4)), cost=[1, 2, 3, 4])
        out = workers.map(CountingSetup("a"), tagged_task, list(range(5)))
    assert all(r["share"] == r["backbone_pool"] == 1 and r["opencv"] == 1 for r in reports)
    assert all(r["environment"]["OMP_WAIT_POLICY"] == "PASSIVE" for r in reports)
    assert [r[0] for r in out] == [i * i for i in range(5)] and all(r[1] != os.getpid() for r in out)
