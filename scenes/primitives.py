"""Parametric furniture made of boxes and cylinders, in the object's local frame.

Local frame (see ``spec``): origin at the footprint centre on the object's base, x = width,
y = depth with the front facing +y, z up. Every part has a material *role* (``main``, ``legs``,
``books``...); an object's roles map to material names through the kind's defaults, the object's
``material`` (role ``main``) and its ``materials`` overrides.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Size = tuple[float, float, float]


@dataclass(frozen=True)
class Part:
    """A box (``size`` = extents) or z-aligned cylinder (diameter = size[0]) centred at ``centre``."""

    role: str
    shape: str
    size: Size
    centre: tuple[float, float, float]
    collide: bool = True


def _box(
    role: str, sx: float, sy: float, sz: float, cx: float, cy: float, z0: float, collide: bool = True
) -> Part:
    return Part(role, "box", (sx, sy, sz), (cx, cy, z0 + sz / 2), collide)


def _legs(w: float, d: float, h: float, t: float = 0.05, inset: float = 0.04) -> list[Part]:
    xs, ys = w / 2 - inset - t / 2, d / 2 - inset - t / 2
    return [_box("legs", t, t, h, sx * xs, sy * ys, 0.0) for sx in (-1, 1) for sy in (-1, 1)]


def _table(w: float, d: float, h: float) -> list[Part]:
    top = 0.04
    return [_box("main", w, d, top, 0, 0, h - top), *_legs(w, d, h - top)]


def _chair(w: float, d: float, h: float) -> list[Part]:
    seat_h = min(0.46, 0.55 * h)
    return [
        _box("main", w, d, 0.05, 0, 0, seat_h - 0.05),
        _box("main", w, 0.05, h - seat_h, 0, -d / 2 + 0.025, seat_h),
        *_legs(w, d, seat_h - 0.05, 0.04, 0.02),
    ]


def _sofa(w: float, d: float, h: float) -> list[Part]:
    arm_w, back_d, seat_h = 0.18, 0.22, 0.42
    return [
        _box("main", w, d, seat_h, 0, 0, 0.0),
        _box("main", w, back_d, h - seat_h, 0, -d / 2 + back_d / 2, seat_h),
        _box("main", arm_w, d - back_d, 0.2, -w / 2 + arm_w / 2, back_d / 2, seat_h),
        _box("main", arm_w, d - back_d, 0.2, w / 2 - arm_w / 2, back_d / 2, seat_h),
        _box("cushion", w - 2 * arm_w - 0.04, d - back_d - 0.06, 0.1, 0, back_d / 2, seat_h),
    ]


def _bed(w: float, d: float, h: float) -> list[Part]:
    frame_h, mattress_h = 0.3, 0.2
    return [
        _box("frame", w, d, frame_h, 0, 0, 0.0),
        _box("main", w - 0.06, d - 0.1, mattress_h, 0, 0.03, frame_h),
        _box("frame", w, 0.08, h, 0, -d / 2 + 0.04, 0.0),
        _box("pillow", 0.7 * w, 0.35, 0.12, 0, -d / 2 + 0.3, frame_h + mattress_h),
    ]


def _hospital_bed(w: float, d: float, h: float) -> list[Part]:
    base_h = 0.5
    return [
        *_legs(w, d, 0.3, 0.06, 0.05),
        _box("frame", w, d, base_h - 0.3, 0, 0, 0.3),
        _box("main", w - 0.06, d - 0.12, 0.16, 0, 0, base_h),
        _box("boards", w, 0.05, h, 0, -d / 2 + 0.025, 0.3),
        _box("boards", w, 0.05, 0.45 * h + 0.3, 0, d / 2 - 0.025, 0.3),
        _box("frame", 0.03, 0.5 * d, 0.25, -w / 2 + 0.015, -0.1 * d, base_h + 0.16),
        _box("pillow", 0.6 * w, 0.3, 0.1, 0, -d / 2 + 0.25, base_h + 0.16),
    ]


def _shelf(w: float, d: float, h: float) -> list[Part]:
    t = 0.025
    n = max(2, int(round(h / 0.38)))
    parts = [
        _box("main", t, d, h, -w / 2 + t / 2, 0, 0.0),
        _box("main", t, d, h, w / 2 - t / 2, 0, 0.0),
        _box("main", w, 0.012, h, 0, -d / 2 + 0.006, 0.0),
    ]
    pitch = (h - t) / n
    for i in range(n + 1):
        parts.append(_box("main", w - 2 * t, d - 0.012, t, 0, 0.006, i * pitch))
        if i < n:
            bh = min(0.29, pitch - t - 0.02)
            parts.append(_box("books", w - 2 * t - 0.01, 0.7 * d, bh, 0, -0.1 * d, i * pitch + t, False))
    return parts


def _cabinet(w: float, d: float, h: float) -> list[Part]:
    n_doors = max(1, int(round(w / 0.5)))
    dw = (w - 0.02 * (n_doors + 1)) / n_doors
    parts = [_box("main", w, d - 0.02, h, 0, -0.01, 0.0)]
    for i in range(n_doors):
        cx = -w / 2 + 0.02 + dw / 2 + i * (dw + 0.02)
        parts.append(_box("doors", dw, 0.02, h - 0.06, cx, d / 2 - 0.01, 0.03, False))
        hx = cx + (dw / 2 - 0.06) * (1 if i % 2 == 0 else -1)
        parts.append(_box("handles", 0.02, 0.02, min(0.2, 0.3 * h), hx, d / 2 + 0.01, 0.6 * h - 0.1, False))
    return parts


def _counter(w: float, d: float, h: float) -> list[Part]:
    top = 0.04
    return [*_cabinet(w, d - 0.03, h - top), _box("top", w + 0.02, d + 0.02, top, 0, 0.0, h - top)]


def _person(w: float, d: float, h: float) -> list[Part]:
    s = h / 1.7
    leg_h, torso_h, head = 0.8 * s, 0.6 * s, 0.24 * s
    leg_w, arm_w = 0.15 * w / 0.5, 0.09 * w / 0.5
    torso_w = w - 2 * arm_w - 0.02
    return [
        _box("trousers", leg_w, 0.6 * d, leg_h, -torso_w / 4, 0, 0.0),
        _box("trousers", leg_w, 0.6 * d, leg_h, torso_w / 4, 0, 0.0),
        _box("shoes", leg_w, 0.9 * d, 0.06, -torso_w / 4, 0.05 * d, 0.0),
        _box("shoes", leg_w, 0.9 * d, 0.06, torso_w / 4, 0.05 * d, 0.0),
        _box("main", torso_w, 0.65 * d, torso_h, 0, 0, leg_h),
        _box("main", arm_w, 0.5 * d, 0.58 * s, -w / 2 + arm_w / 2, 0, leg_h + torso_h - 0.58 * s),
        _box("main", arm_w, 0.5 * d, 0.58 * s, w / 2 - arm_w / 2, 0, leg_h + torso_h - 0.58 * s),
        _box("skin", 0.08 * s, 0.08 * s, h - leg_h - torso_h - head, 0, 0, leg_h + torso_h),
        Part("skin", "cylinder", (0.19 * s, 0.19 * s, head), (0, 0, h - head / 2)),
    ]


def _plant(w: float, d: float, h: float) -> list[Part]:
    pot_h = 0.3 * h
    return [
        Part("pot", "cylinder", (0.6 * min(w, d), 0.6 * min(w, d), pot_h), (0, 0, pot_h / 2)),
        Part("main", "cylinder", (min(w, d), min(w, d), h - pot_h), (0, 0, pot_h + (h - pot_h) / 2)),
    ]


def _picture(w: float, d: float, h: float) -> list[Part]:
    return [
        _box("frame", w, d, h, 0, 0, 0.0, False),
        _box("canvas", w - 0.08, 0.005, h - 0.08, 0, d / 2 + 0.0025, 0.04, False),
    ]


def _poster(w: float, d: float, h: float) -> list[Part]:
    return [_box("canvas", w, d, h, 0, 0, 0.0, False)]


def _panel(w: float, d: float, h: float) -> list[Part]:
    """A thin wall cladding (tiles, whiteboard, backsplash); no collision (it lies on a wall)."""
    return [_box("main", w, d, h, 0, 0, 0.0, False)]


def _rug(w: float, d: float, h: float) -> list[Part]:
    return [_box("main", w, d, h, 0, 0, 0.0, False)]


def _toilet(w: float, d: float, h: float) -> list[Part]:
    return [
        Part("main", "cylinder", (0.8 * w, 0.8 * w, 0.42), (0, 0.1 * d, 0.21)),
        _box("main", w, 0.2, h, 0, -d / 2 + 0.1, 0.0),
    ]


def _sink(w: float, d: float, h: float) -> list[Part]:
    return [*_cabinet(w, d, h - 0.15), _box("top", w, d, 0.15, 0, 0, h - 0.15)]


def _bathtub(w: float, d: float, h: float) -> list[Part]:
    t = 0.08
    return [
        _box("main", w, d, 0.15, 0, 0, 0.0),
        _box("main", w, t, h, 0, -d / 2 + t / 2, 0.0),
        _box("main", w, t, h, 0, d / 2 - t / 2, 0.0),
        _box("main", t, d - 2 * t, h, -w / 2 + t / 2, 0, 0.0),
        _box("main", t, d - 2 * t, h, w / 2 - t / 2, 0, 0.0),
    ]


def _tv(w: float, d: float, h: float) -> list[Part]:
    stand_h = 0.5 * h
    return [
        *_cabinet(w, d, stand_h),
        _box("screen", 0.8 * w, 0.05, h - stand_h - 0.05, 0, -d / 4, stand_h + 0.05, True),
    ]


def _screen(w: float, d: float, h: float) -> list[Part]:
    """A privacy screen / curtain panel on two feet."""
    return [
        _box("legs", 0.04, d, 0.04, -w / 2 + 0.05, 0, 0.0),
        _box("legs", 0.04, d, 0.04, w / 2 - 0.05, 0, 0.0),
        _box("main", w, 0.03, h - 0.2, 0, 0, 0.2),
        _box("legs", 0.03, 0.03, 0.2, -w / 2 + 0.05, 0, 0.0),
        _box("legs", 0.03, 0.03, 0.2, w / 2 - 0.05, 0, 0.0),
    ]


def _box_kind(w: float, d: float, h: float) -> list[Part]:
    return [_box("main", w, d, h, 0, 0, 0.0)]


def _cylinder_kind(w: float, d: float, h: float) -> list[Part]:
    return [Part("main", "cylinder", (w, d, h), (0, 0, h / 2))]


@dataclass(frozen=True)
class Primitive:
    build: Callable[[float, float, float], list[Part]]
    size: Size
    materials: dict[str, str]


PRIMITIVES: dict[str, Primitive] = {
    "box": Primitive(_box_kind, (0.6, 0.4, 0.5), {"main": "wood:pine"}),
    "cylinder": Primitive(_cylinder_kind, (0.4, 0.4, 0.8), {"main": "plastic:grey"}),
    "table": Primitive(_table, (1.4, 0.8, 0.75), {"main": "wood:oak", "legs": "wood:dark"}),
    "desk": Primitive(_table, (1.2, 0.6, 0.75), {"main": "wood:white", "legs": "metal:steel"}),
    "chair": Primitive(_chair, (0.45, 0.5, 0.9), {"main": "wood:walnut", "legs": "wood:dark"}),
    "sofa": Primitive(_sofa, (2.0, 0.9, 0.85), {"main": "fabric:grey", "cushion": "fabric:beige"}),
    "armchair": Primitive(_sofa, (0.9, 0.85, 0.85), {"main": "fabric:teal", "cushion": "fabric:beige"}),
    "bed": Primitive(
        _bed, (1.6, 2.05, 1.0), {"main": "fabric:white", "frame": "wood:oak", "pillow": "fabric:lightblue"}
    ),
    "hospital_bed": Primitive(
        _hospital_bed,
        (1.0, 2.1, 1.0),
        {
            "main": "fabric:lightblue",
            "frame": "metal:steel",
            "legs": "metal:black",
            "boards": "plastic:white",
            "pillow": "fabric:white",
        },
    ),
    "shelf": Primitive(_shelf, (1.0, 0.35, 1.9), {"main": "wood:white", "books": "books"}),
    "cabinet": Primitive(
        _cabinet, (1.0, 0.5, 0.9), {"main": "wood:white", "doors": "wood:white", "handles": "metal:steel"}
    ),
    "wardrobe": Primitive(
        _cabinet, (1.2, 0.6, 2.1), {"main": "wood:oak", "doors": "wood:oak", "handles": "metal:steel"}
    ),
    "fridge": Primitive(
        _cabinet, (0.7, 0.7, 1.85), {"main": "metal:white", "doors": "metal:white", "handles": "metal:steel"}
    ),
    "counter": Primitive(
        _counter,
        (2.4, 0.62, 0.92),
        {"main": "wood:white", "doors": "wood:white", "handles": "metal:steel", "top": "marble:dark"},
    ),
    "person": Primitive(
        _person,
        (0.5, 0.35, 1.7),
        {"main": "fabric:red", "trousers": "fabric:navy", "shoes": "plastic:grey", "skin": "skin:light"},
    ),
    "plant": Primitive(_plant, (0.5, 0.5, 1.2), {"main": "leaves", "pot": "ceramic"}),
    "picture": Primitive(_picture, (0.8, 0.03, 0.6), {"frame": "wood:dark", "canvas": "picture"}),
    "poster": Primitive(_poster, (0.5, 0.005, 0.7), {"canvas": "poster"}),
    "panel": Primitive(_panel, (1.0, 0.01, 1.5), {"main": "smalltiles:white"}),
    "bench": Primitive(_table, (1.6, 0.45, 0.45), {"main": "wood:pine", "legs": "metal:black"}),
    "rug": Primitive(_rug, (2.0, 1.4, 0.01), {"main": "carpet:red"}),
    "toilet": Primitive(_toilet, (0.4, 0.65, 0.8), {"main": "ceramic"}),
    "sink": Primitive(
        _sink,
        (0.8, 0.5, 0.9),
        {"main": "wood:white", "doors": "wood:white", "handles": "metal:steel", "top": "ceramic"},
    ),
    "bathtub": Primitive(_bathtub, (1.7, 0.75, 0.55), {"main": "ceramic"}),
    "tv": Primitive(
        _tv,
        (1.6, 0.45, 1.25),
        {"main": "wood:dark", "doors": "wood:dark", "handles": "metal:black", "screen": "screen"},
    ),
    "screen": Primitive(_screen, (1.2, 0.4, 1.8), {"main": "fabric:lightblue", "legs": "metal:steel"}),
}

PRIMITIVE_KINDS: frozenset[str] = frozenset(PRIMITIVES)

# Roles whose texture shows one image per part (the image is fitted to the part, not tiled).
FITTED_ROLES: frozenset[str] = frozenset({"canvas"})


def primitive_parts(kind: str, size: Size | None) -> tuple[Size, list[Part]]:
    """(size used, parts) for a primitive kind; ``size`` None takes the kind's default size."""
    prim = PRIMITIVES[kind]
    s = prim.size if size is None else size
    parts = prim.build(*s)
    assert all(np.all(np.asarray(p.size) > 0) for p in parts), f"degenerate part in {kind} of size {s}"
    return s, parts


def role_materials(kind: str, material: str | None, overrides: dict[str, str]) -> dict[str, str]:
    """Material name per role: kind defaults, then ``material`` for ``main``, then overrides."""
    mats = dict(PRIMITIVES[kind].materials)
    if material is not None:
        mats["main" if "main" in mats else next(iter(mats))] = material
    mats.update(overrides)
    return mats
