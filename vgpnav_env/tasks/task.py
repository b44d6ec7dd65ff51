"""Versioned benchmark tasks: YAML data (``<name>.yaml`` beside this module) as a typed :class:`Task`.

A task fixes everything a result depends on besides the agent: sensors and image size, actions
and motion noise, success rule and radius, step limit, the perception rules (what the agent may
read, the database run), the protocols it runs, its scene split set (``splits.yaml``) and how its
episode files were generated. A rule change is a new version, in a new file
(``pointnav-v2.yaml``); ``Task.sha256`` (of the YAML bytes) goes into every results file.

``scene_splits`` names a split set of ``splits.yaml`` or, for a task of one's own (a YAML file
anywhere, e.g. a tiny task in a test), gives its ``train`` / ``val`` / ``test`` lists inline. A
task's episode files live in ``data/<name>/`` beside its YAML file
(:func:`~vgpnav_env.tasks.episodes.episode_dir`).
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from vgpnav_env.tasks.splits import SPLIT_NAMES, scene_splits

TASK_DIR = Path(__file__).parent
_NAME = re.compile(r"^[a-z][a-z0-9]*-v\d+$")


@dataclass(frozen=True)
class Camera:
    """The RGB camera: image ``width`` x ``height`` px, vertical field of view ``fovy_deg``,
    ``height_m`` above the floor on the robot's centre, pitched ``pitch_deg`` down."""

    width: int
    height: int
    fovy_deg: float
    height_m: float
    pitch_deg: float


@dataclass(frozen=True)
class PerceptionRules:
    """What perception may use: ``pixels_only`` (no depth, no true pose), the ``database`` run,
    the observation keys the agent may read, and the default ``backbone`` / ``perception_mode``."""

    pixels_only: bool
    database: str
    agent_may_read: tuple[str, ...]
    agent_must_not_read: str
    backbone: str
    perception_mode: str


@dataclass(frozen=True)
class EpisodeRules:
    """How the episode files were generated: episodes ``per_scene`` per split, and the
    ``generator``'s name, version, seed and parameters (geodesic range, straight-path rejection)."""

    per_scene: dict[str, int]
    generator: dict[str, Any]

    def __post_init__(self) -> None:
        keys = ("name", "version", "seed", "min_geodesic_m", "max_geodesic_m", "straight_ratio",
                "straight_reject_prob")  # fmt: skip
        missing = [k for k in keys if k not in self.generator]
        if missing:
            raise ValueError(f"episodes.generator lacks {missing}")

    @property
    def sampler_params(self) -> dict[str, float]:
        """The keyword arguments of :func:`~vgpnav_env.envs.episodes.sample_episode`."""
        g = self.generator
        return {
            "min_geodesic": float(g["min_geodesic_m"]),
            "max_geodesic": float(g["max_geodesic_m"]),
            "straight_ratio": float(g["straight_ratio"]),
            "straight_reject_prob": float(g["straight_reject_prob"]),
        }


@dataclass(frozen=True)
class Task:
    """One versioned task (module docstring); ``path`` is its YAML file."""

    name: str
    version: int
    gym_id: str
    description: str
    camera: Camera
    robot_radius: float
    robot_height: float
    action_mode: str
    forward_step: float
    turn_step_deg: float
    motion_noise: str
    layout: str
    texture: str
    lighting: str
    success_rule: str
    success_distance: float
    max_steps: int
    perception: PerceptionRules
    protocols: tuple[str, ...]
    scene_split_set: str | dict[str, list[str]]
    episodes: EpisodeRules
    path: Path
    sha256: str

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.camera.width, self.camera.height)

    def env_kwargs(self) -> dict[str, Any]:
        """``VGPNav/PointGoal-v0`` keyword arguments of the task's rules (no scene)."""
        c = self.camera
        return {
            "layout": self.layout,
            "image_size": self.image_size,
            "fovy_deg": c.fovy_deg,
            "camera_height": c.height_m,
            "camera_pitch_deg": c.pitch_deg,
            "robot_radius": self.robot_radius,
            "robot_height": self.robot_height,
            "action_mode": self.action_mode,
            "forward_step": self.forward_step,
            "turn_step_deg": self.turn_step_deg,
            "max_steps": self.max_steps,
            "success_distance": self.success_distance,
            "min_geodesic": self.episodes.sampler_params["min_geodesic"],
            "max_geodesic": self.episodes.sampler_params["max_geodesic"],
            "texture": self.texture,
            "lighting": self.lighting,
        }

    def scenes(self, split: str) -> tuple[str, ...]:
        """Scene ids of ``split`` (ValueError in one line for an unknown split)."""
        if split not in SPLIT_NAMES:
            raise ValueError(f"unknown split {split!r} of task {self.name}; allowed: {list(SPLIT_NAMES)}")
        return scene_splits(self.scene_split_set)[split]

    def summary(self) -> dict[str, Any]:
        """What a results file says about the task: name, version, file checksum and the rules."""
        return {
            "name": self.name,
            "version": self.version,
            "sha256": self.sha256,
            "image_size": list(self.image_size),
            "max_steps": self.max_steps,
            "success_distance_m": self.success_distance,
            "layout": self.layout,
            "motion_noise": self.motion_noise,
            "scene_splits": self.scene_split_set,
        }


def _split_set(value: Any) -> str | dict[str, list[str]]:
    """A task's ``scene_splits``: a split set name of ``splits.yaml`` or its own split lists."""
    if isinstance(value, dict):
        return {str(k): [str(s) for s in v] for k, v in value.items()}
    return str(value)


def task_names() -> tuple[str, ...]:
    """The tasks shipped with the package (``<name>.yaml`` beside this module)."""
    return tuple(sorted(p.stem for p in TASK_DIR.glob("*.yaml") if _NAME.match(p.stem)))


def task_path(name: str) -> Path:
    """The YAML file of a task name or path (ValueError in one line if there is none)."""
    candidate = Path(name)
    if candidate.suffix in (".yaml", ".yml") and candidate.is_file():
        return candidate
    path = TASK_DIR / f"{name}.yaml"
    if not _NAME.match(name) or not path.is_file():
        raise ValueError(f"unknown task {name!r}; allowed: {', '.join(task_names())} or a task .yaml file")
    return path


def parse_task(data: dict[str, Any], path: Path, sha256: str) -> Task:
    """The :class:`Task` of parsed YAML ``data`` (ValueError naming the file for a bad field)."""
    try:
        rgb = data["sensors"]["rgb"]
        perception = data["perception"]
        episodes = data["episodes"]
        task = Task(
            name=str(data["name"]),
            version=int(data["version"]),
            gym_id=str(data["gym_id"]),
            description=" ".join(str(data["description"]).split()),
            camera=Camera(
                int(rgb["width"]),
                int(rgb["height"]),
                float(rgb["fovy_deg"]),
                float(rgb["height_m"]),
                float(rgb["pitch_deg"]),
            ),  # fmt: skip
            robot_radius=float(data["robot"]["radius_m"]),
            robot_height=float(data["robot"]["height_m"]),
            action_mode=str(data["actions"]["mode"]),
            forward_step=float(data["actions"]["forward_step_m"]),
            turn_step_deg=float(data["actions"]["turn_step_deg"]),
            motion_noise=str(data["motion_noise"]),
            layout=str(data["scene"]["layout"]),
            texture=str(data["scene"]["texture"]),
            lighting=str(data["scene"]["lighting"]),
            success_rule=str(data["success"]["rule"]),
            success_distance=float(data["success"]["radius_m"]),
            max_steps=int(data["max_steps"]),
            perception=PerceptionRules(
                bool(perception["pixels_only"]),
                " ".join(str(perception["database"]).split()),
                tuple(perception["agent_may_read"]),
                " ".join(str(perception["agent_must_not_read"]).split()),
                str(perception["backbone"]),
                str(perception["perception_mode"]),
            ),
            protocols=tuple(data["protocols"]),
            scene_split_set=_split_set(data["scene_splits"]),
            episodes=EpisodeRules(
                {k: int(v) for k, v in episodes["per_scene"].items()}, dict(episodes["generator"])
            ),
            path=path,
            sha256=sha256,
        )
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"task file {path}: missing or malformed field {e}") from e
    if task.motion_noise != "none":
        raise ValueError(f"task file {path}: motion_noise {task.motion_noise!r} is not supported (only none)")
    if task.protocols != ("navigation",):
        raise ValueError(f"task file {path}: protocols {list(task.protocols)}; supported: [navigation]")
    if sorted(task.episodes.per_scene) != sorted(SPLIT_NAMES):
        raise ValueError(f"task file {path}: episodes.per_scene needs {list(SPLIT_NAMES)}")
    scene_splits(task.scene_split_set)
    return task


def load_task(name: str) -> Task:
    """The task of a shipped name (``pointnav-v1``) or a task YAML path."""
    path = task_path(name)
    raw = path.read_bytes()
    return parse_task(yaml.safe_load(raw), path, hashlib.sha256(raw).hexdigest())
