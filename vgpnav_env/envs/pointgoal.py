"""``VGPNav/PointGoal-v0``: point-goal navigation of a planar robot with a monocular RGB camera."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.envs.body import PlanarRobot, add_robot
from vgpnav_env.envs.episodes import Episode, GeodesicField, sample_episode
from vgpnav_env.envs.topdown import TopDownMap, legend_panel, text_panel
from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.grid import largest_component, path_length, shortest_path
from vgpnav_env.groundtruth import GroundTruthMap, ground_truth_map
from vgpnav_env.measures import EnvState, Measurements
from vgpnav_env.render import Frame, MujocoRenderer
from vgpnav_env.robot import (
    CAMERA_HEIGHT,
    CAMERA_PITCH_DEG,
    FORWARD_STEP,
    FOVY_DEG,
    ROBOT_HEIGHT,
    ROBOT_RADIUS,
    TURN_STEP_DEG,
    Action,
    action_path,
    camera_T_wc,
    velocity_path,
)
from vgpnav_env.scenes import load_scene
from vgpnav_env.scenes.model import build_mjspec
from vgpnav_env.scenes.scene import Scene

logger = logging.getLogger(__name__)

SUCCESS_REWARD = 2.5
STEP_PENALTY = 0.01
#: ``render()`` scales the camera view by an integer factor to at least this many pixels high.
RENDER_MIN_HEIGHT = 360


@dataclass
class _World:
    """What is shared by every env instance of one scene configuration in a process."""

    scene: Scene
    model: mujoco.MjModel
    gt: GroundTruthMap
    navigable: NDArray[np.bool_]  # largest connected component of gt.navigable


_SCENES: dict[tuple[str, str, str, str], Scene] = {}
_WORLDS: dict[tuple, _World] = {}


def _world(
    scene: str | Scene,
    layout: str,
    texture: str,
    lighting: str,
    image_size: tuple[int, int],
    robot_radius: float,
    robot_height: float,
    map_resolution: float,
) -> _World:
    if isinstance(scene, Scene):
        sc = scene
    else:
        key = (str(scene), layout, texture, lighting)
        if key not in _SCENES:
            _SCENES[key] = load_scene(scene, layout=layout, texture=texture, lighting=lighting)
        sc = _SCENES[key]
    size = (max(640, image_size[0]), max(480, image_size[1]))
    wkey = (id(sc), sc.key, size, robot_radius, robot_height, map_resolution)
    if wkey not in _WORLDS:
        spec = build_mjspec(sc, max_image_size=size)
        add_robot(spec, radius=robot_radius, height=robot_height)
        model = spec.compile()
        gt = ground_truth_map(
            sc, resolution=map_resolution, robot_radius=robot_radius, robot_height=robot_height
        )
        navigable = largest_component(gt.navigable)
        if not navigable.any():
            raise ValueError(f"scene {sc.key} has no navigable cells for a robot of radius {robot_radius} m")
        _WORLDS[wkey] = _World(sc, model, gt, navigable)
        logger.info("built env world %s: %d geoms, %d navigable cells", sc.key, model.ngeom, navigable.sum())
    return _WORLDS[wkey]


class PointGoalEnv(gym.Env):
    """Drive a planar robot to a goal point using only its camera (Gymnasium, point-goal).

    ## Action space
    ``action_mode="discrete"`` (default): ``Discrete(4)`` = :class:`~vgpnav_env.robot.Action`
    {0 stop, 1 forward ``forward_step`` m, 2 turn left ``turn_step_deg``, 3 turn right
    ``turn_step_deg``}, moving as :func:`~vgpnav_env.robot.action_path` unless blocked.
    ``action_mode="continuous"``: ``Box(-1, 1, (3,), float32)`` = (linear speed, turn rate, stop):
    the robot moves along a unicycle arc for ``dt`` seconds at ``v = a[0] * max_linear_speed`` m/s
    (negative drives backwards) and ``omega = a[1] * max_angular_speed`` rad/s (counter-clockwise
    positive); ``a[2] > 0`` is the stop action (no motion).

    ## Observation space
    ``Dict(rgb=Box(0, 255, (H, W, 3), uint8), goal=Box(map min, map max, (2,), float32))``: the camera
    image (OpenCV camera at ``camera_height`` m, pitched ``camera_pitch_deg`` down, looking along the
    robot heading, vertical field of view ``fovy_deg``) and the goal's world (x, y) in metres.
    With ``render_rgb=False`` the image is all zeros and nothing is rendered (for agents that do
    not look, e.g. the oracle).

    ## Motion and collisions
    Each motion is checked against the scene's collision geometry through MuJoCo contacts; a blocked
    motion stops at the last collision-free pose (found by bisection) and counts one collision.

    ## Episodes
    ``reset(seed=...)`` samples start and goal (deterministic per seed) on the largest connected
    navigable component of the ground-truth map of this layout, geodesic distance in
    [``min_geodesic``, ``max_geodesic``] m (see ``episodes.sample_episode``); the start yaw is uniform.
    ``reset(options={"start": (x, y, yaw), "goal": (x, y)})`` fixes the episode instead.
    The episode terminates on ``stop`` (success when the robot is within ``success_distance`` m,
    Euclidean, of the goal) and is truncated after ``max_steps`` steps. Stepping a finished
    episode raises ``RuntimeError``: call ``reset``.

    ## Reward
    Decrease of the geodesic distance to the goal + 2.5 on success - 0.01 per step.

    ## Info (evaluation only: agents must not read it)
    ``pose`` (x, y, yaw) true, ``T_wc`` 4x4 camera pose, ``depth`` (H, W) float32 z-depth (None
    without rendering), then the metric of every ``"env"`` measure of :mod:`vgpnav_env.measures`
    under its uuid: ``distance_to_goal`` (geodesic, m), ``euclidean_distance_to_goal``,
    ``success``, ``spl`` = success * shortest / max(shortest, travelled), ``soft_spl`` =
    max(0, 1 - d / d_start) * shortest / max(shortest, travelled), ``collisions``, ``steps``,
    ``travelled`` (m); then ``shortest_path_length`` (m), ``start`` (x, y, yaw), ``goal`` (x, y),
    ``blocked`` (this step's motion hit something), ``stopped``.

    ## Rendering
    ``render_mode="rgb_array"``: the camera view beside a top-down map (ground-truth map, true
    pose, start, goal, trajectory, plus what a wrapper or agent set with :meth:`set_overlay`),
    above a status line (step, action, localized or lost, pose error, distance to the goal,
    collisions) and the map's legend.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        scene: str | Scene = "home",
        layout: str = "changed",
        render_mode: str | None = None,
        image_size: tuple[int, int] = (320, 240),
        fovy_deg: float = FOVY_DEG,
        camera_height: float = CAMERA_HEIGHT,
        camera_pitch_deg: float = CAMERA_PITCH_DEG,
        robot_radius: float = ROBOT_RADIUS,
        robot_height: float = ROBOT_HEIGHT,
        action_mode: str = "discrete",
        forward_step: float = FORWARD_STEP,
        turn_step_deg: float = TURN_STEP_DEG,
        dt: float = 0.25,
        max_linear_speed: float = 1.0,
        max_angular_speed_deg: float = 60.0,
        max_steps: int = 500,
        success_distance: float = 0.5,
        min_geodesic: float = 1.0,
        max_geodesic: float = 10.0,
        texture: str = "realistic",
        lighting: str = "default",
        map_resolution: float = 0.05,
        render_rgb: bool = True,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}"
            )
        if action_mode not in ("discrete", "continuous"):
            raise ValueError(f"action_mode must be 'discrete' or 'continuous', got {action_mode!r}")
        width, height = (int(v) for v in image_size)
        if width <= 0 or height <= 0:
            raise ValueError(f"image_size must be positive (width, height), got {image_size}")
        if max_steps <= 0 or forward_step <= 0 or success_distance <= 0:
            raise ValueError("max_steps, forward_step and success_distance must be positive")
        if not 0.0 < camera_height < robot_height + 1.0:
            raise ValueError(f"camera_height must be in (0, robot_height + 1) m, got {camera_height}")
        self.render_mode = render_mode
        self.action_mode = action_mode
        self.forward_step = float(forward_step)
        self.turn_step = float(np.radians(turn_step_deg))
        self.dt = float(dt)
        self.max_linear_speed = float(max_linear_speed)
        self.max_angular_speed = float(np.radians(max_angular_speed_deg))
        self.max_steps = int(max_steps)
        self.success_distance = float(success_distance)
        self.min_geodesic, self.max_geodesic = float(min_geodesic), float(max_geodesic)
        self.camera_height = float(camera_height)
        self.camera_pitch = float(np.radians(camera_pitch_deg))
        self.robot_radius = float(robot_radius)
        self.render_rgb = bool(render_rgb)
        #: The scene source name (None for a ``Scene`` object), texture and layout, e.g. for wrappers
        #: that build the scene's database.
        self.scene_source = scene if isinstance(scene, str) else None
        self.texture = texture
        self.layout = layout

        self.world = _world(
            scene, layout, texture, lighting, (width, height), robot_radius, robot_height, map_resolution
        )
        self.camera = PinholeCamera(width, height, float(np.radians(fovy_deg)))
        self.robot = PlanarRobot(self.world.model)
        self._renderer: MujocoRenderer | None = None

        lo, hi = (b.astype(np.float32) for b in self.world.gt.spec.bounds)
        self.observation_space = spaces.Dict(
            {
                "rgb": spaces.Box(0, 255, (height, width, 3), np.uint8),
                "goal": spaces.Box(lo, hi, (2,), np.float32),
            }
        )
        if action_mode == "discrete":
            self.action_space: spaces.Space = spaces.Discrete(len(Action))
        else:
            self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)

        self.episode: Episode | None = None
        self._field: GeodesicField | None = None
        self.measurements = Measurements("env")
        self._state: EnvState | None = None
        self._done = True
        self._rgb = np.zeros((height, width, 3), np.uint8)
        self._depth: NDArray[np.float32] | None = None
        self._topdown: TopDownMap | None = None
        self._overlay: dict[str, Any] = {}
        self._localized: bool | None = None
        self._last_action: Any = None
        self.trajectory: list[NDArray[np.float64]] = []

    def set_goal_range(self, min_geodesic: float, max_geodesic: float) -> None:
        """Geodesic distance range (m) of the episodes sampled from the next ``reset`` on (e.g. a
        training curriculum)."""
        if not 0.0 < min_geodesic <= max_geodesic:
            raise ValueError(f"need 0 < min_geodesic <= max_geodesic, got {min_geodesic}, {max_geodesic}")
        self.min_geodesic, self.max_geodesic = float(min_geodesic), float(max_geodesic)

    # -- ground truth for agents that are allowed to see it (oracle) and for evaluation --------
    @property
    def ground_truth(self) -> GroundTruthMap:
        """Ground-truth map of this layout (evaluation and the oracle only)."""
        return self.world.gt

    @property
    def pose(self) -> NDArray[np.float64]:
        """True robot pose (x, y, yaw)."""
        return self.robot.pose

    @property
    def bumped(self) -> bool:
        """The bump sensor: whether the last step's motion was blocked (False after ``reset``).
        A robot's bumper or stalled wheels tell it; agents may read it (nothing else privileged)."""
        return bool(self._state is not None and self._state.blocked)

    def camera_T_wc(self, pose: ArrayLike | None = None) -> NDArray[np.float64]:
        """OpenCV camera pose ``T_wc`` of the robot at ``pose`` (default: the current pose)."""
        return camera_T_wc(self.robot.pose if pose is None else pose, self.camera_height, self.camera_pitch)

    def render_view(self, pose: ArrayLike | None = None) -> Frame:
        """The robot camera's RGB and z-depth at ``pose`` (x, y, yaw; default: the current pose),
        without moving the robot (e.g. extra views for a wrapper that initialises standing still)."""
        return self._camera_renderer().render(self.camera_T_wc(pose))

    def render_depth(self, pose: ArrayLike | None = None) -> NDArray[np.float32]:
        """The robot camera's z-depth only at ``pose`` (default: the current pose); cheaper than
        :meth:`render_view` (e.g. for the privileged ``model`` perception, with ``render_rgb=False``)."""
        return self._camera_renderer().render_depth(self.camera_T_wc(pose))

    def _camera_renderer(self) -> MujocoRenderer:
        if self._renderer is None:  # created lazily: GL state must live in the process that renders
            self._renderer = MujocoRenderer(self.world.model, self.camera, data=self.robot.data)
        return self._renderer

    def set_overlay(
        self,
        estimated_pose: ArrayLike | None = None,
        path: ArrayLike | None = None,
        obstacles: ArrayLike | None = None,
        localized: bool | None = None,
    ) -> None:
        """Extra things to draw on the top-down map until the next ``reset`` (None keeps the old value).

        ``estimated_pose`` (x, y, yaw); ``path`` and ``obstacles`` world (N, 2) points;
        ``localized``: whether perception localized the frame of ``estimated_pose`` (status line).
        """
        for name, value in (("estimated_pose", estimated_pose), ("path", path), ("obstacles", obstacles)):
            if value is not None:
                self._overlay[name] = np.asarray(value, float)
        if localized is not None:
            self._localized = bool(localized)

    # -- episode ----------------------------------------------------------------------------
    def _is_free(self, pose: NDArray[np.float64]) -> bool:
        return not self.robot.in_collision(pose)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        gt, nav = self.world.gt, self.world.navigable
        if "start" in options or "goal" in options:
            if "start" not in options or "goal" not in options:
                raise ValueError("reset options must give both 'start' (x, y, yaw) and 'goal' (x, y)")
            start = np.asarray(options["start"], float)
            goal = np.asarray(options["goal"], float)
            if start.shape != (3,) or goal.shape != (2,):
                raise ValueError(
                    f"start must be (x, y, yaw) and goal (x, y), got {start.shape} and {goal.shape}"
                )
            if not self._is_free(start):
                raise ValueError(f"start {tuple(start)} collides with the scene")
            field = GeodesicField(nav, gt.spec, goal)
            self.episode = Episode((*map(float, start),), (float(goal[0]), float(goal[1])), field(start[:2]))
        else:
            self.episode = sample_episode(
                nav,
                gt.spec,
                self.np_random,
                min_geodesic=self.min_geodesic,
                max_geodesic=self.max_geodesic,
                is_valid=self._is_free,
            )
            field = GeodesicField(nav, gt.spec, self.episode.goal)
        # SPL's shortest path: the any-angle (string-pulled) grid path where one exists, else the
        # octile geodesic distance.
        try:
            path = shortest_path(nav, gt.spec, self.episode.start[:2], self.episode.goal)
        except ValueError:  # start or goal off the map
            path = None
        if path is not None:
            self.episode = replace(self.episode, geodesic=path_length(path))
        self._field = field
        self.robot.set_pose(self.episode.start)
        self._state = EnvState(self.episode, self.robot.pose, None, field, self.success_distance)
        self.measurements.reset(self._state)
        self._done = False
        self._overlay, self._localized, self._last_action = {}, None, None
        self.trajectory = [self.robot.pose]
        return self._observe(), self._info()

    def _move(self, action: Any) -> tuple[bool, bool]:
        """Apply ``action``; returns (stop requested, blocked)."""
        pose = self.robot.pose
        if self.action_mode == "discrete":
            motion = action_path(pose, action, self.forward_step, self.turn_step, self.robot_radius)
            if motion is None:
                return True, False
            return False, self.robot.move_along(*motion)[1]
        a = np.asarray(action, float)
        if a[2] > 0.0:
            return True, False
        v, omega = a[0] * self.max_linear_speed, a[1] * self.max_angular_speed
        path, length = velocity_path(pose, v, omega, self.dt, self.robot_radius)
        if length == 0.0:
            return False, False
        return False, self.robot.move_along(path, length)[1]

    def _check_action(self, action: Any) -> None:
        if self.action_mode == "discrete":
            ok = (
                np.ndim(action) == 0
                and np.issubdtype(np.asarray(action).dtype, np.integer)
                and 0 <= action < len(Action)
            )
            if not ok:
                names = ", ".join(f"{a.value} {a.name.lower().replace('_', ' ')}" for a in Action)
                raise ValueError(
                    f"invalid action {action!r}: discrete actions are integers 0-{len(Action) - 1} ({names})"
                )
            return
        a = np.asarray(action, float)
        if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(np.abs(a) > 1.0 + 1e-6):
            raise ValueError(
                f"invalid action {action!r}: continuous actions are 3 floats in [-1, 1] "
                f"(linear speed, turn rate, stop if > 0)"
            )

    def step(self, action: Any):
        if self.episode is None or self._done:
            raise RuntimeError("step() called on a finished episode (or before reset()): call reset() first")
        self._check_action(action)
        self._last_action = action
        before = self.robot.pose
        stop, blocked = self._move(action)
        after = self.robot.pose
        self.trajectory.append(after)
        m = self.measurements
        previous = m["distance_to_goal"].metric
        self._state = EnvState(
            self.episode, after, before, self._field, self.success_distance, action, stop, blocked
        )
        m.update(self._state)
        terminated = stop
        truncated = not terminated and m["steps"].metric >= self.max_steps
        self._done = terminated or truncated
        distance = m["distance_to_goal"].metric
        reward = (previous - distance) + SUCCESS_REWARD * m["success"].metric - STEP_PENALTY
        return self._observe(), float(reward), terminated, truncated, self._info()

    # -- observation, info, rendering ---------------------------------------------------------
    def _observe(self) -> dict[str, NDArray]:
        if self.render_rgb:
            frame = self.render_view()
            self._rgb, self._depth = frame.rgb, frame.depth
        return {"rgb": self._rgb.copy(), "goal": np.asarray(self.episode.goal, np.float32)}

    def _info(self) -> dict[str, Any]:
        ep = self.episode
        pose = self.robot.pose
        return {
            "pose": pose,
            "T_wc": self.camera_T_wc(pose),
            "depth": self._depth if self.render_rgb else None,
            **self.measurements.metrics(),
            "shortest_path_length": ep.geodesic,
            "start": np.asarray(ep.start),
            "goal": np.asarray(ep.goal),
            "blocked": self._state.blocked,
            "stopped": self._state.stopped,
        }

    def top_down(self, height_px: int | None = None) -> NDArray[np.uint8]:
        """The top-down map image (H, W, 3) with the current episode and overlay drawn."""
        h = height_px or self.camera.height
        if self._topdown is None or self._topdown.size[1] != h:
            gt = self.world.gt
            self._topdown = TopDownMap(gt.spec, gt.free, gt.obstacle, self.world.navigable, h)
        ep = self.episode
        return self._topdown.draw(
            true_pose=self.robot.pose if ep is not None else None,
            goal=ep.goal if ep is not None else None,
            start=ep.start if ep is not None else None,
            trajectory=np.asarray(self.trajectory)[:, :2] if len(self.trajectory) > 1 else None,
            **self._overlay,
        )

    def _action_text(self) -> str:
        a = self._last_action
        if a is None:
            return "none yet"
        if self.action_mode == "discrete":
            return Action(int(a)).name.lower().replace("_", " ")
        a = np.asarray(a, float)
        if a[2] > 0.0:
            return "stop"
        v, w = a[0] * self.max_linear_speed, np.degrees(a[1] * self.max_angular_speed)
        return f"v {v:+.2f} m/s, turn {w:+.0f} deg/s"

    def status_line(self) -> str:
        """What ``render()`` prints under the pictures: step, last action, localization (from the
        overlay a perception wrapper sets: localized or lost, and the horizontal error of the
        estimated pose), geodesic distance to the goal and collisions so far."""
        m = self.measurements
        parts = [f"step {m['steps'].metric}/{self.max_steps}", f"action: {self._action_text()}"]
        estimate = self._overlay.get("estimated_pose")
        if estimate is None:
            parts.append("true pose (no perception)")
        else:
            state = {True: "localized", False: "LOST (odometry)", None: "perception"}[self._localized]
            error = float(np.linalg.norm(estimate[:2] - self.robot.pose[:2]))
            parts.append(f"{state}, pose error {error:.2f} m")
        parts += [f"goal {m['distance_to_goal'].metric:.2f} m", f"collisions {m['collisions'].metric}"]
        return " | ".join(parts)

    def render(self) -> NDArray[np.uint8] | None:
        """The camera view beside the top-down map, then the status line (:meth:`status_line`) and
        the map's legend (:data:`~vgpnav_env.envs.topdown.LEGEND`): an RGB uint8 image."""
        if self.render_mode != "rgb_array":
            return None
        if self.episode is None:
            raise RuntimeError("render() called before reset()")
        view = self._rgb
        if not self.render_rgb:
            view = self._camera_renderer().render_rgb(self.camera_T_wc())
        k = max(1, int(np.ceil(RENDER_MIN_HEIGHT / view.shape[0])))
        view = np.repeat(np.repeat(view, k, axis=0), k, axis=1)
        top = np.concatenate([view, self.top_down(view.shape[0])], axis=1)
        width = top.shape[1]
        return np.concatenate([top, text_panel([self.status_line()], width), legend_panel(width)], axis=0)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()
