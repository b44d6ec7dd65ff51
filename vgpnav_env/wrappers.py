"""``VGPNavObservation``: the point-goal env seen through VGP-Nav perception.

The wrapper runs the VGP-Nav :class:`~vgpnav_env.perception.pipeline.Perceiver` on every camera
image against the scene's database run, keeps the robot's pose between frames in a
:class:`~vgpnav_env.perception.state.PoseState` and replaces the raw observation by a navigation
state. ``perception_mode`` (:data:`~vgpnav_env.perception.pipeline.PERCEPTION_MODES`):

- ``"temporal"`` (default): :class:`~vgpnav_env.perception.state.EKFState` fuses action odometry
  and the perceived poses (Mahalanobis-gated, kidnapping detected); while it is certain, the
  perceiver tracks (references around the predicted camera pose, global retrieval when that
  fails); a frame is fused into the map only when the EKF accepts its pose and the images confirm
  it without the estimate's prior (``PerceptionResult.prior_placed``).
- ``"paper"``: every frame perceived on its own (global retrieval) and fused when it localizes;
  :class:`~vgpnav_env.perception.state.OdometryState` carries the pose between fixes (dead
  reckoning by the robot's motion model, blocked steps seen in the pixels, the odometry gate
  ``motion_gate`` that rejects a perceived pose jumping away from the prediction).

The observation:

``Dict(pose=Box (3,) float32, goal_rel=Box (2,) float32, map=Box uint8 (1, S, S), localized=Discrete(2))``

- ``pose``: estimated (x, y, yaw) of the robot in W (metres, radians), clipped to the map bounds
  plus a margin; the pose state's estimate (carried forward while perception is lost, the map
  centre before the first fix of an episode).
- ``goal_rel``: (distance m, bearing rad counter-clockwise from the estimated heading) of the goal.
- ``map``: egocentric crop of the fused occupancy map (``S`` x ``S`` pixels of ``map_resolution``
  metres, row 0 ahead, columns to the right; 255 occupied, 128 free, 0 unknown), channels first.
  A discrete forward step the bump sensor reports blocked marks what it felt, a band across the
  heading just beyond the robot's radius from the estimated pose, occupied in the fused map
  (:meth:`~vgpnav_env.perception.occupancy.LogOddsMap.mark_contact`;
  :func:`~vgpnav_env.robot.felt_contact`): the reconstruction misses low, plain or close
  furniture, and without the mark a policy pushing into such an obstacle saw the same free crop at
  every step.
- ``localized``: 1 if this frame's perceived pose was taken in by the pose state, 0 if the pose was
  carried forward (lost, or a perceived pose the EKF rejected).

Agents that plan in the world frame read the wrapper's attributes (``env.get_wrapper_attr``):
``fused_map``, the live fused :class:`~vgpnav_env.perception.occupancy.LogOddsMap` (``occupied()``,
``spec``), and ``pose_state`` (its ``covariance``: None in paper mode); the world goal is the
estimated pose plus ``goal_rel``. The full :class:`PerceptionResult` of the last frame (points,
timings) is ``last_result``.

The pose state's motion model reads the env's bump sensor (``env.unwrapped.bumped``: the step's
motion was blocked) beside the actions. ``info`` is for evaluation only: it keeps the env's entries
(true pose etc.) and adds ``perception`` (the frame's status, reason, ``T_wc``, scale, scale
source, anchored ground height -- scale and height left out while undefined --, references and
confident pairs, reference ``source`` -- tracking or global -- and the pose state's ``fix``,
:data:`~vgpnav_env.perception.state.FIX_OUTCOMES`), ``estimated_pose``, ``obstacles`` (bool grid of
occupied cells of the fused map) with ``map_spec`` (its ``GridSpec``), and the metrics of the
``"estimate"`` measures of :mod:`vgpnav_env.measures`: ``localization_error_m`` (horizontal error
of the observed ``pose``), ``localized``, ``tracked``, ``relocalized``, ``gross_pose_error`` and
``no_estimate``; before the pose state's first estimate (``no_estimate`` True) the pose-error
entries are left out, not nan (:meth:`~vgpnav_env.measures.Measurements.defined_metrics`); then
the ``"map"`` measures of the fused map against the true occupancy over the cells the camera saw
(:mod:`vgpnav_env.map_measures`, kept by ``map_tracker``): ``map_precision``, ``map_recall``,
``map_iou`` (None while undefined) and ``path_phantoms``. Timings stay out of it and nothing is
nan, so that ``info`` of identical runs compares equal.

On ``reset`` the robot stands still: the first view plus ``len(init_yaw_jitter_deg) - 1`` views
rendered with tiny yaw offsets (``env.render_view``) initialise the ground anchor (paper: ground
height initialisation with the known camera height); their perceived poses (yaw offsets taken
out) are the pose state's first fixes, the first view's last, each with its verifier score
(the EKF's first estimate needs ``EKFConfig.init_fixes`` consistent fixes, one of them from
another view -- these nearly identical views are one view -- or a fix scoring
``EKFConfig.init_score``). The wrapper also sets the env's render overlay (estimated pose and
fused obstacles).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import astuple
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from vgpnav_env.geometry import wrap_angle
from vgpnav_env.map_measures import MapTracker
from vgpnav_env.measures import EstimateState, Measurements, defined
from vgpnav_env.perception.backbones import Backbone, Privileged, make_backbone
from vgpnav_env.perception.database import Database, DatabaseConfig, open_database
from vgpnav_env.perception.occupancy import LogOddsMap
from vgpnav_env.perception.pipeline import PERCEPTION_MODES, Perceiver, PerceptionConfig, PerceptionResult
from vgpnav_env.perception.state import (
    STALL_THRESHOLD,
    EKFConfig,
    EKFState,
    GateConfig,
    OdometryState,
    PoseState,
)
from vgpnav_env.robot import FOVY_DEG, base_pose, felt_contact

logger = logging.getLogger(__name__)

POSE_MARGIN_M = 5.0
#: Default odometry gate: (max_distance m, max_yaw_deg, growth m per forward step and growth deg per
#: turn since the last fix), see :class:`~vgpnav_env.perception.state.GateConfig`.
MOTION_GATE = astuple(GateConfig())


def scene_database_dir(
    scene: str,
    size: tuple[int, int],
    texture: str = "realistic",
    fovy_deg: float = FOVY_DEG,
    seed: int = 0,
    progress: bool = True,
) -> Path:
    """The default build directory of ``scene`` (a scene source name) at camera ``size`` (W, H),
    built if missing (``vgpnav_env.build.build_runs``)."""
    from vgpnav_env.build import build_runs, default_build_dir

    out = default_build_dir(scene, tuple(size), seed, texture)
    build_runs(scene, out, size=tuple(size), seed=seed, texture=texture, fovy_deg=fovy_deg, progress=progress)
    return out


def navigation_space(base: gym.Env, map_size: int) -> spaces.Dict:
    """The navigation observation space (module docstring) of the point-goal env ``base``: pose
    bounds are the map bounds plus :data:`POSE_MARGIN_M`. Shared by every perception wrapper."""
    goal_space = base.observation_space["goal"]
    lo = np.append(goal_space.low - POSE_MARGIN_M, -np.pi).astype(np.float32)
    hi = np.append(goal_space.high + POSE_MARGIN_M, np.pi).astype(np.float32)
    max_dist = float(np.linalg.norm(hi[:2] - lo[:2]))
    return spaces.Dict(
        {
            "pose": spaces.Box(lo, hi, (3,), np.float32),
            "goal_rel": spaces.Box(
                np.array([0.0, -np.pi], np.float32), np.array([max_dist, np.pi], np.float32), (2,), np.float32
            ),
            "map": spaces.Box(0, 255, (1, map_size, map_size), np.uint8),
            "localized": spaces.Discrete(2),
        }
    )


def navigation_observation(
    space: spaces.Dict,
    estimate: NDArray[np.float64],
    goal: NDArray,
    occupancy: LogOddsMap,
    localized: bool,
    map_resolution: float,
) -> dict[str, Any]:
    """The observation of ``space`` (from :func:`navigation_space`) for the pose ``estimate``
    (x, y, yaw), the world ``goal`` (x, y) and the fused map ``occupancy``."""
    x, y, yaw = estimate
    d = np.asarray(goal, float) - estimate[:2]
    size = space["map"].shape[-1]
    crop = occupancy.egocentric_crop(x, y, yaw, size, map_resolution)
    max_dist = float(space["goal_rel"].high[0])
    return {
        "pose": estimate.astype(np.float32),
        "goal_rel": np.array(
            [min(np.hypot(*d), max_dist), wrap_angle(np.arctan2(d[1], d[0]) - yaw)], np.float32
        ),
        "map": crop[None],
        "localized": int(localized),
    }


class VGPNavObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """VGP-Nav state observations (see the module docstring) over ``VGPNav/PointGoal-v0``.

    ``backbone``: a :class:`Backbone`, or a registry name built by ``make_backbone(backbone,
    database=..., **backbone_options)`` (e.g. ``learned`` with ``model`` and ``weights_path``).
    ``perception_mode``: a :data:`~vgpnav_env.perception.pipeline.PERCEPTION_MODES` name;
    ``motion_gate`` applies to ``paper``, ``ekf`` (an :class:`EKFConfig`) to ``temporal``.
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
        perception_mode: str = "temporal",
        ekf: EKFConfig | None = None,
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
            perception_mode=perception_mode,
            ekf=ekf,
        )
        gym.Wrapper.__init__(self, env)
        if perception_mode not in PERCEPTION_MODES:
            raise ValueError(
                f"unknown perception_mode {perception_mode!r}; allowed: {', '.join(PERCEPTION_MODES)}"
            )
        #: The perception mode (a :data:`~vgpnav_env.perception.pipeline.PERCEPTION_MODES` name).
        self.perception_mode = perception_mode
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
        if motion_gate is not None and len(motion_gate) != 4:
            raise ValueError(
                "motion_gate must be None or (max_distance m, max_yaw_deg, growth m per forward step, "
                f"growth deg per turn), all positive; got {motion_gate}"
            )
        if database is None:
            if database_dir is None:
                if base.scene_source is None:
                    raise ValueError(
                        "the env was made from a Scene object: pass database_dir= (a build of that scene)"
                    )
                size = (base.camera.width, base.camera.height)
                # Rounded: degrees(radians(60)) is 59.99999999999999, and a build made by the
                # command line (60.0) did not match: every wrapper made without database_dir rebuilt.
                fovy = round(float(np.degrees(base.camera.fovy)), 6)
                database_dir = scene_database_dir(base.scene_source, size, base.texture, fovy, build_seed)
            database = open_database(database_dir, database_config)
        config = perception_config or PerceptionConfig(camera_height=base.camera_height)
        if isinstance(backbone, str):
            backbone = make_backbone(backbone, database=database, **(backbone_options or {}))
        self.perceiver = Perceiver(database, backbone, camera=base.camera, config=config)
        self.map_size = int(map_size)
        self.map_resolution = float(map_resolution)
        self.init_yaw_jitter = np.radians(np.asarray(init_yaw_jitter_deg, float))

        self.observation_space = navigation_space(base, self.map_size)
        lo, hi = self.observation_space["pose"].low, self.observation_space["pose"].high
        motion = {
            "discrete": base.action_mode == "discrete",
            "forward_step": base.forward_step,
            "turn_step": base.turn_step,
            "stall_threshold": stall_threshold,
        }
        if perception_mode == "temporal":
            self.pose_state: PoseState = EKFState(lo, hi, config=ekf, **motion)
        else:
            gate = None if motion_gate is None else GateConfig(*motion_gate)
            self.pose_state = OdometryState(lo, hi, gate=gate, **motion)
        self.last_result: PerceptionResult | None = None
        self.measurements = Measurements("estimate")
        self.map_measurements = Measurements("map")
        self.map_tracker = MapTracker(env)

    @property
    def fused_map(self) -> LogOddsMap:
        """The live fused occupancy map of this episode (updated by every localized frame)."""
        return self.perceiver.map

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
        results = self.perceiver.initialize(images, privileged)
        if self.perception_mode != "paper":  # mapped views of a trusted start: sweep references
            for image, result in zip(images, results, strict=True):
                if result.localized:
                    self.perceiver.recent.add(image, result.T_wc)
        self.pose_state.reset(obs["rgb"], fallback=(*self.perceiver.map.spec.centre, 0.0))
        for view, dyaw in zip(results[1:], self.init_yaw_jitter[1:], strict=True):
            # The robot stands still: each view's pose, its known yaw offset taken out, is a fix of
            # the start pose (the first view's follows in _observe).
            fix = None
            if view.localized and view.T_wc is not None:
                fix = base_pose(view.T_wc)
                fix[2] = wrap_angle(fix[2] - dyaw)
            self.pose_state.correct(fix, view.confidence)
        return self._observe(obs, info, results[0], first=True)

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.pose_state.predict(action, obs["rgb"], bumped=self.env.unwrapped.bumped)
        if self.pose_state.has_estimate and felt_contact(self.env, action):
            self.perceiver.map.mark_contact(
                self.pose_state.estimate, self.env.unwrapped.robot_radius, depth=self.map_resolution
            )
        privileged = self._privileged(info["T_wc"], info["depth"])
        predicted = self.pose_state.tracking_pose()
        result = self.perceiver.perceive(
            obs["rgb"],
            privileged,
            gate=self.pose_state.gate(),
            predicted=None if predicted is None else self.env.unwrapped.camera_T_wc(predicted),
            prior=self.pose_state.prior(),
            fuse=self.perception_mode == "paper",
        )
        new_obs, info = self._observe(obs, info, result, first=False)
        return new_obs, reward, terminated, truncated, info

    def _observe(
        self, obs: dict[str, NDArray], info: dict[str, Any], result: PerceptionResult, first: bool
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """The navigation observation (and the evaluation info) after the pose state took in ``result``."""
        measured = result.measurement
        self.pose_state.correct(None if measured is None else base_pose(measured), result.confidence)
        localized = self.pose_state.localized
        if localized and not first and self.perception_mode != "paper" and not result.prior_placed:
            # the map takes only frames whose pose the estimator trusts and the images confirm alone
            self.perceiver.fuse(result, obs["rgb"])
        estimate = self.pose_state.estimate
        self.last_result = result
        occupancy = self.perceiver.map
        new_obs = navigation_observation(
            self.observation_space, estimate, obs["goal"], occupancy, localized, self.map_resolution
        )
        obstacles = occupancy.occupied()
        state = EstimateState(
            new_obs["pose"],
            localized,
            np.asarray(info["pose"]),
            self.pose_state.fix,
            result.source,
            self.pose_state.has_estimate,
        )
        (self.measurements.reset if first else self.measurements.update)(state)
        if first:
            self.map_tracker.start(occupancy.spec, info)
        map_state = self.map_tracker.observe(obstacles, info)
        (self.map_measurements.reset if first else self.map_measurements.update)(map_state)
        info = dict(info)
        info.update(
            perception=defined(
                {
                    "status": result.status,
                    "reason": result.reason,
                    "T_wc": result.T_wc,
                    "scale": result.scale,
                    "scale_source": result.scale_source,
                    "z_ground": result.z_ground,
                    # a tuple: its length varies per frame, so vector envs keep it as an object
                    "references": tuple(int(i) for i in result.references),
                    "n_confident_pairs": result.n_confident_pairs,
                    "source": result.source,
                    "fix": self.pose_state.fix,
                }
            ),
            estimated_pose=estimate.copy(),
            obstacles=obstacles,
            map_spec=occupancy.spec,
            **self.measurements.defined_metrics(),
            **self.map_measurements.metrics(),
        )
        self.env.unwrapped.set_overlay(
            estimated_pose=estimate,
            obstacles=occupancy.spec.cell_to_world(np.argwhere(obstacles)),
            localized=localized,
        )
        return new_obs, info
