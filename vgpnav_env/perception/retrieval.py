"""Global image retrieval: DenseVLAD descriptors and the geometry-aware reference selection.

- :class:`VladIndex` turns pixels into one global descriptor per image: VLAD over local RootSIFT
  descriptors (a k-means vocabulary learned on the database, intra-normalisation then L2,
  optional PCA-whitening), optionally concatenated with a coarse colour layout (hue-saturation
  histograms of a 2x2 image grid), which helps tell rooms apart in rendered indoor scenes.
  Similarity = dot product of descriptors (cosine, in [-1, 1]). The local descriptors are the
  classical backbone's SIFT features (``local_features="sift"``, default: the database's stored
  features fit the index and a query's features are extracted once for retrieval and backbone)
  or DenseVLAD's dense grid (``"dense"``).
- :func:`geometric_rerank` (optional, ``RetrievalConfig.rerank``) re-scores the top-N VLAD
  candidates by how many feature matches one epipolar geometry explains (hloc-style
  verification against the database's stored features);
- :func:`select_references` is the paper's Alg. 1 (geometry-aware retrieval) or plain top-k.

Database poses ``T_w`` are ``T_wi`` (camera i -> world, OpenCV camera, metres).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from tqdm import tqdm

from vgpnav_env.atomic import atomic_write
from vgpnav_env.geometry import PinholeCamera, transform_points
from vgpnav_env.perception.backbones.classical import (
    ClassicalConfig,
    Features,
    match_descriptors,
    rootsift,
    sift_settings,
)
from vgpnav_env.perception.backbones.threads import resolve_threads, thread_map

#: Bumped whenever the descriptor computation changes, so stale caches are not loaded.
FORMAT_VERSION = 3
_ARRAYS_FILE = "vlad_index.npz"
_META_FILE = "vlad_index.json"


@dataclass(frozen=True)
class VladConfig:
    """Descriptor settings.

    ``local_features="dense"`` (DenseVLAD, default): images are converted to grey and resized so
    the longer side is ``max_side`` pixels; SIFT descriptors are computed on a dense grid
    (``grid_step`` pixels apart) at every patch size in ``patch_sizes`` (pixels, SIFT keypoint
    diameter) and RootSIFT-normalised. ``"sift"``: the classical backbone's RootSIFT features
    (the :class:`~vgpnav_env.perception.backbones.classical.ClassicalConfig` feature settings given
    to :meth:`VladIndex.fit`): the index is fitted on the database's stored features and a query's
    features are extracted once for retrieval and backbone. ``n_words`` k-means words are learned
    from at most ``max_training_descriptors`` descriptors. ``power_norm`` applies signed square
    roots to the VLAD residuals (burstiness). ``colour_weight`` w > 0 appends the colour layout so
    that the similarity is ``(vlad . vlad' + w colour . colour') / (1 + w)``; 0 = pure VLAD.
    """

    local_features: Literal["dense", "sift"] = "dense"
    max_side: int = 160
    grid_step: int = 6
    patch_sizes: tuple[int, ...] = (8,)
    n_words: int = 64
    max_training_descriptors: int = 60000
    kmeans_iterations: int = 40
    power_norm: bool = True
    whiten: bool = False
    whiten_dim: int = 256
    colour_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.local_features not in ("sift", "dense"):
            raise ValueError(f"local_features must be 'sift' or 'dense', got {self.local_features!r}")
        if self.max_side < 32:
            raise ValueError(f"max_side must be >= 32 pixels, got {self.max_side}")
        if self.grid_step < 1 or not self.patch_sizes or min(self.patch_sizes) < 2:
            raise ValueError(
                f"grid_step must be >= 1 and patch_sizes non-empty with sizes >= 2, "
                f"got {self.grid_step}, {self.patch_sizes}"
            )
        if self.n_words < 2:
            raise ValueError(f"n_words must be >= 2, got {self.n_words}")
        if self.whiten_dim < 1:
            raise ValueError(f"whiten_dim must be >= 1, got {self.whiten_dim}")
        if self.colour_weight < 0:
            raise ValueError(f"colour_weight must be >= 0, got {self.colour_weight}")


def _to_grey(image: ArrayLike, max_side: int) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"images must be uint8 (HxWx3 RGB or HxW grey), got dtype {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    elif img.ndim != 2:
        raise ValueError(f"images must be HxWx3 RGB or HxW grey, got shape {img.shape}")
    h, w = img.shape
    f = max_side / max(h, w)
    if f < 1.0:
        img = cv2.resize(img, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    return img


class _DenseRootSift:
    """RootSIFT descriptors (n, 128) float32 on a dense grid of an image (grey, ``max_side``)."""

    def __init__(self, config: VladConfig) -> None:
        self._config = config
        self._local = threading.local()  # one OpenCV SIFT per thread
        self._grids: dict[tuple[int, int], list[cv2.KeyPoint]] = {}
        self._lock = threading.Lock()

    def _keypoints(self, h: int, w: int) -> list[cv2.KeyPoint]:
        with self._lock:
            if (h, w) not in self._grids:
                c = self._config
                kps = []
                for size in c.patch_sizes:
                    m = size / 2.0
                    ys = np.arange(m, h - m + 1e-9, c.grid_step)
                    xs = np.arange(m, w - m + 1e-9, c.grid_step)
                    kps += [cv2.KeyPoint(float(x), float(y), float(size)) for y in ys for x in xs]
                self._grids[(h, w)] = kps
            return self._grids[(h, w)]

    def __call__(self, image: ArrayLike) -> NDArray[np.float32]:
        grey = _to_grey(image, self._config.max_side)
        kps = self._keypoints(*grey.shape)
        if not kps:
            return np.zeros((0, 128), np.float32)
        sift = getattr(self._local, "sift", None)
        if sift is None:
            sift = self._local.sift = cv2.SIFT_create()
        _, desc = sift.compute(grey, kps)
        if desc is None:
            return np.zeros((0, 128), np.float32)
        desc = desc.astype(np.float32)
        desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)
        return np.sqrt(desc)


class _SparseRootSift:
    """The classical backbone's RootSIFT descriptors (n, 128) float32 of an image
    (:func:`~vgpnav_env.perception.backbones.classical.rootsift`, shared with the backbone)."""

    def __init__(self, sift: ClassicalConfig) -> None:
        self.sift = sift

    def __call__(self, image: ArrayLike) -> NDArray[np.float32]:
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
            raise ValueError(f"images must be uint8 HxWx3 RGB or HxW grey, got {img.dtype} {img.shape}")
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        return rootsift(img, self.sift).descriptors


def _colour_layout(image: ArrayLike, grid: int = 2) -> NDArray[np.float32]:
    """Unit-norm colour layout: square-rooted 8x4 hue-saturation histograms of a grid x grid split."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    hsv = cv2.cvtColor(cv2.resize(img, (64, 48), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2HSV)
    parts = []
    for rows in np.array_split(np.arange(48), grid):
        for cols in np.array_split(np.arange(64), grid):
            cell = np.ascontiguousarray(hsv[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1])
            h = cv2.calcHist([cell], [0, 1], None, [8, 4], [0, 180, 0, 256]).ravel()
            parts.append(np.sqrt(h / max(float(h.sum()), 1e-12)))
    v = np.concatenate(parts).astype(np.float32)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _vlad(desc: NDArray[np.float32], centres: NDArray[np.float32], power_norm: bool) -> NDArray[np.float32]:
    """Intra-normalised, L2-normalised VLAD (K*128,) of local descriptors (n, 128)."""
    K, D = centres.shape
    if len(desc) == 0:
        return np.zeros(K * D, np.float32)
    d2 = (desc**2).sum(1)[:, None] - 2.0 * desc @ centres.T + (centres**2).sum(1)[None, :]
    words = np.argmin(d2, axis=1)
    V = np.zeros((K, D), np.float32)
    np.add.at(V, words, desc)
    V -= np.bincount(words, minlength=K)[:, None].astype(np.float32) * centres
    if power_norm:
        V = np.sign(V) * np.sqrt(np.abs(V))
    V /= np.maximum(np.linalg.norm(V, axis=1, keepdims=True), 1e-12)
    v = V.ravel()
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _vocabulary(
    descriptors: Sequence[NDArray[np.float32]], config: VladConfig, seed: int, threads: int = 1
) -> NDArray[np.float32]:
    """``config.n_words`` k-means centres (seeded) of a sample of the local descriptors; OpenCV's
    k-means runs on ``threads`` threads (<= 0: the process's share; the centres do not depend on it)."""
    stacked = np.concatenate(descriptors, axis=0)
    if len(stacked) < config.n_words:
        raise ValueError(
            f"only {len(stacked)} local descriptors for {config.n_words} words: "
            "use larger or more textured images, a smaller grid_step or fewer n_words"
        )
    rng = np.random.default_rng(seed)
    if len(stacked) > config.max_training_descriptors:
        stacked = stacked[rng.choice(len(stacked), config.max_training_descriptors, replace=False)]
    cv2.setRNGSeed(int(rng.integers(2**31 - 1)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, config.kmeans_iterations, 1e-4)
    before = cv2.getNumThreads()  # one big call: OpenCV's own pool (configure_threads gives it 1)
    cv2.setNumThreads(resolve_threads(threads))
    try:
        _, _, centres = cv2.kmeans(
            np.ascontiguousarray(stacked, np.float32),
            config.n_words,
            None,
            criteria,
            1,
            cv2.KMEANS_PP_CENTERS,
        )
    finally:
        cv2.setNumThreads(before)
    return centres.astype(np.float32)


@dataclass
class VladIndex:
    """A learned VLAD vocabulary (+ optional whitening) and the database's descriptors.

    Build with :meth:`fit`; ``database`` holds the (M, D) descriptors of the fitting images
    in order, so ``similarity(query)`` gives one score per database image.
    """

    config: VladConfig
    centres: NDArray[np.float32]
    database: NDArray[np.float32]
    fingerprint: str = ""
    pca_mean: NDArray[np.float32] | None = None
    pca_projection: NDArray[np.float32] | None = None
    sift: ClassicalConfig = field(default_factory=ClassicalConfig)
    _extractor: Callable[[ArrayLike], NDArray[np.float32]] | None = field(
        default=None, repr=False, compare=False
    )

    @property
    def dim(self) -> int:
        """Length of a global descriptor."""
        return int(self.database.shape[1])

    def local_descriptors(self, image: ArrayLike) -> NDArray[np.float32]:
        """Unit local descriptors (n, 128) of one uint8 RGB (HxWx3) or grey (HxW) image."""
        if self._extractor is None:
            sparse = self.config.local_features == "sift"
            self._extractor = _SparseRootSift(self.sift) if sparse else _DenseRootSift(self.config)
        return self._extractor(image)

    @classmethod
    def fit(
        cls,
        images: Sequence[ArrayLike],
        *,
        config: VladConfig | None = None,
        seed: int = 0,
        fingerprint: str = "",
        sift: ClassicalConfig | None = None,
        descriptors: Sequence[NDArray[np.float32]] | None = None,
        threads: int = 1,
        progress: bool = False,
    ) -> VladIndex:
        """Learn the vocabulary (k-means, seeded) on ``images`` and describe them as the database.

        ``sift``: the feature settings of ``local_features="sift"`` (default :class:`ClassicalConfig`).
        ``descriptors``: the images' local descriptors when already at hand (e.g. the database's
        stored features with the same settings; else they are extracted on ``threads`` threads).
        ``progress`` shows a progress bar.
        """
        config = config or VladConfig()
        if len(images) == 0:
            raise ValueError("VladIndex.fit needs at least one database image")
        if descriptors is not None and len(descriptors) != len(images):
            raise ValueError(f"got {len(descriptors)} descriptor sets for {len(images)} images")
        index = cls(config, np.zeros((0, 128), np.float32), np.zeros((0, 0), np.float32), fingerprint)
        index.sift = sift or ClassicalConfig()
        n = len(images)
        with tqdm(total=2 * n, desc="VLAD index", unit="image", disable=not progress) as bar:
            if descriptors is None:
                bar.set_description(f"VLAD index: {config.local_features} RootSIFT of {n} images")

                def extract(image: ArrayLike) -> NDArray[np.float32]:
                    local = index.local_descriptors(image)
                    bar.update()
                    return local

                descriptors = thread_map(extract, images, threads)
            else:
                bar.update(n)
            bar.set_description(f"VLAD index: k-means ({config.n_words} words)")
            bar.refresh()
            index.centres = _vocabulary(descriptors, config, seed, threads)
            bar.set_description(f"VLAD index: describing {n} images")
            raw = np.empty((n, config.n_words * 128), np.float32)
            for i, local in enumerate(descriptors):
                raw[i] = _vlad(local, index.centres, config.power_norm)
                bar.update()
        if config.whiten and len(images) >= 3:
            mean = raw.mean(axis=0)
            _, s, Vt = np.linalg.svd(raw - mean, full_matrices=False)
            dim = min(config.whiten_dim, len(images) - 1)
            eig = s[:dim] ** 2 / max(len(images) - 1, 1)
            index.pca_mean = mean.astype(np.float32)
            index.pca_projection = (Vt[:dim] / np.sqrt(eig + 1e-6 * eig[0])[:, None]).astype(np.float32)
        index.database = index._global(raw, images)
        return index

    def _global(self, raw: NDArray[np.float32], images: Sequence[ArrayLike]) -> NDArray[np.float32]:
        """Final descriptors from raw VLADs (n, K*128): whitening, then the colour layout."""
        out = raw.astype(np.float32)
        if self.pca_projection is not None and self.pca_mean is not None:
            out = (raw - self.pca_mean) @ self.pca_projection.T
            out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
        w = self.config.colour_weight
        if w > 0:
            colour = np.stack([_colour_layout(im) for im in images])
            out = np.concatenate([out, np.sqrt(w) * colour], axis=1) / np.sqrt(1.0 + w)
        return out.astype(np.float32)

    def describe(self, images: Sequence[ArrayLike] | NDArray[np.uint8]) -> NDArray[np.float32]:
        """Global descriptors (n, D) float32, unit L2 norm, of uint8 RGB (HxWx3) or grey images.

        A single image array (HxWx3 or HxW) is also accepted and gives shape (1, D).
        """
        if isinstance(images, np.ndarray) and (
            images.ndim == 2 or (images.ndim == 3 and images.shape[2] == 3)
        ):
            images = [images]
        c = self.config
        raw = np.stack([_vlad(self.local_descriptors(im), self.centres, c.power_norm) for im in images])
        return self._global(raw, images)

    def similarity(self, image: ArrayLike) -> NDArray[np.float64]:
        """Similarity (M,) of one query image to every database image (dot products)."""
        return (self.database @ self.describe(np.asarray(image))[0]).astype(np.float64)

    def save(self, directory: str | os.PathLike) -> None:
        """Write ``vlad_index.npz`` + ``vlad_index.json`` into ``directory`` (each atomically)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        arrays = {
            "centres": self.centres,
            "database": self.database,
            "fingerprint": np.array(self.fingerprint),
        }
        if self.pca_mean is not None and self.pca_projection is not None:
            arrays |= {"pca_mean": self.pca_mean, "pca_projection": self.pca_projection}
        atomic_write(d / _ARRAYS_FILE, lambda f: np.savez(f, **arrays))
        meta = {
            "format_version": FORMAT_VERSION,
            "fingerprint": self.fingerprint,
            "config": asdict(self.config),
            "sift": sift_settings(self.sift),
        }
        atomic_write(d / _META_FILE, lambda f: f.write(json.dumps(meta, indent=2).encode()))

    @classmethod
    def load(
        cls,
        directory: str | os.PathLike,
        expected_fingerprint: str | None = None,
        sift: ClassicalConfig | None = None,
    ) -> VladIndex | None:
        """Load a saved index, or ``None`` on a cache miss.

        A cache miss is: no saved index in ``directory``, an older ``FORMAT_VERSION``, a stored
        fingerprint different from ``expected_fingerprint`` (not checked when None), or, for
        ``local_features="sift"``, other feature settings than ``sift``'s (default
        :class:`ClassicalConfig`). Files that exist but cannot be parsed raise ``ValueError``.
        """
        d = Path(directory)
        if not (d / _META_FILE).is_file() or not (d / _ARRAYS_FILE).is_file():
            return None
        sift = sift or ClassicalConfig()
        try:
            meta = json.loads((d / _META_FILE).read_text())
            if meta.get("format_version") != FORMAT_VERSION:
                return None
            if expected_fingerprint is not None and meta["fingerprint"] != expected_fingerprint:
                return None
            cfg = meta["config"]
            config = VladConfig(**(cfg | {"patch_sizes": tuple(cfg["patch_sizes"])}))
            if config.local_features == "sift" and meta["sift"] != sift_settings(sift):
                return None
            with np.load(d / _ARRAYS_FILE) as z:
                if str(z["fingerprint"]) != meta["fingerprint"]:
                    return None
                pca = ("pca_mean" in z, "pca_projection" in z)
                return cls(
                    config,
                    z["centres"].astype(np.float32),
                    z["database"].astype(np.float32),
                    meta["fingerprint"],
                    z["pca_mean"].astype(np.float32) if all(pca) else None,
                    z["pca_projection"].astype(np.float32) if all(pca) else None,
                    sift,
                )
        except (OSError, KeyError, TypeError, ValueError) as e:
            raise ValueError(f"corrupt VLAD index in {d}: {e}") from e


#: Reference selection methods: Alg. 1 (geometry-aware) and plain top-k (ablation).
RETRIEVAL_METHODS = ("geometry", "topk")


@dataclass(frozen=True)
class RetrievalConfig:
    """Reference selection (paper Alg. 1 defaults).

    ``method="geometry"`` is Alg. 1; ``"topk"`` is plain top-k by similarity (ablation).
    ``l_scale`` (metres) normalises translation distances in the diversity term; None =
    the largest pairwise camera distance in the valid pool (the paper leaves it undefined).
    ``rerank`` > 0: the ``rerank`` most similar database images are re-scored by
    :func:`geometric_rerank` before the selection (``rerank_keypoints`` query keypoints,
    candidates with fewer than ``rerank_min_inliers`` verified matches drop to the end); 0 = off,
    the default: in identical wards the candidates with most verified matches are as often the
    other ward's. ``twins``: verification of a global pose also matches the query with this many
    :func:`twin_references`, so that a place with an identical twin elsewhere is ambiguous rather
    than placed in whichever of the two the references showed; 0 = off.
    """

    k: int = 10
    pool_factor: int = 4
    method: Literal["geometry", "topk"] = "geometry"
    lambda_pos: float = 0.2
    lambda_ang: float = 0.6
    lambda_sim: float = 0.2
    outlier_percentile: float = 95.0
    l_scale: float | None = None
    rerank: int = 0
    rerank_keypoints: int = 600
    rerank_min_inliers: int = 20
    twins: int = 3

    def __post_init__(self) -> None:
        if self.twins < 0:
            raise ValueError(f"twins must be >= 0, got {self.twins}")
        if self.rerank < 0 or self.rerank_keypoints < 8 or self.rerank_min_inliers < 8:
            raise ValueError(
                f"need rerank >= 0, rerank_keypoints >= 8 and rerank_min_inliers >= 8, got "
                f"{self.rerank}, {self.rerank_keypoints}, {self.rerank_min_inliers}"
            )
        if self.k < 1 or self.pool_factor < 1:
            raise ValueError(f"k and pool_factor must be >= 1, got {self.k}, {self.pool_factor}")
        if self.method not in RETRIEVAL_METHODS:
            raise ValueError(f"method must be one of {RETRIEVAL_METHODS}, got {self.method!r}")
        if not 0.0 <= self.outlier_percentile <= 100.0:
            raise ValueError(f"outlier_percentile must be in [0, 100], got {self.outlier_percentile}")
        if self.l_scale is not None and self.l_scale <= 0:
            raise ValueError(f"l_scale must be positive metres or None, got {self.l_scale}")


def twin_references(
    similarity: ArrayLike,
    T_w: ArrayLike,
    T_wc: ArrayLike,
    camera: PinholeCamera,
    exclude: ArrayLike,
    n: int,
    tracking: TrackingConfig | None = None,
) -> NDArray[np.int64]:
    """Indices (<= ``n``,) of the database images most similar to the query (``similarity`` (M,),
    best first) among those that cannot see what the pose ``T_wc`` (4, 4) sees -- not among the
    cameras tracking would take there (``tracking``'s :func:`nearby_cameras` and
    :func:`overlapping_cameras`) -- nor in ``exclude``: where an identical twin of the pose's
    place would show, when Alg. 1's spatial-outlier rule left it out of the references."""
    tracking = tracking or TrackingConfig()
    s, T = np.asarray(similarity, float), np.asarray(T_w, float)
    near = nearby_cameras(T, T_wc, tracking.radius, tracking.max_angle_deg).index
    overlap = overlapping_cameras(
        T, T_wc, camera, tracking.overlap_radius, tracking.max_angle_deg,
        tracking.overlap_depths_m, tracking.min_overlap,
    )  # fmt: skip
    order = np.argsort(-s, kind="stable")
    seeing = np.concatenate([near, overlap, np.asarray(exclude, np.int64)])
    return order[~np.isin(order, seeing)][:n].astype(np.int64)


def geometric_median(points: ArrayLike, iterations: int = 100, tol: float = 1e-7) -> NDArray[np.float64]:
    """Geometric median (Weiszfeld) of points (n, d): the point minimising the sum of distances."""
    P = np.asarray(points, float)
    m = np.median(P, axis=0)
    for _ in range(iterations):
        d = np.linalg.norm(P - m, axis=1)
        if np.any(d < tol):
            # Weiszfeld is undefined at a data point; the coordinate-wise start may sit on one.
            keep = d >= tol
            if not keep.any():
                return m
            w = 1.0 / d[keep]
            step = (P[keep] * w[:, None]).sum(0) / w.sum()
        else:
            w = 1.0 / d
            step = (P * w[:, None]).sum(0) / w.sum()
        if np.linalg.norm(step - m) < tol:
            return step
        m = step
    return m


def verified_matches(query: Features, reference: Features, ratio: float, max_error_px: float = 1.0) -> int:
    """How many ratio-test mutual matches of ``query`` with ``reference`` one fundamental matrix
    explains (OpenCV USAC-MAGSAC++, ``max_error_px`` pixels); 0 under 8 matches."""
    pairs = match_descriptors(query.descriptors, reference.descriptors, ratio, mutual=True)
    if len(pairs) < 8:
        return 0
    pq = np.ascontiguousarray(query.keypoints[pairs[:, 0]], np.float32)
    pr = np.ascontiguousarray(reference.keypoints[pairs[:, 1]], np.float32)
    try:
        _, mask = cv2.findFundamentalMat(pq, pr, cv2.USAC_MAGSAC, max_error_px, 0.999, 1000)
    except cv2.error:  # OpenCV 5's USAC asserts when no model is found (degenerate matches)
        return 0
    return int(mask.sum()) if mask is not None else 0


def geometric_rerank(
    similarity: ArrayLike,
    query: Features,
    features: Callable[[int], Features],
    config: RetrievalConfig,
    ratio: float = 0.8,
) -> NDArray[np.float64]:
    """Similarity (M,) with the ``config.rerank`` most similar database images re-scored by geometry.

    ``query``: the query's RootSIFT features (every ``n / rerank_keypoints``-th keypoint is used);
    ``features``: a database image's features by index (e.g. from :attr:`Database.feature_cache`). A
    candidate with ``v >= rerank_min_inliers`` :func:`verified_matches` scores ``1 + v / v_max``
    (above every unverified image, ordered by verified matches); one with fewer scores its
    similarity minus 3 (below every other image); images beyond the top-N keep their similarity.
    """
    s = np.asarray(similarity, float).copy()
    n = min(config.rerank, len(s))
    if n == 0:
        return s
    candidates = np.argsort(-s, kind="stable")[:n]
    m = len(query.keypoints)
    keep = np.unique(np.linspace(0, m - 1, min(m, config.rerank_keypoints)).round().astype(np.int64))
    sub = Features(query.keypoints[keep], query.descriptors[keep]) if m else query
    verified = np.array([verified_matches(sub, features(int(i)), ratio) for i in candidates], float)
    good = verified >= config.rerank_min_inliers
    s[candidates[good]] = 1.0 + verified[good] / max(float(verified.max()), 1.0)
    s[candidates[~good]] -= 3.0
    return s


def select_references(
    similarity: ArrayLike, T_w: ArrayLike, config: RetrievalConfig | None = None
) -> NDArray[np.int64]:
    """Indices (<= k,) of the reference images for one query, best match first.

    ``similarity`` (M,) scores every database image; ``T_w`` (M, 4, 4) are their ``T_wi``.
    ``geometry`` follows paper Alg. 1: pool = top-N (N = pool_factor * k) by similarity;
    spatial outliers = distance to the pool's geometric median camera position above the
    ``outlier_percentile`` percentile (the best match is always kept); then greedy
    farthest-point selection maximising ``min_s [lambda_pos |t_c - t_s| / L_scale +
    lambda_ang angle(v_c, v_s) / pi] + lambda_sim S_norm(c)`` with ``v`` the optical axis and
    ``S_norm`` the similarity min-max normalised over the valid pool. The remaining
    indices come in selection order. ``topk`` returns the k most similar, in order.
    """
    config = config or RetrievalConfig()
    s = np.asarray(similarity, float)
    T = np.asarray(T_w, float)
    if s.ndim != 1 or T.shape != (len(s), 4, 4):
        raise ValueError(f"need similarity (M,) and T_w (M, 4, 4); got {s.shape} and {T.shape}")
    if not np.all(np.isfinite(s)):
        raise ValueError("similarity contains NaN or inf")
    if len(s) == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(-s, kind="stable")
    if config.method == "topk":
        return order[: config.k].astype(np.int64)

    pool = order[: config.pool_factor * config.k]  # pool[0] is the best match
    t = T[pool, :3, 3]
    d = np.linalg.norm(t - geometric_median(t), axis=1)
    tau = np.percentile(d, config.outlier_percentile)
    valid_mask = d <= tau
    valid_mask[0] = True  # the best match is always kept
    valid = pool[valid_mask]  # still sorted by similarity, best first
    if len(valid) == 1:
        return valid.astype(np.int64)

    sv = s[valid]
    span = sv.max() - sv.min()
    s_norm = (sv - sv.min()) / span if span > 0 else np.ones_like(sv)
    tv = T[valid, :3, 3]
    axes = T[valid, :3, 2]
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    dist = np.linalg.norm(tv[:, None] - tv[None], axis=2)
    if config.l_scale is not None:
        l_scale = config.l_scale
    else:
        l_scale = float(dist.max()) if dist.max() > 0 else 1.0
    ang = np.arccos(np.clip(axes @ axes.T, -1.0, 1.0))
    delta = config.lambda_pos * dist / l_scale + config.lambda_ang * ang / np.pi

    selected = [0]
    d_geo = delta[0].copy()  # min over the selected set, updated incrementally
    available = np.ones(len(valid), bool)
    available[0] = False
    while len(selected) < min(config.k, len(valid)):
        score = np.where(available, d_geo + config.lambda_sim * s_norm, -np.inf)
        c = int(np.argmax(score))  # ties -> the more similar candidate
        selected.append(c)
        available[c] = False
        d_geo = np.minimum(d_geo, delta[c])
    return valid[selected].astype(np.int64)


@dataclass(frozen=True)
class TrackingConfig:
    """Reference selection around a predicted pose (the "temporal" perception mode): the database
    cameras within ``radius`` metres and ``max_angle_deg`` degrees of the predicted camera
    (:func:`nearby_cameras`) are the pool. Fewer than ``min_candidates`` of them (the database
    path passed the place at a distance, or facing elsewhere): with them, the cameras within
    ``overlap_radius`` metres and ``max_angle_deg`` whose images hold at least ``min_overlap`` of
    the predicted view (:func:`overlapping_cameras`, the view sampled at ``overlap_depths_m``);
    still fewer: none (global retrieval).
    """

    radius: float = 2.0
    max_angle_deg: float = 45.0
    min_candidates: int = 3
    overlap_radius: float = 4.0
    min_overlap: float = 0.3
    overlap_depths_m: tuple[float, ...] = (1.0, 2.0, 3.0)

    def __post_init__(self) -> None:
        if self.radius <= 0 or not 0 < self.max_angle_deg <= 180 or self.min_candidates < 1:
            raise ValueError(
                f"need radius > 0 m, max_angle_deg in (0, 180] and min_candidates >= 1, got {self}"
            )
        if self.overlap_radius < self.radius or not 0 < self.min_overlap <= 1:
            raise ValueError(f"need overlap_radius >= radius and min_overlap in (0, 1], got {self}")
        if not self.overlap_depths_m or min(self.overlap_depths_m) <= 0:
            raise ValueError(f"need positive overlap_depths_m, got {self.overlap_depths_m}")


def tracked_references(
    similarity: ArrayLike,
    T_w: ArrayLike,
    predicted: ArrayLike,
    camera: PinholeCamera,
    config: RetrievalConfig | None = None,
    tracking: TrackingConfig | None = None,
) -> NDArray[np.int64]:
    """:func:`select_references` restricted to the database cameras near the ``predicted`` camera
    pose ``T_wc`` (4, 4): tracking picks references around the pose a state estimator predicts
    instead of the whole database. Fewer than ``tracking.min_candidates`` near: with them, those
    whose view through ``camera`` overlaps the predicted one (:func:`overlapping_cameras`); still
    fewer: empty."""
    tracking = tracking or TrackingConfig()
    T = np.asarray(T_w, float)
    near = nearby_cameras(T, predicted, tracking.radius, tracking.max_angle_deg).index
    if len(near) < tracking.min_candidates:
        overlap = overlapping_cameras(
            T, predicted, camera, tracking.overlap_radius, tracking.max_angle_deg,
            tracking.overlap_depths_m, tracking.min_overlap,
        )  # fmt: skip
        near = np.union1d(near, overlap).astype(np.int64)
    if len(near) < tracking.min_candidates:
        return np.zeros(0, np.int64)
    chosen = select_references(np.asarray(similarity, float)[near], T[near], config)
    return near[chosen].astype(np.int64)


class NearbyCameras(NamedTuple):
    """Cameras near a pose: ``index`` (ascending), centre ``distance`` (metres) and ``cos_angle``
    (cosine of the angle between the optical axes), one entry per camera."""

    index: NDArray[np.int64]
    distance: NDArray[np.float64]
    cos_angle: NDArray[np.float64]


def nearby_cameras(
    T_w: ArrayLike, T: ArrayLike, max_distance: float, max_angle_deg: float, *, min_distance: float = 0.0
) -> NearbyCameras:
    """The cameras ``T_w`` (M, 4, 4) whose centre lies ``min_distance`` to ``max_distance`` metres
    from the centre of the pose ``T`` (4, 4) and whose optical axis (z) is within ``max_angle_deg``
    degrees of ``T``'s: the one test of "a camera that sees what ``T`` sees"."""
    T_w, T = np.asarray(T_w, float), np.asarray(T, float)
    distance = np.linalg.norm(T_w[:, :3, 3] - T[:3, 3], axis=1)
    cos_angle = np.clip(T_w[:, :3, 2] @ T[:3, 2], -1.0, 1.0)
    ok = (distance >= min_distance) & (distance <= max_distance)
    ok &= np.degrees(np.arccos(cos_angle)) <= max_angle_deg
    index = np.flatnonzero(ok)
    return NearbyCameras(index.astype(np.int64), distance[index], cos_angle[index])


def overlapping_cameras(
    T_w: ArrayLike,
    T: ArrayLike,
    camera: PinholeCamera,
    max_distance: float,
    max_angle_deg: float,
    depths_m: Sequence[float],
    min_overlap: float,
    grid: tuple[int, int] = (8, 6),
) -> NDArray[np.int64]:
    """The :func:`nearby_cameras` of the pose ``T`` (4, 4) among ``T_w`` (M, 4, 4) (``max_distance``
    metres, ``max_angle_deg``) whose image holds at least ``min_overlap`` of ``T``'s view (both of
    the same ``camera``; features rarely match across a wider angle): ``T``'s
    view is sampled at a ``grid`` (columns, rows) of pixel centres, each at every depth of ``depths_m``
    (metres; the scene's depth is unknown), and a sample counts when it lies in front of the
    camera and inside its image. Occlusion is not modelled (a camera behind a wall may count).
    Indices ascending."""
    T_w, T = np.asarray(T_w, float), np.asarray(T, float)
    near = nearby_cameras(T_w, T, max_distance, max_angle_deg).index
    su, sv = max(camera.width // grid[0], 1), max(camera.height // grid[1], 1)
    rays = camera.rays()[sv // 2 :: sv, su // 2 :: su].reshape(-1, 3)
    points_w = transform_points(T, np.concatenate([rays * d for d in depths_m]))
    seen = []
    for T_wi in T_w[near]:
        uv, z = camera.project_world(T_wi, points_w)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1)
        seen.append(np.mean(inside & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1)))
    return near[np.asarray(seen) >= min_overlap].astype(np.int64)


def pose_guided_references(
    T_w: ArrayLike,
    hypotheses: ArrayLike,
    n: int,
    *,
    exclude: ArrayLike = (),
    radius: float = 1.5,
    max_angle_deg: float = 35.0,
) -> NDArray[np.int64]:
    """Up to ``n`` database indices whose cameras should see what a query at a hypothesised pose sees.

    ``T_w`` (M, 4, 4) are the database ``T_wi``; ``hypotheses`` (h, 4, 4) are rough query poses
    ``T_wq`` (e.g. a reference's centre with the rotation ``R_wi R_iq`` a backbone pair implies),
    most trusted first. A database camera qualifies for a hypothesis when it is one of its
    :func:`nearby_cameras` (``radius`` metres, ``max_angle_deg``); it is ranked by
    ``distance / radius + angle / max_angle``. The hypotheses take turns (best-ranked first),
    indices in ``exclude`` are skipped, each index appears once.
    """
    T = np.asarray(T_w, float)
    H = np.asarray(hypotheses, float).reshape(-1, 4, 4)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_w must have shape (M, 4, 4), got {T.shape}")
    if n < 0 or radius <= 0 or not 0 < max_angle_deg <= 180:
        raise ValueError(
            f"need n >= 0, radius > 0 and max_angle_deg in (0, 180]; got {n}, {radius}, {max_angle_deg}"
        )
    ranked = []
    for hyp in H:
        near = nearby_cameras(T, hyp, radius, max_angle_deg)
        score = near.distance / radius + np.degrees(np.arccos(near.cos_angle)) / max_angle_deg
        ranked.append(list(near.index[np.argsort(score, kind="stable")]))
    chosen: list[int] = []
    taken = {int(i) for i in np.asarray(exclude, np.int64).ravel()}
    while len(chosen) < n and any(ranked):
        for queue in ranked:
            while queue and int(queue[0]) in taken:
                queue.pop(0)
            if queue and len(chosen) < n:
                chosen.append(int(queue.pop(0)))
                taken.add(chosen[-1])
    return np.array(chosen, np.int64)
