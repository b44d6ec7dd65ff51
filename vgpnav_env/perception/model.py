"""``model`` perception (PRIVILEGED): VGP-Nav's measured errors drawn at RL speed, no pixel work.

A :class:`PerceptionModel` is fitted (``vgpnav calibrate``, :func:`fit_model`) to the per-frame
records of a classical localization run on a build's query run, beside the ground-truth depth of
those frames. :class:`ModelObservation` then replaces the pixel pipeline of
:class:`~vgpnav_env.wrappers.VGPNavObservation` (same observation space) by draws from it:

- **Lost.** Per frame, ``p = stickiness * lost_before + (1 - stickiness) * p_lost[bin]``, where the
  bin is that of the view's median ground-truth depth (close views lose more often) and
  ``stickiness`` (fitted by maximum likelihood on consecutive query frames) makes lost spells as
  long as measured; the marginal lost rate per bin is the measured one.
- **Pose error when localized.** With probability ``p_gross`` a gross error resampled from the
  measured gross errors (> 0.5 m or 10 deg, e.g. a room mistaken for a similar one); otherwise
  log-normal translation (m) and rotation (deg) errors fitted to the other localized frames. The
  translation error is applied horizontally in a uniform direction, the rotation error to the
  yaw with a random sign.
- **While lost.** The pose is carried forward by the robot's odometry (the true relative motion of
  the step, i.e. ideal wheel odometry), as the pixel wrapper carries it forward between fixes.
- **Pose state.** :class:`ModelPoseState` (``pose_state``, as the pixel wrapper's): the estimate,
  the localized flag and a covariance -- on a fix that of the fitted error distribution, growing
  while lost by the EKF's process noise per action (:class:`~vgpnav_env.perception.state.EKFConfig`,
  what the pixel wrapper's temporal mode assumes; the model's own odometry is ideal).
- **Map.** Localized frames fuse the rendered depth (every ``point_stride``-th pixel, a random
  ``coverage`` fraction of them, Gaussian noise of ``depth_noise_m`` along the optical axis,
  fitted from the measured Acc) placed with the *estimated* pose, into a log-odds map that starts
  from the ground truth of the database's ``base`` layout clamped to +-2 (an idealised database
  prior; the pixel wrapper's prior is reconstructed from the database images). A blocked forward
  step marks what it felt ahead of the estimate, as the pixel wrapper does.

- **Randomised** (``randomize=True``, a training-time option; the evaluation default is off): the
  statistics of the pixel wrapper in navigation, which differ from the query-run calibration. The
  prior is the ground truth degraded per episode by the fitted errors of the database prior
  (:class:`PriorErrors`: obstacles near free space missed or hollow, phantom obstacles along
  walls, unknown cells), in spatially correlated blobs; each episode draws a lost regime (the lost
  probabilities scaled by up to :data:`MAX_LOST_FACTOR`, the stickiness up to
  :data:`MAX_STICKINESS`: pixel navigation lost 1-100 % of an episode's frames, in spells of tens
  of steps); an episode whose first frame is lost starts without an estimate (the pixel wrapper's
  placeholder at the map centre, yaw 0, until the first fix); and obstacles that depth never shows:
  a fraction of the map up to :data:`MAX_UNSEEN`, in blobs of ~:data:`UNSEEN_BLOB_M`, where
  rendered depth points above the floor are dropped (the pixel pipeline's reconstruction misses
  low, plain or close furniture). The policy meets contacts its map does not explain, as on pixels.

Everything privileged (true pose, rendered depth, ground-truth prior) comes from the env; the name
says so. Same seed (``reset(seed=...)``), same draws. The default fit
(``data/model_classical_home.json``) ships with the package; see its ``source`` for the command.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.geometry import PinholeCamera, wrap_angle
from vgpnav_env.grid import GridSpec
from vgpnav_env.map_measures import MapTracker
from vgpnav_env.measures import EstimateState, Measurements
from vgpnav_env.perception.occupancy import LogOddsMap, OccupancyConfig
from vgpnav_env.perception.state import EKFConfig
from vgpnav_env.robot import Action, felt_contact

#: Errors above (metres, degrees) are gross (as the localization reports count them).
GROSS_ERROR = (0.5, 10.0)
#: The shipped default fit.
DEFAULT_FIT = "model_classical_home.json"
#: Log-odds of the ground-truth prior (as the database prior's clamp).
PRIOR_LOGODDS = 2.0
#: Median depth of a view that sees nothing (metres).
NO_DEPTH = 10.0
#: Randomised episodes (``randomize=True``): the largest factor on the lost probabilities and the
#: largest stickiness an episode draws (log-uniform from 1 and uniform from the fit's).
MAX_LOST_FACTOR = 4.0
MAX_STICKINESS = 0.95
#: The lost probability a randomised episode never exceeds.
MAX_LOST_PROBABILITY = 0.95
#: Randomised episodes: the largest fraction of the map (uniform from 0 per episode) whose obstacles
#: depth never shows, in spatially correlated blobs (Gaussian smoothing of ``UNSEEN_BLOB_M`` m).
#: A randomisation, not a fit: it makes contacts the map does not explain common in training.
MAX_UNSEEN = 0.5
UNSEEN_BLOB_M = 0.2


@dataclass(frozen=True)
class PriorErrors:
    """How the database prior's labels (free / unknown / occupied) err against the ground truth of
    the base layout, fitted by :func:`fit_prior_errors`: for free cells by their distance to the
    nearest obstacle (bins at ``free_edges`` m), for obstacle cells by their distance to the nearest
    free cell (``obstacle_edges`` m), the probabilities of the occupied and of the unknown label;
    ``correlation_cells``: the Gaussian smoothing (cells of the fitted map) that makes the drawn
    errors blobs."""

    free_edges: list[float]
    free_occupied: list[float]
    free_unknown: list[float]
    obstacle_edges: list[float]
    obstacle_occupied: list[float]
    obstacle_unknown: list[float]
    correlation_cells: float = 1.0

    def draw(
        self,
        free: NDArray[np.bool_],
        obstacle: NDArray[np.bool_],
        resolution: float,
        rng: np.random.Generator,
    ) -> NDArray[np.float32]:
        """Prior log-odds (+-:data:`PRIOR_LOGODDS`, 0 unknown) of a map with ground-truth ``free``
        and ``obstacle`` cells (``resolution`` m): every cell's label drawn from its bin's
        probabilities by a spatially correlated uniform field; other cells unknown."""
        from scipy import ndimage, special

        field = ndimage.gaussian_filter(rng.standard_normal(free.shape), self.correlation_cells)
        u = special.ndtr(field / max(float(field.std()), 1e-9))  # uniform marginals, blobby
        out = np.zeros(free.shape, np.float32)
        for cells, dist, edges, p_occ, p_unk in (
            (free, ndimage.distance_transform_edt(~obstacle), self.free_edges, self.free_occupied,
             self.free_unknown),
            (obstacle, ndimage.distance_transform_edt(~free), self.obstacle_edges,
             self.obstacle_occupied, self.obstacle_unknown),
        ):  # fmt: skip
            b = np.searchsorted(edges, dist * resolution, side="right")
            occ, unk = np.asarray(p_occ)[b], np.asarray(p_unk)[b]
            out[cells & (u < occ)] = PRIOR_LOGODDS
            out[cells & (u >= occ + unk)] = -PRIOR_LOGODDS
        return out


def fit_prior_errors(
    probability: NDArray[np.float64],
    free: NDArray[np.bool_],
    obstacle: NDArray[np.bool_],
    resolution: float,
    free_edges: tuple[float, ...] = (0.1, 0.2, 0.3, 0.5),
    obstacle_edges: tuple[float, ...] = (0.1, 0.2, 0.3, 0.5),
    occupied: float = 0.65,
    free_below: float = 0.35,
) -> PriorErrors:
    """:class:`PriorErrors` of a prior map's occupancy ``probability`` against the ground truth
    ``free`` and ``obstacle`` cells of the same grid (``resolution`` m); labels as the observation's
    crop draws them (occupied above ``occupied``, free below ``free_below``)."""
    from scipy import ndimage

    if not (probability.shape == free.shape == obstacle.shape):
        raise ValueError("probability, free and obstacle must be grids of one shape")
    occ, unk = probability > occupied, (probability >= free_below) & (probability <= occupied)

    def rates(cells: NDArray[np.bool_], dist: NDArray[np.float64], edges: tuple[float, ...]):
        b = np.searchsorted(edges, dist, side="right")
        n = np.bincount(b[cells], minlength=len(edges) + 1).astype(float)
        k_occ = np.bincount(b[cells], weights=occ[cells], minlength=len(edges) + 1)
        k_unk = np.bincount(b[cells], weights=unk[cells], minlength=len(edges) + 1)
        return [float(x) for x in k_occ / np.maximum(n, 1)], [float(x) for x in k_unk / np.maximum(n, 1)]

    free_occ, free_unk = rates(free, ndimage.distance_transform_edt(~obstacle) * resolution, free_edges)
    obs_occ, obs_unk = rates(obstacle, ndimage.distance_transform_edt(~free) * resolution, obstacle_edges)
    return PriorErrors(list(free_edges), free_occ, free_unk, list(obstacle_edges), obs_occ, obs_unk)


@dataclass(frozen=True)
class PerceptionModel:
    """A fitted error model (see the module docstring); metres and degrees."""

    depth_edges: list[float]  # inner bin edges of the view's median depth (m)
    p_lost: list[float]  # lost probability per bin (len(depth_edges) + 1)
    stickiness: float
    p_gross: float  # among localized frames
    log_translation: tuple[float, float]  # (mean, std) of log(translation error m), non-gross
    log_rotation: tuple[float, float]  # (mean, std) of log(rotation error deg), non-gross
    gross_translation_m: list[float]
    gross_rotation_deg: list[float]
    depth_noise_m: float
    coverage: float  # fraction of the sampled pixels that give a point
    source: dict[str, Any] = field(default_factory=dict)
    prior_errors: PriorErrors | None = None  # the database prior's (randomised episodes)

    def __post_init__(self) -> None:
        if len(self.p_lost) != len(self.depth_edges) + 1:
            raise ValueError("p_lost needs one probability per depth bin (len(depth_edges) + 1)")
        if not (0 <= self.stickiness < 1 and 0 <= self.p_gross <= 1 and 0 < self.coverage <= 1):
            raise ValueError("need 0 <= stickiness < 1, 0 <= p_gross <= 1 and 0 < coverage <= 1")
        if len(self.gross_translation_m) != len(self.gross_rotation_deg):
            raise ValueError("gross translation and rotation errors must pair up")

    def lost_probability(
        self, median_depth: float, lost_before: bool, factor: float = 1.0, stickiness: float | None = None
    ) -> float:
        """This frame's lost probability; ``factor`` scales the bin's (capped at
        :data:`MAX_LOST_PROBABILITY`), ``stickiness`` replaces the fit's (randomised episodes)."""
        p = self.p_lost[int(np.searchsorted(self.depth_edges, median_depth, side="right"))]
        p = min(p * factor, MAX_LOST_PROBABILITY) if factor != 1.0 else p
        stick = self.stickiness if stickiness is None else stickiness
        return stick * float(lost_before) + (1.0 - stick) * p

    def pose_error(self, rng: np.random.Generator) -> tuple[float, float]:
        """(translation m, rotation deg) of one localized frame."""
        if self.gross_translation_m and rng.random() < self.p_gross:
            k = int(rng.integers(len(self.gross_translation_m)))
            return self.gross_translation_m[k], self.gross_rotation_deg[k]
        return float(np.exp(rng.normal(*self.log_translation))), float(np.exp(rng.normal(*self.log_rotation)))

    def fix_covariance(self) -> NDArray[np.float64]:
        """3x3 covariance over (x, y, yaw) (m^2, rad^2) of a localized frame's non-gross error: the
        mean squared translation error split over the two axes, the mean squared rotation error
        (gross errors are outliers a covariance does not describe, as for the EKF's fixes)."""
        t2, r2 = [float(np.exp(2 * m + 2 * s**2)) for m, s in (self.log_translation, self.log_rotation)]
        return np.diag([t2 / 2, t2 / 2, np.radians(np.sqrt(r2)) ** 2])

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(json.dumps(asdict(self), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path | None = None) -> PerceptionModel:
        """A fit from ``path`` (default: the shipped :data:`DEFAULT_FIT`)."""
        if path is None:
            text = resources.files("vgpnav_env.perception").joinpath("data", DEFAULT_FIT).read_text()
        else:
            text = Path(path).read_text()
        data = json.loads(text)
        data["log_translation"] = tuple(data["log_translation"])
        data["log_rotation"] = tuple(data["log_rotation"])
        if data.get("prior_errors") is not None:
            data["prior_errors"] = PriorErrors(**data["prior_errors"])
        return cls(**data)


def median_depth(depth: ArrayLike) -> float:
    """Median of the finite positive z-depths of a view (any shape; :data:`NO_DEPTH` when nothing
    is hit)."""
    d = np.asarray(depth).reshape(-1)
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else NO_DEPTH


def _log_normal(x: NDArray[np.float64]) -> tuple[float, float]:
    logs = np.log(np.maximum(x, 1e-5))
    return (float(logs.mean()), float(logs.std())) if len(logs) else (np.log(1e-3), 0.0)


def _stickiness(lost: NDArray[np.bool_], p: NDArray[np.float64], consecutive: NDArray[np.bool_]) -> float:
    """Maximum-likelihood stickiness on frames that follow their predecessor (grid of 0.01)."""
    if not consecutive.any():
        return 0.0
    prev, now, base = lost[:-1][consecutive], lost[1:][consecutive], p[1:][consecutive]
    grid = np.arange(0.0, 0.96, 0.01)
    q = grid[:, None] * prev[None] + (1 - grid[:, None]) * base[None]
    q = np.clip(q, 1e-6, 1 - 1e-6)
    loglik = np.where(now[None], np.log(q), np.log(1 - q)).sum(axis=1)
    return float(grid[int(np.argmax(loglik))])


def fit_model(
    records: list[dict[str, Any]],
    median_depths: ArrayLike,
    sampled_pixels: int,
    n_bins: int = 4,
    source: dict[str, Any] | None = None,
) -> PerceptionModel:
    """Fit a :class:`PerceptionModel` to localization records (``frame``, ``status``,
    ``translation_m``, ``rotation_deg``, ``acc_m``, ``n_points``; as the localization report's),
    the median ground-truth depth of each record's view, and the number of pixels the pipeline
    samples points from (``n_points`` / ``sampled_pixels`` is the coverage)."""
    if not records:
        raise ValueError("no records to fit")
    md = np.asarray(median_depths, float)
    if md.shape != (len(records),):
        raise ValueError(f"need one median depth per record, got {md.shape} for {len(records)}")
    lost = np.array([r["status"] != "localized" for r in records])
    edges = np.unique(np.quantile(md, np.linspace(0, 1, n_bins + 1)[1:-1]))
    bins = np.searchsorted(edges, md, side="right")
    counts = np.bincount(bins, minlength=len(edges) + 1)
    losses = np.bincount(bins, weights=lost, minlength=len(edges) + 1)
    p_lost = (losses + 1.0) / (counts + 2.0)  # Laplace: no bin is certain from a few frames
    frames = np.array([r["frame"] for r in records])
    stick = _stickiness(lost, p_lost[bins], np.diff(frames) == 1)
    loc = ~lost
    t = np.array([r["translation_m"] for r in records], float)[loc]
    rot = np.array([r["rotation_deg"] for r in records], float)[loc]
    gross = (t > GROSS_ERROR[0]) | (rot > GROSS_ERROR[1])
    acc = np.array([r.get("acc_m") for r in records], float)[loc]
    acc = acc[np.isfinite(acc)]
    points = np.array([r.get("n_points", 0) for r in records], float)[loc]
    return PerceptionModel(
        depth_edges=[float(e) for e in edges],
        p_lost=[float(p) for p in p_lost],
        stickiness=stick,
        p_gross=float(gross.mean()) if loc.any() else 0.0,
        log_translation=_log_normal(t[~gross]),
        log_rotation=_log_normal(rot[~gross]),
        gross_translation_m=[float(x) for x in t[gross]],
        gross_rotation_deg=[float(x) for x in rot[gross]],
        # Acc is a mean nearest-neighbour distance: for Gaussian noise of std s it is ~ s * sqrt(2 / pi).
        depth_noise_m=float(np.median(acc) / np.sqrt(2 / np.pi)) if len(acc) else 0.0,
        coverage=float(np.clip(np.median(points) / sampled_pixels, 1e-3, 1.0)) if len(points) else 1.0,
        source=dict(source or {}),
    )


def base_cells(
    source: str, spec: GridSpec, robot_radius: float, robot_height: float
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(free, obstacle) cells of the grid ``spec`` in the ground truth of ``source``'s ``base``
    layout (nearest cell; cached per process)."""
    key = (source, spec, robot_radius, robot_height)
    if key not in _BASE:
        from vgpnav_env.groundtruth import ground_truth_map
        from vgpnav_env.scenes import load_scene

        gt = ground_truth_map(load_scene(source, layout="base"), spec.resolution, robot_radius, robot_height)
        rows, cols = np.indices(spec.shape)
        cells = gt.spec.world_to_cell(spec.cell_to_world(np.stack([rows, cols], axis=-1)))
        inside = gt.spec.contains(cells)
        r, c = cells[..., 0].clip(0, gt.spec.shape[0] - 1), cells[..., 1].clip(0, gt.spec.shape[1] - 1)
        _BASE[key] = (inside & gt.free[r, c], inside & gt.obstacle[r, c])
    return _BASE[key]


_BASE: dict[tuple, tuple[NDArray[np.bool_], NDArray[np.bool_]]] = {}


def prior_map(source: str, spec: GridSpec, robot_radius: float, robot_height: float) -> NDArray[np.float32]:
    """Log-odds (``spec.shape``) of the ground truth of ``source``'s ``base`` layout: obstacles
    +:data:`PRIOR_LOGODDS`, free cells -:data:`PRIOR_LOGODDS`, else 0."""
    free, obstacle = base_cells(source, spec, robot_radius, robot_height)
    prior = np.zeros(spec.shape, np.float32)
    prior[free] = -PRIOR_LOGODDS
    prior[obstacle] = PRIOR_LOGODDS
    return prior


class ModelPoseState:
    """The ``pose_state`` of :class:`ModelObservation` (the read side of
    :class:`~vgpnav_env.perception.state.PoseState`): ``estimate`` (x, y, yaw) in W, ``localized``,
    ``fix`` and ``covariance`` -- ``fix_covariance`` after a fix, plus the EKF's process noise
    (``ekf``) per action while lost."""

    def __init__(self, fix_covariance: NDArray[np.float64], ekf: EKFConfig | None = None) -> None:
        self.fix_covariance = np.asarray(fix_covariance, float)
        ekf = ekf or EKFConfig()
        self._forward = np.diag([ekf.forward_sigma**2, ekf.lateral_sigma**2])
        self._turn = np.radians(ekf.turn_sigma_deg) ** 2
        self.estimate = np.zeros(3)
        self.localized = False
        self._P = self.fix_covariance.copy()

    @property
    def fix(self) -> str:
        return "accepted" if self.localized else "none"

    @property
    def covariance(self) -> NDArray[np.float64]:
        return self._P.copy()

    def tracking_pose(self) -> None:
        return None

    def prior(self) -> None:
        return None

    def update(self, estimate: NDArray[np.float64], localized: bool, action: Any = None) -> None:
        """This frame's ``estimate`` and outcome, after ``action`` (None at the episode start)."""
        self.estimate, self.localized = np.asarray(estimate, float).copy(), bool(localized)
        if localized or action is None:
            self._P = self.fix_covariance.copy()
        elif int(action) == Action.FORWARD:
            c, s = np.cos(self.estimate[2]), np.sin(self.estimate[2])
            R = np.array([[c, -s], [s, c]])
            self._P[:2, :2] += R @ self._forward @ R.T
        elif int(action) in (Action.TURN_LEFT, Action.TURN_RIGHT):
            self._P[2, 2] += self._turn


class ModelObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """``model`` perception (PRIVILEGED, module docstring) over ``VGPNav/PointGoal-v0``: the
    observation space, ``info`` entries and ``fused_map`` of :class:`~vgpnav_env.wrappers.VGPNavObservation`.

    ``fit``: a fit file (default: the shipped one) or a :class:`PerceptionModel`; ``randomize``:
    the randomised episodes of the module docstring (training; needs a fit with ``prior_errors``
    for the prior, draws the lost regime and the missing first estimate without);
    ``map_measures``: score the fused map in ``info`` every step (evaluation; about a third of this
    wrapper's step time, so training turns it off and ``info`` has no map entries).
    """

    perception_mode = "model"

    def __init__(
        self,
        env: gym.Env,
        fit: str | Path | PerceptionModel | None = None,
        *,
        map_size: int = 64,
        map_resolution: float = 0.1,
        point_stride: int = 4,
        prior: bool = True,
        randomize: bool = False,
        map_measures: bool = True,
    ) -> None:
        from vgpnav_env.wrappers import navigation_space

        gym.utils.RecordConstructorArgs.__init__(
            self,
            fit=None if fit is None else str(fit) if not isinstance(fit, PerceptionModel) else fit,
            map_size=map_size,
            map_resolution=map_resolution,
            point_stride=point_stride,
            prior=prior,
            randomize=randomize,
            map_measures=map_measures,
        )
        gym.Wrapper.__init__(self, env)
        base = env.unwrapped
        if not hasattr(base, "render_depth"):
            raise TypeError(f"ModelObservation wraps VGPNav/PointGoal-v0, got {type(base).__name__}")
        if map_size < 8 or map_resolution <= 0 or point_stride < 1:
            raise ValueError("need map_size >= 8, map_resolution > 0 and point_stride >= 1")
        self.model = fit if isinstance(fit, PerceptionModel) else PerceptionModel.load(fit)
        self.map_resolution = float(map_resolution)
        self.point_stride = int(point_stride)
        self.observation_space = navigation_space(base, int(map_size))
        self._occ = OccupancyConfig()
        spec = base.ground_truth.spec
        self.randomize = bool(randomize)
        known = prior and base.scene_source is not None
        self._base = (
            base_cells(base.scene_source, spec, base.robot_radius, base.world.gt.robot_height)
            if known
            else None
        )
        self._prior = np.zeros(spec.shape, np.float32)
        if self._base is not None:
            self._prior[self._base[0]], self._prior[self._base[1]] = -PRIOR_LOGODDS, PRIOR_LOGODDS
        self.fused_map = LogOddsMap(spec, self._occ.l_free, self._occ.l_occ, self._occ.clamp)
        self._rays = self._sampled_rays(base.camera)
        self.rng = np.random.default_rng(0)
        self.estimate = np.zeros(3)
        self._lost = False
        self._true = np.zeros(3)
        self._factor, self._stickiness = 1.0, None  # this episode's lost regime
        self.unseen: NDArray[np.bool_] | None = None  # cells whose obstacles depth never shows
        self.has_estimate = True
        self.measurements = Measurements("estimate")
        self.map_measurements = Measurements("map")
        self.map_tracker = MapTracker(env) if map_measures else None
        self.pose_state = ModelPoseState(self.model.fix_covariance())

    def _sampled_rays(self, camera: PinholeCamera) -> NDArray[np.float64]:
        return camera.rays()[:: self.point_stride, :: self.point_stride].reshape(-1, 3)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.rng = np.random.default_rng(self.env.unwrapped.np_random.integers(2**63))
        self._true = np.asarray(info["pose"], float)
        self._lost = self.randomize  # randomised: the first fix is drawn as if lost before it
        self.estimate = self._true.copy()  # the robot initialises standing still where it starts
        self.has_estimate = True
        self.fused_map.logodds = self._prior.copy()
        self.unseen = None
        if self.randomize:
            m, rng = self.model, self.rng
            self._factor = float(np.exp(rng.uniform(0.0, np.log(MAX_LOST_FACTOR))))
            self._stickiness = float(rng.uniform(m.stickiness, MAX_STICKINESS))
            if m.prior_errors is not None and self._base is not None:
                spec = self.fused_map.spec
                self.fused_map.logodds = m.prior_errors.draw(*self._base, spec.resolution, rng)
            self.has_estimate = False  # until the first fix (_perceive)
            self.estimate = np.array([*self.fused_map.spec.centre, 0.0])
            self.unseen = self._draw_unseen(rng)
        return self._observe(obs, info, action=None)

    def _draw_unseen(self, rng: np.random.Generator) -> NDArray[np.bool_]:
        """A randomised episode's unseen cells: a uniform fraction up to :data:`MAX_UNSEEN` of the
        map, the highest values of a Gaussian-smoothed (:data:`UNSEEN_BLOB_M`) noise field."""
        from scipy import ndimage

        spec = self.fused_map.spec
        field = ndimage.gaussian_filter(rng.standard_normal(spec.shape), UNSEEN_BLOB_M / spec.resolution)
        return field > np.quantile(field, 1.0 - rng.uniform(0.0, MAX_UNSEEN))

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        true = np.asarray(info["pose"], float)
        # Odometry: the true relative motion of this step, applied to the estimate (before the
        # first fix of a randomised episode the placeholder stays, as the pixel wrapper's).
        dx, dy = (true[:2] - self._true[:2]) * self.has_estimate
        c, s = np.cos(self.estimate[2] - self._true[2]), np.sin(self.estimate[2] - self._true[2])
        turn = (true[2] - self._true[2]) * self.has_estimate
        self.estimate = self.estimate + np.array([c * dx - s * dy, s * dx + c * dy, turn])
        self.estimate[2] = wrap_angle(self.estimate[2])
        self._true = true
        if self.has_estimate and felt_contact(self.env, action):
            self.fused_map.mark_contact(
                self.estimate, self.env.unwrapped.robot_radius, depth=self.map_resolution
            )
        new_obs, info = self._observe(obs, info, action=action)
        return new_obs, reward, terminated, truncated, info

    def _perceive(self, depth: NDArray[np.float32]) -> bool:
        """Draw this frame's outcome; on a fix, set the estimate and fuse the depth. Returns localized."""
        m, rng = self.model, self.rng
        d = depth[:: self.point_stride, :: self.point_stride].reshape(-1)
        valid = np.isfinite(d) & (d > 0) & (d <= self._occ.max_depth)
        p = m.lost_probability(median_depth(d), self._lost, self._factor, self._stickiness)
        self._lost = bool(rng.random() < p)
        if self._lost:
            return False
        self.has_estimate = True
        t, r = m.pose_error(rng)
        heading = rng.uniform(0.0, 2.0 * np.pi)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        error = np.array([t * np.cos(heading), t * np.sin(heading), sign * np.radians(r)])
        self.estimate = self._true + error
        self.estimate[2] = wrap_angle(self.estimate[2])
        keep = valid & (rng.random(len(d)) < m.coverage)
        z = d[keep] + rng.normal(0.0, m.depth_noise_m, int(keep.sum()))
        base = self.env.unwrapped
        camera = self._rays[keep] * z[:, None]
        if self.unseen is not None:
            camera = camera[~self._hidden(camera)]
        T_wc = base.camera_T_wc(self.estimate)
        points = camera @ T_wc[:3, :3].T + T_wc[:3, 3]
        self.fused_map.update(
            points,
            0.0,
            base.camera_height,
            camera_xy=T_wc[:2, 3],
            free_tol=self._occ.free_tol,
            obstacle_min=self._occ.obstacle_min,
        )
        return True

    def _hidden(self, camera: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which camera-frame points (N, 3) are obstacle points (at least the occupancy's
        ``obstacle_min`` above the floor) whose true cell is :attr:`unseen`."""
        spec = self.fused_map.spec
        T_true = self.env.unwrapped.camera_T_wc(self._true)
        world = camera @ T_true[:3, :3].T + T_true[:3, 3]
        cells = spec.world_to_cell(world[:, :2])
        inside = spec.contains(cells)
        hidden = np.zeros(len(world), bool)
        hidden[inside] = self.unseen[cells[inside, 0], cells[inside, 1]]
        return hidden & (world[:, 2] >= self._occ.obstacle_min)

    def _observe(self, obs: dict[str, NDArray], info: dict[str, Any], action: Any):
        """The observation and info of this frame (``action``: the step's, None after reset)."""
        from vgpnav_env.wrappers import navigation_observation

        depth = info["depth"] if info["depth"] is not None else self.env.unwrapped.render_depth()
        localized = self._perceive(depth)
        self.pose_state.update(self.estimate, localized, action)
        new_obs = navigation_observation(
            self.observation_space, self.estimate, obs["goal"], self.fused_map, localized, self.map_resolution
        )
        state = EstimateState(new_obs["pose"], localized, self._true, has_estimate=self.has_estimate)
        (self.measurements.reset if action is None else self.measurements.update)(state)
        if self.map_tracker is not None:
            if action is None:
                self.map_tracker.start(self.fused_map.spec, info)
            map_state = self.map_tracker.observe(self.fused_map.occupied(), {**info, "depth": depth})
            (self.map_measurements.reset if action is None else self.map_measurements.update)(map_state)
        info = dict(info)
        info.update(
            perception={"status": "localized" if localized else "lost", "mode": "model"},
            estimated_pose=self.estimate.copy(),
            map_spec=self.fused_map.spec,
            **self.measurements.metrics(),
            **(self.map_measurements.metrics() if self.map_tracker is not None else {}),
        )
        if self.env.unwrapped.render_mode is not None:
            self.env.unwrapped.set_overlay(estimated_pose=self.estimate, localized=localized)
        return new_obs, info
