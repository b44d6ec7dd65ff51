"""Procedural scenes of a style (``home``, ``hospital``) from a seed: unseen layouts, same spec types.

Plan: the outer rectangle is cut into a south band of rooms, a corridor and a north band of rooms
(a grid-style split); every room gets a door to the corridor (the home's living room also one to
the kitchen). Furniture is sampled per room kind from the style's catalogue and placed with its
back against a wall (or free-standing with clearance), without overlaps, away from doors, and only
if the free space stays connected for the robot (``freespace.connectivity_report``). Pictures and
posters go on free wall spans. ``changed`` / ``changed2`` move, remove and add objects (people,
boxes). Everything is a pure function of (style, seed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vgpnav_env.scenes.freespace import blocks, connectivity_report, footprint
from vgpnav_env.scenes.primitives import PRIMITIVES
from vgpnav_env.scenes.spec import DoorSpec, LayoutEdit, ObjectSpec, RoomSpec, SceneError, SceneSpec, WallSpec

#: Clearance (m) of the free-space check when accepting placements (passages >= 0.5 m + discretisation).
PLACEMENT_CLEARANCE = 0.25
MAX_LOST = 0.08  # largest fraction of navigable cells allowed outside the main component
#: Furniture, materials and movable kinds per style (package data beside the built-in scenes).
CATALOGUE_FILE = Path(__file__).parent / "builtin" / "catalogue.yaml"


@dataclass(frozen=True)
class Item:
    """A catalogue entry: kind, category, size ranges (w, d, h), material choices, placement, count."""

    kind: str
    category: str
    size: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
    materials: tuple[str, ...] = ()
    place: str = "wall"  # wall | free | table (a chair at a table of the room, else at a wall)
    count: tuple[int, int] = (1, 1)
    roles: tuple[tuple[str, tuple[str, ...]], ...] = ()


def _choices(values: list[str]) -> tuple[str, ...]:
    return tuple(str(v) for v in values)


def _item(entry: dict[str, Any]) -> Item:
    return Item(
        kind=entry["kind"],
        category=entry["category"],
        size=tuple((float(lo), float(hi)) for lo, hi in entry["size"]),  # type: ignore[arg-type]
        materials=_choices(entry.get("materials", [])),
        place=entry.get("place", "wall"),
        count=tuple(int(n) for n in entry.get("count", (1, 1))),  # type: ignore[arg-type]
        roles=tuple((role, _choices(choices)) for role, choices in entry.get("roles", {}).items()),
    )


@dataclass(frozen=True)
class Catalogue:
    """What procedural scenes are made of (``builtin/catalogue.yaml``): ``plan[style]`` band
    dimension ranges, ``furniture[style][room kind]``, ``floors[style][room kind]`` and
    ``paints[style]`` material choices, what people wear and the object kinds the changed layouts
    may move."""

    plan: dict[str, dict[str, tuple[float, float]]]
    furniture: dict[str, dict[str, tuple[Item, ...]]]
    floors: dict[str, dict[str, tuple[str, ...]]]
    paints: dict[str, tuple[str, ...]]
    tops: tuple[str, ...]
    trousers: tuple[str, ...]
    skins: tuple[str, ...]
    movable: frozenset[str]


@lru_cache(maxsize=1)
def load_catalogue(path: Path = CATALOGUE_FILE) -> Catalogue:
    """The catalogue YAML as typed data (cached; treat it as read-only)."""
    data = yaml.safe_load(Path(path).read_text())
    return Catalogue(
        plan={
            style: {k: (float(lo), float(hi)) for k, (lo, hi) in ranges.items()}
            for style, ranges in data["plan"].items()
        },
        furniture={
            style: {room: tuple(_item(e) for e in items) for room, items in rooms.items()}
            for style, rooms in data["furniture"].items()
        },
        floors={
            style: {room: _choices(c) for room, c in rooms.items()} for style, rooms in data["floors"].items()
        },
        paints={style: _choices(c) for style, c in data["paints"].items()},
        tops=_choices(data["people"]["tops"]),
        trousers=_choices(data["people"]["trousers"]),
        skins=_choices(data["people"]["skins"]),
        movable=frozenset(data["movable"]),
    )


@dataclass
class _Room:
    name: str
    kind: str
    x0: float
    y0: float
    x1: float
    y1: float
    doors: list[tuple[str, float, float]]  # (side 'S'|'N'|'W'|'E', centre coordinate along side, width)


def _u(rng: np.random.Generator, lo: float, hi: float, digits: int | None = None) -> float:
    v = float(rng.uniform(lo, hi))
    return v if digits is None else round(v, digits)


def _split(rng: np.random.Generator, total: float, widths: list[tuple[float, float]]) -> list[float]:
    """Cut a length into pieces with the given (min, max) widths; the last piece absorbs the rest."""
    cuts, pos = [0.0], 0.0
    for lo, hi in widths[:-1]:
        pos = round(pos + _u(rng, lo, hi), 2)
        cuts.append(pos)
    cuts.append(total)
    return cuts


def _bands(rng: np.random.Generator, style: str) -> tuple[float, float, float, float]:
    """(width W, depth H, corridor's south edge ys, its north edge yc) of a plan, metres: a south
    band of rooms, a corridor and a north band with depths drawn from the catalogue's ranges."""
    ranges = load_catalogue().plan[style]
    W, south_d, corr_w, north_d = (_u(rng, *ranges[k], 2) for k in ("width", "south", "corridor", "north"))
    return W, round(south_d + corr_w + north_d, 2), south_d, round(south_d + corr_w, 2)


def _plan_home(rng: np.random.Generator) -> tuple[float, float, list[_Room], float, float]:
    W, H, ys, yc = _bands(rng, "home")
    W = min(W, round(118.0 / H, 2))
    xk = round(W * _u(rng, 0.55, 0.65), 2)
    rooms = [_Room("living", "living", 0, 0, xk, ys, []), _Room("kitchen", "kitchen", xk, 0, W, ys, [])]
    if rng.random() < 0.5:
        rooms[0].x0, rooms[0].x1, rooms[1].x0, rooms[1].x1 = W - xk, W, 0, W - xk
    north_kinds = ["bedroom", "bath", "bedroom"] + (["bedroom"] if W > 11.3 else [])
    order = list(rng.permutation(len(north_kinds)))
    kinds = [north_kinds[i] for i in order]
    spans = [(2.2, 2.7) if k == "bath" else (3.0, 4.4) for k in kinds]
    cuts = _split(rng, W, spans)
    if cuts[-1] - cuts[-2] < (2.2 if kinds[-1] == "bath" else 2.8):
        cuts = [round(float(c), 2) for c in np.linspace(0, W, len(kinds) + 1)]
    nb = 0
    for k, (a, b) in zip(kinds, zip(cuts[:-1], cuts[1:], strict=True), strict=True):
        name = k if k == "bath" else f"bedroom{(nb := nb + 1)}"
        rooms.append(_Room(name, k, round(a, 2), yc, round(b, 2), H, []))
    rooms.append(_Room("corridor", "corridor", 0, ys, W, yc, []))
    return W, H, rooms, ys, yc


def _plan_hospital(rng: np.random.Generator) -> tuple[float, float, list[_Room], float, float]:
    W, H, ys, yc = _bands(rng, "hospital")
    rooms: list[_Room] = []
    for band, (y0, y1) in (("s", (0.0, ys)), ("n", (yc, H))):
        n = max(3, int(W // 4.6))
        cuts = np.linspace(0, W, n + 1)
        cuts[1:-1] += rng.uniform(-0.4, 0.4, n - 1)
        cuts = np.round(cuts, 2)
        for i, (a, b) in enumerate(zip(cuts[:-1], cuts[1:], strict=True)):
            rooms.append(_Room(f"{band}{i}", "ward", round(float(a), 2), y0, round(float(b), 2), y1, []))
    south = [r for r in rooms if r.name.startswith("s")]
    north = [r for r in rooms if r.name.startswith("n")]
    reception = south[0] if rng.random() < 0.5 else south[-1]
    reception.kind = "reception"
    others = [r for r in south + north if r is not reception]
    for r, k in zip(rng.permutation(len(others))[:2], ("office", "office"), strict=True):
        others[int(r)].kind = k
    counts: dict[str, int] = {}
    for r in south + north:
        counts[r.kind] = counts.get(r.kind, 0) + 1
        r.name = f"{r.kind}{counts[r.kind]}" if r.kind != "reception" else "reception"
    rooms.append(_Room("corridor", "corridor", 0, ys, W, yc, []))
    return W, H, rooms, ys, yc


def _walls_and_doors(
    rng: np.random.Generator, style: str, W: float, H: float, rooms: list[_Room], ys: float, yc: float
) -> list[WallSpec]:
    ext, inner = 0.12 if style == "home" else 0.15, 0.1
    height = 2.6 if style == "home" else 2.7
    door_h = 2.1
    paints = load_catalogue().paints[style]

    def paint() -> str:
        return paints[int(rng.integers(len(paints)))]

    exterior = paint()
    walls = [
        WallSpec("south", (0, 0), (W, 0), ext, height, exterior),
        WallSpec("north", (0, H), (W, H), ext, height, exterior),
        WallSpec("west", (0, 0), (0, H), ext, height, exterior),
        WallSpec("east", (W, 0), (W, H), ext, height, exterior),
    ]
    corridor_paint = paint()
    for y, side in ((ys, "N"), (yc, "S")):
        doors = []
        for r in rooms:
            if r.kind == "corridor" or not (abs(r.y1 - y) < 1e-6 or abs(r.y0 - y) < 1e-6):
                continue
            width = 1.2 if style == "hospital" else 1.0
            if r.kind in ("living", "reception"):
                width = min(_u(rng, 1.4, 2.4), r.x1 - r.x0 - 1.0)
            margin = 0.35 + width / 2
            c = _u(rng, r.x0 + margin, r.x1 - margin)
            doors.append(DoorSpec(round(c, 3), round(width, 3), door_h))
            r.doors.append((side, c, width))
        walls.append(
            WallSpec(
                f"corridor_{'south' if y == ys else 'north'}",
                (0, y),
                (W, y),
                inner,
                height,
                corridor_paint,
                tuple(sorted(doors, key=lambda d: d.at)),
            )
        )
    band_rooms = [r for r in rooms if r.kind != "corridor"]
    for r in band_rooms:
        if r.x1 >= W - 1e-6:
            continue
        right = next(q for q in band_rooms if abs(q.x0 - r.x1) < 1e-6 and q.y0 == r.y0)
        doors = ()
        if {r.kind, right.kind} == {"living", "kitchen"} and rng.random() < 0.8:
            c = _u(rng, r.y0 + 0.9, r.y1 - 0.9)
            doors = (DoorSpec(round(c - r.y0, 3), 1.0, door_h),)
            r.doors.append(("E", c, 1.0))
            right.doors.append(("W", c, 1.0))
        walls.append(
            WallSpec(f"{r.name}_{right.name}", (r.x1, r.y0), (r.x1, r.y1), inner, height, paint(), doors)
        )
    return walls


def _door_zones(r: _Room) -> list[np.ndarray]:
    """Keep-out rectangles (4, 2) in front of a room's doors (1.0 m deep, door width + 0.3 wide)."""
    zones = []
    for side, c, w in r.doors:
        h = (w + 0.3) / 2
        if side == "S":
            zones.append(np.array([[c - h, r.y0], [c + h, r.y0], [c + h, r.y0 + 1.0], [c - h, r.y0 + 1.0]]))
        elif side == "N":
            zones.append(np.array([[c - h, r.y1 - 1.0], [c + h, r.y1 - 1.0], [c + h, r.y1], [c - h, r.y1]]))
        elif side == "W":
            zones.append(np.array([[r.x0, c - h], [r.x0 + 1.0, c - h], [r.x0 + 1.0, c + h], [r.x0, c + h]]))
        else:
            zones.append(np.array([[r.x1 - 1.0, c - h], [r.x1, c - h], [r.x1, c + h], [r.x1 - 1.0, c + h]]))
    return zones


def _overlap(a: np.ndarray, b: np.ndarray, margin: float) -> bool:
    """Separating-axis test of two convex quads (4, 2), inflated by ``margin``."""
    for poly in (a, b):
        for i in range(4):
            e = poly[(i + 1) % 4] - poly[i]
            n = np.array([-e[1], e[0]]) / (np.linalg.norm(e) + 1e-12)
            pa, pb = a @ n, b @ n
            if pa.max() + margin < pb.min() or pb.max() + margin < pa.min():
                return False
    return True


def _inside(q: np.ndarray, r: _Room, wall_gap: float) -> bool:
    return bool(
        np.all(q[:, 0] >= r.x0 + wall_gap - 1e-6)
        and np.all(q[:, 0] <= r.x1 - wall_gap + 1e-6)
        and np.all(q[:, 1] >= r.y0 + wall_gap - 1e-6)
        and np.all(q[:, 1] <= r.y1 - wall_gap + 1e-6)
    )


def _wall_pose(rng: np.random.Generator, r: _Room, w: float, d: float) -> tuple[float, float, float]:
    """A random pose with the object's back (width w, depth d) against one of the room's walls."""
    side = "SNWE"[int(rng.integers(4))]
    g = 0.05 + 0.01
    if side in "SN":
        x = _u(rng, r.x0 + g + w / 2, r.x1 - g - w / 2) if r.x1 - r.x0 > w + 2 * g else (r.x0 + r.x1) / 2
        y = r.y0 + g + d / 2 if side == "S" else r.y1 - g - d / 2
        return x, y, 0.0 if side == "S" else math.pi
    y = _u(rng, r.y0 + g + w / 2, r.y1 - g - w / 2) if r.y1 - r.y0 > w + 2 * g else (r.y0 + r.y1) / 2
    x = r.x0 + g + d / 2 if side == "W" else r.x1 - g - d / 2
    return x, y, -math.pi / 2 if side == "W" else math.pi / 2


def _chair_pose(rng: np.random.Generator, t: ObjectSpec, d: float) -> tuple[float, float, float]:
    """A chair of depth d at a random side of table t, slightly tucked in, facing the table."""
    tw, td, _ = t.size or PRIMITIVES[t.kind].size
    side = int(rng.integers(4))
    if side < 2:
        u = _u(rng, -max(tw / 2 - 0.3, 0.0), max(tw / 2 - 0.3, 0.0))
        off, rel = (u, (td / 2 + d / 2 - 0.12) * (1 if side == 0 else -1)), (math.pi if side == 0 else 0.0)
    else:
        v = _u(rng, -max(td / 2 - 0.3, 0.0), max(td / 2 - 0.3, 0.0))
        off, rel = (
            ((tw / 2 + d / 2 - 0.12) * (1 if side == 2 else -1), v),
            (math.pi / 2 if side == 2 else -math.pi / 2),
        )
    c, s = math.cos(t.yaw), math.sin(t.yaw)
    return t.x + c * off[0] - s * off[1], t.y + s * off[0] + c * off[1], t.yaw + rel


class _Placer:
    """Places objects one by one, keeping them apart, off door zones and the space connected."""

    def __init__(self, spec_stub: SceneSpec, rooms: list[_Room], rng: np.random.Generator) -> None:
        self.stub, self.rooms, self.rng = spec_stub, rooms, rng
        self.objects: list[ObjectSpec] = []

    def _ok(self, o: ObjectSpec, r: _Room, others: list[ObjectSpec], free_margin: float) -> bool:
        q = footprint(o)
        if not _inside(q, r, 0.05 + 0.005):
            return False
        if blocks(o) and any(_overlap(q, z, 0.0) for z in _door_zones(r)):
            return False
        for p in others:
            margin = free_margin if (o.kind in ("rug",) or p.kind == "rug") else 0.03
            if o.kind == "rug" or p.kind == "rug":
                if o.kind == p.kind and _overlap(q, footprint(p), 0.0):
                    return False
                continue
            if _overlap(q, footprint(p), margin):
                return False
        return True

    def connected(self, objects: list[ObjectSpec]) -> bool:
        lost_rooms, lost = connectivity_report(self.stub, objects, PLACEMENT_CLEARANCE, 0.1)
        return not lost_rooms and lost <= MAX_LOST

    def place(
        self, o: ObjectSpec, r: _Room, mode: str, tries: int = 40, free_margin: float = 0.7
    ) -> ObjectSpec | None:
        w, d, _ = o.size or PRIMITIVES[o.kind].size
        for _ in range(tries):
            tables = [
                p for p in self.objects if p.kind in ("table", "desk") and _inside(footprint(p), r, 0.0)
            ]
            others = self.objects
            if mode == "table" and tables:
                t = tables[int(self.rng.integers(len(tables)))]
                others = [p for p in self.objects if p is not t]
                x, y, yaw = _chair_pose(self.rng, t, d)
            elif mode in ("wall", "table"):
                x, y, yaw = _wall_pose(self.rng, r, w, d)
            else:
                x, y = _u(self.rng, r.x0 + 0.6, r.x1 - 0.6), _u(self.rng, r.y0 + 0.6, r.y1 - 0.6)
                yaw = float(self.rng.choice([0.0, math.pi / 2, math.pi, -math.pi / 2])) + _u(
                    self.rng, -0.2, 0.2
                )
            cand = o.with_pose(x, y, yaw)
            margin = free_margin if mode == "free" else 0.03
            if self._ok(cand, r, others, margin) and (
                not blocks(cand) or self.connected(self.objects + [cand])
            ):
                self.objects.append(cand)
                return cand
        return None


def _sample_object(rng: np.random.Generator, item: Item, name: str) -> ObjectSpec:
    size = tuple(round(_u(rng, lo, hi), 3) for lo, hi in item.size)
    material = item.materials[int(rng.integers(len(item.materials)))] if item.materials else None
    roles = tuple((role, choices[int(rng.integers(len(choices)))]) for role, choices in item.roles)
    return ObjectSpec(name, item.kind, item.category, 0.0, 0.0, size=size, material=material, materials=roles)  # type: ignore[arg-type]


def _decorate(rng: np.random.Generator, r: _Room, objects: list[ObjectSpec], n: int) -> list[ObjectSpec]:
    """Pictures and posters on free wall spans of a room (not over doors or tall furniture)."""
    out: list[ObjectSpec] = []
    for k in range(n * 6):
        if len(out) >= n:
            break
        poster = rng.random() < 0.35
        w, h = (_u(rng, 0.4, 0.6), _u(rng, 0.6, 0.85)) if poster else (_u(rng, 0.5, 1.1), _u(rng, 0.4, 0.8))
        d = 0.005 if poster else 0.03
        x, y, yaw = _wall_pose(rng, r, w, 0.6)
        probe = ObjectSpec("probe", "picture", "picture", x, y, yaw, size=(w, 0.6, 1.0))
        q = footprint(probe)
        if any(_overlap(q, z, 0.0) for z in _door_zones(r)):
            continue
        tall = [
            o
            for o in objects + out
            if o.kind in ("picture", "poster") or o.z + (o.size or PRIMITIVES[o.kind].size)[2] > 1.15
        ]
        if any(_overlap(q, footprint(o), 0.05) for o in tall):
            continue
        back = 0.05 + d / 2 + 0.001
        if abs(yaw) < 1e-6:
            x, y = x, r.y0 + back
        elif abs(abs(yaw) - math.pi) < 1e-6:
            x, y = x, r.y1 - back
        else:
            x, y = (r.x0 + back if yaw < 0 else r.x1 - back), y
        kind = "poster" if poster else "picture"
        out.append(
            ObjectSpec(f"{kind}_{r.name}_{k}", kind, kind, x, y, yaw, round(_u(rng, 1.1, 1.5), 2), (w, d, h))
        )
    return out


def _furnish(rng: np.random.Generator, style: str, stub: SceneSpec, rooms: list[_Room]) -> list[ObjectSpec]:
    placer = _Placer(stub, rooms, rng)
    decorations: list[ObjectSpec] = []
    for r in rooms:
        for item in load_catalogue().furniture[style][r.kind]:
            for i in range(int(rng.integers(item.count[0], item.count[1] + 1))):
                o = _sample_object(rng, item, f"{item.kind}_{r.name}_{i}")
                placer.place(o, r, item.place)
        if r.kind == "bath":
            for side in "WE":
                x = r.x0 + 0.055 if side == "W" else r.x1 - 0.055
                decorations.append(
                    ObjectSpec(
                        f"tiles_{r.name}_{side}",
                        "panel",
                        "panel",
                        x,
                        (r.y0 + r.y1) / 2,
                        -math.pi / 2 if side == "W" else math.pi / 2,
                        0.0,
                        (r.y1 - r.y0 - 0.12, 0.01, 1.5),
                        "smalltiles:white",
                    )
                )
        else:
            decorations += _decorate(rng, r, placer.objects, int(rng.integers(1, 4)))
    return placer.objects + decorations


def _person(rng: np.random.Generator, name: str) -> ObjectSpec:
    h = _u(rng, 1.6, 1.85)
    wear = load_catalogue()
    mats = (
        ("main", wear.tops[int(rng.integers(len(wear.tops)))]),
        ("skin", wear.skins[int(rng.integers(len(wear.skins)))]),
        ("trousers", wear.trousers[int(rng.integers(len(wear.trousers)))]),
    )
    return ObjectSpec(
        name, "person", "person", 0, 0, size=(round(0.5 * h / 1.7, 3), 0.35, round(h, 3)), materials=mats
    )


def _edit(
    rng: np.random.Generator, stub: SceneSpec, rooms: list[_Room], base: list[ObjectSpec], tag: str
) -> LayoutEdit:
    """Move 3-5 movable objects, remove 2-3, add 2-4 people and 1-2 boxes, keeping space connected."""
    movable = [o for o in base if o.kind in load_catalogue().movable and blocks(o)]
    order = list(rng.permutation(len(movable)))
    removed = [movable[i].name for i in order[: int(rng.integers(2, 4))]]
    current = [o for o in base if o.name not in removed]
    room_of = {r.name: r for r in rooms}
    placer = _Placer(stub, rooms, rng)
    moves: list[tuple[str, tuple[float, float, float, float]]] = []
    n_moves = int(rng.integers(3, 6))
    for i in order[len(removed) :]:
        if len(moves) >= n_moves:
            break
        o = movable[i]
        r = next(q for q in room_of.values() if q.x0 <= o.x <= q.x1 and q.y0 <= o.y <= q.y1)
        placer.objects = [p for p in current if p.name != o.name]
        for _ in range(30):
            dx, dy = rng.uniform(-1.0, 1.0, 2)
            cand = o.with_pose(o.x + dx, o.y + dy, o.yaw + _u(rng, -0.8, 0.8))
            if (
                math.hypot(dx, dy) > 0.3
                and placer._ok(cand, r, placer.objects, 0.03)
                and placer.connected(placer.objects + [cand])
            ):
                current = placer.objects + [cand]
                moves.append((o.name, (cand.x, cand.y, cand.yaw, cand.z)))
                break
    placer.objects = list(current)
    added: list[ObjectSpec] = []
    targets = rng.permutation(len(rooms))
    n_people, n_boxes = int(rng.integers(2, 5)), int(rng.integers(1, 3))
    for k in range(n_people + n_boxes):
        if k < n_people:
            o = _person(rng, f"person_{tag}_{k}")
        else:
            s = (round(_u(rng, 0.4, 0.7), 3), round(_u(rng, 0.3, 0.5), 3), round(_u(rng, 0.35, 0.7), 3))
            o = ObjectSpec(f"box_{tag}_{k}", "box", "box", 0, 0, size=s, material="wood:pine")
        r = rooms[int(targets[k % len(rooms)])]
        placed = placer.place(o, r, "free", tries=30, free_margin=0.45)
        if placed is not None:
            added.append(placed)
    return LayoutEdit(remove=tuple(removed), move=tuple(moves), add=tuple(added))


def generate(style: str, seed: int) -> SceneSpec:
    """A new scene of ``style`` ('home' or 'hospital') from ``seed``, with base, changed and changed2."""
    catalogue = load_catalogue()
    if style not in catalogue.furniture:
        raise SceneError(f"unknown procedural style {style!r}; allowed: {sorted(catalogue.furniture)}")
    rng = np.random.default_rng([seed, 0 if style == "home" else 1])
    W, H, rooms, ys, yc = (_plan_home if style == "home" else _plan_hospital)(rng)
    walls = _walls_and_doors(rng, style, W, H, rooms, ys, yc)
    floors = catalogue.floors[style]
    room_specs = tuple(
        RoomSpec(
            r.name,
            ((r.x0, r.y0), (r.x1, r.y0), (r.x1, r.y1), (r.x0, r.y1)),
            floors[r.kind][int(rng.integers(len(floors[r.kind])))],
            "paint:white",
            r.kind,
        )
        for r in rooms
    )
    name = f"{style}-{seed}"
    stub = SceneSpec(name, style, room_specs, tuple(walls), (), seed=seed, source=f"{style}:{seed}")
    objects = _furnish(rng, style, stub, rooms)
    layouts = tuple(
        (tag, _edit(np.random.default_rng([seed, k + 10]), stub, rooms, objects, tag))
        for k, tag in enumerate(("changed", "changed2"))
    )
    return SceneSpec(
        name,
        style,
        room_specs,
        tuple(walls),
        tuple(objects),
        layouts,
        seed,
        f"{style}:{seed}",
        description=f"procedural {style} scene, seed {seed}",
    )
