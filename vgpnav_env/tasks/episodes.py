"""Fixed episode datasets of a task split: generated once, shipped, checked at load, replayed in order.

``vgpnav episodes generate TASK --split SPLIT [--out DIR]`` writes ``DIR/<split>.json.gz``
(default: ``data/<task>/`` beside this module) and the content checksum into
``DIR/SHA256SUMS``. The file is gzip-compressed JSON in a Habitat-like schema (positions are
world (x, y) in metres on the floor, z up; yaw in radians counter-clockwise from +x)::

    {"format": "vgpnav-episodes", "format_version": 1, "task": "pointnav-v1", "task_version": 1,
     "split": "test", "generator": {name, version, seed, params, layout, map_resolution_m},
     "episodes": [{"episode_id": "test-home-000", "scene_id": "home", "seed": 123,
                   "start_position": [x, y], "start_yaw": yaw,
                   "goals": [{"position": [x, y], "radius": 0.5}],
                   "info": {"geodesic_distance": d}}, ...]}

Episode ``i`` of scene ``s`` is the env's own sampler (:func:`~vgpnav_env.envs.episodes.
sample_episode` on the changed layout's largest navigable component) under ``reset(seed=...)``
with a seed drawn from ``SeedSequence([generator seed, crc32(s), i])``; ``geodesic_distance`` is
the env's shortest path length (the any-angle grid path, as SPL uses it). The same code gives the
same bytes: the JSON is written with sorted keys, Python's shortest float repr and gzip's mtime
0. ``SHA256SUMS`` holds the SHA-256 of the **uncompressed** JSON (``zcat test.json.gz |
sha256sum``), so a zlib version that compresses differently does not change it;
:func:`load_episodes` refuses a file whose content does not match.
"""

from __future__ import annotations

import gzip
import hashlib
import inspect
import json
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vgpnav_env.tasks.splits import scene_source
from vgpnav_env.tasks.task import Task

FORMAT = "vgpnav-episodes"
FORMAT_VERSION = 1
CHECKSUMS = "SHA256SUMS"


@dataclass(frozen=True)
class TaskEpisode:
    """One fixed episode: id, scene id, reset seed, start (x, y, yaw), goal (x, y), geodesic (m)."""

    episode_id: str
    scene_id: str
    seed: int
    start: tuple[float, float, float]
    goal: tuple[float, float]
    geodesic: float

    def as_json(self, radius: float) -> dict[str, Any]:
        return {
            "episode_id": self.episode_id,
            "scene_id": self.scene_id,
            "seed": self.seed,
            "start_position": [self.start[0], self.start[1]],
            "start_yaw": self.start[2],
            "goals": [{"position": list(self.goal), "radius": radius}],
            "info": {"geodesic_distance": self.geodesic},
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> TaskEpisode:
        x, y = (float(v) for v in data["start_position"])
        gx, gy = (float(v) for v in data["goals"][0]["position"])
        return cls(
            str(data["episode_id"]),
            str(data["scene_id"]),
            int(data["seed"]),
            (x, y, float(data["start_yaw"])),
            (gx, gy),
            float(data["info"]["geodesic_distance"]),
        )


@dataclass(frozen=True)
class EpisodeSet:
    """A split's episodes in replay order, with the file's header and content checksum."""

    task: str
    split: str
    generator: dict[str, Any]
    episodes: tuple[TaskEpisode, ...]
    sha256: str

    def __len__(self) -> int:
        return len(self.episodes)

    def scenes(self) -> list[str]:
        """Scene ids in order of first appearance."""
        return list(dict.fromkeys(e.scene_id for e in self.episodes))


def episode_dir(task: Task) -> Path:
    """Where the task's episode files are: ``data/<task name>/`` beside its YAML file (the
    package's for a shipped task)."""
    return task.path.parent / "data" / task.name


def episode_seed(generator_seed: int, scene: str, index: int) -> int:
    """The ``reset`` seed of episode ``index`` of ``scene`` (module docstring)."""
    sequence = np.random.SeedSequence([generator_seed, zlib.crc32(scene.encode()), index])
    return int(sequence.generate_state(1)[0])


def generator_header(task: Task) -> dict[str, Any]:
    """The ``generator`` entry of the task's episode files; ValueError if the task's sampler
    parameters are not the ones the env's sampler runs with (the env passes only the geodesic
    range, so the others must be its defaults)."""
    from vgpnav_env.envs.episodes import sample_episode
    from vgpnav_env.envs.pointgoal import PointGoalEnv

    g = task.episodes.generator
    params = task.episodes.sampler_params
    defaults = {k: p.default for k, p in inspect.signature(sample_episode).parameters.items()}
    for key in ("straight_ratio", "straight_reject_prob"):
        if params[key] != defaults[key]:
            raise ValueError(f"task {task.name}: {key} {params[key]} is not the sampler's {defaults[key]}")
    resolution = inspect.signature(PointGoalEnv).parameters["map_resolution"].default
    return {
        "name": str(g["name"]),
        "version": int(g["version"]),
        "seed": int(g["seed"]),
        "params": params,
        "layout": task.layout,
        "map_resolution_m": resolution,
    }


def generate_scene_episodes(task: Task, split: str, scene: str, count: int) -> list[TaskEpisode]:
    """``count`` episodes of ``scene`` sampled by the env (module docstring)."""
    from vgpnav_env.envs.pointgoal import PointGoalEnv

    kwargs = task.env_kwargs()
    env = PointGoalEnv(scene=scene_source(scene), render_rgb=False, **kwargs)
    seed0 = int(task.episodes.generator["seed"])
    out = []
    try:
        for i in range(count):
            seed = episode_seed(seed0, scene, i)
            _, info = env.reset(seed=seed)
            start = tuple(float(v) for v in info["start"])
            goal = tuple(float(v) for v in info["goal"])
            out.append(TaskEpisode(f"{split}-{scene}-{i:03d}", scene, seed, start, goal,
                                   float(info["shortest_path_length"])))  # fmt: skip
    finally:
        env.close()
    return out


def episodes_json(task: Task, split: str, episodes: list[TaskEpisode]) -> bytes:
    """The canonical JSON bytes of a split's episode file."""
    data = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "task": task.name,
        "task_version": task.version,
        "split": split,
        "generator": generator_header(task),
        "episodes": [e.as_json(task.success_distance) for e in episodes],
    }
    return (json.dumps(data, sort_keys=True, separators=(",", ":")) + "\n").encode()


def read_checksums(directory: Path) -> dict[str, str]:
    """File name -> SHA-256 of its JSON content, from ``directory/SHA256SUMS`` (empty if absent)."""
    path = directory / CHECKSUMS
    if not path.is_file():
        return {}
    out = {}
    for line in path.read_text().splitlines():
        if line.strip():
            digest, name = line.split(maxsplit=1)
            out[name.strip()] = digest
    return out


def write_episodes(directory: Path, split: str, content: bytes) -> Path:
    """Write ``directory/<split>.json.gz`` (gzip mtime 0) and its line in ``SHA256SUMS``."""
    from vgpnav_env.atomic import atomic_write

    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{split}.json.gz"
    packed = gzip.compress(content, compresslevel=9, mtime=0)
    atomic_write(path, lambda f: f.write(packed))
    sums = read_checksums(directory)
    sums[path.name] = hashlib.sha256(content).hexdigest()
    text = "".join(f"{sums[name]}  {name}\n" for name in sorted(sums))
    atomic_write(directory / CHECKSUMS, lambda f: f.write(text.encode()))
    return path


def generate_episodes(
    task: Task,
    split: str,
    directory: Path | None = None,
    on_scene: Callable[[str], None] | None = None,
) -> Path:
    """Generate and write the episode file of ``task``'s ``split`` (module docstring)."""
    count = task.episodes.per_scene[split]
    episodes: list[TaskEpisode] = []
    for scene in task.scenes(split):
        if on_scene is not None:
            on_scene(scene)
        episodes += generate_scene_episodes(task, split, scene, count)
    return write_episodes(directory or episode_dir(task), split, episodes_json(task, split, episodes))


def load_episodes(task: Task, split: str, directory: Path | None = None) -> EpisodeSet:
    """The episodes of ``task``'s ``split`` in replay order; ValueError in one line if the file is
    missing, its content does not match its ``SHA256SUMS`` line, or it belongs to another task."""
    task.scenes(split)  # an unknown split fails here
    directory = Path(directory or episode_dir(task))
    path = directory / f"{split}.json.gz"
    if not path.is_file():
        raise ValueError(
            f"no episode file {path}: generate it with vgpnav episodes generate {task.name} --split {split}"
        )
    try:
        content = gzip.decompress(path.read_bytes())
    except (OSError, EOFError, zlib.error) as e:
        raise ValueError(f"episode file {path} is not gzip ({e})") from e
    digest = hashlib.sha256(content).hexdigest()
    expected = read_checksums(directory).get(path.name)
    if expected is None:
        raise ValueError(f"episode file {path} has no line in {directory / CHECKSUMS}")
    if digest != expected:
        raise ValueError(
            f"episode file {path} fails its checksum (sha256 {digest[:12]}..., expected {expected[:12]}...)"
        )
    data = json.loads(content)
    if data.get("format") != FORMAT or data.get("task") != task.name or data.get("split") != split:
        raise ValueError(f"episode file {path} is not the {split} split of task {task.name}")
    episodes = tuple(TaskEpisode.from_json(e) for e in data["episodes"])
    return EpisodeSet(task.name, split, data["generator"], episodes, digest)


def add_arguments(parser: Any) -> None:
    """CLI arguments of ``vgpnav episodes generate``."""
    from vgpnav_env.tasks.splits import SPLIT_NAMES
    from vgpnav_env.tasks.task import task_names

    parser.add_argument("task", help=f"a task name ({', '.join(task_names())}) or a task .yaml file")
    parser.add_argument("--split", required=True, choices=SPLIT_NAMES, help="the split to generate")
    parser.add_argument(
        "--out", type=Path, default=None, help="directory (default: the package's data/<task>/)"
    )


def run(args: Any) -> int:
    """Entry point of ``vgpnav episodes generate``; returns the exit code."""
    from tqdm import tqdm

    from vgpnav_env.tasks.task import load_task

    task = load_task(args.task)
    scenes = task.scenes(args.split)
    for scene in scenes:
        scene_source(scene)  # an unbuilt corpus scene fails before any work
    bar = tqdm(total=len(scenes), desc=f"episodes {task.name} {args.split}", unit="scene")

    def on_scene(scene: str) -> None:
        bar.set_postfix_str(scene)
        bar.update(0 if scene == scenes[0] else 1)

    try:
        path = generate_episodes(task, args.split, args.out, on_scene)
        bar.update()
    finally:
        bar.close()
    count = len(scenes) * task.episodes.per_scene[args.split]
    print(f"{count} episodes of {task.name} {args.split} on {len(scenes)} scenes: {path}")
    return 0
