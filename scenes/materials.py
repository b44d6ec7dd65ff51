"""Procedural interior materials: tileable textures made with numpy/OpenCV, deterministic per seed.

A material name is ``kind`` or ``kind:variant`` (e.g. ``paint:beige``, ``wood:walnut``,
``tiles:white``); variants pick a base colour from the kind's palette. ``make_material`` turns a
name, a texture level and a seed into a ``Material`` whose image repeats every ``tile_m`` metres.

Texture levels (``TEXTURE_LEVELS``):
- ``rich``: strong texture everywhere (patterned wallpaper, high-contrast grain and speckle);
- ``realistic`` (default): what real rooms look like, including the hard cases: near-blank painted
  walls (faint plaster mottling, sparse chips), repeated tiles; wood grain and knots, parquet seams,
  stone-look tiles, heathered carpet/fabric, speckled vinyl, wallpaper, pictures, posters and books
  carry the structure (median >= 200 default-SIFT keypoints per 320x240 frame on the built-in runs);
- ``sparse``: mostly plain colours with faint structure.
Images are uint8 RGB, 256x256 (512x512 for parquet and brick), cached per (name, level, seed, tile).
"""

from __future__ import annotations

import string
import zlib
from collections.abc import Callable
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from vgpnav_env.scenes.scene import Material

TEXTURE_LEVELS: tuple[str, ...] = ("rich", "realistic", "sparse")

#: Version of the scene appearance (material images and the lighting presets in ``lighting.py``);
#: part of the build parameters, so bump it whenever either changes or older builds would be reused.
MATERIALS_VERSION = 4

_RGB = dict[str, tuple[int, int, int]]

_PALETTES: dict[str, _RGB] = {
    "paint": {
        "white": (236, 234, 228),
        "cream": (234, 226, 206),
        "beige": (216, 202, 178),
        "grey": (196, 196, 194),
        "sage": (188, 202, 180),
        "blue": (188, 204, 220),
        "mint": (200, 226, 212),
        "yellow": (236, 222, 172),
        "pink": (232, 208, 204),
        "terracotta": (196, 128, 100),
    },
    "wallpaper": {
        "cream": (232, 222, 200),
        "sage": (190, 204, 182),
        "blue": (186, 200, 218),
        "grey": (204, 202, 198),
        "rose": (226, 204, 198),
    },
    "wood": {
        "oak": (172, 126, 80),
        "walnut": (112, 74, 46),
        "pine": (204, 166, 116),
        "cherry": (152, 84, 58),
        "dark": (72, 52, 40),
        "white": (226, 222, 212),
        "grey": (150, 146, 140),
    },
    "parquet": {
        "oak": (176, 130, 84),
        "walnut": (118, 80, 52),
        "pine": (206, 170, 122),
        "grey": (160, 150, 138),
    },
    "tiles": {
        "white": (232, 232, 228),
        "grey": (168, 168, 166),
        "beige": (212, 196, 170),
        "blue": (150, 178, 204),
        "terracotta": (184, 110, 80),
        "green": (150, 186, 160),
    },
    "smalltiles": {
        "white": (236, 236, 234),
        "blue": (140, 172, 206),
        "green": (160, 196, 176),
        "grey": (190, 190, 188),
    },
    "carpet": {
        "grey": (128, 126, 124),
        "beige": (188, 170, 142),
        "blue": (86, 104, 140),
        "red": (140, 62, 60),
    },
    "fabric": {
        "grey": (128, 128, 132),
        "blue": (70, 96, 150),
        "navy": (44, 52, 84),
        "green": (88, 124, 86),
        "red": (160, 60, 56),
        "beige": (200, 184, 156),
        "brown": (118, 84, 60),
        "white": (232, 232, 230),
        "teal": (56, 128, 128),
        "mustard": (200, 160, 60),
        "lightblue": (170, 196, 224),
        "pink": (220, 170, 180),
    },
    "linoleum": {
        "green": (150, 176, 150),
        "blue": (150, 170, 196),
        "grey": (176, 176, 172),
        "beige": (206, 194, 168),
    },
    "brick": {"red": (150, 72, 52), "brown": (120, 80, 60), "white": (220, 214, 204)},
    "marble": {"white": (226, 224, 220), "dark": (60, 60, 64)},
    "concrete": {"grey": (160, 158, 154), "light": (196, 194, 190)},
    "metal": {"steel": (170, 172, 176), "white": (226, 228, 230), "black": (46, 46, 50)},
    "plastic": {
        "white": (230, 230, 226),
        "grey": (150, 152, 156),
        "blue": (90, 130, 190),
        "green": (90, 160, 120),
    },
    "ceramic": {"white": (240, 240, 238)},
    "skin": {"light": (230, 190, 160), "medium": (196, 146, 108), "dark": (120, 80, 56)},
    "leaves": {"green": (70, 120, 60)},
    "screen": {"black": (22, 24, 28)},
    "picture": {"art": (128, 128, 128)},
    "poster": {"print": (128, 128, 128)},
    "books": {"mixed": (128, 128, 128)},
}

_TILE_M: dict[str, float] = {
    "paint": 2.0,
    "wallpaper": 0.53,
    "wood": 1.0,
    "parquet": 1.6,
    "tiles": 1.2,
    "smalltiles": 0.6,
    "carpet": 1.0,
    "fabric": 0.5,
    "linoleum": 1.5,
    "brick": 1.2,
    "marble": 1.0,
    "concrete": 2.0,
    "metal": 0.5,
    "plastic": 0.5,
    "ceramic": 0.5,
    "skin": 0.5,
    "leaves": 0.4,
    "screen": 1.0,
    "picture": 0.6,
    "poster": 0.5,
    "books": 0.3,
}

MATERIAL_KINDS: frozenset[str] = frozenset(_PALETTES)


def parse_material_name(name: str) -> tuple[str, str]:
    """Split ``kind[:variant]`` into (kind, variant); the default variant is the palette's first."""
    kind, _, variant = name.partition(":")
    if kind not in _PALETTES:
        raise ValueError(f"unknown material kind {kind!r} in {name!r}")
    palette = _PALETTES[kind]
    if not variant:
        return kind, next(iter(palette))
    if variant not in palette:
        raise ValueError(f"material {kind!r} has no variant {variant!r}; variants: {sorted(palette)}")
    return kind, variant


# ----------------------------------------------------------------------------------------- helpers


def _noise(
    rng: np.random.Generator, n: int, sigma: float, sigma_v: float | None = None
) -> NDArray[np.float64]:
    """Periodic (tileable) Gaussian-filtered noise, zero mean, unit std; sigma in pixels (u, v)."""
    sv = sigma if sigma_v is None else sigma_v
    white = rng.standard_normal((n, n), dtype=np.float32)
    fy, fx = np.meshgrid(np.fft.fftfreq(n), np.fft.rfftfreq(n), indexing="ij")
    kernel = np.exp(-2 * np.pi**2 * ((fx * sigma) ** 2 + (fy * sv) ** 2)).astype(np.float32)
    out = np.fft.irfft2(np.fft.rfft2(white) * kernel, s=(n, n)).astype(np.float64)
    return (out - out.mean()) / (out.std() + 1e-12)


def _grid(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(u, v) in [0, 1) per pixel; v grows downwards in the image (rows)."""
    t = np.arange(n) / n
    v, u = np.meshgrid(t, t, indexing="ij")
    return u, v


def _tone(base: NDArray[np.float64], shade: NDArray[np.float64]) -> NDArray[np.float64]:
    """Multiply a base colour (3,) by a per-pixel shade map (H, W)."""
    return base[None, None, :] * shade[..., None]


def _flecks(rng: np.random.Generator, n: int, density: float, size: float) -> NDArray[np.float64]:
    """Tileable signed flecks (dark and light dots of ``size`` pixels), peak magnitude ~1, zero elsewhere."""
    dots = (rng.random((n, n)) < density) * rng.choice([-1.0, 1.0], (n, n))
    blurred = cv2.GaussianBlur(np.tile(dots, (3, 3)), (0, 0), size)[n : 2 * n, n : 2 * n]
    return blurred * (2 * np.pi * size**2)


def _wood(rng: np.random.Generator, n: int, base: NDArray, contrast: float, rings: int = 12) -> NDArray:
    """Grain running along u: growth rings (sawtooth of a gently warped v) and fine fibres."""
    u, v = _grid(n)
    warp = 0.6 * _noise(rng, n, n / 4, n / 10) / rings + 0.15 * _noise(rng, n, n / 3, n / 40) / rings
    f = np.mod(rings * (v + warp), 1.0)
    grain = f**3
    fibre = _noise(rng, n, n / 6, 0.7)
    if base.mean() > 0.8:
        contrast *= 0.25
    streaks = _noise(rng, n, n / 5, 2.0)
    pores = np.abs(_flecks(rng, n, 0.004, 0.9)) + 1.2 * np.abs(_flecks(rng, n, 0.0004, n / 90))
    shade = 1.0 - contrast * (
        0.26 * grain + 0.08 * fibre + 0.08 * streaks + 0.05 * _noise(rng, n, n / 3) + 0.12 * pores
    )
    return _tone(base, shade)


def _parquet(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    rows, per_row = 16, 3
    ph, pw = n // rows, n // per_row
    wood = _wood(rng, n, base, contrast, rings=30)
    out = np.empty_like(wood)
    for r in range(rows):
        offset = (r * 5 % 7) * (pw // 7)
        for k in range(per_row + 1):
            x0 = k * pw - offset
            tone = 1.0 + contrast * rng.normal(0, 0.12)
            sx, sy = rng.integers(0, n, 2)
            patch = wood[np.ix_((sy + np.arange(ph)) % n, (sx + np.arange(pw)) % n)] * tone
            out[r * ph : (r + 1) * ph, (x0 + np.arange(pw)) % n] = patch
    seam = np.ones((n, n))
    dark = 1 - 0.5 * min(contrast, 1.5)
    seam[(np.arange(n) % ph) < 2, :] = dark

    for r in range(rows):
        offset = (r * 5 % 7) * (pw // 7)
        for k in range(per_row + 1):
            x = (k * pw - offset) % n
            seam[r * ph : (r + 1) * ph, [x, (x + 1) % n]] = dark
    return out * seam[..., None]


def _tiles(
    rng: np.random.Generator, n: int, base: NDArray, contrast: float, count: int, level: str
) -> NDArray:
    step = n // count
    grout_w = max(3, n // 80)
    img = np.ones((n, n, 3)) * base
    for r in range(count):
        for c in range(count):
            tone = 1.0 + contrast * rng.normal(0, 0.05)
            img[r * step : (r + 1) * step, c * step : (c + 1) * step] *= tone
    stone = 0.015 * _noise(rng, n, 1.0) + 0.012 * _noise(rng, n, 4.0) + 0.12 * _flecks(rng, n, 0.004, 3.0)
    img *= (1.0 + contrast * stone)[..., None]
    if level == "rich":
        specks = (rng.random((n, n)) < 0.02).astype(float)
        specks = cv2.GaussianBlur(specks, (0, 0), 1.2) * 6
        img *= (1.0 - 0.5 * np.clip(specks, 0, 1) + 0.1 * _noise(rng, n, 6))[..., None]
    grout = np.zeros((n, n), bool)
    for k in range(count):
        grout[k * step : k * step + grout_w, :] = True
        grout[:, k * step : k * step + grout_w] = True
    lum = float(base.mean())
    g_col = base * (0.62 if lum > 0.55 else 1.35)
    g_col = base + min(contrast, 1.0) * (np.clip(g_col, 0, 1) - base)
    img[grout] = g_col
    return img


def _paint(rng: np.random.Generator, n: int, base: NDArray, level: str) -> NDArray:
    if level == "rich":
        u, v = _grid(n)
        stripes = 0.06 * np.sign(np.sin(2 * np.pi * 8 * u))
        motif = np.cos(2 * np.pi * 8 * (u + 1 / 16)) * np.cos(2 * np.pi * 12 * v)
        motif = 0.12 * (motif > 0.6)
        shade = 1.0 + stripes - motif + 0.05 * _noise(rng, n, 1.5) + 0.04 * _noise(rng, n, 12)
        return _tone(base, shade)
    # Paint over a faint plaster/woodchip ground: roller mottling, plaster grain and sparse chips of
    # ~1.5 cm; still the hardest surface.
    amp = {"realistic": 1.0, "sparse": 0.15}[level]
    chips = np.abs(_flecks(rng, n, 0.001, 2.0))
    plaster = 0.012 * _noise(rng, n, 2.5) + 0.012 * _noise(rng, n, n / 8) + 0.002 * _noise(rng, n, 1.0)
    shade = 1.0 + amp * (plaster - 0.14 * chips)
    return _tone(base, shade)


def _wallpaper(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    """Printed wallpaper: pin stripes and a staggered small floral motif over paper grain."""
    u, v = _grid(n)
    stripes = (np.mod(8 * u, 1.0) < 0.06).astype(float)
    img = np.zeros((n, n))
    step = n // 4
    for r in range(4):
        for k in range(4):
            cx = k * step + step // 2 + (step // 2 if r % 2 else 0)
            cy = r * step + step // 2
            for a in range(5):
                ang = 2 * np.pi * a / 5 + (r % 2) * 0.6
                p = (int(cx + 0.16 * step * np.cos(ang)) % n, int(cy + 0.16 * step * np.sin(ang)) % n)
                for dx in (-n, 0, n):
                    for dy in (-n, 0, n):
                        cv2.circle(img, (p[0] + dx, p[1] + dy), step // 12, 1.0, -1)
            for dx in (-n, 0, n):
                cv2.circle(img, (cx % n + dx, cy), step // 16, -1.0, -1)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    shade = 1.0 + contrast * (-0.16 * img - 0.06 * stripes + 0.01 * _noise(rng, n, 1.0))
    return _tone(base, shade)


def _carpet(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    u, v = _grid(n)
    loops = np.sin(2 * np.pi * 24 * u) * np.sin(2 * np.pi * 24 * v)
    shade = 1.0 + contrast * (
        0.08 * _noise(rng, n, 0.8)
        + 0.06 * _noise(rng, n, 2.5)
        + 0.05 * _noise(rng, n, n / 10)
        + 0.04 * loops
        + 0.2 * _flecks(rng, n, 0.003, 3.0)
    )
    return _tone(base, shade)


def _fabric(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    u, v = _grid(n)
    weave = np.sin(2 * np.pi * 32 * u) * np.sin(2 * np.pi * 32 * v)
    slubs = _noise(rng, n, 6.0, 1.0) + _noise(rng, n, 1.0, 6.0)
    shade = 1.0 + contrast * (
        0.07 * weave
        + 0.05 * _noise(rng, n, 1.0)
        + 0.05 * slubs
        + 0.04 * _noise(rng, n, n / 6)
        + 0.15 * _flecks(rng, n, 0.003, 2.5)
    )
    return _tone(base, shade)


def _brick(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    rows, per_row = 16, 5
    bh, bw = n // rows, n // per_row
    mortar = max(2, n // 100)
    img = np.empty((n, n, 3))
    for r in range(rows):
        off = bw // 2 if r % 2 else 0
        for k in range(per_row + 1):
            tone = base * (
                1.0 + contrast * rng.normal(0, 0.09, 3).clip(-0.25, 0.25) * np.array([1, 0.9, 0.8])
            )
            xs = (np.arange(bw) + k * bw - off) % n
            img[r * bh : (r + 1) * bh, xs] = tone
    img *= (1.0 + contrast * (0.08 * _noise(rng, n, 1.5) + 0.05 * _noise(rng, n, 8)))[..., None]
    m_col = np.array([0.78, 0.76, 0.72])
    m_col = base + min(contrast, 1.0) * (m_col - base)
    for r in range(rows):
        img[r * bh : r * bh + mortar, :] = m_col
        off = bw // 2 if r % 2 else 0
        for k in range(per_row + 1):
            x = (k * bw - off) % n
            img[r * bh : (r + 1) * bh, x : x + mortar] = m_col
    return img


def _speckled(
    rng: np.random.Generator, n: int, base: NDArray, contrast: float, density: float, chips: float = 0.0
) -> NDArray:
    """Fine dark specks of ``density`` per pixel plus, optionally, larger signed chips (vinyl, terrazzo)."""
    specks = (rng.random((n, n)) < density).astype(float)
    specks = cv2.GaussianBlur(np.tile(specks, (3, 3)), (0, 0), 1.2)[n : 2 * n, n : 2 * n] * 5
    shade = 1.0 + contrast * (
        0.03 * _noise(rng, n, n / 10) + 0.02 * _noise(rng, n, 1.0) + 0.02 * _noise(rng, n, 4.0) - 0.3 * specks
    )
    if chips:
        shade += contrast * 0.12 * _flecks(rng, n, chips, 2.5)
    return _tone(base, shade)


def _marble(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    u, v = _grid(n)
    turb = 1.5 * _noise(rng, n, n / 10) + 0.5 * _noise(rng, n, n / 30)
    veins = np.abs(np.sin(2 * np.pi * (2 * u + 3 * v) + turb)) ** 0.3
    dark = base.mean() < 0.5
    shade = 1.0 + contrast * (0.18 if dark else -0.18) * (1 - veins)
    return _tone(base, shade)


def _brushed(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    return _tone(base, 1.0 + contrast * (0.04 * _noise(rng, n, n / 4, 0.7) + 0.02 * _noise(rng, n, n / 5)))


def _leaves(rng: np.random.Generator, n: int, base: NDArray, contrast: float) -> NDArray:
    img = np.ones((n, n, 3)) * base * 0.6
    for _ in range(220):
        c = (int(rng.integers(0, n)), int(rng.integers(0, n)))
        axes = (int(rng.integers(n // 30, n // 12)), int(rng.integers(n // 70, n // 30)))
        col = np.clip(base * (1 + contrast * rng.normal(0, 0.25)), 0, 1)
        for dx in (-n, 0, n):
            for dy in (-n, 0, n):
                cv2.ellipse(
                    img, (c[0] + dx, c[1] + dy), axes, float(rng.uniform(0, 180)), 0, 360, col.tolist(), -1
                )
    return img


def _picture(rng: np.random.Generator, n: int, contrast: float) -> NDArray:
    """A framed painting's canvas: a landscape or an abstract composition."""
    img = np.zeros((n, n, 3))
    if rng.random() < 0.5:
        sky_top, sky_bottom = rng.uniform(0.3, 0.9, 3), rng.uniform(0.6, 1.0, 3)
        t = np.linspace(0, 1, n)[:, None, None]
        img[:] = sky_top * (1 - t) + sky_bottom * t
        cx, cy = int(rng.integers(n // 5, 4 * n // 5)), int(rng.integers(n // 8, n // 3))
        cv2.circle(img, (cx, cy), int(rng.integers(n // 20, n // 9)), rng.uniform(0.8, 1.0, 3).tolist(), -1)
        x = np.arange(n)
        for layer in range(3):
            h = n * (0.45 + 0.15 * layer) + n * 0.08 * np.sin(
                2 * np.pi * x / n * rng.uniform(1, 3) + rng.uniform(0, 6)
            )
            col = rng.uniform(0.1, 0.7, 3) * np.array([0.7, 1.0, 0.6])
            for xi in range(n):
                img[int(h[xi]) :, xi] = col
        for _ in range(int(rng.integers(2, 5))):
            hx, hy, hw = int(rng.integers(0, n)), int(rng.integers(n // 2, 3 * n // 4)), n // 12
            cv2.rectangle(img, (hx, hy), (hx + hw, hy + hw), rng.uniform(0.5, 0.95, 3).tolist(), -1)
            cv2.fillConvexPoly(
                img,
                np.array([[hx - 3, hy], [hx + hw + 3, hy], [hx + hw // 2, hy - hw // 2]], np.int32),
                rng.uniform(0.2, 0.6, 3).tolist(),
            )
            door = ((hx + hw // 3, hy + hw // 3), (hx + 2 * hw // 3, hy + hw))
            cv2.rectangle(img, *door, (0.15, 0.1, 0.1), -1)
        for _ in range(int(rng.integers(8, 16))):
            tx, ty = int(rng.integers(0, n)), int(rng.integers(n // 2, n))
            cv2.rectangle(img, (tx - 2, ty), (tx + 2, ty + n // 12), (0.25, 0.17, 0.1), -1)
            cv2.circle(
                img, (tx, ty), int(rng.integers(n // 30, n // 14)), rng.uniform(0.05, 0.4, 3).tolist(), -1
            )
    else:
        img[:] = rng.uniform(0.5, 0.95, 3)
        for _ in range(int(rng.integers(12, 24))):
            col = rng.uniform(0.05, 0.95, 3).tolist()
            p = rng.integers(0, n, 4)
            if rng.random() < 0.6:
                cv2.rectangle(img, (int(p[0]), int(p[1])), (int(p[2]), int(p[3])), col, -1)
            else:
                cv2.circle(img, (int(p[0]), int(p[1])), int(rng.integers(n // 16, n // 4)), col, -1)
            if rng.random() < 0.3:
                cv2.line(img, (int(p[0]), 0), (int(p[0]), n), (0.05, 0.05, 0.05), int(rng.integers(2, 6)))
    strokes = _noise(rng, n, 2.0, 0.7)
    img = cv2.GaussianBlur(img, (0, 0), 0.8) * (1.0 + 0.06 * strokes)[..., None]
    return img.mean() + contrast * (img - img.mean())


def _poster(rng: np.random.Generator, n: int, contrast: float) -> NDArray:
    """A printed poster: coloured background, a title, lines of text and a block figure."""
    bg = rng.uniform(0.75, 1.0, 3) if rng.random() < 0.6 else rng.uniform(0.1, 0.5, 3)
    ink = (10, 10, 20) if bg.mean() > 0.5 else (240, 240, 230)
    img = np.ascontiguousarray(np.broadcast_to(np.round(bg * 255).astype(np.uint8), (n, n, 3)))

    def col() -> tuple[int, int, int]:
        return tuple(int(c) for c in rng.integers(20, 235, 3))  # type: ignore[return-value]

    def word(k: int) -> str:
        return "".join(rng.choice(list(string.ascii_uppercase), size=k))

    cv2.rectangle(img, (0, 0), (n, n // 5), col(), -1)
    cv2.putText(
        img, word(int(rng.integers(4, 8))), (n // 14, n // 7), cv2.FONT_HERSHEY_DUPLEX, n / 300, ink, 2
    )
    fig = rng.integers(n // 4, n // 2, 2)
    cv2.rectangle(img, (n // 10, n // 4), (n // 10 + int(fig[0]), n // 4 + int(fig[1])), col(), -1)
    cv2.circle(img, (3 * n // 4, n // 2), n // 8, col(), -1)
    y = n // 4 + int(fig[1]) + n // 12
    while y < n - n // 20:
        line = " ".join(word(int(rng.integers(2, 7))) for _ in range(3)).lower()
        cv2.putText(img, line, (n // 12, y), cv2.FONT_HERSHEY_SIMPLEX, n / 900, ink, 1)
        y += n // 16
    out = img.astype(float) / 255.0
    return out.mean() + contrast * (out - out.mean())


def _books(rng: np.random.Generator, n: int, contrast: float) -> NDArray:
    """Book spines standing on the bottom edge (image bottom = v 0), dark shelf interior above."""
    img = np.ones((n, n, 3)) * 0.12
    x = 0
    palette = np.array(
        [
            [0.55, 0.1, 0.1],
            [0.1, 0.2, 0.5],
            [0.1, 0.4, 0.2],
            [0.85, 0.8, 0.65],
            [0.2, 0.2, 0.2],
            [0.7, 0.45, 0.1],
            [0.5, 0.3, 0.5],
            [0.9, 0.9, 0.9],
            [0.3, 0.5, 0.6],
        ]
    )
    while x < n:
        w = int(rng.integers(n // 40, n // 14))
        h = int(n * rng.uniform(0.6, 0.9))
        col = palette[rng.integers(len(palette))] * rng.uniform(0.8, 1.1)
        x1 = min(n, x + w)
        img[n - h :, x:x1] = col
        for _ in range(int(rng.integers(0, 3))):
            yb = n - int(h * rng.uniform(0.1, 0.9))
            img[yb : yb + max(1, n // 100), x:x1] = (0.85, 0.7, 0.3) if rng.random() < 0.5 else col * 0.5
        img[n - h : n, x1 - 1 : x1] *= 0.5
        x = x1
    img *= (1.0 + 0.04 * _noise(rng, n, 1.0))[..., None]
    return img.mean() + contrast * (img - img.mean())


_SIZE_512 = {"parquet", "brick"}

_CONTRAST = {"rich": 2.4, "realistic": 1.8, "sparse": 0.2}


def _image(kind: str, base: NDArray, level: str, rng: np.random.Generator) -> NDArray:
    n = 512 if kind in _SIZE_512 else 256
    c = _CONTRAST[level]
    gens: dict[str, Callable[[], NDArray]] = {
        "paint": lambda: _paint(rng, n, base, level),
        "wallpaper": lambda: _wallpaper(rng, n, base, c),
        "wood": lambda: _wood(rng, n, base, c),
        "parquet": lambda: _parquet(rng, n, base, c),
        "tiles": lambda: _tiles(rng, n, base, c, 6, level),
        "smalltiles": lambda: _tiles(rng, n, base, c, 4, level),
        "carpet": lambda: _carpet(rng, n, base, c),
        "fabric": lambda: _fabric(rng, n, base, c),
        "linoleum": lambda: _speckled(rng, n, base, c, 0.03, chips=0.012),
        "concrete": lambda: _speckled(rng, n, base, 1.5 * c, 0.004),
        "brick": lambda: _brick(rng, n, base, c),
        "marble": lambda: _marble(rng, n, base, c),
        "metal": lambda: _brushed(rng, n, base, c),
        "plastic": lambda: _speckled(rng, n, base, 0.5 * c, 0.0),
        "ceramic": lambda: _speckled(rng, n, base, 0.3 * c, 0.0),
        "skin": lambda: _speckled(rng, n, base, 0.3 * c, 0.0),
        "screen": lambda: _tone(base, 1.0 + 0.3 * np.linspace(-1, 1, n)[None, :] * np.ones((n, 1))),
        "leaves": lambda: _leaves(rng, n, base, max(c, 0.3)),
        "picture": lambda: _picture(rng, n, min(c, 1.4)),
        "poster": lambda: _poster(rng, n, min(c, 1.4)),
        "books": lambda: _books(rng, n, min(c, 1.4)),
    }
    img = gens[kind]()
    if level == "rich" and kind not in ("paint", "picture", "poster", "books"):
        img = img * (1.0 + 0.07 * _noise(rng, n, 1.2) + 0.05 * _noise(rng, n, 5))[..., None]
    return img


@lru_cache(maxsize=512)
def make_material(
    name: str, level: str = "realistic", seed: int = 0, tile_m: float | None = None
) -> Material:
    """The material ``kind[:variant]`` at a texture level; same arguments, same (shared, read-only) image.

    ``tile_m`` overrides the kind's default repeat length (metres per texture tile).
    """
    if level not in TEXTURE_LEVELS:
        raise ValueError(f"unknown texture level {level!r}; allowed: {list(TEXTURE_LEVELS)}")
    kind, variant = parse_material_name(name)
    rng = np.random.default_rng([zlib.crc32(f"{kind}:{variant}".encode()), int(seed) & 0xFFFFFFFF])
    base = np.asarray(_PALETTES[kind][variant], float) / 255.0
    img = _image(kind, base, level, rng)
    image = np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
    image.setflags(write=False)
    mean = image.reshape(-1, 3).mean(axis=0) / 255.0
    return Material(
        name=f"{kind}:{variant}"
        + (f"#{seed}" if seed else "")
        + (f"@{tile_m:g}" if tile_m is not None else ""),
        rgba=(float(mean[0]), float(mean[1]), float(mean[2]), 1.0),
        image=image,
        tile_m=float(tile_m if tile_m is not None else _TILE_M[kind]),
        specular=0.15 if kind in ("metal", "ceramic", "screen") else 0.05,
    )
