"""The database a robot localizes against: posed RGB images, their VLAD index and a prior map.

:func:`open_database` (the one way to open one: once per process and settings) loads a database
run (:mod:`vgpnav_env.runs`; a build directory is accepted too and its ``database/`` run is used)
with :meth:`Database.open`, which computes once, caching under
``<run_dir>/index/`` keyed by :func:`vgpnav_env.runs.run_fingerprint` (a changed run invalidates
the cache; every file is written atomically):

- the classical backbone's features of every database image (:class:`StoredFeatures`: keypoints
  as float32 pixels and raw descriptors -- SIFT as uint8, ~0.2 MB per image at 1500 keypoints;
  XFeat as float16, ~0.07 MB per image at 512 -- keyed by the feature settings of the
  :class:`ClassicalConfig`, one file per kind). They are loaded into
  :attr:`Database.feature_cache`, which decodes them on demand, so a query never re-extracts a
  reference's features (the database is preprocessed, as a real system would);
- the VLAD index (:class:`~vgpnav_env.perception.retrieval.VladIndex`) of every database image,
  fitted on the stored features when it uses the backbone's SIFT features (the default);
- the PRIOR occupancy map (log-odds on a 0.05 m :class:`~vgpnav_env.grid.GridSpec` covering the
  database cameras + margin), built from database images and poses ONLY (never ground-truth
  depth or meshes): the classical backbone reconstructs every ``prior_stride``-th database frame
  against its pose neighbours; the metric scale comes from the known database baselines
  (metres / backbone units of the scale-linked pairs); the floor height is the median of the
  per-frame ground peaks; points are classified by height and fused like the online map.

Each step that computes shows a progress bar naming what it does; images are processed on the
backbone's threads (``ClassicalConfig.threads``). The prior's frames are independent (each is
reconstructed from stored features only) and mostly Python-bound, so they may also be spread over
processes (``open_database(..., processes=N)``; the caller's ``__main__`` must be importable
without side effects, as for any ``spawn`` process pool): this process and spawned helpers that open
the database from its cache take chunks of frames; the map is fused here in frame order, so it does
not depend on the process or thread count. On home (606 images, 2 cores) the three steps took
23 + 27 + 63 s before threads, shared features and the faster backbone; 10 + 8 + 11 s with them
and the prior on 2 processes.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Hashable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from vgpnav_env.atomic import atomic_write
from vgpnav_env.geometry import PinholeCamera, invert_pose, transform_points
from vgpnav_env.grid import GridSpec
from vgpnav_env.perception.backbones.classical import (
    ClassicalBackbone,
    ClassicalConfig,
    FeatureCache,
    Features,
    backbone_feature_settings,
    remember_features,
    rootsift,
)
from vgpnav_env.perception.backbones.stereo import SweepConfig
from vgpnav_env.perception.backbones.threads import configure_threads, cpu_share, thread_map
from vgpnav_env.perception.occupancy import LogOddsMap, OccupancyConfig
from vgpnav_env.perception.points import depth_points
from vgpnav_env.perception.resolution import MAX_WIDTH, downscale, working_camera, working_size
from vgpnav_env.perception.retrieval import VladConfig, VladIndex, nearby_cameras
from vgpnav_env.perception.scale_recovery import ground_peak
from vgpnav_env.robot import CAMERA_HEIGHT
from vgpnav_env.runs import Run, RunFormatError, load_run, read_run_meta, run_fingerprint

logger = logging.getLogger(__name__)

#: Bumped whenever the prior-map computation changes, so stale caches are not loaded.
PRIOR_VERSION = 1
_PRIOR_FILE = "prior.npz"
_PRIOR_META = "prior.json"
#: Bumped whenever the stored feature format changes.
FEATURES_VERSION = 1
#: Prior frames one task reconstructs (the unit of work spread over processes).
PRIOR_CHUNK = 4
#: Fewest prior frames per process for which helper processes are spawned: a helper needs ~2 s to
#: start and open the database, the time of ~20 frames on home at 320x240.
PRIOR_FRAMES_PER_PROCESS = 24
#: The stored features' files (arrays, metadata) and descriptor array name, by kind.
_FEATURE_FILES = {
    "rootsift": ("features.npz", "features.json", "sift"),
    "xfeat": ("features-xfeat.npz", "features-xfeat.json", "xfeat"),
}


@dataclass(frozen=True)
class DatabaseConfig:
    """How the database's index and prior map are computed (metres, degrees).

    ``prior``: ``"database"`` builds the prior map from the database run (cached on disk),
    ``"none"`` starts every map empty. The prior reconstructs every ``prior_stride``-th frame
    against up to ``prior_neighbours`` database frames whose centres lie ``prior_baseline``
    (min, max) metres away and whose optical axes differ by at most ``prior_max_angle_deg``;
    pixels with depth confidence >= ``prior_min_confidence`` and metric depth <=
    ``prior_max_depth`` enter the map, obstacles up to ``obstacle_max`` above the floor.
    The fused log-odds are clamped to +-``prior_clamp`` so that live observations can
    overturn the prior (the layout may have changed since the database was recorded).
    ``store_features``: extract the classical features of every database image once and cache
    them on disk (else they are extracted on first use); ``feature_cache_size`` decoded
    (RootSIFT, float32) images are kept in memory. ``prior_sweep``: the plane sweep the prior's
    frames are reconstructed with (the map's resolution, not the backbone's coarser default).
    ``max_width``: images wider than this many pixels are area-downscaled to it, database and
    queries alike (:mod:`~vgpnav_env.perception.resolution`; None: every image at its own size);
    the caches of a downscaled database live in ``index-WxH/`` beside the run's ``index/``.
    """

    vlad: VladConfig = field(default_factory=VladConfig)
    vlad_seed: int = 0
    prior: Literal["database", "none"] = "database"
    map_resolution: float = 0.05
    map_margin: float = 1.5
    prior_stride: int = 4
    prior_neighbours: int = 5
    prior_baseline: tuple[float, float] = (0.15, 2.0)
    prior_max_angle_deg: float = 40.0
    prior_min_confidence: float = 0.3
    prior_max_depth: float = 5.0
    prior_point_stride: int = 2
    obstacle_max: float = CAMERA_HEIGHT
    prior_clamp: float = 2.0
    feature_cache_size: int = 64
    store_features: bool = True
    prior_sweep: SweepConfig = field(default_factory=SweepConfig)
    max_width: int | None = MAX_WIDTH

    def __post_init__(self) -> None:
        if self.max_width is not None and self.max_width < 16:
            raise ValueError(f"max_width must be >= 16 pixels or None, got {self.max_width}")
        if self.prior not in ("database", "none"):
            raise ValueError(f"prior must be 'database' or 'none', got {self.prior!r}")
        if self.map_resolution <= 0 or self.map_margin < 0:
            raise ValueError("map_resolution must be > 0 and map_margin >= 0 metres")
        if (
            min(self.prior_stride, self.prior_neighbours, self.prior_point_stride, self.feature_cache_size)
            < 1
        ):
            raise ValueError(
                "prior_stride, prior_neighbours, prior_point_stride, feature_cache_size must be >= 1"
            )
        if not 0 <= self.prior_baseline[0] < self.prior_baseline[1]:
            raise ValueError(
                f"prior_baseline must be (min, max) with 0 <= min < max, got {self.prior_baseline}"
            )
        if self.prior_clamp <= 0 or self.obstacle_max <= 0 or self.prior_max_depth <= 0:
            raise ValueError("prior_clamp, obstacle_max and prior_max_depth must be positive")


def _prior_key(config: DatabaseConfig, backbone_config: ClassicalConfig) -> dict[str, Any]:
    keys = [k for k in asdict(config) if k.startswith("prior") or k in ("map_resolution", "map_margin")]
    keys.remove("prior_sweep")  # part of the backbone the prior runs (prior_backbone_config)
    return {
        "version": PRIOR_VERSION,
        "database": {k: asdict(config)[k] for k in keys} | {"obstacle_max": config.obstacle_max},
        # The thread count does not change the result, nor does the scene check (queries only).
        "backbone": {
            k: v
            for k, v in asdict(prior_backbone_config(config, backbone_config)).items()
            if k not in ("threads", "switch_share")
        },
    }


def prior_backbone_config(config: DatabaseConfig, backbone_config: ClassicalConfig) -> ClassicalConfig:
    """The classical backbone settings the prior map is reconstructed with: ``backbone_config`` with
    the map's sweep (``config.prior_sweep``: the prior's points come from the backbone's depth) and
    without the XFeat fallback (it would extract XFeat features of most database images while the
    database is prepared)."""
    return replace(backbone_config, sweep=config.prior_sweep, fallback_pairs=0)


def _jsonable_key(key: dict[str, Any]) -> Any:
    return json.loads(json.dumps(key))


def feature_settings(config: ClassicalConfig) -> dict[str, Any]:
    """The :class:`ClassicalConfig` fields that determine a reference's features (the store's key)."""
    return {"version": FEATURES_VERSION, **backbone_feature_settings(config)}


def _kind(settings: dict[str, Any]) -> str:
    return str(settings.get("features", "rootsift"))


class StoredFeatures(FeatureCache):
    """The classical features of every database image, compact in memory, as a :class:`FeatureCache`.

    Image ``i`` (key = database index) owns rows ``offsets[i]:offsets[i + 1]`` of ``keypoints``
    (float32 pixels, (n, 2)) and ``descriptors`` (raw: SIFT uint8 (n, 128) or XFeat float16 (n,
    64), as ``settings`` say); :meth:`get` decodes its :class:`Features` on demand (RootSIFT, or
    XFeat of images of ``image_size`` (width, height)) and keeps the ``max_items`` most recently
    used decoded images. Other keys behave as in a plain :class:`FeatureCache`. ``settings`` is the
    :func:`feature_settings` the features were extracted with.
    """

    def __init__(
        self,
        keypoints: NDArray[np.float32],
        descriptors: NDArray[Any],
        offsets: NDArray[np.int64],
        settings: dict[str, Any],
        max_items: int = 64,
        image_size: tuple[int, int] = (0, 0),
    ) -> None:
        super().__init__(max_items)
        offsets = np.asarray(offsets, np.int64)
        dim, dtype = (128, np.uint8) if _kind(settings) == "rootsift" else (64, np.float16)
        if (
            keypoints.ndim != 2
            or keypoints.shape[1] != 2
            or descriptors.shape != (len(keypoints), dim)
            or descriptors.dtype != dtype
            or offsets.ndim != 1
            or len(offsets) < 1
            or offsets[0] != 0
            or offsets[-1] != len(keypoints)
            or np.any(np.diff(offsets) < 0)
        ):
            raise ValueError(
                f"need keypoints (n, 2), {np.dtype(dtype)} descriptors (n, {dim}) and non-decreasing "
                f"offsets from 0 to n; got {keypoints.shape}, {descriptors.dtype} {descriptors.shape}, "
                f"offsets of length {len(offsets)}"
            )
        self.keypoints = keypoints.astype(np.float32, copy=False)
        self.descriptors = descriptors
        self.offsets = offsets
        self.settings = settings
        self.image_size = (int(image_size[0]), int(image_size[1]))

    @property
    def kind(self) -> str:
        """The features' kind: "rootsift" or "xfeat"."""
        return _kind(self.settings)

    @property
    def sift(self) -> NDArray[Any]:
        """The raw descriptors (the name of the RootSIFT store's array)."""
        return self.descriptors

    @property
    def n_images(self) -> int:
        return len(self.offsets) - 1

    @property
    def nbytes(self) -> int:
        """Bytes held by the compact store (decoded images come on top: ~0.8 MB each)."""
        return int(self.keypoints.nbytes + self.descriptors.nbytes + self.offsets.nbytes)

    def _stored(self, key: Hashable) -> bool:
        return isinstance(key, int | np.integer) and not isinstance(key, bool) and 0 <= key < self.n_images

    def __contains__(self, key: Hashable) -> bool:
        return self._stored(key) or super().__contains__(key)

    def get(self, key: Hashable) -> Features | None:
        features = super().get(key)
        if features is None and self._stored(key):
            features = self.decoded(int(key))
            self.put(key, features)
        return features

    @classmethod
    def extract(
        cls,
        images: NDArray[np.uint8],
        backbone: ClassicalBackbone,
        max_items: int = 64,
        progress: bool = False,
    ) -> StoredFeatures:
        """Detect the features of every image (M, H, W, 3) with the backbone's settings, on the
        backbone's ``threads``; ``progress`` shows a progress bar."""
        name = "SIFT" if backbone.config.features == "rootsift" else "XFeat"
        with tqdm(
            total=len(images),
            desc=f"database features: {name} of {len(images)} images",
            unit="image",
            disable=not progress,
        ) as bar:

            def detect(image: NDArray[np.uint8]) -> tuple[NDArray[np.float32], NDArray[Any]]:
                found = backbone.detect(image)
                bar.update()
                return found

            detected = thread_map(detect, images, backbone.config.threads)
        offsets = np.concatenate([[0], np.cumsum([len(k) for k, _ in detected])]).astype(np.int64)
        keypoints = np.concatenate([k for k, _ in detected]) if detected else np.zeros((0, 2), np.float32)
        settings = feature_settings(backbone.config)
        empty = (
            np.zeros((0, 128), np.uint8) if _kind(settings) == "rootsift" else np.zeros((0, 64), np.float16)
        )
        descriptors = np.concatenate([d for _, d in detected]) if detected else empty
        size = (images.shape[2], images.shape[1]) if np.ndim(images) == 4 else (0, 0)
        return cls(keypoints, descriptors, offsets, settings, max_items, size)

    def decoded(self, key: int) -> Features:
        """Image ``key``'s :class:`Features`, decoded without entering the cache."""
        a, b = self.offsets[key], self.offsets[key + 1]
        if self.kind == "rootsift":
            return Features.from_sift(self.keypoints[a:b], self.descriptors[a:b])
        return Features.from_xfeat(self.keypoints[a:b], self.descriptors[a:b], self.image_size)

    def save(self, directory: str | os.PathLike, fingerprint: str) -> None:
        """Write the kind's arrays and metadata (``features.npz`` + ``features.json`` for RootSIFT;
        each atomically) for the run ``fingerprint``."""
        d = Path(directory)
        arrays_name, meta_name, array = _FEATURE_FILES[self.kind]
        arrays = {
            "keypoints": self.keypoints,
            array: self.descriptors,
            "offsets": self.offsets,
            "image_size": np.array(self.image_size),
            "fingerprint": np.array(fingerprint),
        }
        atomic_write(d / arrays_name, lambda f: np.savez(f, **arrays))
        meta = {"fingerprint": fingerprint, "settings": self.settings, "n_images": self.n_images}
        atomic_write(d / meta_name, lambda f: f.write(json.dumps(meta, indent=2).encode()))

    @classmethod
    def load(
        cls, directory: str | os.PathLike, fingerprint: str, settings: dict[str, Any], max_items: int = 64
    ) -> StoredFeatures | None:
        """The stored features, or None when missing, unreadable, of another run or other settings."""
        d = Path(directory)
        arrays_name, meta_name, array = _FEATURE_FILES[_kind(settings)]
        meta_file, arrays_file = d / meta_name, d / arrays_name
        if not (meta_file.is_file() and arrays_file.is_file()):
            return None
        try:
            meta = json.loads(meta_file.read_text())
            if meta.get("fingerprint") != fingerprint or meta.get("settings") != _jsonable_key(settings):
                return None
            with np.load(arrays_file) as z:
                if str(z["fingerprint"]) != fingerprint:
                    return None
                size = tuple(z["image_size"]) if "image_size" in z else (0, 0)
                return cls(z["keypoints"], z[array], z["offsets"], settings, max_items, size)
        except (OSError, KeyError, ValueError) as e:
            logger.warning("ignoring unreadable feature cache in %s: %s", d, e)
            return None


@dataclass(eq=False)
class Database:
    """A database run with its retrieval index, a classical feature cache and the prior map.

    ``prior`` is the prior log-odds map (None with ``config.prior="none"``); ``z_ground`` the
    floor height estimated from the database (world frame, metres; nan without a prior);
    ``timings`` how long the features, index and prior took to load or compute (wall seconds;
    ``<step>_cpu``: the process's CPU seconds, all threads). ``feature_cache`` holds the backbone's
    features (of kind ``feature_kind``); retrieval's RootSIFT of references live there too when the
    backbone's features are RootSIFT, else in ``retrieval_cache``. ``run`` holds the images at the
    size perception works at (``config.max_width``); ``cache_dir`` the caches of that size
    (:func:`index_dir`).
    """

    path: Path
    run: Run
    index: VladIndex
    fingerprint: str
    config: DatabaseConfig
    map_spec: GridSpec
    feature_cache: FeatureCache
    cache_dir: Path
    prior: LogOddsMap | None = None
    z_ground: float = float("nan")
    timings: dict[str, float] = field(default_factory=dict)
    feature_kind: str = "rootsift"
    retrieval_cache: FeatureCache = field(default_factory=FeatureCache)
    other_features: dict[str, FeatureCache] = field(default_factory=dict)

    @property
    def poses(self) -> NDArray[np.float64]:
        """(M, 4, 4) ``T_wi`` of the database cameras."""
        return self.run.poses

    @property
    def images(self) -> NDArray[np.uint8]:
        return self.run.images

    @property
    def camera(self) -> PinholeCamera:
        return self.run.camera

    def __len__(self) -> int:
        return len(self.run)

    def features_for(
        self, config: ClassicalConfig, progress: bool = True, every: bool = True
    ) -> FeatureCache:
        """The feature cache a classical backbone with ``config`` shares with this database.

        Features of another kind than the database's backbone's (``config.features``, e.g. XFeat
        beside RootSIFT) are loaded from their own cache file; when none is stored, ``every``
        extracts and stores every image's once (``progress``: a progress bar), else (a fallback
        that matches few references) they are extracted on first use and kept in memory
        (``feature_cache_size`` images). Raises ValueError when the stored features of
        ``config``'s kind were extracted with other settings (:func:`feature_settings`): open the
        database with that ``backbone_config`` instead.
        """
        if config.features == self.feature_kind:
            store = self.feature_cache
        else:
            store = self.other_features.get(config.features)
            stored = isinstance(store, StoredFeatures)
            if store is None or (every and self.config.store_features and not stored):
                store = _open_features(
                    self.cache_dir, self.run, self.fingerprint, self.config, config, progress, every
                )
                self.other_features[config.features] = store
        if isinstance(store, StoredFeatures) and store.settings != feature_settings(config):
            raise ValueError(
                f"the database's stored features were extracted with {store.settings}, the backbone "
                f"uses {feature_settings(config)}: open the database with the backbone's "
                "ClassicalConfig (open_database(..., backbone_config=...))"
            )
        return store

    def reference_features(self, i: int) -> Features:
        """Database image ``i``'s RootSIFT features with the index's feature settings (stored, else
        extracted and kept in :attr:`feature_cache`)."""
        cache = self.feature_cache if self.feature_kind == "rootsift" else self.retrieval_cache
        features = cache.get(i)
        if features is None:
            features = rootsift(self.images[i], self.index.sift)
            cache.put(i, features)
        return features

    def new_map(self, config: OccupancyConfig | None = None) -> LogOddsMap:
        """A fresh log-odds map over :attr:`map_spec` fusing with ``config``'s ``l_free``, ``l_occ``
        and ``clamp``: starting from the prior's log-odds times ``config.prior_weight``, or empty."""
        c = config or OccupancyConfig()
        if self.prior is None:
            return LogOddsMap(self.map_spec, c.l_free, c.l_occ, c.clamp)
        prior = self.prior.logodds * c.prior_weight
        return LogOddsMap.from_prior(self.map_spec, prior, c.l_free, c.l_occ, c.clamp)

    @classmethod
    def open(
        cls,
        run_dir: str | os.PathLike,
        *,
        config: DatabaseConfig | None = None,
        backbone_config: ClassicalConfig | None = None,
        progress: bool = True,
        processes: int = 1,
    ) -> Database:
        """Load the database run at ``run_dir`` (or ``<build>/database``) with its cached index and prior.

        ``backbone_config`` configures the classical backbone used for the features and the prior
        (default :class:`ClassicalConfig`). What is computed (not loaded) shows a progress bar per
        step unless ``progress`` is False. ``processes``: how many processes reconstruct the prior
        map when it is computed (this one and spawned helpers: :func:`reconstruct_prior_frames`;
        the map does not depend on it). Raises :class:`~vgpnav_env.runs.RunFormatError` if the
        directory is not a readable run.
        """
        config = config or DatabaseConfig()
        backbone_config = backbone_config or ClassicalConfig()
        path = database_run_dir(run_dir)
        run = load_run(path)
        if run.metadata.get("kind") not in (None, "database"):
            raise RunFormatError(f"{path}: is a {run.metadata.get('kind')!r} run, expected a database run")
        fingerprint = run_fingerprint(path)
        cache = index_dir(path, config)
        cache.mkdir(exist_ok=True)
        run = _working_run(run, config.max_width)
        timings: dict[str, float] = {}

        xy = run.positions[:, :2]
        spec = GridSpec.covering(xy.min(axis=0), xy.max(axis=0), config.map_resolution, config.map_margin)
        t0, c0 = time.perf_counter(), time.process_time()
        feature_cache = _open_features(cache, run, fingerprint, config, backbone_config, progress)
        if config.store_features:
            timings["features"] = time.perf_counter() - t0
            timings["features_cpu"] = time.process_time() - c0

        t0, c0 = time.perf_counter(), time.process_time()
        index = VladIndex.load(cache, expected_fingerprint=fingerprint, sift=backbone_config)
        if index is None or index.config != config.vlad:
            logger.info("fitting the VLAD index of %d database images (%s)", len(run), path)
            stored = None
            if (
                config.vlad.local_features == "sift"
                and isinstance(feature_cache, StoredFeatures)
                and feature_cache.kind == "rootsift"
            ):
                stored = [feature_cache.decoded(i).descriptors for i in range(len(run))]
            index = VladIndex.fit(
                list(run.images),
                config=config.vlad,
                seed=config.vlad_seed,
                fingerprint=fingerprint,
                sift=backbone_config,
                descriptors=stored,
                threads=backbone_config.threads,
                progress=progress,
            )
            index.save(cache)
        timings["index"] = time.perf_counter() - t0
        timings["index_cpu"] = time.process_time() - c0

        db = cls(
            path,
            run,
            index,
            fingerprint,
            config,
            spec,
            feature_cache,
            cache,
            timings=timings,
            feature_kind=backbone_config.features,
        )
        if config.prior == "database":
            t0, c0 = time.perf_counter(), time.process_time()
            db._load_or_build_prior(cache, backbone_config, progress, processes)
            timings["prior"] = time.perf_counter() - t0
            timings["prior_cpu"] = time.process_time() - c0
        return db

    def _load_or_build_prior(
        self, cache: Path, backbone_config: ClassicalConfig, progress: bool, processes: int
    ) -> None:
        key = _jsonable_key(_prior_key(self.config, backbone_config))
        meta_file, arrays_file = cache / _PRIOR_META, cache / _PRIOR_FILE
        if meta_file.is_file() and arrays_file.is_file():
            try:
                meta = json.loads(meta_file.read_text())
                with np.load(arrays_file) as z:
                    if (
                        meta.get("fingerprint") == self.fingerprint
                        and meta.get("key") == key
                        and str(z["fingerprint"]) == self.fingerprint
                        and tuple(z["logodds"].shape) == self.map_spec.shape
                    ):
                        self.prior = LogOddsMap.from_prior(self.map_spec, z["logodds"])
                        self.z_ground = float(z["z_ground"])
                        return
            except (OSError, KeyError, ValueError) as e:
                logger.warning("ignoring unreadable prior map cache in %s: %s", cache, e)
        logger.info(
            "building the prior map from %d database frames",
            len(range(0, len(self), self.config.prior_stride)),
        )
        self.prior, self.z_ground, stats = build_prior(
            self,
            ClassicalBackbone(prior_backbone_config(self.config, backbone_config), self.feature_cache),
            progress=progress,
            processes=processes,
        )
        atomic_write(
            arrays_file,
            lambda f: np.savez(
                f, logodds=self.prior.logodds, z_ground=self.z_ground, fingerprint=np.array(self.fingerprint)
            ),
        )
        meta = {"fingerprint": self.fingerprint, "key": key, "stats": stats}
        atomic_write(meta_file, lambda f: f.write(json.dumps(meta, indent=2).encode()))


def _open_features(
    cache: Path,
    run: Run,
    fingerprint: str,
    config: DatabaseConfig,
    backbone_config: ClassicalConfig,
    progress: bool,
    extract: bool = True,
) -> FeatureCache:
    """The database images' features with ``backbone_config``'s settings: loaded from ``cache``,
    else extracted and saved there; an empty :class:`FeatureCache` (features extracted on first
    use) without ``store_features``, or when none are stored and not ``extract``."""
    if not config.store_features:
        return FeatureCache(config.feature_cache_size)
    settings = feature_settings(backbone_config)
    store = StoredFeatures.load(cache, fingerprint, settings, config.feature_cache_size)
    missing = store is None or store.n_images != len(run)
    if missing and not extract:
        return FeatureCache(config.feature_cache_size)
    if missing:
        logger.info("extracting the %s features of %d database images", backbone_config.features, len(run))
        backbone = ClassicalBackbone(backbone_config)
        store = StoredFeatures.extract(run.images, backbone, config.feature_cache_size, progress=progress)
        store.save(cache, fingerprint)
    return store


def _working_run(run: Run, max_width: int | None) -> Run:
    """``run`` with its images at the size perception works at (:func:`working_camera`)."""
    camera = working_camera(run.camera, max_width)
    if camera == run.camera:
        return run
    images = np.stack([downscale(image, camera) for image in run.images])
    return Run(images, run.poses, camera, run.metadata | {"width": camera.width, "height": camera.height})


def index_dir(run_dir: str | os.PathLike, config: DatabaseConfig | None = None) -> Path:
    """The cache directory of the database run at ``run_dir`` (or a build's ``database/``) opened
    with ``config``: ``index/`` when perception works at the images' own size, else
    ``index-WxH/`` (W x H the size they are downscaled to, ``DatabaseConfig.max_width``)."""
    path = database_run_dir(run_dir)
    meta = read_run_meta(path)
    width, height = int(meta["width"]), int(meta["height"])
    size = working_size(width, height, (config or DatabaseConfig()).max_width)
    return path / ("index" if size == (width, height) else f"index-{size[0]}x{size[1]}")


def database_run_dir(path: str | os.PathLike) -> Path:
    """The database run of a build directory (``<build>/database``), else ``path`` itself."""
    path = Path(path)
    if (path / "summary.json").is_file() and (path / "database").is_dir():
        return path / "database"
    return path


#: Databases opened in this process by :func:`open_database`, by (directory, settings).
_OPEN: dict[tuple[str, str, str], Database] = {}


def open_database(
    path: str | os.PathLike,
    config: DatabaseConfig | None = None,
    backbone_config: ClassicalConfig | None = None,
    processes: int = 1,
) -> Database:
    """The database at ``path`` (a database run or a build directory), opened once per process.

    The one way to open a database: :meth:`Database.open` (index, stored features and prior
    map from the on-disk cache, computed when missing, the prior on ``processes`` processes) on
    the first call for a directory and settings (defaults: :class:`DatabaseConfig`,
    :class:`ClassicalConfig`), the same object after that. A run changed on disk while the
    process runs is not noticed.
    """
    path = database_run_dir(Path(path).resolve())
    config, backbone_config = config or DatabaseConfig(), backbone_config or ClassicalConfig()
    key = (str(path), repr(config), repr(backbone_config))
    if key not in _OPEN:
        _OPEN[key] = Database.open(path, config=config, backbone_config=backbone_config, processes=processes)
    return _OPEN[key]


def prior_neighbours(poses: NDArray[np.float64], j: int, config: DatabaseConfig) -> NDArray[np.int64]:
    """Up to ``prior_neighbours`` database frames overlapping frame ``j``, widest baseline first.

    Candidates are the :func:`nearby_cameras` ``prior_baseline`` metres away with optical axes
    within ``prior_max_angle_deg``; they are picked greedily to spread the baselines (farthest
    from the already picked ones).
    """
    lo, hi = config.prior_baseline
    near = nearby_cameras(poses, poses[j], hi, config.prior_max_angle_deg, min_distance=lo)
    if len(near.index) == 0:
        return near.index
    # Score overlap: close in angle and moderate in distance; then greedy spread.
    c = poses[:, :3, 3]
    score = near.cos_angle - 0.2 * near.distance
    cand = near.index[np.argsort(-score)][: 4 * config.prior_neighbours]
    picked = [int(cand[0])]
    while len(picked) < min(config.prior_neighbours, len(cand)):
        gap = np.min(np.linalg.norm(c[cand][:, None] - c[picked][None], axis=2), axis=1)
        gap[np.isin(cand, picked)] = -np.inf
        picked.append(int(cand[int(np.argmax(gap))]))
    return np.array(picked, np.int64)


@dataclass(frozen=True)
class PriorFrame:
    """One reconstructed prior frame: its metric camera-frame points (n, 3) (OpenCV frame, metres)
    and, when its ground peak was found, the floor's world height (metres)."""

    points: NDArray[np.float64]
    ground_z: float | None


def reconstruct_prior_frame(db: Database, backbone: ClassicalBackbone, j: int) -> PriorFrame | None:
    """Database frame ``j`` reconstructed against its :func:`prior_neighbours` and scaled by their
    known baselines (module docstring); None when it has too few neighbours, scale-linked pairs
    or confident points. Depends on ``j`` and the database only (not on frames done before)."""
    cfg = db.config
    refs = prior_neighbours(db.poses, j, cfg)
    if len(refs) < 2:
        return None
    if j in backbone.feature_cache:
        remember_features(db.images[j], backbone.config, backbone.feature_cache.get(j))
    out = backbone(
        db.images[j], [db.images[i] for i in refs], db.camera, reference_keys=[int(i) for i in refs]
    )
    ok = out.scale_valid & (out.confidence > 0)
    if not ok.any():
        return None
    T_ji = invert_pose(db.poses[j]) @ db.poses[refs]  # reference i -> query j, metric
    metric = np.linalg.norm(T_ji[ok, :3, 3], axis=1)
    units = np.linalg.norm(out.T_qi[ok, :3, 3], axis=1)
    good = units > 1e-9
    if not good.any():
        return None
    scale = float(np.median(metric[good] / units[good]))
    pts, conf = depth_points(
        db.camera,
        out.query_depth * scale,
        out.query_depth_confidence,
        stride=cfg.prior_point_stride,
        min_confidence=cfg.prior_min_confidence,
        max_depth=cfg.prior_max_depth,
    )
    if len(pts) < 50:
        return None
    g = ground_peak(pts, db.poses[j][:3, :3], conf)
    return PriorFrame(pts, float(db.poses[j][2, 3] + g.height_b) if g.found else None)


#: A prior helper process's database and backbone (set by :func:`_start_prior_helper`).
_HELPER: tuple[Database, ClassicalBackbone] | None = None


def _start_prior_helper(
    path: str, config: DatabaseConfig, backbone_config: ClassicalConfig, threads: int
) -> None:
    """Initializer of a prior helper process: ``threads`` threads, the database from its cache."""
    global _HELPER
    configure_threads(threads=threads)
    db = Database.open(
        path, config=replace(config, prior="none"), backbone_config=backbone_config, progress=False
    )
    _HELPER = (db, ClassicalBackbone(prior_backbone_config(config, backbone_config), db.feature_cache))


def _reconstruct_in_helper(frames: Sequence[int]) -> list[PriorFrame | None]:
    assert _HELPER is not None, "not a prior helper process"
    db, backbone = _HELPER
    return [reconstruct_prior_frame(db, backbone, j) for j in frames]


def _advance(bar: tqdm, n: int, future: Future) -> None:
    if not future.cancelled():
        bar.update(n)


def reconstruct_prior_frames(
    db: Database,
    backbone: ClassicalBackbone,
    frames: Sequence[int],
    processes: int = 1,
    progress: bool = False,
) -> list[PriorFrame | None]:
    """:func:`reconstruct_prior_frame` of each of ``frames``, in order, on up to ``processes``
    processes (this one plus spawned helpers, each on its share of this process's threads; helpers
    only for at least :data:`PRIOR_FRAMES_PER_PROCESS` frames each). Helpers take chunks of
    :data:`PRIOR_CHUNK` frames from the front; this process takes the chunks not yet started from
    the back, so whoever is faster does more. ``progress`` shows a progress bar."""
    frames = list(frames)
    chunks = [frames[i : i + PRIOR_CHUNK] for i in range(0, len(frames), PRIOR_CHUNK)]
    processes = max(1, min(processes, len(frames) // PRIOR_FRAMES_PER_PROCESS))
    threads = max(1, cpu_share() // processes)
    done: list[list[PriorFrame | None] | None] = [None] * len(chunks)
    desc = f"prior map: reconstructing {len(frames)} database frames"
    with tqdm(total=len(frames), desc=desc, unit="frame", disable=not progress) as bar:

        def here(i: int, backbone: ClassicalBackbone) -> None:
            done[i] = [reconstruct_prior_frame(db, backbone, j) for j in chunks[i]]
            bar.update(len(chunks[i]))

        if processes == 1:
            for i in range(len(chunks)):
                here(i, backbone)
            return [frame for chunk in done for frame in chunk or []]
        local = ClassicalBackbone(replace(backbone.config, threads=threads), backbone.feature_cache)
        setup = (str(db.path), db.config, backbone.config, threads)
        pool = ProcessPoolExecutor(
            processes - 1, get_context("spawn"), initializer=_start_prior_helper, initargs=setup
        )
        try:
            futures = [pool.submit(_reconstruct_in_helper, chunk) for chunk in chunks]
            for future, chunk in zip(futures, chunks, strict=True):
                future.add_done_callback(partial(_advance, bar, len(chunk)))
            for i in reversed(range(len(chunks))):
                if futures[i].cancel():
                    here(i, local)
            helped = [i for i in range(len(chunks)) if done[i] is None]
            for i in helped:
                done[i] = futures[i].result()
            logger.info(
                "prior map: %d of %d frames reconstructed in %d helper processes",
                sum(len(chunks[i]) for i in helped),
                len(frames),
                processes - 1,
            )
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    return [frame for chunk in done for frame in chunk or []]


def build_prior(
    db: Database, backbone: ClassicalBackbone, progress: bool = False, processes: int = 1
) -> tuple[LogOddsMap, float, dict[str, Any]]:
    """The prior log-odds map, the estimated floor height and build statistics (see module docstring).

    A frame's features come from the backbone's feature cache (the database's stored features)
    when it holds them; the frames are reconstructed on ``processes`` processes (see
    :func:`reconstruct_prior_frames`) and fused here in frame order;
    ``progress`` shows a progress bar over the frames."""
    cfg = db.config
    t0 = time.perf_counter()
    tried = range(0, len(db), cfg.prior_stride)
    reconstructed = reconstruct_prior_frames(db, backbone, tried, processes, progress)
    frames = [(j, f.points) for j, f in zip(tried, reconstructed, strict=True) if f is not None]
    ground_z = [f.ground_z for f in reconstructed if f is not None and f.ground_z is not None]
    z_ground = float(np.median(ground_z)) if ground_z else 0.0
    fused = LogOddsMap(db.map_spec)
    for j, pts in frames:
        T = db.poses[j]
        fused.update(transform_points(T, pts), z_ground, cfg.obstacle_max, camera_xy=T[:2, 3])
    prior = LogOddsMap.from_prior(db.map_spec, np.clip(fused.logodds, -cfg.prior_clamp, cfg.prior_clamp))
    stats = {
        "frames_used": len(frames),
        "frames_tried": len(tried),
        "ground_estimates": len(ground_z),
        "z_ground": z_ground,
        "seconds": time.perf_counter() - t0,
    }
    logger.info("prior map: %s", stats)
    return prior, z_ground, stats
