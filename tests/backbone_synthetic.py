"""Analytic multi-view images of a textured room corner for backbone tests (no renderer needed).

A floor (z = 0) and two walls (x = 4, y = 4) carry different multi-scale noise textures; each
pixel's ray is intersected with the planes, so images, metric z-depth and poses are exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera, camera_pose

PX_PER_M = 80.0


@dataclass(frozen=True)
class TexturedPlane:
    origin: NDArray[np.float64]
    u: NDArray[np.float64]
    v: NDArray[np.float64]
    size: tuple[float, float]
    texture: NDArray[np.float32]

    @property
    def normal(self) -> NDArray[np.float64]:
        return np.cross(self.u, self.v)


def noise_texture(rng: np.random.Generator, size_m: tuple[float, float]) -> NDArray[np.float32]:
    """Colourful multi-scale blob texture (H, W, 3) in [0, 255], sampled at PX_PER_M."""
    w, h = int(size_m[0] * PX_PER_M), int(size_m[1] * PX_PER_M)
    tex = np.zeros((h, w, 3), np.float32)
    for sigma in (1.5, 3.0, 6.0, 12.0):
        layer = cv2.GaussianBlur(rng.standard_normal((h, w, 3)).astype(np.float32), (0, 0), sigma)
        tex += layer / layer.std()
    tex = (tex - tex.mean()) / tex.std()
    return np.clip(128.0 + 50.0 * tex, 0, 255).astype(np.float32)


def room_corner(seed: int = 0) -> list[TexturedPlane]:
    rng = np.random.default_rng(seed)
    ex, ey, ez = np.eye(3)
    return [
        TexturedPlane(np.zeros(3), ex, ey, (4.0, 4.0), noise_texture(rng, (4.0, 4.0))),
        TexturedPlane(np.array([4.0, 0.0, 0.0]), ey, ez, (4.0, 2.5), noise_texture(rng, (4.0, 2.5))),
        TexturedPlane(np.array([0.0, 4.0, 0.0]), ex, ez, (4.0, 2.5), noise_texture(rng, (4.0, 2.5))),
    ]


def render(
    planes: list[TexturedPlane], camera: PinholeCamera, T_wc: NDArray[np.float64]
) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """RGB (H, W, 3) uint8 and metric z-depth (H, W) of the planes seen from ``T_wc`` (0 = nothing)."""
    rays = camera.rays() @ T_wc[:3, :3].T
    centre = T_wc[:3, 3]
    depth = np.full(rays.shape[:2], np.inf)
    rgb = np.zeros((*rays.shape[:2], 3), np.float32)
    for plane in planes:
        n = plane.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (n @ (plane.origin - centre)) / (rays @ n)
        p = centre + rays * t[..., None] - plane.origin
        a, b = p @ plane.u, p @ plane.v
        hit = (t > 1e-3) & (t < depth) & (a >= 0) & (b >= 0) & (a < plane.size[0]) & (b < plane.size[1])
        map_x = np.where(hit, a * PX_PER_M, -1).astype(np.float32)
        map_y = np.where(hit, b * PX_PER_M, -1).astype(np.float32)
        sampled = cv2.remap(plane.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        rgb[hit] = sampled[hit]
        depth[hit] = t[hit]
    depth[~np.isfinite(depth)] = 0.0
    return np.clip(rgb + 0.5, 0, 255).astype(np.uint8), depth.astype(np.float32)


def corner_views(
    camera: PinholeCamera, k: int = 5, seed: int = 0
) -> tuple[NDArray[np.float64], NDArray[np.float64], list[TexturedPlane]]:
    """A query pose (1.2 m high) and ``k`` reference poses (1.5 m, within ~1 m) looking into the corner."""
    rng = np.random.default_rng(seed)
    yaw0 = np.deg2rad(45.0)
    T_wq = camera_pose([1.5, 1.5, 1.2], yaw0, np.deg2rad(20.0))
    T_wi = []
    for _ in range(k):
        offset = rng.uniform(-0.8, 0.5, size=2)
        yaw = yaw0 + np.deg2rad(rng.uniform(-15.0, 15.0))
        T_wi.append(
            camera_pose([1.5 + offset[0], 1.5 + offset[1], 1.5], yaw, np.deg2rad(rng.uniform(15, 25)))
        )
    return T_wq, np.stack(T_wi), room_corner(seed)


def render_corner(camera: PinholeCamera, k: int = 5, seed: int = 0):
    """The :func:`corner_views` rendered: query RGB, its metric depth (0 = nothing), the ``k``
    reference RGBs, ``T_wq`` and ``T_wi`` (k, 4, 4)."""
    T_wq, T_wi, planes = corner_views(camera, k, seed)
    query, depth = render(planes, camera, T_wq)
    refs = [render(planes, camera, T)[0] for T in T_wi]
    return query, depth, refs, T_wq, T_wi


def plain_room(seed: int = 0, details: int = 3) -> list[TexturedPlane]:
    """The room corner painted plain (one colour per plane, with a faint shading gradient and
    sensor-like noise), each wall carrying ``details`` small textured posters (0.3-0.5 m)."""
    rng = np.random.default_rng(seed)
    planes = []
    colours = ((150, 140, 130), (200, 198, 190), (190, 195, 200))
    for plane, colour in zip(room_corner(seed), colours, strict=True):
        h, w = plane.texture.shape[:2]
        ramp = np.linspace(-8.0, 8.0, w, dtype=np.float32)[None, :, None]
        tex = np.broadcast_to(np.array(colour, np.float32) + ramp, (h, w, 3)).copy()
        tex += rng.normal(0.0, 1.0, tex.shape).astype(np.float32)
        if plane.normal[2] == 0:  # a wall
            for _ in range(details):
                pw, ph = (int(PX_PER_M * s) for s in rng.uniform(0.3, 0.5, 2))
                x0 = int(rng.integers(0, w - pw))
                y0 = int(rng.integers(int(0.6 * PX_PER_M), max(int(0.6 * PX_PER_M) + 1, h - ph)))
                tex[y0 : y0 + ph, x0 : x0 + pw] = noise_texture(rng, (pw / PX_PER_M, ph / PX_PER_M))[:ph, :pw]
        planes.append(TexturedPlane(plane.origin, plane.u, plane.v, plane.size, tex))
    return planes
