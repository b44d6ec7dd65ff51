"""``VGPNavObservation``: the point-goal env seen through VGP-Nav perception.

The wrapper runs the VGP-Nav :class:`~vgpnav_env.perception.pipeline.Perceiver` on every camera
image against the scene's database run and replaces the raw observation by a navigation state:

``Dict(pose=Box (3,) float32, goal_rel=Box (2,) float32, map=Box uint8 (1, S, S), localized=Discrete(2))``

- ``pose``: estimated (x, y, yaw) of the robot in W (metres, radians), clipped to the map bounds
  plus a margin. While perception is lost the last estimate is carried forward by the commanded
  discrete motion (nominal odometry: ``forward_step`` ahead, ``turn_step`` turns; a forward step
  after which the camera image did not change -- mean absolute grey difference of a small
  thumbnail below ``stall_threshold`` levels -- was blocked and moves nothing). With
  ``motion_gate`` (discrete actions), a perceived pose farther from that odometry prediction than
  ``max_distance`` m / ``max_yaw_deg`` is rejected as lost before it is fused. Since the last
  accepted fix the distance grows by ``growth_m`` per forward step and the angle by ``growth_deg``
  per turn (odometry uncertainty grows with motion, not with time: turning in place to look
  around does not widen the distance gate), so a drifted estimate is re-captured once it moves.
- ``goal_rel``: (distance m, bearing rad counter-clockwise from the estimated heading) of the goal.
- ``map``: egocentric crop of the fused occupancy map (``S`` x ``S`` pixels of ``map_resolution``
  metres, row 0 ahead, columns to the right; 255 occupied, 128 free, 0 unknown), channels first.
- ``localized``: 1 if this frame's pose came from perception, 0 if it was carried forward.

``info`` keeps the env's entries (true pose etc., for evaluation) and adds ``perception`` (the
frame's status, reason, ``T_wc``, scale, scale source, anchored ground height, references and
confident pairs), ``estimated_pose``, ``obstacles`` (bool grid of occupied cells of the fused map)
with ``map_spec`` (its ``GridSpec``), and ``localization_error_m``. The full
:class:`PerceptionResult` of the last frame (points, timings) is ``wrapper.last_result`` and the
live fused ``LogOddsMap`` is ``wrapper.perceiver.map``; they stay out of ``info`` so that ``info``
is comparable between runs (timings differ).

On ``reset`` the robot stands still: the first view plus ``len(init_yaw_jitter_deg) - 1`` views
rendered with tiny yaw offsets initialise the ground anchor (paper: ground height initialisation
with the known camera height). The wrapper also sets the env's render overlay (estimated pose
and fused obstacles).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from vgpnav_env.geometry import camera_yaw_pitch, wrap_angle
from vgpnav_env.perception.backbones import Backbone, Privileged, make_backbone
from vgpnav_env.perception.database import Database, DatabaseConfig, open_database
from vgpnav_env.perception.pipeline import Perceiver, PerceptionConfig, PerceptionResult
from vgpnav_env.perception.verify import PoseGate
from vgpnav_env.robot import Action, predict_pose

logger = logging.getLogger(__name__)

POSE_MARGIN_M = 5.0
#: Default odometry gate: (max_distance m, max_yaw_deg, growth m per forward step and growth deg per
#: turn since the last fix).
MOTION_GATE = (0.5, 30.0, 0.1, 5.0)
#: Mean absolute grey-level change (of a 40x30 thumbnail) below which a forward step was blocked.
STALL_THRESHOLD = 0.5


def _thumbnail(rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
    """A 40x30 grey thumbnail (float grey levels) for detecting a blocked step from pixels."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (40, 30), interpolation=cv2.INTER_AREA).astype(np.float32)


def scene_database_dir(env: gym.Env, seed: int = 0, progress: bool = False) -> Path:
    """The default build directory of ``env``'s scene at its camera size, built if missing."""
    from vgpnav_env.build import build_runs, default_build_dir

    base = env.unwrapped
    if base.scene_source is None:
        raise ValueError("the env was made from a Scene object: pass database_dir= (a build of that scene)")
    size = (base.camera.width, base.camera.height)
    out = default_build_dir(base.scene_source, size, seed, base.texture)
    build_runs(
        base.scene_source,
        out,
        size=size,
        seed=seed,
        texture=base.texture,
        fovy_deg=float(np.degrees(base.camera.fovy)),
        progress=progress,
    )
    return out


class VGPNavObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """VGP-Nav state observations (see the module docstring) over ``VGPNav/PointGoal-v0``.

    ``backbone``: a :class:`Backbone`, or a registry name built by ``make_backbone(backbone,
    database=..., **backbone_options)`` (e.g. ``learned`` with ``model`` and ``weights_path``).
    """

    def __init__(
        self,
        env: gym.Env,
        backbone: str | Backbone = "classical",
        database_dir: str | Path | None = None,
        *,
        database: Database | None = None,
        database_config: DatabaseConfig | None = None,
        perception_config: PerceptionConfig | None = None,
        map_size: int = 64,
        map_resolution: float = 0.1,
        init_yaw_jitter_deg: tuple[float, ...] = (0.0, -1.5, 1.5),
        build_seed: int = 0,
        motion_gate: tuple[float, float, float, float] | None = MOTION_GATE,
        stall_threshold: float = STALL_THRESHOLD,
        backbone_options: Mapping[str, Any] | None = None,
    ) -> None:
        # Recorded for env re-creation from the spec; an open database is recorded by its directory.
        gym.utils.RecordConstructorArgs.__init__(
            self,
            backbone=backbone,
            database_dir=database.path if database is not None else database_dir,
            database_config=database.config if database is not None else database_config,
            perception_config=perception_config,
            map_size=map_size,
            map_resolution=map_resolution,
            init_yaw_jitter_deg=init_yaw_jitter_deg,
            build_seed=build_seed,
            motion_gate=motion_gate,
            stall_threshold=stall_threshold,
            backbone_options=backbone_options,
        )
        gym.Wrapper.__init__(self, env)
        base = env.unwrapped
        if not hasattr(base, "camera_T_wc"):
            raise TypeError(f"VGPNavObservation wraps VGPNav/PointGoal-v0, got {type(base).__name__}")
        if map_size < 8 or map_resolution <= 0:
            raise ValueError(
                f"need map_size >= 8 cells and map_resolution > 0, got {map_size}, {map_resolution}"
            )
        if not base.render_rgb:
            raise ValueError("VGPNavObservation needs camera images: make the env with render_rgb=True")
        if not init_yaw_jitter_deg:
            raise ValueError("init_yaw_jitter_deg needs at least one yaw offset (0 = the first view)")
        if motion_gate is not None and (len(motion_gate) != 4 or min(motion_gate) <= 0):
            raise ValueError(
                "motion_gate must be None or (max_distance m, max_yaw_deg, growth m per forward step, "
                "growth deg per turn), "
                f"all positive; got {motion_gate}"
            )
        self.motion_gate = motion_gate
        if stall_threshold < 0:
            raise ValueError(f"stall_threshold must be >= 0 grey levels (0 = off), got {stall_threshold}")
        self.stall_threshold = float(stall_threshold)
        if database is None:
            if database_dir is None:
                database_dir = scene_database_dir(env, build_seed)
            database = open_database(database_dir, database_config)
        config = perception_config or PerceptionConfig(camera_height=base.camera_height)
        if isinstance(backbone, str):
            backbone = make_backbone(backbone, database=database, **(backbone_options or {}))
        self.perceiver = Perceiver(database, backbone, camera=base.camera, config=config)
        self.map_size = int(map_size)
        self.map_resolution = float(map_resolution)
        self.init_yaw_jitter = np.radians(np.asarray(init_yaw_jitter_deg, float))

        goal_space = base.observation_space["goal"]
        lo = np.append(goal_space.low - POSE_MARGIN_M, -np.pi).astype(np.float32)
        hi = np.append(goal_space.high + POSE_MARGIN_M, np.pi).astype(np.float32)
        self._pose_low, self._pose_high = lo, hi
        max_dist = float(np.linalg.norm(hi[:2] - lo[:2]))
        self.observation_space = spaces.Dict(
            {
                "pose": spaces.Box(lo, hi, (3,), np.float32),
                "goal_rel": spaces.Box(
                    np.array([0.0, -np.pi], np.float32),
                    np.array([max_dist, np.pi], np.float32),
                    (2,),
                    np.float32,
                ),
                "map": spaces.Box(0, 255, (1, self.map_size, self.map_size), np.uint8),
                "localized": spaces.Discrete(2),
            }
        )
        self.estimate: NDArray[np.float64] = np.zeros(3)
        self.last_result: PerceptionResult | None = None

    @property
    def backbone_privileged(self) -> bool:
        return bool(getattr(self.perceiver.backbone, "privileged", False))

    def _privileged(self, T_wc: NDArray[np.float64], depth: NDArray[np.float32] | None) -> Privileged | None:
        if not self.backbone_privileged:
            return None
        if depth is None:
            raise ValueError(
                "the simulated backbone needs the env's depth: make the env with render_rgb=True"
            )
        return Privileged(T_wq=T_wc, T_wi=np.zeros((0, 4, 4)), query_depth=depth)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        base = self.env.unwrapped
        self.perceiver.backbone.reseed(base.np_random)
        self.perceiver.reset()
        pose = np.asarray(info["pose"], float)
        images, privileged = [obs["rgb"]], [self._privileged(info["T_wc"], info["depth"])]
        for dyaw in self.init_yaw_jitter[1:]:
            view = pose + np.array([0.0, 0.0, dyaw])
            frame = base.render_view(view)
            images.append(frame.rgb)
            privileged.append(self._privileged(base.camera_T_wc(view), frame.depth))
        result = self.perceiver.initialize(images, privileged)[0]
        self.estimate = np.zeros(3)
        self._have_estimate = False
        self._moves_since_fix = np.zeros(2)  # forward steps, turns
        self._thumbnail = _thumbnail(obs["rgb"])
        return self._observe(obs, info, result, None)

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        thumbnail = _thumbnail(obs["rgb"])
        stalled = float(np.abs(thumbnail - self._thumbnail).mean()) < self.stall_threshold
        self._thumbnail = thumbnail
        if stalled and action is not None and self.env.unwrapped.action_mode == "discrete":
            action = Action.STOP if action == Action.FORWARD else action  # blocked: the robot stayed
        predicted = self._dead_reckon(action) if self._have_estimate else None
        if action is not None and self.env.unwrapped.action_mode == "discrete":
            turn = action in (Action.TURN_LEFT, Action.TURN_RIGHT)
            self._moves_since_fix += (action == Action.FORWARD, turn)
        result = self.perceiver.perceive(
            obs["rgb"], self._privileged(info["T_wc"], info["depth"]), gate=self._gate(predicted)
        )
        new_obs, info = self._observe(obs, info, result, predicted)
        return new_obs, reward, terminated, truncated, info

    def _dead_reckon(self, action: Any) -> NDArray[np.float64]:
        """The estimate moved by the commanded discrete action (unchanged for continuous actions)."""
        base = self.env.unwrapped
        if action is None or base.action_mode != "discrete":
            return self.estimate.copy()
        return predict_pose(self.estimate, action, base.forward_step, base.turn_step)

    def _gate(self, predicted: NDArray[np.float64] | None) -> PoseGate | None:
        """The odometry gate around ``predicted`` (None: no estimate yet, no gate, or continuous actions)."""
        base = self.env.unwrapped
        if predicted is None or self.motion_gate is None or base.action_mode != "discrete":
            return None
        distance, yaw_deg, growth_m, growth_deg = self.motion_gate
        forward, turns = self._moves_since_fix
        return PoseGate(
            base.camera_T_wc(predicted),
            distance + growth_m * forward,
            float(np.radians(yaw_deg + growth_deg * turns)),
        )

    def _observe(
        self,
        obs: dict[str, NDArray],
        info: dict[str, Any],
        result: PerceptionResult,
        predicted: NDArray[np.float64] | None,
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        localized = result.localized and result.T_wc is not None
        if localized:
            yaw, _ = camera_yaw_pitch(result.T_wc)
            self.estimate = np.array([result.T_wc[0, 3], result.T_wc[1, 3], yaw])
            self._have_estimate = True
            self._moves_since_fix = np.zeros(2)
        elif predicted is not None:
            self.estimate = predicted
        else:  # never localized in this episode: nothing better than the map centre
            self.estimate = np.array([*self.perceiver.map.spec.centre, 0.0])
        self.estimate = np.clip(self.estimate, self._pose_low, self._pose_high)
        self.last_result = result
        x, y, yaw = self.estimate
        goal = np.asarray(obs["goal"], float)
        d = goal - self.estimate[:2]
        occupancy = self.perceiver.map
        crop = occupancy.egocentric_crop(x, y, yaw, self.map_size, self.map_resolution)
        max_dist = float(self.observation_space["goal_rel"].high[0])
        new_obs = {
            "pose": self.estimate.astype(np.float32),
            "goal_rel": np.array(
                [min(np.hypot(*d), max_dist), wrap_angle(np.arctan2(d[1], d[0]) - yaw)], np.float32
            ),
            "map": crop[None],
            "localized": int(localized),
        }
        obstacles = occupancy.occupied()
        info = dict(info)
        info.update(
            perception={
                "status": result.status,
                "reason": result.reason,
                "T_wc": result.T_wc,
                "scale": result.scale,
                "scale_source": result.scale_source,
                "z_ground": result.z_ground,
                "references": result.references,
                "n_confident_pairs": result.n_confident_pairs,
            },
            estimated_pose=self.estimate.copy(),
            localized=localized,
            obstacles=obstacles,
            map_spec=occupancy.spec,
            localization_error_m=float(np.linalg.norm(self.estimate[:2] - np.asarray(info["pose"])[:2])),
        )
        self.env.unwrapped.set_overlay(
            estimated_pose=self.estimate, obstacles=occupancy.spec.cell_to_world(np.argwhere(obstacles))
        )
        return new_obs, info
