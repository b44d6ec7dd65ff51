"""The Gymnasium env of a task split (``VGPNav/PointNav-v1``): its fixed episodes, replayed in order."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym

from vgpnav_env.tasks.episodes import EpisodeSet, TaskEpisode, load_episodes
from vgpnav_env.tasks.splits import scene_source
from vgpnav_env.tasks.task import Task, load_task


class EpisodeReplay(gym.Wrapper):
    """Resets a point-goal env (or a wrapper of one) to a given :class:`TaskEpisode`: the next
    ``reset`` starts ``episode`` (set by :meth:`set_episode`) with its start, goal and seed."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.episode: TaskEpisode | None = None

    def set_episode(self, episode: TaskEpisode) -> None:
        self.episode = episode

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if self.episode is None:
            raise RuntimeError("EpisodeReplay.reset before set_episode")
        e = self.episode
        return self.env.reset(seed=e.seed, options={**(options or {}), "start": e.start, "goal": e.goal})


class TaskEnv(gym.Env):
    """A task's split as one env: ``reset()`` starts the split's next fixed episode (in the episode
    file's order, cycling), ``reset(options={"episode_id": ID})`` a chosen one.

    Rules (image size, actions, step limit, success radius, layout) are the task's and cannot be
    overridden; ``perception`` / ``wrapper`` are :func:`~vgpnav_env.make.make_env`'s keys (None:
    the raw point-goal observation). One env per scene is built on first use.

    ## Observation (what an agent may read)
    Without perception: ``{"rgb": uint8 (H, W, 3) image, "goal": float32 (2,) world (x, y) of the
    goal in metres}`` (:class:`~vgpnav_env.envs.pointgoal.PointGoalEnv`). With a perception
    backbone: ``{"pose": (x, y, yaw) estimate, "goal_rel": (distance, bearing), "map": uint8 (1, S,
    S) egocentric occupancy, "localized": 0 | 1}`` (:class:`~vgpnav_env.wrappers.VGPNavObservation`).
    The bump sensor is ``env.unwrapped.bumped`` (the last step's motion was blocked). Spaces are
    the first scene's (``goal`` bounds are its map bounds; other scenes' values may lie outside).

    ## Info (evaluation only: an agent must not read it)
    The point-goal env's info (true ``pose``, ``T_wc``, ``depth``, the measures ``success``,
    ``spl``, ``soft_spl``, ``distance_to_goal``, ``collisions``, ``steps``, ...; with perception
    also ``perception``, ``estimated_pose``, ``localization_error_m``, ...) plus ``episode_id`` and
    ``scene_id`` of the running episode.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        task: str | Task = "pointnav-v1",
        split: str = "train",
        perception: str | None = None,
        wrapper: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
        episodes: EpisodeSet | None = None,
    ) -> None:
        self.task = task if isinstance(task, Task) else load_task(task)
        self.split = split
        self.episode_set = episodes if episodes is not None else load_episodes(self.task, split)
        self.render_mode = render_mode
        self._config = {"perception": perception, "wrapper": dict(wrapper or {})}
        self._envs: dict[str, EpisodeReplay] = {}
        self._next = 0
        self.current: EpisodeReplay = self._env(self.episode_set.episodes[0].scene_id)
        self.observation_space = self.current.observation_space
        self.action_space = self.current.action_space
        self.episode: TaskEpisode | None = None

    def _env(self, scene: str) -> EpisodeReplay:
        if scene not in self._envs:
            from vgpnav_env.make import make_env

            kwargs = {**self.task.env_kwargs(), "render_mode": self.render_mode}
            config = {"scene": scene_source(scene), "env": kwargs, **self._config}
            self._envs[scene] = EpisodeReplay(make_env(config))
        return self._envs[scene]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """The next episode (module docstring); ``seed`` is ignored: each episode has its own."""
        super().reset(seed=seed)
        options = dict(options or {})
        episodes = self.episode_set.episodes
        if "episode_id" in options:
            wanted = options.pop("episode_id")
            ids = [e.episode_id for e in episodes]
            if wanted not in ids:
                raise ValueError(f"no episode {wanted!r} in {self.task.name} {self.split}")
            self._next = ids.index(wanted)
        self.episode = episodes[self._next % len(episodes)]
        self._next = (self._next + 1) % len(episodes)
        self.current = self._env(self.episode.scene_id)
        self.current.set_episode(self.episode)
        obs, info = self.current.reset(options=options or None)
        return obs, self._info(info)

    def _info(self, info: dict[str, Any]) -> dict[str, Any]:
        return {**info, "episode_id": self.episode.episode_id, "scene_id": self.episode.scene_id}

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.current.step(action)
        return obs, reward, terminated, truncated, self._info(info)

    def render(self) -> Any:
        return self.current.render()

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()
        super().close()


def make_task_env(task: str = "pointnav-v1", **kwargs: Any) -> TaskEnv:
    """Entry point of a task's Gymnasium id: ``gym.make("VGPNav/PointNav-v1", split="test")``."""
    return TaskEnv(task, **kwargs)
