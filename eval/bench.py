"""``vgpnav bench TASK --split SPLIT --agent AGENT``: a versioned task's split, one results file.

``vgpnav bench pointnav-v1 --split test --agent astar|oracle|ppo:PATH|MODULE:FACTORY
[--perception pixels|model] [--backbone B [--model MODULE:FACTORY --weights PATH]]
[--perception-mode M] [--out DIR] [--limit N] [--resume] [--workers N | --ray [ADDRESS]]``

runs the task's navigation protocol on every episode of the split's episode file, in its order,
under the task's rules (image size, step limit, success radius, layout:
:mod:`vgpnav_env.tasks`), with the machinery of ``vgpnav eval navigation``
(:func:`~vgpnav_env.eval.navigation.run_episode`, the agents, the perception wrapper, the
measures; the localization measures of the agent's pose estimate are recorded per episode).
Perception agents use each scene's default database build at the task's image size (built if
missing, before the episodes start).

``DIR`` (default ``bench/<task>-<split>-<agent>``) gets:

- ``episodes.jsonl``: the episode log, one line per finished episode, written as it finishes
  (:class:`~vgpnav_env.eval.records.EpisodeLog`); ``--resume`` continues a stopped run from it;
- ``report.json``: the results file (:data:`~vgpnav_env.eval.records.RESULTS_SCHEMA`), validated
  before it is written; a resumed run's file equals an uninterrupted run's except for its ``run``
  section (``digest`` compares them);
- ``report.md``: the leaderboard row, the per-scene table (perception tuning or held-out scene)
  and the failures; ``leaderboard.md``: the row alone under its header.

An episode whose code raises is recorded with ``status: "error"`` and the message, and the run
goes on (its scene's env is rebuilt for the next episode); summaries are over the ``ok``
episodes and ``errors`` counts the others. Undefined values (nan: a frame without a pose
estimate) are written as null. ``--limit N`` runs the first N episodes only and marks
the file ``complete: false``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import re
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vgpnav_env.arguments import positive_int_arg
from vgpnav_env.eval.navigation import (
    FAILURES,
    AgentPlan,
    EpisodeRecord,
    _recorded,
    agent_arg,
    make_env,
    make_policy,
    plan_agent,
    prepare_database,
    run_episode,
    summarize,
)
from vgpnav_env.eval.records import (
    SCHEMA,
    SCHEMA_VERSION,
    EpisodeLog,
    canonical,
    json_safe,
    results_digest,
    validate_results,
)
from vgpnav_env.eval.report import RunClock, markdown_table, package_version, print_headline
from vgpnav_env.eval.workers import Workers, add_worker_arguments, note, workers_from_args
from vgpnav_env.tasks.env import EpisodeReplay
from vgpnav_env.tasks.episodes import EpisodeSet, TaskEpisode, load_episodes
from vgpnav_env.tasks.splits import SPLIT_NAMES, perception_split, scene_source
from vgpnav_env.tasks.task import Task, load_task

logger = logging.getLogger(__name__)

#: Per-episode fields of the results file beside the measures (the log keeps the full records).
RECORD_FIELDS = (
    "index",
    "episode_id",
    "scene_id",
    "seed",
    "status",
    "error",
    "start",
    "goal",
    "shortest_path_length",
    "dataset_geodesic",
    "failure",
    "trajectory_sha256",
)
#: Leaderboard columns: (header, summary key, format).
LEADERBOARD = (
    ("SR", "success_rate", ".3f"),
    ("SPL", "spl", ".3f"),
    ("soft SPL", "soft_spl", ".3f"),
    ("collisions / ep", "collisions_per_episode", ".1f"),
    ("lost frames", "mean_lost_fraction", ".1%"),
)


@dataclass(frozen=True)
class BenchSetup:
    """A worker's setup (:mod:`vgpnav_env.eval.workers`): the agent ``plan``, the task's env keyword
    arguments, the perception wrapper's and each scene's database directory (perception agents)."""

    plan: AgentPlan
    env_kwargs: dict[str, Any]
    wrapper_kwargs: dict[str, Any]
    databases: dict[str, str] = field(default_factory=dict)

    def __call__(self) -> BenchWorker:
        return BenchWorker(self)


class BenchWorker:
    """A worker's state: the env and policy of the scene it ran last (episodes come grouped by
    scene, so a worker builds each scene it meets once)."""

    def __init__(self, setup: BenchSetup) -> None:
        self.setup = setup
        self.scene: str | None = None
        self.env: EpisodeReplay | None = None
        self.policy: Any = None

    def navigator(self, scene: str) -> tuple[EpisodeReplay, Any]:
        """The env (replaying fixed episodes) and the policy of ``scene``, built on first use."""
        if scene != self.scene or self.env is None:
            self.close()
            s = self.setup
            kwargs = {**s.env_kwargs, "scene": scene_source(scene)}
            wrapper = dict(s.wrapper_kwargs)
            if scene in s.databases:
                wrapper["database_dir"] = s.databases[scene]
            self.env = EpisodeReplay(make_env(s.plan, kwargs, wrapper))
            self.policy = make_policy(s.plan, self.env)
            self.scene = scene
        return self.env, self.policy

    def close(self) -> None:
        if self.env is not None:
            self.env.close()
        self.env, self.policy, self.scene = None, None, None


def trajectory_sha256(record: dict[str, Any]) -> str:
    """SHA-256 of an episode's true and estimated trajectories (4-decimal metres / radians)."""
    return hashlib.sha256(canonical([record["trajectory"], record["estimated_trajectory"]])).hexdigest()


def bench_task(state: BenchWorker, item: tuple[int, TaskEpisode]) -> dict[str, Any]:
    """One episode on a worker: its JSON-ready log record (``status`` ok or error)."""
    index, episode = item
    head = {
        "index": index,
        "episode_id": episode.episode_id,
        "scene_id": episode.scene_id,
        "seed": episode.seed,
        "dataset_geodesic": episode.geodesic,
    }
    try:
        env, policy = state.navigator(episode.scene_id)
        env.set_episode(episode)
        record = run_episode(
            env, policy, episode.seed, index, lambda n: note(f"{episode.episode_id}: step {n}")
        )
    except Exception as e:  # recorded, and the run goes on with a fresh env
        logger.warning("episode %s raised", episode.episode_id, exc_info=True)
        state.close()
        return {**head, "status": "error", "error": f"{type(e).__name__}: {e}"}
    out = {**head, "status": "ok", "error": None, **record.as_dict()}
    out["trajectory_sha256"] = trajectory_sha256(out)
    return json.loads(canonical(json_safe(out)))  # exactly what the log gives back on --resume


def episode_record(entry: dict[str, Any]) -> EpisodeRecord:
    """The :class:`EpisodeRecord` of an ``ok`` log record (for the summaries)."""
    return EpisodeRecord(
        index=entry["index"],
        seed=entry["seed"],
        start=entry["start"],
        goal=entry["goal"],
        shortest_path_length=entry["shortest_path_length"],
        failure=entry["failure"],
        metrics={m.record: entry.get(m.record) for m in _recorded()},
        trajectory=entry["trajectory"],
        estimated_trajectory=entry["estimated_trajectory"],
        frames=entry["frames"],
        collision_steps=entry["collision_steps"],
    )


def compact(entry: dict[str, Any]) -> dict[str, Any]:
    """A log record as the results file keeps it: :data:`RECORD_FIELDS` and the measures."""
    out = {k: entry.get(k) for k in RECORD_FIELDS}
    if entry["status"] == "ok":
        out |= {m.record: entry.get(m.record) for m in _recorded()}
    return out


def summary_of(entries: list[dict[str, Any]]) -> dict[str, Any]:
    """Summary metrics over the ``ok`` entries (:func:`~vgpnav_env.eval.navigation.summarize`)
    plus ``errors``; the means are None without an ``ok`` episode."""
    ok = [episode_record(e) for e in entries if e["status"] == "ok"]
    if ok:
        summary = summarize(ok)
    else:
        summary = {"episodes": 0, "failures": dict.fromkeys(FAILURES, 0)}
        summary |= {m.summary: None for m in _recorded() if m.summary}
        summary |= {m.frame_p95: None for m in _recorded() if m.frame_p95}
    summary["episodes"] = len(entries)
    summary["errors"] = len(entries) - len(ok)
    return json_safe(summary)


def git_commit() -> str | None:
    """The package checkout's commit (``+dirty`` with uncommitted changes), None outside git."""
    root = Path(__file__).resolve().parent
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "")


def bench_settings(task: Task, plan: AgentPlan, agent: str, wrapper_kwargs: dict[str, Any]) -> dict[str, Any]:
    """What the agent ran with (the log header's and results file's ``settings``)."""
    options = wrapper_kwargs.get("backbone_options") or {}
    return {
        "agent": agent,
        "agent_kind": plan.name,
        "backbone": plan.backbone,
        "perception_mode": wrapper_kwargs.get("perception_mode")
        if plan.backbone not in (None, "model")
        else None,
        "backbone_model": str(options["model"]) if "model" in options else None,
        "backbone_weights_sha256": _file_sha256(options.get("weights_path")),
        "actions": plan.actions if plan.name == "ppo" else None,
        "ppo_model_sha256": _file_sha256(plan.model),
        "image_size": list(task.image_size),
        "max_steps": task.max_steps,
    }


def _file_sha256(path: Any) -> str | None:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest() if path is not None else None


@dataclass
class BenchRun:
    """What :func:`run_bench` needs besides the workers."""

    task: Task
    split: str
    agent: str
    out: Path
    backbone: str | None = None
    perception: str | None = None
    perception_mode: str | None = None
    backbone_options: dict[str, Any] = field(default_factory=dict)
    actions: str = "deterministic"
    limit: int | None = None
    resume: bool = False
    episodes: EpisodeSet | None = None
    progress: bool = True
    #: Scene id -> database build directory (default: the scene's build in the cache).
    databases: dict[str, str] = field(default_factory=dict)
    #: Extra ``VGPNavObservation`` keyword arguments (e.g. a ``database_config``), API only.
    wrapper_options: dict[str, Any] = field(default_factory=dict)

    def plan(self) -> tuple[AgentPlan, dict[str, Any], dict[str, Any]]:
        """The agent plan, env keyword arguments (the task's rules win over the agent's) and the
        perception wrapper's keyword arguments."""
        backbone = self.backbone or self.task.perception.backbone
        plan = plan_agent(self.agent, backbone, self.perception, self.actions)
        env_kwargs = {**plan.env_kwargs, **self.task.env_kwargs()}
        wrapper = {
            "perception_mode": self.perception_mode or self.task.perception.perception_mode,
            "backbone_options": dict(self.backbone_options),
            **self.wrapper_options,
        }
        return plan, env_kwargs, wrapper


def run_bench(run: BenchRun, workers: Workers | None = None) -> dict[str, Any]:
    """Run the benchmark (module docstring); returns the results file's content."""
    clock = RunClock()
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    commit = git_commit()  # of the code that runs, whatever changes in the checkout meanwhile
    task = run.task
    episodes = run.episodes or load_episodes(task, run.split)
    chosen = list(episodes.episodes[: run.limit] if run.limit else episodes.episodes)
    plan, env_kwargs, wrapper = run.plan()
    settings = bench_settings(task, plan, run.agent, wrapper)
    header = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "task": task.summary(),
        "split": run.split,
        "episode_file_sha256": episodes.sha256,
        "settings": settings,
    }
    log = EpisodeLog(run.out)
    done = {e["episode_id"]: e for e in log.start(header, run.resume)}
    todo = [(i, e) for i, e in enumerate(chosen) if e.episode_id not in done]
    own = workers is None
    workers = workers or Workers(1, progress=run.progress)
    try:
        databases = {}
        if plan.backbone not in (None, "model"):
            for scene in dict.fromkeys(e.scene_id for _, e in todo):
                given = {"database_dir": run.databases[scene]} if scene in run.databases else {}
                kwargs = prepare_database(
                    scene_source(scene),
                    env_kwargs,
                    {**wrapper, **given},
                    run.progress,
                    workers,
                    plan.backbone,
                )
                databases[scene] = str(kwargs["database_dir"])
        setup = BenchSetup(plan, env_kwargs, wrapper, databases)

        def finished(_: int, entry: dict[str, Any]) -> None:
            log.append(entry)
            done[entry["episode_id"]] = entry

        workers.map(
            setup,
            bench_task,
            todo,
            f"bench {task.name} {run.split} {run.agent}",
            cost=[e.geodesic for _, e in todo],  # the longest first, so the last does not run alone
            on_result=finished,
        )
    finally:
        if own:
            workers.close()
    entries = [done[e.episode_id] for e in chosen]
    results = results_file(task, run, episodes, settings, entries, commit)
    results["run"] = {
        "workers": workers.where,
        "wall_s": round(clock.wall(), 1),
        "cpu_s": round(clock.cpu(workers.cpu_seconds), 1),
        "started_utc": started,
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "resumed_episodes": len(chosen) - len(todo),
    }
    results["digest"] = results_digest(results)
    validate_results(results)
    write_results(run.out, results)
    return results


def results_file(
    task: Task,
    run: BenchRun,
    episodes: EpisodeSet,
    settings: dict[str, Any],
    entries: list[dict[str, Any]],
    commit: str | None,
) -> dict[str, Any]:
    """The compared part of the results file (everything but ``run`` and ``digest``)."""
    scenes = {}
    for scene in dict.fromkeys(e["scene_id"] for e in entries):
        mine = [e for e in entries if e["scene_id"] == scene]
        scenes[scene] = {"perception": perception_split(scene), **summary_of(mine)}
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "task": task.summary(),
        "split": run.split,
        "episode_file": {
            "sha256": episodes.sha256,
            "episodes": len(episodes),
            "generator": episodes.generator,
        },
        "package_version": package_version(),
        "git_commit": commit,
        "settings": settings,
        "complete": len(entries) == len(episodes),
        "limit": run.limit,
        **summary_of(entries),
        "scenes": scenes,
        "records": [compact(e) for e in entries],
    }


def _cell(value: Any, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def leaderboard_row(results: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(header, row) of the results' leaderboard line."""
    s = results["settings"]
    name = s["agent"]
    if name.startswith("ppo:"):  # a run directory's name, not the machine's path
        name = "ppo:" + Path(name[4:]).name
    agent = name + (f" + {s['backbone']}" if s["backbone"] else "")
    commit = (results["git_commit"] or "-")[:12]
    header = ["task", "split", "agent", *(h for h, _, _ in LEADERBOARD), "episodes", "errors", "commit"]
    episodes = f"{results['episodes']}" + (
        "" if results["complete"] else f" of {results['episode_file']['episodes']}"
    )
    row = [
        f"{results['task']['name']}",
        results["split"],
        agent,
        *(_cell(results.get(k), f) for _, k, f in LEADERBOARD),
        episodes,
        str(results["errors"]),
        commit,
    ]
    return header, row


def write_results(out: Path, results: dict[str, Any]) -> None:
    """``report.json``, ``report.md`` and ``leaderboard.md`` in ``out``."""
    from vgpnav_env.atomic import atomic_write_text

    header, row = leaderboard_row(results)
    leaderboard = markdown_table(header, [row])
    scene_rows = [
        (scene, s["perception"], s["episodes"], s["errors"], *(_cell(s.get(k), f) for _, k, f in LEADERBOARD))
        for scene, s in results["scenes"].items()
    ]
    scenes = markdown_table(
        ["scene", "perception", "episodes", "errors", *(h for h, _, _ in LEADERBOARD)], scene_rows
    )
    failures = markdown_table(["failure", "episodes"], list(results["failures"].items()))
    errors = [f"- `{r['episode_id']}`: {r['error']}" for r in results["records"] if r["status"] == "error"]
    run = results["run"]
    md = [
        f"# {results['task']['name']} {results['split']}: {results['settings']['agent']}",
        leaderboard,
        "" if results["complete"] else f"**Partial**: the first {results['limit']} episodes of the split.",
        "## Scenes\n\n`perception`: whether the scene's frames were used to tune perception "
        "(`tuning`) or not (`held-out`); see `vgpnav_env/tasks/splits.yaml`.\n\n" + scenes,
        "## Failures\n\n" + failures,
        "## Errors\n\n" + ("\n".join(errors) if errors else "none"),
        f"## Run\n\nworkers: {run['workers']}, wall {run['wall_s']} s, CPU {run['cpu_s']} s, "
        f"resumed episodes {run['resumed_episodes']}, package {results['package_version']}, "
        f"commit {results['git_commit']}, digest `{results['digest'][:16]}`",
    ]
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "report.json", json.dumps(results, indent=1) + "\n")
    atomic_write_text(out / "report.md", "\n\n".join(p for p in md if p) + "\n")
    atomic_write_text(out / "leaderboard.md", leaderboard + "\n")


def headline(results: dict[str, Any]) -> str:
    """One line: SR, SPL, soft SPL, episodes, errors and the digest."""
    r = results
    n = r["episodes"] - r["errors"]
    wins = "-" if r["success_rate"] is None else f"{round(r['success_rate'] * n)}/{n}"
    partial = "" if r["complete"] else ", PARTIAL"
    return (
        f"bench {r['task']['name']} {r['split']} ({r['settings']['agent']}): success {wins}, "
        f"SR {_cell(r['success_rate'], '.3f')}, SPL {_cell(r['spl'], '.3f')}, "
        f"soft SPL {_cell(r['soft_spl'], '.3f')}, {r['errors']} errors{partial}; digest {r['digest'][:16]}"
    )


def _agent_slug(agent: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(agent.split(":", 1)[-1]).stem if "/" in agent else agent)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """CLI arguments of ``vgpnav bench``."""
    from vgpnav_env.eval.navigation import ACTION_KINDS, PERCEPTION_KINDS
    from vgpnav_env.eval.perception_runs import add_backbone_arguments
    from vgpnav_env.perception.pipeline import PERCEPTION_MODES
    from vgpnav_env.tasks import task_names

    parser.add_argument("task", help=f"a task ({', '.join(task_names())}) or a task .yaml file")
    parser.add_argument("--split", choices=SPLIT_NAMES, default="test", help="default test")
    parser.add_argument(
        "--agent",
        type=agent_arg,
        default="astar",
        metavar="AGENT",
        help="astar, oracle, ppo:PATH or MODULE:FACTORY (your own agent, docs/benchmark.md)",
    )
    add_backbone_arguments(parser)
    parser.set_defaults(backbone=None)
    parser.add_argument(
        "--perception",
        choices=list(PERCEPTION_KINDS),
        default=None,
        help="what perception agents drive on (default: pixels for astar, none for "
        "MODULE:FACTORY, as trained for ppo)",
    )
    parser.add_argument(
        "--perception-mode", choices=list(PERCEPTION_MODES), default=None, help="default: the task's"
    )
    parser.add_argument(
        "--actions", choices=list(ACTION_KINDS), default="deterministic", help="how a ppo:PATH policy acts"
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="run directory (default bench/TASK-SPLIT-AGENT)"
    )
    parser.add_argument(
        "--limit",
        type=positive_int_arg,
        default=None,
        help="run only the first N episodes (the results file says partial)",
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its episode log"
    )
    parser.add_argument(
        "--database",
        action="append",
        default=[],
        metavar="SCENE=DIR",
        help="a scene's database build (vgpnav build, at the task's image size); repeatable; "
        "default: the cache's, built if missing",
    )
    add_worker_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``vgpnav bench``; returns the exit code."""
    from vgpnav_env.eval.perception_runs import backbone_options

    task = load_task(args.task)
    if args.backbone is None:
        args.backbone = task.perception.backbone
    options = backbone_options(args)
    episodes = load_episodes(task, args.split)
    databases = {}
    for entry in args.database:
        scene, sep, directory = entry.partition("=")
        if not sep or not Path(directory).is_dir():
            raise ValueError(f"--database {entry}: expected SCENE=DIR with a build directory")
        databases[scene] = directory
    out = args.out or Path("bench") / f"{task.name}-{args.split}-{_agent_slug(args.agent)}"
    bench = BenchRun(
        task,
        args.split,
        args.agent,
        out,
        args.backbone,
        args.perception,
        args.perception_mode,
        options,
        args.actions,
        args.limit,
        args.resume,
        episodes,
        databases=databases,
    )
    with workers_from_args(args) as workers:
        results = run_bench(bench, workers)
    print_headline(headline(results), out)
    return 0
