"""Navigation protocol: success rate, SPL and soft SPL of an agent over point-goal episodes.

``vgpnav eval navigation SCENE --agent astar|oracle|ppo:PATH --backbone B [--perception pixels|model]
[--perception-mode temporal|paper] --episodes N --out DIR
[--seed S] [--size WxH] [--max-steps N] [--workers N] [--ray [ADDRESS]]`` writes
``DIR/report.json`` (settings, aggregates, one record per episode with its per-frame pose errors),
``DIR/report.md`` (settings, failure labels, summary, per-episode table, plots), ``DIR/errors.png``
(pose-error CDF over all frames, lost fraction per episode) and one picture per episode under
``DIR/trajectories/`` (:mod:`vgpnav_env.eval.navigation_plots`). Episode ``i`` is
``reset(seed=seed + i)`` on the scene's changed layout, so every agent sees the same start/goal
pairs, and episodes run in parallel on ``--workers`` processes or a Ray cluster
(:mod:`vgpnav_env.eval.workers`; each worker builds the env, the perception and the agent once)
with the same records as a sequential run.

Metrics come from the measures registry (:mod:`vgpnav_env.measures`). Failure labels (one per
failed episode, the first that applies; :data:`FAILURES`): ``lost`` (perception never localized),
``mislocalized`` (the pose estimate was more than the success distance off at the end or on most
frames), ``stopped-too-far`` and ``timeout``.
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

from vgpnav_env.agents import AGENTS, agent_choices, parse_agent, ppo
from vgpnav_env.agents.astar import REOPEN_FREE, AStarAgent
from vgpnav_env.agents.oracle import OracleAgent
from vgpnav_env.agents.proprioception import LOOP_WINDOW
from vgpnav_env.arguments import positive_int_arg, seed_arg, size_arg
from vgpnav_env.eval.perception_runs import (
    add_backbone_arguments,
    add_perception_mode_argument,
    backbone_options,
    classical_features,
)
from vgpnav_env.eval.report import RunClock, markdown_table, print_headline, run_settings, write_report
from vgpnav_env.eval.workers import Workers, add_worker_arguments, note, workers_from_args
from vgpnav_env.measures import MEASURES, Measure, frame_value
from vgpnav_env.robot import Action

logger = logging.getLogger(__name__)

ENV_ID = "VGPNav/PointGoal-v0"
#: A pose estimate this many times the success distance off counts as wrong (``mislocalized``).
MISLOCALIZED = 1.0
#: Failure label -> definition (``{d}``: the success distance in metres); checked in this order.
FAILURES: dict[str, str] = {
    "lost": "perception never localized in the episode: the agent never had a pose to plan from",
    "mislocalized": "the pose estimate was more than the success distance ({d:g} m) off at the end "
    "of the episode or on at least half of its frames",
    "stopped-too-far": "the agent stopped farther than {d:g} m from the goal with a right pose estimate "
    "(or none: the oracle's is the true pose)",
    "timeout": "the step budget ran out with a right pose estimate (or none)",
}


class Policy(Protocol):
    """What the protocol drives: ``reset()`` per episode, ``act(obs) -> action`` per step.

    Policies see observations only (plus what they were given at construction); the env's
    ``info`` is for evaluation. ``reset(seed)`` gets the episode's seed (a policy that samples its
    actions draws them from it, so that an episode's actions do not depend on the worker).
    """

    def reset(self, seed: int | None = None) -> None: ...

    def act(self, obs: Any) -> Any: ...


class PerceptionAStar:
    """The A* agent on the VGP-Nav wrapper's estimated pose and fused obstacle map.

    Reads ``obs["pose"]`` (x, y, yaw), ``obs["goal_rel"]`` (distance, bearing) and
    ``obs["localized"]``, and the wrapper's ``fused_map`` (its occupied cells are the obstacles)
    and ``pose_state``. Until the first localized frame of an episode (there is no pose to plan
    from) it explores: one full turn in place, then straight ahead; whenever a forward step was
    blocked (the robot's bump sensor, the env's ``bumped``) it turns to the untried heading (turns
    are exact: headings are counted in turn steps from the start) farthest from every heading it
    drove along, and after every ``explore_steps`` steps moved it turns once more in full (a new
    viewpoint each time): turning about after every bump kept it on one line in a pocket.
    When the pose becomes uncertain -- its position standard deviation
    (the pose state's covariance, largest axis) above ``max_sigma`` metres, or without a
    covariance (paper mode) after ``max_blind_steps`` dead-reckoned steps -- it turns in place for
    at most one full turn to look for a view that localizes, then goes on by dead reckoning.
    """

    def __init__(
        self,
        env: gym.Env,
        max_blind_steps: int = 8,
        max_sigma: float = 0.3,
        explore_steps: int = 8,
        **agent_kwargs: Any,
    ) -> None:
        self.env = env
        base = env.unwrapped
        agent_kwargs.setdefault("robot_radius", base.robot_radius)
        agent_kwargs.setdefault("forward_step", base.forward_step)
        agent_kwargs.setdefault("turn_step_deg", float(np.degrees(base.turn_step)))
        self.agent = AStarAgent(**agent_kwargs)
        self.max_blind_steps = int(max_blind_steps)
        self.max_sigma = float(max_sigma)
        self.explore_steps = int(explore_steps)
        self.turns_per_circle = int(np.ceil(2.0 * np.pi / base.turn_step))
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        self.agent.reset()
        self.seen = False  # localized at least once this episode
        self.blind = 0  # consecutive frames without localization
        self.searched = 0  # look-around turns in the current blind spell
        self._turns_left = self.turns_per_circle  # exploration before the first fix (< 0: right)
        self._moved = 0  # forward steps moved since the last full turn of the exploration
        self._last: Action | None = None  # the last exploration action
        self._heading = 0  # turn steps left of the start heading, modulo a full turn
        self._tried: set[int] = set()  # headings driven along

    def _uncertain(self) -> bool:
        """Whether the pose is too uncertain to drive on (see the class docstring)."""
        covariance = self.env.get_wrapper_attr("pose_state").covariance
        if covariance is None:
            return self.blind > self.max_blind_steps
        return bool(np.sqrt(np.linalg.eigvalsh(covariance[:2, :2]).max()) > self.max_sigma)

    def _blocked(self) -> bool:
        """Whether the last step was blocked: the robot's bump sensor (the env's ``bumped``)."""
        return bool(self.env.unwrapped.bumped)

    def _explore(self) -> Action:
        """The exploration before the first fix (see the class docstring)."""
        if self._last == Action.FORWARD:
            self._tried.add(self._heading)
            if self._blocked():
                self._turns_left = self._turn_to_untried()
            else:
                self._moved += 1
        if self._moved >= self.explore_steps:
            self._moved, self._turns_left = 0, self.turns_per_circle
        turn = int(np.sign(self._turns_left))  # +1: left, -1: right, 0: forward
        action = {1: Action.TURN_LEFT, -1: Action.TURN_RIGHT, 0: Action.FORWARD}[turn]
        self._turns_left -= turn
        self._heading = (self._heading + turn) % self.turns_per_circle
        self._last = action
        return action

    def _turn_to_untried(self) -> int:
        """Signed turn steps (left > 0) to the heading farthest from every tried one (ties: the
        fewest turns, then left); once every heading was tried, a new round from this one."""
        n = self.turns_per_circle
        if len(self._tried) == n:
            self._tried = {self._heading}
        headings = np.arange(n)
        gap = np.abs(headings[:, None] - np.array(sorted(self._tried))[None])
        farthest = np.minimum(gap, n - gap).min(axis=1)
        turns = (headings - self._heading + n // 2) % n - n // 2  # in [-n/2, n/2)
        best = max(range(n), key=lambda h: (farthest[h], -abs(turns[h]), turns[h]))
        return int(turns[best])

    def act(self, obs: dict[str, Any]) -> Action:
        if int(np.asarray(obs["localized"]).reshape(-1)[0]):
            self.seen, self.blind, self.searched = True, 0, 0
        else:
            self.blind += 1
        if not self.seen:  # no pose yet: explore for a view that localizes
            return self._explore()
        if self.searched < self.turns_per_circle and self._uncertain():
            self.searched += 1
            return Action.TURN_LEFT
        x, y, yaw = np.asarray(obs["pose"], float)
        dist, bearing = np.asarray(obs["goal_rel"], float)
        goal = np.array([x + dist * np.cos(yaw + bearing), y + dist * np.sin(yaw + bearing)])
        fused = self.env.get_wrapper_attr("fused_map")
        covariance = self.env.get_wrapper_attr("pose_state").covariance
        sigma = 0.0 if covariance is None else float(np.sqrt(np.linalg.eigvalsh(covariance[:2, :2]).max()))
        action = self.agent.act(
            (x, y, yaw),
            fused.occupied(),
            fused.spec,
            goal,
            self._blocked(),
            free=fused.floor_seen(REOPEN_FREE),
            position_sigma=sigma,
        )
        if self.agent.path is not None:
            self.env.unwrapped.set_overlay(path=self.agent.path)  # drawn by render()
        return action


@dataclass(frozen=True)
class AgentPlan:
    """What running an ``--agent`` takes: its ``name`` (:data:`vgpnav_env.agents.AGENTS`), the
    perception ``backbone`` it drives on (None: none), the env keyword arguments it needs, and for
    a PPO policy the ``model`` file, the ``database_dir`` it was trained with and how it picks its
    ``actions`` (:data:`ACTION_KINDS`); for an agent from outside the package its ``factory``
    (``MODULE:FACTORY``, :mod:`vgpnav_env.agents.external`)."""

    name: str
    backbone: str | None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    model: Path | None = None
    database_dir: str | None = None
    actions: str = "deterministic"
    factory: str | None = None

    @property
    def description(self) -> str:
        """E.g. ``astar (VGP-Nav, classical backbone)``."""
        what = f"VGP-Nav, {self.backbone} backbone" if self.backbone else "no perception"
        if self.backbone == "model":
            what = "model perception, privileged"
        if self.name == "oracle":
            what = "true pose and map"
        return f"{self.name} ({what})"


#: ``--perception``: what perception agents drive on.
PERCEPTION_KINDS = {
    "pixels": "VGP-Nav on the camera images with --backbone",
    "model": "the PRIVILEGED error model fitted to classical runs (vgpnav_env.perception.model)",
}


#: ``--actions``: how a PPO policy picks its action from its action distribution.
ACTION_KINDS = {
    "deterministic": "the most likely action (default)",
    "sampled": "drawn from the distribution, seeded per episode",
    "escape-loops": "the most likely action, but drawn (seeded per episode) at a step whose input and "
    f"dead-reckoned pose repeat one of the last {LOOP_WINDOW} steps' exactly (a deterministic policy's loop)",
}


def plan_agent(
    agent: str, backbone: str, perception: str | None = None, actions: str = "deterministic"
) -> AgentPlan:
    """The :class:`AgentPlan` of an ``--agent`` string (a one-line ValueError for an unknown name,
    FileNotFoundError for a missing PPO model). Perception agents drive on ``perception``
    (:data:`PERCEPTION_KINDS`; ``pixels`` uses ``backbone``): A* by default on pixels, a PPO policy
    by default on the perception it was trained with (and its image size and database).
    ``actions`` (:data:`ACTION_KINDS`) applies to PPO policies only (the others are planners)."""
    if perception is not None and perception not in PERCEPTION_KINDS:
        raise ValueError(f"unknown perception {perception!r}; allowed: {list(PERCEPTION_KINDS)}")
    if actions not in ACTION_KINDS:
        raise ValueError(f"unknown actions {actions!r}; allowed: {list(ACTION_KINDS)}")
    chosen = {None: None, "pixels": backbone, "model": "model"}[perception]
    name, path = parse_agent(agent)
    if actions != "deterministic" and name != "ppo":
        raise ValueError(f"--actions {actions} applies to ppo:PATH agents, not {name}")
    if name == "ppo":
        model = ppo.model_path(path)
        config = ppo.load_config(model)["env"]
        trained = config["perception"]
        env_kwargs = dict(config["env"])
        env_kwargs.pop("max_steps", None)  # the protocol's budget
        if chosen is None or chosen == trained:
            env_kwargs["image_size"] = tuple(env_kwargs["image_size"])
            return AgentPlan(name, trained, env_kwargs, model, config.get("database_dir"), actions)
        env_kwargs.pop("image_size")  # another perception: the protocol's image size (its database)
        return AgentPlan(name, chosen, env_kwargs, model, actions=actions)
    if name == "oracle":
        return AgentPlan(name, None, {"render_rgb": False})
    if name == "external":  # the raw observation unless --perception says otherwise
        return AgentPlan(name, chosen, factory=path)
    return AgentPlan(name, (chosen or backbone) if AGENTS[name].perception else None)


def make_policy(plan: AgentPlan, env: gym.Env) -> Policy:
    """The policy of ``plan`` acting in ``env`` (already wrapped for perception when it needs it)."""
    if plan.name == "oracle":
        return OracleAgent(env)
    if plan.name == "astar":
        return PerceptionAStar(env)
    if plan.name == "external":
        from vgpnav_env.agents.external import ExternalPolicy

        return ExternalPolicy(plan.factory, env)
    return ppo.SB3Policy(
        plan.model, env, sample=plan.actions == "sampled", escape_loops=plan.actions == "escape-loops"
    )


def make_env(plan: AgentPlan, env_kwargs: dict[str, Any], wrapper_kwargs: dict[str, Any]) -> gym.Env:
    """The point-goal env with ``env_kwargs``, wrapped in ``VGPNavObservation(**wrapper_kwargs)``
    when the agent drives on perception."""
    env = gym.make(ENV_ID, **env_kwargs)
    if plan.backbone is None:
        return env
    if plan.backbone == "model":
        from vgpnav_env.perception.model import ModelObservation

        return ModelObservation(env, fit=wrapper_kwargs.get("fit"))
    from vgpnav_env.wrappers import VGPNavObservation

    return VGPNavObservation(env, backbone=plan.backbone, **wrapper_kwargs)


@dataclass
class EpisodeRecord:
    """One evaluated episode (metres, radians; failure None on success, else a :data:`FAILURES` label).

    ``metrics``: the episode value of every registered measure with a ``record`` name
    (:mod:`vgpnav_env.measures`): ``final_distance``, ``final_euclidean_distance``, ``success``,
    ``spl``, ``soft_spl``, ``collisions``, ``steps``, ``travelled``, and for agents with a pose
    estimate ``localization_error_m`` (mean over the frames acted on) and ``lost_fraction`` (None
    without an estimate). ``frames``: the per-frame values of the per-frame measures (uuid -> one
    value per frame the agent acted on; empty without an estimate). ``collision_steps``: the steps
    whose motion was blocked (the robot stood at ``trajectory[s + 1]`` after step ``s``);
    ``burst_step``: the step that completed the first collision burst (:func:`run_episode`), None
    without one.
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
    frames: dict[str, list[Any]] = field(default_factory=dict, repr=False)
    collision_steps: list[int] = field(default_factory=list, repr=False)
    burst_step: int | None = None

    def as_dict(self) -> dict[str, Any]:
        """The record as one flat JSON-ready dict (the metrics beside the other fields)."""
        fields = asdict(self)
        head = {k: fields.pop(k) for k in ("index", "seed", "start", "goal", "shortest_path_length")}
        return {**head, **fields.pop("metrics"), **fields}


def _recorded() -> list[type[Measure]]:
    return [m for m in MEASURES.values() if m.record]


def classify_failure(
    metrics: dict[str, Any], frames: dict[str, list[Any]], stopped: bool, success_distance: float
) -> str | None:
    """The :data:`FAILURES` label of an episode (None on success), the first that applies."""
    if metrics["success"]:
        return None
    localized = frames.get("localized", [])
    errors = np.asarray(frames.get("localization_error_m", []), float)
    if len(localized) and not any(localized):
        return "lost"
    wrong = errors > MISLOCALIZED * success_distance
    if len(errors) and (wrong[-1] or wrong.mean() >= 0.5):
        return "mislocalized"
    return "stopped-too-far" if stopped else "timeout"


#: A collision burst: this many blocked steps within the last :data:`BURST_WINDOW` steps.
BURST_COLLISIONS, BURST_WINDOW = 3, 10


def run_episode(
    env: gym.Env,
    policy: Policy,
    seed: int,
    index: int = 0,
    on_step: Callable[[int], None] | None = None,
    on_burst: Callable[[int], None] | None = None,
) -> EpisodeRecord:
    """Drive one episode ``reset(seed=seed)`` to its end with ``policy``.

    Per-frame measures are collected from ``info`` at every frame the policy acts on; the others
    give their value at the end of the episode. ``on_step(n)`` is called after the n-th step;
    ``on_burst(n)`` once, after the step that completes the episode's first collision burst
    (:data:`BURST_COLLISIONS` blocked steps within :data:`BURST_WINDOW`), e.g. to keep the map and
    plan of that moment; the record's ``burst_step`` is that step's index.
    """
    obs, info = env.reset(seed=seed)
    policy.reset(seed)
    frames: dict[str, list[Any]] = {m.uuid: [] for m in _recorded() if m.per_frame}
    estimated: list[list[float]] = []
    collisions: list[int] = []
    burst: int | None = None
    done, steps = False, 0
    while not done:
        if isinstance(obs, dict) and "pose" in obs:
            estimated.append(np.asarray(obs["pose"], float).tolist())
        for uuid, values in frames.items():
            value = frame_value(info, uuid)
            if value is not None:
                values.append(value)
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        if info["blocked"]:
            collisions.append(int(info["steps"]) - 1)
            recent = sum(c > collisions[-1] - BURST_WINDOW for c in collisions)
            if burst is None and recent >= BURST_COLLISIONS:
                burst = collisions[-1]
                if on_burst is not None:
                    on_burst(burst)
        done = terminated or truncated
        steps += 1
        if on_step is not None:
            on_step(steps)
    metrics: dict[str, Any] = {}
    for m in _recorded():
        values = frames[m.uuid] if m.per_frame else [info[m.uuid]] if m.uuid in info else []
        metrics[m.record] = m.episode_value(values)
    frames = {uuid: [_plain(v) for v in values] for uuid, values in frames.items() if values}
    return EpisodeRecord(
        index=index,
        seed=seed,
        start=[float(v) for v in info["start"]],
        goal=[float(v) for v in info["goal"]],
        shortest_path_length=float(info["shortest_path_length"]),
        failure=classify_failure(metrics, frames, info["stopped"], env.unwrapped.success_distance),
        metrics=metrics,
        trajectory=np.asarray(env.unwrapped.trajectory).round(4).tolist(),
        estimated_trajectory=estimated or None,
        frames=frames,
        collision_steps=collisions,
        burst_step=burst,
    )


def _plain(value: Any) -> Any:
    """A per-frame value as a plain Python number (rounded floats keep records small)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    return round(float(value), 4)


def summarize(records: list[EpisodeRecord]) -> dict[str, Any]:
    """Aggregates over episode records: the mean of every measure with a ``summary`` key (over
    the episodes that have a value; None if none has), the 95th percentile over all frames of
    every per-frame measure with a ``frame_p95`` key, and the failure counts."""
    summary: dict[str, Any] = {"episodes": len(records)}
    for m in _recorded():
        if m.summary:
            values = [r.metrics[m.record] for r in records if r.metrics.get(m.record) is not None]
            summary[m.summary] = float(np.mean(values)) if values else None
        if m.frame_p95:
            values = np.asarray([v for r in records for v in r.frames.get(m.uuid, [])], float)
            values = values[np.isfinite(values)]  # nan: a frame without an estimate
            summary[m.frame_p95] = float(np.percentile(values, 95)) if len(values) else None
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


@dataclass(frozen=True)
class NavigationSetup:
    """A worker's setup (:mod:`vgpnav_env.eval.workers`): the env (``env_kwargs``), the perception
    wrapper (``wrapper_kwargs``) and the agent of ``plan``, built once per worker; ``plots``: each
    episode also returns its picture (PNG bytes)."""

    plan: AgentPlan
    env_kwargs: dict[str, Any]
    wrapper_kwargs: dict[str, Any]
    plots: bool = True

    def __call__(self) -> Navigator:
        env = make_env(self.plan, self.env_kwargs, self.wrapper_kwargs)
        return Navigator(env, make_policy(self.plan, env), self.plots)


@dataclass
class Navigator:
    """A worker's state: the env and the policy it keeps between episodes."""

    env: gym.Env
    policy: Policy
    plots: bool

    def close(self) -> None:
        self.env.close()


def episode_task(state: Navigator, item: tuple[int, int]) -> tuple[EpisodeRecord, bytes | None]:
    """One episode ``(index, seed)`` on a worker: its record and (with plots) its picture."""
    from vgpnav_env.eval.navigation_plots import MapSnapshot, episode_png

    index, seed = item
    snapshots: list[MapSnapshot] = []

    def keep(step: int) -> None:
        if state.plots:
            snapshots.append(MapSnapshot.of(state.env, state.policy, step))

    record = run_episode(
        state.env, state.policy, seed, index, lambda n: note(f"episode {index}: step {n}"), on_burst=keep
    )
    burst = snapshots[0] if snapshots else None
    return record, episode_png(state.env, record, state.policy, burst) if state.plots else None


def geodesic_task(state: Navigator, item: tuple[int, int]) -> float:
    """The geodesic distance (metres) of episode ``(index, seed)``: the order of the episodes'
    costs (the env's reset alone, no perception)."""
    state.env.unwrapped.reset(seed=item[1])
    return float(state.env.unwrapped.episode.geodesic)


def navigation_settings(
    scene: str,
    plan: AgentPlan,
    env_kwargs: dict[str, Any],
    episodes: int,
    seed: int,
    perception_mode: str = "temporal",
) -> dict[str, Any]:
    """The head of the report's settings table (:func:`~vgpnav_env.eval.report.run_settings` ends it)."""
    import inspect

    from vgpnav_env.envs.pointgoal import PointGoalEnv
    from vgpnav_env.perception.resolution import describe_size

    defaults = {k: p.default for k, p in inspect.signature(PointGoalEnv).parameters.items()}
    size = env_kwargs["image_size"]
    pixels = plan.backbone not in (None, "model")
    mode = perception_mode if pixels else plan.backbone or "none"
    return {
        "scene": scene,
        "layout": env_kwargs["layout"],
        "agent": plan.name,
        **({"actions": plan.actions} if plan.name == "ppo" else {}),
        "image size": describe_size(*size) if pixels else f"{size[0]}x{size[1]}",
        "backbone": plan.backbone or "none",
        "perception mode": mode,
        "max steps": env_kwargs.get("max_steps", defaults["max_steps"]),
        "success radius (m)": env_kwargs.get("success_distance", defaults["success_distance"]),
        "episodes": episodes,
        "seeds": f"{seed}-{seed + episodes - 1}" if episodes > 1 else str(seed),
    }


def classical_settings(backbone: str | None, wrapper_kwargs: dict[str, Any]) -> dict[str, str]:
    """The report's ``features`` line for the classical backbone: its features and matcher and,
    once made, the database's scene check (:func:`~vgpnav_env.eval.perception_runs.classical_features`)."""
    if backbone != "classical" or wrapper_kwargs.get("database_dir") is None:
        return {}
    from vgpnav_env.perception.backbones import ClassicalConfig
    from vgpnav_env.perception.feature_choice import cached_choice

    options = dict(wrapper_kwargs.get("backbone_options") or {})
    config = options.get("config") or ClassicalConfig(**options)
    choice = cached_choice(wrapper_kwargs["database_dir"], config) if config.checks_scene else None
    return {"features": classical_features(options, choice)}


def prepare_database(
    scene: str,
    env_kwargs: dict[str, Any],
    wrapper_kwargs: dict[str, Any],
    progress: bool,
    workers: Workers,
    backbone: str = "classical",
) -> dict[str, Any]:
    """``wrapper_kwargs`` with a ``database_dir``: the given one or the scene's default build at
    the env's image size (built now if missing, with progress). When ``workers`` run elsewhere than
    this process, it is opened once here so that its index, features, prior and the classical
    backbone's scene check are cached before they open it; the prior on as many processes as local
    workers (at most this process's CPU share)."""
    from vgpnav_env.perception.backbones.threads import cpu_share
    from vgpnav_env.perception.database import open_database
    from vgpnav_env.robot import FOVY_DEG
    from vgpnav_env.wrappers import scene_database_dir

    kwargs = dict(wrapper_kwargs)
    if kwargs.get("database_dir") is None:
        size = env_kwargs["image_size"]
        texture = env_kwargs.get("texture", "realistic")
        fovy = env_kwargs.get("fovy_deg", FOVY_DEG)
        kwargs["database_dir"] = scene_database_dir(scene, size, texture, fovy, progress=progress)
    if workers.workers > 1 or workers.ray_address is not None:
        processes = 1 if workers.ray_address is not None else min(workers.workers, cpu_share())
        db = open_database(kwargs["database_dir"], kwargs.get("database_config"), processes=processes)
        if backbone == "classical":
            from vgpnav_env.perception.backbones import ClassicalConfig
            from vgpnav_env.perception.feature_choice import choose_features

            options = kwargs.get("backbone_options") or {}
            config = options.get("config") or ClassicalConfig(**options)
            if config.checks_scene:
                choose_features(db, config)
    return kwargs


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
    workers: Workers | None = None,
    perception: str | None = None,
    actions: str = "deterministic",
) -> dict[str, Any]:
    """Run the protocol; returns the report dict (also written to ``out_dir`` if given).
    ``perception`` and ``actions``: see :func:`plan_agent`.

    Perception agents use the database build at ``database_dir`` (default: the scene's build at
    the env's image size in the vgpnav cache, built if missing); ``wrapper_kwargs`` go to
    ``VGPNavObservation``. ``workers`` (default: this process) runs the episodes.
    """
    from vgpnav_env.scenes import list_layouts

    clock = RunClock()
    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    plan = plan_agent(agent, backbone, perception, actions)
    kwargs = {"scene": scene, "layout": "changed", "image_size": tuple(size), **plan.env_kwargs}
    kwargs.update(env_kwargs or {})
    if kwargs["layout"] not in list_layouts(scene):  # an unknown scene fails here, before any work
        raise ValueError(f"scene {scene!r} has no layout {kwargs['layout']!r}; it has {list_layouts(scene)}")
    wrapper_kwargs = dict(wrapper_kwargs or {})
    if database_dir is not None or plan.database_dir is not None:
        wrapper_kwargs["database_dir"] = database_dir if database_dir is not None else plan.database_dir
    own = workers is None
    workers = workers or Workers(1, progress=progress)
    try:
        several = workers.workers > 1 or workers.ray_address is not None
        if plan.backbone not in (None, "model"):
            wrapper_kwargs = prepare_database(scene, kwargs, wrapper_kwargs, progress, workers, plan.backbone)
        setup = NavigationSetup(plan, kwargs, wrapper_kwargs, plots=out_dir is not None)
        items = [(i, seed + i) for i in range(episodes)]
        # Several workers: the longest episodes first, so that the last one does not run alone.
        ordered = several and episodes > workers.workers
        cost = workers.map(setup, geodesic_task, items, desc="episode lengths") if ordered else None
        results = workers.map(setup, episode_task, items, desc=f"navigation {scene} {agent}", cost=cost)
    finally:
        if own:
            workers.close()
    records = [record for record, _ in results]
    mode = "model" if plan.backbone == "model" else wrapper_kwargs.get("perception_mode", "temporal")
    settings = {
        **navigation_settings(scene, plan, kwargs, episodes, seed, mode),
        **classical_settings(plan.backbone, wrapper_kwargs),
        **run_settings(clock, workers.where, workers.cpu_seconds),
    }
    report = {
        "protocol": "navigation",
        "scene": scene,
        "layout": kwargs["layout"],
        "agent": agent,
        **({"actions": plan.actions} if plan.name == "ppo" else {}),
        "backbone": plan.backbone,
        "seed": seed,
        "image_size": list(size),
        "perception_mode": mode if plan.backbone else None,
        **summarize(records),
        "records": [r.as_dict() for r in records],
    }
    if out_dir is not None:
        write_navigation_report(Path(out_dir), f"Navigation: {scene} ({plan.description})", report, settings,
                                records, [png for _, png in results])  # fmt: skip
    report["settings"] = settings
    return report


def write_navigation_report(
    out: Path,
    title: str,
    report: dict[str, Any],
    settings: dict[str, Any],
    records: list[EpisodeRecord],
    pictures: list[bytes | None],
) -> None:
    """``report.json`` / ``report.md``, ``errors.png`` and ``trajectories/episode_NNN.png``."""
    from vgpnav_env.atomic import atomic_write
    from vgpnav_env.eval.navigation_plots import summary_figure

    success_distance = float(settings["success radius (m)"])
    for r, png in zip(records, pictures, strict=True):
        if png is not None:
            (out / "trajectories").mkdir(parents=True, exist_ok=True)
            atomic_write(out / "trajectories" / f"episode_{r.index:03d}.png", lambda f, png=png: f.write(png))
    failures = markdown_table(["failure", "episodes"], list(report["failures"].items()))
    pictures_md = "\n".join(f"![episode {r.index}](trajectories/episode_{r.index:03d}.png)" for r in records)
    figures = {}
    if any(r.frames for r in records):
        figures["errors.png"] = summary_figure(records, success_distance)
    write_report(
        out,
        title,
        report,
        sections=[
            "Map measures (`map prec.`, `map recall`, `map_iou`, `path phantoms`) score the fused map at the "
            "end of the episode against the true occupancy of the changed layout over the cells the camera "
            "saw (within 5 m), with one cell of tolerance; path phantoms are occupied cells with no true "
            "obstacle near, within the robot radius of the true shortest path. "
            "Means are over episodes; `p95_localization_error_m` is over all frames the agent acted on "
            "that had a pose estimate. `lost frames` is the fraction of those frames on which "
            "perception did not localize (the pose was carried by odometry); `no estimate` the "
            "fraction before the first (confirmed) fix of the episode, when there is no pose at all; "
            "`mean pose err` and `err > 0.5 m` are over the frames with an estimate (the horizontal "
            "error of the pose the agent acted on, localized or not).",
            "## Failures\n\n" + failures,
            "## Episodes\n\n" + episode_table(records),
            "## Episodes, one picture each\n\nTop left: the true (green) and estimated (orange) "
            "trajectories on the ground-truth map; red dots mark frames where perception was lost, "
            "black crosses collisions. Right: the fused obstacle map and the agent's plan at the end of the "
            "episode and, left of it, at the first collision burst (3 blocked steps within 10) when there "
            "was one; black occupied near a true obstacle, red phantoms, blue observed true obstacles the "
            "map misses. Bottom: pose error over time, lost stretches shaded.\n\n" + pictures_md,
        ],
        figures=figures,
        settings=settings,
        labels={k: v.format(d=success_distance) for k, v in FAILURES.items()},
    )


def headline(report: dict[str, Any]) -> str:
    """One line of the numbers that matter: SR, SPL, soft SPL, collisions, pose error, failures."""
    n = report["episodes"]
    line = (
        f"navigation {report['scene']} ({report['agent']}): success {round(report['success_rate'] * n)}/{n} "
        f"(SR {report['success_rate']:.2f}), SPL {report['spl']:.2f}, soft SPL {report['soft_spl']:.2f}, "
        f"{report['collisions_per_episode']:.1f} collisions/episode"
    )
    if report.get("mean_localization_error_m") is not None:
        line += (
            f", pose error mean {report['mean_localization_error_m']:.2f} m / p95 "
            f"{report['p95_localization_error_m']:.2f} m, lost {report['mean_lost_fraction']:.0%} of frames"
        )
    if report.get("mean_map_precision") is not None:
        p, r, iou = (report.get(k) for k in ("mean_map_precision", "mean_map_recall", "mean_map_iou"))
        line += "; map precision {} / recall {} / IoU {}, {:.1f} phantom cells on the true path".format(
            *(f"{v:.2f}" if v is not None else "n/a" for v in (p, r, iou)), report["mean_path_phantom_cells"]
        )
    failures = ", ".join(f"{k} {v}" for k, v in report["failures"].items() if v)
    return line + (f"; failures: {failures}" if failures else "")


def evaluate_policy(
    path: str | Path,
    episodes: int = 20,
    scene: str | None = None,
    seed: int = 1000,
    out_dir: str | Path | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """The navigation protocol for a trained PPO policy (run directory or model file) in the env it
    was trained on (scene, backbone, image size, step limit and database from its ``config.json``)."""
    config = ppo.load_config(path)["env"]
    scenes = config["scene"] if isinstance(config["scene"], list) else [config["scene"]]
    limit = {"max_steps": config["env"]["max_steps"]} if "max_steps" in config["env"] else None
    return evaluate_navigation(
        scene or scenes[0],
        agent=f"ppo:{ppo.model_path(path)}",
        episodes=episodes,
        seed=seed,
        size=tuple(config["env"]["image_size"]),
        env_kwargs=limit,
        out_dir=out_dir,
        progress=progress,
        database_dir=config.get("database_dir"),
    )


def agent_arg(text: str) -> str:
    """argparse type of ``--agent``: a registered name, ``ppo:PATH`` with a model there, or an
    importable ``MODULE:FACTORY``."""
    try:
        name, path = parse_agent(text)
        if name == "external":
            from vgpnav_env.agents.external import load_factory

            load_factory(path)
        elif path is not None:
            ppo.load_config(ppo.model_path(path))
    except (ValueError, FileNotFoundError) as e:
        raise argparse.ArgumentTypeError(str(e)) from e
    return text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """CLI arguments of ``vgpnav eval navigation``."""
    parser.add_argument("scene", help="built-in scene name (e.g. home, hospital) or scene source")
    parser.add_argument(
        "--agent",
        type=agent_arg,
        default="astar",
        metavar="AGENT",
        help=f"one of {agent_choices()} (default astar)",
    )
    add_backbone_arguments(parser)
    parser.add_argument(
        "--perception",
        choices=list(PERCEPTION_KINDS),
        default=None,
        help="what perception agents drive on: "
        + "; ".join(f"{k}: {v}" for k, v in PERCEPTION_KINDS.items())
        + " (default: pixels for astar, as trained for ppo)",
    )
    parser.add_argument(
        "--actions",
        choices=list(ACTION_KINDS),
        default="deterministic",
        help="how a ppo:PATH policy acts: " + "; ".join(f"{k}: {v}" for k, v in ACTION_KINDS.items()),
    )
    add_perception_mode_argument(parser)
    parser.add_argument("--episodes", type=positive_int_arg, default=20, help="number of start/goal pairs")
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
        "--max-steps",
        type=positive_int_arg,
        default=500,
        help="steps before an episode times out (default 500, Habitat)",
    )
    add_worker_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``vgpnav eval navigation``; returns the process exit code."""
    options = backbone_options(args)
    if args.database is not None and not args.database.is_dir():
        raise ValueError(f"--database {args.database}: no such build directory (make one with vgpnav build)")
    with workers_from_args(args) as workers:
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
            wrapper_kwargs={"backbone_options": options, "perception_mode": args.perception_mode},
            workers=workers,
            perception=args.perception,
            actions=args.actions,
        )
    print_headline(headline(report), args.out)
    return 0
