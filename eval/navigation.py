"""Navigation protocol: success rate, SPL and soft SPL of an agent over point-goal episodes.

``vgpnav eval navigation SCENE --agent astar|oracle|ppo:PATH --backbone classical|simulated
--episodes N --out DIR [--seed S] [--size WxH]`` writes ``DIR/report.json`` (aggregates and one
record per episode), ``DIR/report.md`` and a top-down picture of every trajectory under
``DIR/trajectories/``. Episode ``i`` is ``reset(seed=seed + i)`` on the scene's changed layout, so
every agent sees the same start/goal pairs.

Failure reasons: ``timeout`` (no stop within the step budget), ``stopped-too-far`` (stop farther
than the success distance) and ``lost`` (a perception agent whose pose estimate was not localized
on at least half of the steps).
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from tqdm import tqdm

from vgpnav_env.agents import ppo
from vgpnav_env.agents.astar import AStarAgent
from vgpnav_env.agents.oracle import OracleAgent
from vgpnav_env.arguments import seed_arg, size_arg
from vgpnav_env.eval.perception_runs import add_backbone_arguments, backbone_options
from vgpnav_env.eval.report import markdown_table, write_report
from vgpnav_env.measures import MEASURES, Measure
from vgpnav_env.robot import Action

logger = logging.getLogger(__name__)

ENV_ID = "VGPNav/PointGoal-v0"
FAILURES = ("timeout", "stopped-too-far", "lost")


class Policy(Protocol):
    """What the protocol drives: ``reset()`` per episode, ``act(obs) -> action`` per step.

    Policies see observations only (plus what they were given at construction); the env's
    ``info`` is for evaluation.
    """

    def reset(self) -> None: ...

    def act(self, obs: Any) -> Any: ...


class PerceptionAStar:
    """The A* agent on the VGP-Nav wrapper's estimated pose and fused obstacle map.

    Reads ``obs["pose"]`` (x, y, yaw), ``obs["goal_rel"]`` (distance, bearing) and
    ``obs["localized"]``, and the wrapper's ``fused_map`` (its occupied cells are the obstacles).
    Until the first localized frame of an episode it turns in place (there is no pose to plan
    from); after ``max_blind_steps`` dead-reckoned steps it turns in place for at most one full
    turn to look for a view that localizes, then goes on by dead reckoning.
    """

    def __init__(self, env: gym.Env, max_blind_steps: int = 8, **agent_kwargs: Any) -> None:
        self.env = env
        base = env.unwrapped
        agent_kwargs.setdefault("robot_radius", base.robot_radius)
        agent_kwargs.setdefault("forward_step", base.forward_step)
        agent_kwargs.setdefault("turn_step_deg", float(np.degrees(base.turn_step)))
        self.agent = AStarAgent(**agent_kwargs)
        self.max_blind_steps = int(max_blind_steps)
        self.turns_per_circle = int(np.ceil(2.0 * np.pi / base.turn_step))
        self.reset()

    def reset(self) -> None:
        self.agent.reset()
        self.seen = False  # localized at least once this episode
        self.blind = 0  # consecutive frames without localization
        self.searched = 0  # look-around turns in the current blind spell

    def act(self, obs: dict[str, Any]) -> Action:
        if int(np.asarray(obs["localized"]).reshape(-1)[0]):
            self.seen, self.blind, self.searched = True, 0, 0
        else:
            self.blind += 1
        looking = self.blind > self.max_blind_steps and self.searched < self.turns_per_circle
        if not self.seen or looking:
            self.searched += int(self.seen)
            return Action.TURN_LEFT
        x, y, yaw = np.asarray(obs["pose"], float)
        dist, bearing = np.asarray(obs["goal_rel"], float)
        goal = np.array([x + dist * np.cos(yaw + bearing), y + dist * np.sin(yaw + bearing)])
        fused = self.env.get_wrapper_attr("fused_map")
        return self.agent.act((x, y, yaw), fused.occupied(), fused.spec, goal)


def perception_wrapper(backbone: str, **wrapper_kwargs: Any) -> Callable[[gym.Env], gym.Env]:
    """``env -> VGPNavObservation(env, backbone=backbone, **wrapper_kwargs)``."""
    from vgpnav_env.wrappers import VGPNavObservation

    return lambda env: VGPNavObservation(env, backbone=backbone, **wrapper_kwargs)


def make_agent(
    agent: str, backbone: str, wrapper_kwargs: dict[str, Any] | None = None
) -> tuple[Callable[[gym.Env], Policy], Callable[[gym.Env], gym.Env] | None, dict[str, Any]]:
    """(policy factory over the env, observation wrapper or None, env keyword arguments the agent
    needs) for an ``--agent`` string; ``wrapper_kwargs`` go to ``VGPNavObservation``."""
    wrapper_kwargs = wrapper_kwargs or {}
    if agent == "oracle":
        return OracleAgent, None, {"render_rgb": False}
    if agent == "astar":
        return PerceptionAStar, perception_wrapper(backbone, **wrapper_kwargs), {}
    if agent.startswith("ppo:"):
        path = ppo.model_path(agent[4:])
        config = ppo.load_config(path)
        wrapper = perception_wrapper(config["backbone"], **wrapper_kwargs) if config.get("backbone") else None
        env_kwargs = {**config["env_kwargs"], "image_size": tuple(config["env_kwargs"]["image_size"])}
        return (lambda env: ppo.SB3Policy(path)), wrapper, env_kwargs
    raise ValueError(f"unknown agent {agent!r}; allowed: astar, oracle, ppo:PATH")


@dataclass
class EpisodeRecord:
    """One evaluated episode (metres, radians; failure None on success).

    ``metrics``: the episode value of every registered measure with a ``record`` name
    (:mod:`vgpnav_env.measures`): ``final_distance``, ``final_euclidean_distance``, ``success``,
    ``spl``, ``soft_spl``, ``collisions``, ``steps``, ``travelled``, and for agents with a pose
    estimate ``localization_error_m`` (mean over the frames acted on) and ``lost_fraction`` (None
    without an estimate).
    """

    index: int
    seed: int
    start: list[float]
    goal: list[float]
    shortest_path_length: float
    failure: str | None
    metrics: dict[str, Any]
    trajectory: list[list[float]] = field(repr=False)
    estimated_trajectory: list[list[float]] | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        """The record as one flat JSON-ready dict (the metrics beside the other fields)."""
        fields = asdict(self)
        head = {k: fields.pop(k) for k in ("index", "seed", "start", "goal", "shortest_path_length")}
        return {**head, **fields.pop("metrics"), **fields}


def _recorded() -> list[type[Measure]]:
    return [m for m in MEASURES.values() if m.record]


def _failure(metrics: dict[str, Any], stopped: bool) -> str | None:
    lost = metrics.get("lost_fraction")
    if metrics["success"]:
        return None
    if lost is not None and lost >= 0.5:
        return "lost"
    return "stopped-too-far" if stopped else "timeout"


def run_episode(env: gym.Env, policy: Policy, seed: int, index: int = 0) -> EpisodeRecord:
    """Drive one episode ``reset(seed=seed)`` to its end with ``policy``.

    Per-frame measures are collected from ``info`` at every frame the policy acts on; the others
    give their value at the end of the episode.
    """
    obs, info = env.reset(seed=seed)
    policy.reset()
    frames: dict[str, list[Any]] = {m.uuid: [] for m in _recorded() if m.per_frame}
    estimated: list[list[float]] = []
    done = False
    while not done:
        if isinstance(obs, dict) and "pose" in obs:
            estimated.append(np.asarray(obs["pose"], float).tolist())
        for uuid, values in frames.items():
            if uuid in info:
                values.append(info[uuid])
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        done = terminated or truncated
    metrics: dict[str, Any] = {}
    for m in _recorded():
        values = frames[m.uuid] if m.per_frame else [info[m.uuid]] if m.uuid in info else []
        metrics[m.record] = m.episode_value(values)
    return EpisodeRecord(
        index=index,
        seed=seed,
        start=[float(v) for v in info["start"]],
        goal=[float(v) for v in info["goal"]],
        shortest_path_length=float(info["shortest_path_length"]),
        failure=_failure(metrics, info["stopped"]),
        metrics=metrics,
        trajectory=np.asarray(env.unwrapped.trajectory).round(4).tolist(),
        estimated_trajectory=estimated or None,
    )


def summarize(records: list[EpisodeRecord]) -> dict[str, Any]:
    """Aggregates over episode records: the mean of every measure with a ``summary`` key (over
    the episodes that have a value; None if none has) and the failure counts."""
    summary: dict[str, Any] = {"episodes": len(records)}
    for m in _recorded():
        if m.summary:
            values = [r.metrics[m.record] for r in records if r.metrics.get(m.record) is not None]
            summary[m.summary] = float(np.mean(values)) if values else None
    summary["failures"] = {f: sum(r.failure == f for r in records) for f in FAILURES}
    return summary


def episode_table(records: list[EpisodeRecord]) -> str:
    """Markdown table of the episodes: index, seed, shortest path, every measure with a ``column``
    and the failure."""
    columns = [m for m in _recorded() if m.column]
    header = ["#", "seed", "shortest (m)", *(m.column for m in columns), "failure"]
    rows = [
        (r.index, r.seed, r.shortest_path_length, *(r.metrics[m.record] for m in columns), r.failure or "")
        for r in records
    ]
    return markdown_table(header, rows)


def plot_trajectory(env: gym.Env, record: EpisodeRecord, path: Path) -> None:
    """Top-down picture of one episode over the ground-truth map (matplotlib PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = env.unwrapped.ground_truth
    spec = gt.spec
    img = np.full(spec.shape, 0.15)
    img[gt.free] = 0.75
    img[env.unwrapped.world.navigable] = 1.0
    img[gt.obstacle] = 0.4
    (x0, y0), (x1, y1) = spec.bounds
    extent = (x0, x1, y0, y1)
    fig, ax = plt.subplots(figsize=(6, 6 * spec.shape[0] / max(spec.shape[1], 1) + 0.5))
    ax.imshow(img, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent, interpolation="nearest")
    traj = np.asarray(record.trajectory)
    ax.plot(traj[:, 0], traj[:, 1], "-", color="tab:green", lw=1.5, label="true")
    if record.estimated_trajectory:
        est = np.asarray(record.estimated_trajectory)
        ax.plot(est[:, 0], est[:, 1], "--", color="tab:orange", lw=1.0, label="estimated")
    ax.plot(*record.start[:2], "o", color="tab:cyan", label="start")
    ax.plot(*record.goal, "*", color="tab:purple", ms=12, label="goal")
    ax.add_patch(
        plt.Circle(record.goal, env.unwrapped.success_distance, fill=False, ls=":", color="tab:purple")
    )
    outcome = record.failure or "success"
    spl = record.metrics["spl"]
    ax.set_title(f"episode {record.index} (seed {record.seed}): {outcome}, SPL {spl:.2f}")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def evaluate_navigation(
    scene: str,
    agent: str = "oracle",
    backbone: str = "classical",
    episodes: int = 20,
    seed: int = 0,
    size: tuple[int, int] = (320, 240),
    out_dir: str | Path | None = None,
    env_kwargs: dict[str, Any] | None = None,
    progress: bool = True,
    database_dir: str | Path | None = None,
    wrapper_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run the protocol; returns the report dict (also written to ``out_dir`` if given).

    Perception agents use the database build at ``database_dir`` (default: the scene's build at
    the env's image size in the vgpnav cache, built if missing); ``wrapper_kwargs`` go to
    ``VGPNavObservation``.
    """
    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    wrapper_kwargs = dict(wrapper_kwargs or {})
    if database_dir is not None:
        wrapper_kwargs["database_dir"] = database_dir
    make_policy, wrapper, agent_env_kwargs = make_agent(agent, backbone, wrapper_kwargs)
    kwargs = {"scene": scene, "layout": "changed", "image_size": tuple(size), **agent_env_kwargs}
    kwargs.update(env_kwargs or {})
    env = gym.make(ENV_ID, **kwargs)
    if wrapper is not None:
        env = wrapper(env)
    policy = make_policy(env)
    records: list[EpisodeRecord] = []
    try:
        for i in tqdm(range(episodes), desc=f"navigation {scene} {agent}", disable=not progress):
            record = run_episode(env, policy, seed + i, i)
            records.append(record)
            if out_dir is not None:
                plot_trajectory(env, record, Path(out_dir) / "trajectories" / f"episode_{i:03d}.png")
    finally:
        env.close()
    report = {
        "protocol": "navigation",
        "scene": scene,
        "layout": kwargs["layout"],
        "agent": agent,
        "backbone": backbone if wrapper is not None else None,
        "seed": seed,
        "image_size": list(size),
        **summarize(records),
        "records": [r.as_dict() for r in records],
    }
    if out_dir is not None:
        table = episode_table(records)
        pictures = "\n".join(f"![episode {r.index}](trajectories/episode_{r.index:03d}.png)" for r in records)
        write_report(
            out_dir,
            f"Navigation: {scene} ({agent})",
            report,
            sections=["## Episodes\n\n" + table, "## Trajectories\n\n" + pictures],
        )
    return report


def evaluate_policy(
    path: str | Path,
    episodes: int = 20,
    scene: str | None = None,
    seed: int = 1000,
    out_dir: str | Path | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """The navigation protocol for a trained PPO policy (run directory or model file) in the env it
    was trained on (scene, backbone, image size and database from its ``config.json``)."""
    config = ppo.load_config(path)
    return evaluate_navigation(
        scene or config["scene"],
        agent=f"ppo:{ppo.model_path(path)}",
        backbone=config["backbone"] or "classical",
        episodes=episodes,
        seed=seed,
        size=tuple(config["env_kwargs"]["image_size"]),
        out_dir=out_dir,
        progress=progress,
        database_dir=config.get("database_dir"),
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """CLI arguments of ``vgpnav eval navigation``."""
    parser.add_argument("scene", help="built-in scene name (e.g. home, hospital) or scene source")
    parser.add_argument("--agent", default="astar", help="astar | oracle | ppo:PATH (default astar)")
    add_backbone_arguments(parser)
    parser.add_argument("--episodes", type=int, default=20, help="number of start/goal pairs")
    parser.add_argument("--out", required=True, type=Path, help="report directory")
    parser.add_argument("--seed", type=seed_arg, default=0, help="episode i uses seed + i")
    parser.add_argument("--size", type=size_arg, default=(320, 240), help="camera image WxH")
    parser.add_argument(
        "--database",
        type=Path,
        default=None,
        help="build directory (vgpnav build) of the scene at --size; default: the cache, built if missing",
    )
    parser.add_argument(
        "--max-steps", type=int, default=500, help="steps before an episode times out (default 500, Habitat)"
    )


def run(args: argparse.Namespace) -> int:
    """Entry point of ``vgpnav eval navigation``; returns the process exit code."""
    if args.max_steps <= 0:
        raise ValueError(f"--max-steps must be a positive integer, got {args.max_steps}")
    options = backbone_options(args)
    report = evaluate_navigation(
        args.scene,
        args.agent,
        args.backbone,
        args.episodes,
        args.seed,
        args.size,
        out_dir=args.out,
        env_kwargs={"max_steps": args.max_steps},
        database_dir=args.database,
        wrapper_kwargs={"backbone_options": options},
    )
    perception = "true pose and map" if args.agent == "oracle" else f"VGP-Nav, {args.backbone} backbone"
    print(
        f"navigation {args.scene} ({args.agent}, {perception}): success rate "
        f"{report['success_rate']:.2f} ({round(report['success_rate'] * report['episodes'])}/"
        f"{report['episodes']}), SPL {report['spl']:.2f}\nreport: {Path(args.out) / 'report.md'}"
    )
    return 0
