"""Adapter for learned feed-forward reconstruction models with VGGT's output contract.

The wrapped ``torch.nn.Module`` takes images ``(S, 3, H, W)`` float in [0, 1] (query first,
then the references) and returns a mapping with

- ``extrinsic`` (S, 3, 4): camera-from-world, world = the FIRST camera (OpenCV axes), at the
  model's normalised scale -- the naming of VGGT's ``pose_encoding_to_extri_intri`` output;
- ``depth`` (S, H, W, 1) or (S, H, W): z-depth at that scale;
- ``depth_conf`` (S, H, W): per-pixel confidence (VGGT: ``1 + exp(x)`` >= 1).

A leading batch axis of size 1 is accepted. For VGGT itself, wrap it in a small module that
runs ``pose_encoding_to_extri_intri`` and returns these keys. Weights are loaded ONLY from the
local file the user gives (``torch.load(..., weights_only=True)``); nothing is downloaded.
Scale convention ``"model"``: whatever the model normalises to (VGGT: mean point distance 1).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from pathlib import Path

import cv2
import numpy as np
import torch
from numpy.typing import NDArray

from vgpnav_env.geometry import invert_pose
from vgpnav_env.perception.backbones.base import Backbone, BackboneOutput, Views

ModelSpec = torch.nn.Module | Callable[[], torch.nn.Module] | str


def vggt_confidence(conf: NDArray[np.floating]) -> NDArray[np.float32]:
    """Map VGGT-style confidences (>= 1, unbounded) into [0, 1): ``1 - 1 / max(c, 1)``."""
    return (1.0 - 1.0 / np.maximum(np.asarray(conf, np.float32), 1.0)).astype(np.float32)


def resolve_model(spec: ModelSpec) -> torch.nn.Module:
    """A module instance, a zero-argument factory, or ``"package.module:factory"``."""
    if isinstance(spec, torch.nn.Module):
        return spec
    if isinstance(spec, str):
        module_name, sep, attr = spec.partition(":")
        if not sep or not module_name or not attr:
            raise ValueError(f"model path must look like 'package.module:factory', got {spec!r}")
        spec = getattr(importlib.import_module(module_name), attr)
    if not callable(spec):
        raise TypeError(f"model must be a torch.nn.Module, a factory or 'module:factory', got {type(spec)}")
    model = spec()
    if not isinstance(model, torch.nn.Module):
        raise TypeError(f"model factory returned {type(model)}, expected a torch.nn.Module")
    return model


def load_weights(model: torch.nn.Module, weights_path: str | Path) -> None:
    """Load a local state dict (optionally wrapped as {'model': ...} or {'state_dict': ...})."""
    path = Path(weights_path)
    if not path.is_file():
        raise FileNotFoundError(
            f"weights file {str(path)!r} does not exist: the learned backbone never downloads weights, "
            "give the path of a local checkpoint"
        )
    state = torch.load(path, map_location="cpu", weights_only=True)
    for wrapper in ("model", "state_dict"):
        if isinstance(state, Mapping) and set(state) == {wrapper} and isinstance(state[wrapper], Mapping):
            state = state[wrapper]
    model.load_state_dict(state)


def _numpy(x: torch.Tensor | NDArray, name: str, ndim: tuple[int, ...]) -> NDArray[np.float64]:
    arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    if arr.ndim == max(ndim) + 1 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim not in ndim:
        raise ValueError(f"model output {name!r} has shape {arr.shape}, expected {ndim}-dimensional")
    return arr.astype(np.float64)


class LearnedBackbone(Backbone):
    """Feed-forward learned model behind the backbone contract (see the module docstring)."""

    name = "learned"
    privileged = False

    def __init__(
        self,
        model: ModelSpec,
        weights_path: str | Path,
        device: str = "cpu",
        input_size: tuple[int, int] | None = None,
        confidence_transform: Callable[[NDArray[np.floating]], NDArray[np.float32]] = vggt_confidence,
    ) -> None:
        """``input_size`` = (width, height) the model expects (images are resized; depth resized back)."""
        self.model = resolve_model(model)
        load_weights(self.model, weights_path)
        self.device = torch.device(device)
        self.model.to(self.device).eval()
        self.input_size = input_size
        self.confidence_transform = confidence_transform

    def reconstruct(self, views: Views) -> BackboneOutput:
        query, references, camera = views.query, views.references, views.camera
        images = [query, *references]
        if self.input_size is not None:
            images = [cv2.resize(im, self.input_size, interpolation=cv2.INTER_AREA) for im in images]
        batch = torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float().div(255.0).to(self.device)
        with torch.inference_mode():
            out = self.model(batch)
        missing = {"extrinsic", "depth", "depth_conf"} - set(out)
        if missing:
            raise KeyError(
                f"model output lacks {sorted(missing)}; it must return extrinsic, depth and depth_conf"
            )
        S = len(images)
        extrinsic = _numpy(out["extrinsic"], "extrinsic", (3,))
        depth = _numpy(out["depth"], "depth", (3, 4))
        conf = _numpy(out["depth_conf"], "depth_conf", (3,))
        if depth.ndim == 4:
            depth = depth[..., 0]
        if extrinsic.shape != (S, 3, 4) or len(depth) != S or conf.shape != depth.shape:
            raise ValueError(
                f"model outputs for {S} images have shapes extrinsic {extrinsic.shape}, depth {depth.shape}, "
                f"depth_conf {conf.shape}; expected ({S}, 3, 4), ({S}, H, W), ({S}, H, W)"
            )
        size = (camera.width, camera.height)
        if depth.shape[1:] != (camera.height, camera.width):
            depth = np.stack([cv2.resize(d, size, interpolation=cv2.INTER_NEAREST) for d in depth])
            conf = np.stack([cv2.resize(c, size, interpolation=cv2.INTER_LINEAR) for c in conf])
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
        conf01 = np.clip(self.confidence_transform(conf), 0.0, 1.0).astype(np.float32) * (depth > 0)

        T_cw = np.tile(np.eye(4), (S, 1, 1))
        T_cw[:, :3, :] = extrinsic
        # T_iq = T_iw @ T_wq with w the model's world (the first camera, up to the model's exactness).
        T_iq = T_cw[1:] @ invert_pose(T_cw[0])
        k = S - 1
        return BackboneOutput(
            T_qi=invert_pose(T_iq),
            confidence=np.array([float(np.median(c)) for c in conf01[1:]]).reshape(k),
            n_matches=np.zeros(k, np.int64),
            query_depth=depth[0],
            query_depth_confidence=conf01[0],
            name=self.name,
            scale="model",
            reference_depths=depth[1:],
            scale_valid=np.ones(k, bool),
        )
