"""The on-disk run format (versioned, written atomically) and built database/query run pairs.

A run directory::

    meta.json               {"format": "vgpnav-run", "version": 1, "scene", "layout", "kind", "seed",
                             "width", "height", "fovy_deg", "texture", "lighting", "n_frames", ...}
    intrinsics.json         {"width", "height", "fovy_rad", "K"}
    poses.npy               (N, 4, 4) float64 T_wc (OpenCV camera -> world)
    images/000000.png ...   N RGB images (uint8, H x W x 3)
    groundtruth/depth.npz   optional, key "depth": (N, H, W) float16 metric z-depth (inf = no hit)

Ground-truth depth lives apart: VGP-Nav never reads it except through the privileged
``simulated`` backbone (and evaluation), via :func:`load_run_depth`.

A *build* directory holds ``database/`` (base layout), ``query/`` (changed layout) and
``summary.json``; see :func:`vgpnav_env.build.build_runs` which writes it and :func:`load_build`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera

logger = logging.getLogger(__name__)

RUN_FORMAT = "vgpnav-run"
RUN_VERSION = 1
BUILD_FORMAT = "vgpnav-build"
BUILD_VERSION = 1
#: Keys every run's metadata carries (``save_run`` fills the format keys and ``n_frames``).
METADATA_KEYS = ("scene", "layout", "kind", "seed", "texture", "lighting")
RUN_KINDS = ("database", "query")
_IMAGE_NAME = re.compile(r"^\d{6}\.png$")


class RunFormatError(ValueError):
    """A directory is not a readable run or build (missing, partial, damaged, foreign or too new)."""


@dataclass(eq=False)
class Run:
    """A sequence of posed RGB frames.

    ``images`` (N, H, W, 3) uint8 RGB; ``poses`` (N, 4, 4) float64 ``T_wc`` with OpenCV cameras;
    ``camera`` the shared pinhole intrinsics; ``metadata`` at least :data:`METADATA_KEYS`
    (plus ``width``, ``height``, ``fovy_deg``, ``n_frames`` and the format keys once saved or loaded).
    """

    images: NDArray[np.uint8]
    poses: NDArray[np.float64]
    camera: PinholeCamera
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.images = np.asarray(self.images)
        self.poses = np.asarray(self.poses, np.float64)
        n = len(self.poses)
        shape = (n, self.camera.height, self.camera.width, 3)
        if self.images.dtype != np.uint8 or self.images.shape != shape:
            raise ValueError(
                f"run images must be uint8 of shape {shape} (N, H, W, 3) to match the poses and camera, "
                f"got {self.images.dtype} {self.images.shape}"
            )
        if self.poses.shape != (n, 4, 4) or not np.all(np.isfinite(self.poses)):
            raise ValueError(f"run poses must be finite (N, 4, 4) T_wc, got shape {self.poses.shape}")
        kind = self.metadata.get("kind")
        if kind is not None and kind not in RUN_KINDS:
            raise ValueError(f"run kind must be one of {RUN_KINDS}, got {kind!r}")

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def positions(self) -> NDArray[np.float64]:
        """Camera centres (N, 3) in W."""
        return self.poses[:, :3, 3]


@dataclass(eq=False)
class Build:
    """A database run (base layout), a query run (changed layout) and the build summary."""

    path: Path
    database: Run
    query: Run
    summary: dict[str, Any]


def _write_bytes(path: Path, data: bytes, sync: bool = True) -> None:
    with open(path, "wb") as f:
        f.write(data)
        if sync:
            f.flush()
            os.fsync(f.fileno())


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON and fsync it."""
    _write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True) + "\n").encode())


def _write_npy(path: Path, array: NDArray[Any], compressed_npz: bool = False) -> None:
    with open(path, "wb") as f:
        if compressed_npz:
            np.savez_compressed(f, depth=array)
        else:
            np.save(f, array)
        f.flush()
        os.fsync(f.fileno())


#: Directory kinds written atomically: marker file and its "format" value.
_MARKERS = {"run": ("meta.json", RUN_FORMAT), "build": ("summary.json", BUILD_FORMAT)}


def check_replaceable(path: Path | str, kind: str) -> None:
    """Raise FileExistsError unless ``path`` is absent, an empty directory, or a vgpnav ``kind``
    ("run" or "build") directory, so that saving never deletes unrelated data."""
    path = Path(path)
    marker, fmt = _MARKERS[kind]
    if not path.exists() or (path.is_dir() and not any(path.iterdir())):
        return
    try:
        ok = path.is_dir() and json.loads((path / marker).read_text()).get("format") == fmt
    except (OSError, ValueError, AttributeError):
        ok = False
    if not ok:
        raise FileExistsError(
            f"refusing to replace {path}: it exists and is not a vgpnav {kind} directory ({marker} with "
            f"format {fmt!r}); choose another directory or remove it"
        )


def atomic_directory(path: Path | str, write: Callable[[Path], None], kind: str) -> Path:
    """Create directory ``path`` atomically: ``write(tmp)`` fills a temporary sibling directory,
    which then replaces ``path``. An existing ``path`` must be replaceable (see
    :func:`check_replaceable`) and is only removed after ``write`` succeeded; on any exception the
    temporary directory is deleted and ``path`` is left as it was."""
    path = Path(path)
    check_replaceable(path, kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    tag = uuid.uuid4().hex[:8]
    tmp = path.parent / f".{path.name}.tmp-{tag}"
    tmp.mkdir()
    try:
        write(tmp)
        check_replaceable(path, kind)
        if path.exists():
            old = path.parent / f".{path.name}.old-{tag}"
            os.replace(path, old)
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def _run_metadata(run: Run) -> dict[str, Any]:
    missing = [k for k in METADATA_KEYS if k not in run.metadata]
    if missing:
        raise ValueError(f"run metadata lacks {missing}; required keys: {list(METADATA_KEYS)}")
    meta = {k: v for k, v in run.metadata.items() if k not in ("format", "version")}
    meta.update(
        format=RUN_FORMAT,
        version=RUN_VERSION,
        width=run.camera.width,
        height=run.camera.height,
        fovy_deg=float(np.rad2deg(run.camera.fovy)),
        n_frames=len(run),
    )
    return meta


def write_run(
    directory: Path,
    run: Run,
    depth: NDArray[np.floating] | None = None,
    on_frame: Callable[[], None] | None = None,
) -> None:
    """Write ``run`` (and optional depth (N, H, W)) into an existing empty ``directory`` (not atomic;
    see :func:`save_run`); images are encoded on the process's thread pool
    (:func:`~vgpnav_env.perception.backbones.threads.thread_map`), ``on_frame()`` is called (from
    one of its threads) after each image is written."""
    meta = _run_metadata(run)
    if depth is not None:
        depth = np.asarray(depth)
        if depth.shape != run.images.shape[:3]:
            raise ValueError(f"depth shape {depth.shape} must be (N, H, W) = {run.images.shape[:3]}")
    (directory / "images").mkdir()
    from vgpnav_env.perception.backbones.threads import thread_map  # here: perception imports runs

    def write_image(i: int) -> None:
        ok, png = cv2.imencode(".png", cv2.cvtColor(run.images[i], cv2.COLOR_RGB2BGR))
        if not ok:
            raise OSError(f"could not encode frame {i} as PNG")
        # Not fsynced (costs ~6 ms per frame): a torn PNG fails to decode, so loading still detects it.
        _write_bytes(directory / "images" / f"{i:06d}.png", png.tobytes(), sync=False)
        if on_frame is not None:
            on_frame()

    thread_map(write_image, range(len(run)), 0)
    _write_npy(directory / "poses.npy", run.poses.astype(np.float64))
    cam = run.camera
    write_json(
        directory / "intrinsics.json",
        {"width": cam.width, "height": cam.height, "fovy_rad": cam.fovy, "K": cam.K.tolist()},
    )
    if depth is not None:
        (directory / "groundtruth").mkdir()
        _write_npy(directory / "groundtruth" / "depth.npz", depth.astype(np.float16), compressed_npz=True)
    write_json(directory / "meta.json", meta)


def save_run(path: Path | str, run: Run, depth: NDArray[np.floating] | None = None) -> Path:
    """Save ``run`` to directory ``path`` atomically (temp directory + rename). ``depth`` (N, H, W)
    metric z-depth goes to ``groundtruth/depth.npz`` (float16). Returns the path."""
    path = atomic_directory(path, lambda tmp: write_run(tmp, run, depth), "run")
    logger.info("saved %s run of %d frames to %s", run.metadata.get("kind"), len(run), path)
    return path


def _read_json(path: Path, what: str) -> dict[str, Any]:
    if not path.is_file():
        raise RunFormatError(f"{path.parent}: missing {path.name} ({what}); not a complete vgpnav run/build")
    try:
        obj = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise RunFormatError(f"{path}: unreadable {what}: {e}") from e
    if not isinstance(obj, dict):
        raise RunFormatError(f"{path}: {what} must be a JSON object, got {type(obj).__name__}")
    return obj


def _read_versioned(path: Path, name: str, what: str, kind: str, fmt: str, version: int) -> dict[str, Any]:
    """The JSON object ``name`` (``what``) of the ``kind`` directory ``path``; RunFormatError unless
    the directory exists and the object's ``format`` and ``version`` are ``fmt`` and ``version``."""
    if not path.is_dir():
        raise RunFormatError(f"{path}: no such {kind} directory")
    obj = _read_json(path / name, what)
    if obj.get("format") != fmt:
        raise RunFormatError(f"{path}: {name} format is {obj.get('format')!r}, expected {fmt!r}")
    if obj.get("version") != version:
        raise RunFormatError(
            f"{path}: {kind} version {obj.get('version')!r} is not supported "
            f"(this vgpnav reads version {version})"
        )
    return obj


def read_run_meta(path: Path | str) -> dict[str, Any]:
    """The validated ``meta.json`` of a run directory (format, version, frame count)."""
    path = Path(path)
    meta = _read_versioned(path, "meta.json", "run metadata", "run", RUN_FORMAT, RUN_VERSION)
    n = meta.get("n_frames")
    if not isinstance(n, int) or n < 0:
        raise RunFormatError(f"{path}: meta.json n_frames must be a non-negative integer, got {n!r}")
    return meta


def _read_camera(path: Path, meta: dict[str, Any]) -> PinholeCamera:
    intr = _read_json(path / "intrinsics.json", "intrinsics")
    try:
        cam = PinholeCamera(int(intr["width"]), int(intr["height"]), float(intr["fovy_rad"]))
    except (KeyError, TypeError, ValueError) as e:
        raise RunFormatError(f"{path}: bad intrinsics.json ({e}); needs width, height, fovy_rad") from e
    if (cam.width, cam.height) != (meta.get("width"), meta.get("height")):
        raise RunFormatError(
            f"{path}: intrinsics size {cam.width}x{cam.height} differs from meta.json "
            f"{meta.get('width')}x{meta.get('height')}"
        )
    return cam


def _read_poses(path: Path, n: int) -> NDArray[np.float64]:
    try:
        poses = np.load(path / "poses.npy", allow_pickle=False)
    except FileNotFoundError as e:
        raise RunFormatError(f"{path}: missing poses.npy") from e
    except (OSError, ValueError) as e:
        raise RunFormatError(f"{path}: unreadable poses.npy: {e}") from e
    if poses.shape != (n, 4, 4) or not np.all(np.isfinite(poses)):
        raise RunFormatError(f"{path}: poses.npy must be finite ({n}, 4, 4) T_wc, got shape {poses.shape}")
    return poses.astype(np.float64)


def _image_files(path: Path, n: int) -> list[Path]:
    folder = path / "images"
    if not folder.is_dir():
        raise RunFormatError(f"{path}: missing images/ folder")
    names = sorted(p.name for p in folder.iterdir() if _IMAGE_NAME.match(p.name))
    expected = [f"{i:06d}.png" for i in range(n)]
    if names != expected:
        missing = sorted(set(expected) - set(names))
        extra = sorted(set(names) - set(expected))
        raise RunFormatError(
            f"{path}: images/ holds {len(names)} frames but poses.npy has {n}"
            + (f"; missing {missing[:3]}" if missing else "")
            + (f"; unexpected {extra[:3]}" if extra else "")
        )
    return [folder / name for name in expected]


def load_run(path: Path | str) -> Run:
    """Load and validate a run directory (eagerly: all images in memory, decoded on the process's
    thread pool).

    Raises :class:`RunFormatError` naming the problem and the path for a missing, partial,
    damaged, foreign or unsupported-version directory.
    """
    path = Path(path)
    meta = read_run_meta(path)
    n = meta["n_frames"]
    cam = _read_camera(path, meta)
    poses = _read_poses(path, n)
    images = np.empty((n, cam.height, cam.width, 3), np.uint8)
    from vgpnav_env.perception.backbones.threads import thread_map  # here: perception imports runs

    def read_image(item: tuple[int, Path]) -> None:
        i, file = item
        bgr = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if bgr is None:
            raise RunFormatError(f"{file}: unreadable PNG image")
        if bgr.shape != images.shape[1:]:
            raise RunFormatError(
                f"{file}: image shape {bgr.shape} differs from intrinsics {images.shape[1:]}"
            )
        images[i] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    thread_map(read_image, list(enumerate(_image_files(path, n))), 0)
    return Run(images, poses, cam, meta)


def load_run_depth(path: Path | str) -> NDArray[np.float32]:
    """Ground-truth z-depth (N, H, W) float32 (inf = no surface) of a run. Privileged: only
    evaluation and the ``simulated`` backbone may call this."""
    path = Path(path)
    meta = read_run_meta(path)
    file = path / "groundtruth" / "depth.npz"
    if not file.is_file():
        raise RunFormatError(f"{path}: no ground-truth depth (groundtruth/depth.npz) in this run")
    try:
        with np.load(file, allow_pickle=False) as z:
            depth = z["depth"]
    except (OSError, ValueError, KeyError) as e:
        raise RunFormatError(f"{file}: unreadable depth archive: {e}") from e
    shape = (meta["n_frames"], meta["height"], meta["width"])
    if depth.shape != shape:
        raise RunFormatError(f"{file}: depth shape {depth.shape} differs from the run's (N, H, W) = {shape}")
    return depth.astype(np.float32)


def run_fingerprint(path: Path | str) -> str:
    """SHA-256 hex digest of a run's metadata, intrinsics, poses and image bytes (for caches)."""
    path = Path(path)
    meta = read_run_meta(path)
    h = hashlib.sha256()
    for file in [path / "meta.json", path / "intrinsics.json", path / "poses.npy"]:
        if not file.is_file():
            raise RunFormatError(f"{path}: missing {file.name}")
        h.update(file.read_bytes())
    for file in _image_files(path, meta["n_frames"]):
        h.update(file.read_bytes())
    return h.hexdigest()


def default_cache_dir() -> Path:
    """``$VGPNAV_CACHE`` or ``~/.cache/vgpnav``."""
    return Path(os.environ.get("VGPNAV_CACHE") or Path.home() / ".cache" / "vgpnav")


def build_dir_name(slug: str, size: tuple[int, int], seed: int, texture: str) -> str:
    """``<slug>-<W>x<H>-s<seed>-<texture>``, the folder name of a build in the cache."""
    return f"{slug}-{size[0]}x{size[1]}-s{seed}-{texture}"


def read_build_summary(path: Path | str) -> dict[str, Any]:
    """The validated ``summary.json`` of a build directory."""
    return _read_versioned(Path(path), "summary.json", "build summary", "build", BUILD_FORMAT, BUILD_VERSION)


def load_build(path: Path | str) -> Build:
    """Load a build directory (``database/``, ``query/``, ``summary.json``); RunFormatError if damaged."""
    path = Path(path)
    summary = read_build_summary(path)
    database, query = load_run(path / "database"), load_run(path / "query")
    for run, n_key in ((database, "database_frames"), (query, "query_frames")):
        if summary.get(n_key) != len(run):
            raise RunFormatError(
                f"{path}: summary.json {n_key}={summary.get(n_key)!r} but the run has {len(run)}"
            )
    return Build(path, database, query, summary)
