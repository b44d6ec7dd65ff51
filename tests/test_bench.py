"""Benchmark tasks, episode files and ``vgpnav bench``: on a tiny task (64x48 images, home, 3
episodes of at most 30 steps) so that every run takes seconds."""

from __future__ import annotations

import copy
import gzip
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from bench_agents import RAISE_SEED, StillCamera

from vgpnav_env.eval.bench import BenchRun, run_bench
from vgpnav_env.eval.records import RESULTS_SCHEMA, SchemaError, _check, results_digest, validate_results
from vgpnav_env.eval.workers import Workers
from vgpnav_env.tasks import load_task, task_names
from vgpnav_env.tasks.env import TaskEnv
from vgpnav_env.tasks.episodes import generate_episodes, load_episodes
from vgpnav_env.tasks.splits import perception_split, perception_tuning_scenes, scene_splits
from vgpnav_env.tasks.task import TASK_DIR

TESTS = Path(__file__).parent


def write_task(directory: Path, name: str, size: tuple[int, int], max_steps: int, test_episodes: int) -> Path:
    """A copy of pointnav-v1 with another name, image size, step limit and its own splits."""
    data = yaml.safe_load((TASK_DIR / "pointnav-v1.yaml").read_text())
    data = copy.deepcopy(data)
    data["name"], data["gym_id"] = name, f"VGPNav/Test-{name}"
    data["sensors"]["rgb"] |= {"width": size[0], "height": size[1]}
    data["max_steps"] = max_steps
    data["scene_splits"] = {"train": ["home:1"], "val": ["home:2"], "test": ["home"]}
    data["episodes"]["per_scene"] = {"train": 1, "val": 1, "test": test_episodes}
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def tiny_task(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny task's YAML file, its test episodes generated beside it."""
    path = write_task(tmp_path_factory.mktemp("task"), "tinynav-v1", (64, 48), 30, 3)
    generate_episodes(load_task(str(path)), "test")
    return path


def bench(task: Path, out: Path, agent: str, **kwargs) -> dict:
    run = BenchRun(load_task(str(task)), "test", agent, out, progress=False, **kwargs)
    return run_bench(run)


def compared(results: dict) -> dict:
    return {k: v for k, v in results.items() if k != "run"}


def test_perception_split_of_a_corpus_directory(tmp_path, monkeypatch) -> None:
    """A corpus tuning scene is tuning by its id and by its directory in the corpus (what a report
    of ``vgpnav eval ... DIR`` names); the same folder name elsewhere, or another corpus scene's
    directory, is held out."""
    monkeypatch.setenv("VGPNAV_CACHE", str(tmp_path / "cache"))
    corpus = tmp_path / "cache" / "corpus"
    for d in (corpus / "sh3d_studio", corpus / "sh3d_office", tmp_path / "mine" / "sh3d_studio"):
        d.mkdir(parents=True)
    assert perception_split("corpus:sh3d_studio") == "tuning"
    assert perception_split(str(corpus / "sh3d_studio")) == "tuning"
    assert perception_split(str(corpus / "sh3d_studio") + "/") == "tuning"
    assert perception_split(str(corpus / "sh3d_office")) == "held-out"
    assert perception_split(str(tmp_path / "mine" / "sh3d_studio")) == "held-out"
    assert perception_split(str(corpus / "nothing_here")) == "held-out"


def test_shipped_task_splits_and_episode_files_agree() -> None:
    assert "pointnav-v1" in task_names()
    task = load_task("pointnav-v1")
    assert task.image_size == (320, 240) and task.max_steps == 500 and task.success_distance == 0.5
    splits = scene_splits(task.scene_split_set)
    assert len(splits["train"]) >= 40 and {"home:1", "hospital:30"} <= set(splits["train"])
    assert {"home", "hospital", "corpus:sh3d_office", "corpus:sh3d_apartment"} <= set(splits["test"])
    tuning = set(perception_tuning_scenes())
    # Perception is tuned on the built-ins, train seeds and corpus scenes of no navigation split:
    # nothing else of val / test.
    real = {"corpus:sh3d_studio", "corpus:sh3d_bedsit", "corpus:sh3d_lounge"}
    assert real <= tuning and not any(set(s) & real for s in splits.values())
    assert not tuning & set(splits["val"]) and tuning & set(splits["test"]) == {"home", "hospital"}
    assert perception_split("home") == "tuning" and perception_split("home-2") == "tuning"
    assert perception_split("corpus:sh3d_office") == "held-out" and perception_split("home:101") == "held-out"
    for split in ("val", "test"):
        episodes = load_episodes(task, split)  # checksum checked
        assert episodes.scenes() == list(splits[split])
        assert len(episodes) == len(splits[split]) * task.episodes.per_scene[split]
        assert all(1.0 <= e.geodesic <= 10.0 * 1.5 for e in episodes.episodes)


def test_episode_files_are_reproducible_round_trip_and_reject_a_changed_file(
    tiny_task: Path, tmp_path: Path
) -> None:
    task = load_task(str(tiny_task))
    shipped = tiny_task.parent / "data" / task.name
    again = tmp_path / "again"
    generate_episodes(task, "test", again)
    for name in ("test.json.gz", "SHA256SUMS"):  # the same bytes from a second generation
        assert (again / name).read_bytes() == (shipped / name).read_bytes()
    episodes = load_episodes(task, "test", again)
    assert [e.episode_id for e in episodes.episodes] == [f"test-home-{i:03d}" for i in range(3)]
    assert len({e.seed for e in episodes.episodes}) == 3
    data = json.loads(gzip.decompress((again / "test.json.gz").read_bytes()))
    assert data["generator"]["params"]["min_geodesic"] == 1.0 and data["task_version"] == 1
    data["episodes"][1]["start_yaw"] += 1e-9  # one changed number
    content = json.dumps(data, sort_keys=True, separators=(",", ":")).encode() + b"\n"
    (again / "test.json.gz").write_bytes(gzip.compress(content, mtime=0))
    with pytest.raises(ValueError, match="fails its checksum"):
        load_episodes(task, "test", again)
    with pytest.raises(ValueError, match="unknown split 'dev'"):
        load_episodes(task, "dev")


def test_task_env_replays_the_episode_file_in_order(tiny_task: Path) -> None:
    task = load_task(str(tiny_task))
    episodes = load_episodes(task, "test")
    env = TaskEnv(task, split="test")
    try:
        for e in [*episodes.episodes, episodes.episodes[0]]:  # in order, then from the start again
            obs, info = env.reset()
            assert info["episode_id"] == e.episode_id and info["scene_id"] == "home"
            assert tuple(info["start"]) == pytest.approx(e.start, abs=0)
            assert info["shortest_path_length"] == pytest.approx(e.geodesic, abs=1e-9)
            assert obs["rgb"].shape == (48, 64, 3)
        _, info = env.reset(options={"episode_id": episodes.episodes[2].episode_id})
        assert info["episode_id"] == episodes.episodes[2].episode_id
        _, _, _, _, info = env.step(1)
        assert info["steps"] == 1 and info["episode_id"] == episodes.episodes[2].episode_id
    finally:
        env.close()


def test_external_agent_end_to_end_schema_and_leaderboard(tiny_task: Path, tmp_path: Path) -> None:
    results = bench(tiny_task, tmp_path / "run", "bench_agents:BumpAndTurn")
    saved = json.loads((tmp_path / "run" / "report.json").read_text())
    assert saved == results
    validate_results(saved)
    _check(saved, RESULTS_SCHEMA, "$")  # without jsonschema
    assert saved["complete"] and saved["episodes"] == 3 and saved["errors"] == 0
    assert saved["settings"]["agent_kind"] == "external" and saved["settings"]["backbone"] is None
    assert [r["steps"] for r in saved["records"]] == [26, 26, 26]  # 25 moves, then stop
    assert saved["scenes"]["home"]["perception"] == "tuning"
    assert saved["task"]["name"] == "tinynav-v1" and saved["task"]["version"] == 1
    row = (tmp_path / "run" / "leaderboard.md").read_text().splitlines()[-1]
    assert row.startswith("| tinynav-v1 | test | bench_agents:BumpAndTurn |") and "| 3 | 0 |" in row
    broken = {k: v for k, v in saved.items() if k != "spl"}
    with pytest.raises(SchemaError, match="'spl' is a required property"):
        validate_results(broken)
    with pytest.raises(SchemaError, match="'spl' is a required property"):
        _check(broken, RESULTS_SCHEMA, "$")
    edited = {**saved, "success_rate": 1.0}
    with pytest.raises(SchemaError, match="digest"):
        validate_results(edited)
    # A factory without arguments whose object has act() only.
    turner = bench(tiny_task, tmp_path / "turner", "bench_agents:make_turner")
    assert turner["errors"] == 0 and [r["steps"] for r in turner["records"]] == [30, 30, 30]
    assert turner["failures"]["timeout"] == 3


def test_interrupted_run_resumes_to_the_same_results_and_errors_are_recorded(
    tiny_task: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    agent = "bench_agents:Raising"
    episodes = load_episodes(load_task(str(tiny_task)), "test")
    monkeypatch.setenv(RAISE_SEED, str(episodes.episodes[1].seed))
    whole = bench(tiny_task, tmp_path / "whole", agent)
    assert [r["status"] for r in whole["records"]] == ["ok", "error", "ok"]
    assert whole["records"][1]["error"] == "RuntimeError: the agent fell over"
    assert whole["errors"] == 1 and whole["complete"] and whole["scenes"]["home"]["errors"] == 1

    from vgpnav_env.eval import records

    append = records.EpisodeLog.append
    calls = []

    def killed_after_two(self, record):  # the run dies while the third episode is written
        calls.append(record["episode_id"])
        if len(calls) == 3:
            with self.path.open("a") as f:
                f.write('{"index": 2, "episode_id": "torn')
            raise KeyboardInterrupt
        append(self, record)

    monkeypatch.setattr(records.EpisodeLog, "append", killed_after_two)
    with pytest.raises(KeyboardInterrupt):
        bench(tiny_task, tmp_path / "resumed", agent)
    monkeypatch.setattr(records.EpisodeLog, "append", append)
    assert not (tmp_path / "resumed" / "report.json").exists()
    with pytest.raises(ValueError, match="add --resume"):
        bench(tiny_task, tmp_path / "resumed", agent)
    with pytest.raises(ValueError, match="other settings"):
        bench(tiny_task, tmp_path / "resumed", "bench_agents:BumpAndTurn", resume=True)
    resumed = bench(tiny_task, tmp_path / "resumed", agent, resume=True)
    assert resumed["run"]["resumed_episodes"] == 2
    assert compared(resumed) == compared(whole) and resumed["digest"] == whole["digest"]
    lines = (tmp_path / "resumed" / "episodes.jsonl").read_text().splitlines()
    assert len(lines) == 4 and all(json.loads(line) for line in lines)  # header + 3, torn line gone


def test_limit_marks_the_results_partial(tiny_task: Path, tmp_path: Path) -> None:
    partial = bench(tiny_task, tmp_path / "partial", "oracle", limit=1)
    assert not partial["complete"] and partial["episodes"] == 1 and partial["limit"] == 1
    assert "Partial" in (tmp_path / "partial" / "report.md").read_text()


@pytest.mark.slow
def test_same_task_gives_identical_results_in_fresh_processes_and_on_two_workers(
    tiny_task: Path, tmp_path: Path
) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    digests = []
    for name in ("a", "b"):
        out = tmp_path / name
        argv = [sys.executable, "-m", "vgpnav_env.cli", "bench", str(tiny_task), "--agent", "oracle",
                "--workers", "1", "--out", str(out)]  # fmt: skip
        done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        results = json.loads((out / "report.json").read_text())
        assert results["digest"] == results_digest(results)
        digests.append(results["digest"])
    assert digests[0] == digests[1]
    with Workers(2, progress=False) as workers:
        two = run_bench(
            BenchRun(load_task(str(tiny_task)), "test", "oracle", tmp_path / "two", progress=False), workers
        )
    assert two["run"]["workers"] == "2 processes" and two["digest"] == digests[0]


@pytest.mark.slow
def test_external_backbone_factory_end_to_end(home_build: Path, tmp_path: Path) -> None:
    from conftest import HOME_DATABASE_CONFIG, HOME_SIZE

    path = write_task(tmp_path / "task", "homesize-v1", HOME_SIZE, 4, 1)
    task = load_task(str(path))
    generate_episodes(task, "test")
    weights = tmp_path / "still.pt"
    import torch

    torch.save(StillCamera().state_dict(), weights)
    options = {"model": "bench_agents:StillCamera", "weights_path": weights}
    run = BenchRun(task, "test", "astar", tmp_path / "run", backbone="learned", backbone_options=options,
                   progress=False, databases={"home": str(home_build)},
                   wrapper_options={"database_config": HOME_DATABASE_CONFIG})  # fmt: skip
    results = run_bench(run)
    assert results["errors"] == 0, results["records"]
    assert results["settings"]["backbone"] == "learned"
    assert results["settings"]["backbone_model"] == "bench_agents:StillCamera"
    record = results["records"][0]
    # One pose for every image: nothing localizes, the agent explores for the step limit.
    assert record["steps"] == 4 and record["lost_fraction"] == 1.0 and record["failure"] == "lost"
