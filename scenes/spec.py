"""Scene specification: typed dataclasses parsed from YAML (or built by the procedural generator).

Coordinates are metres in W (z up, floor z = 0). In spec *files* yaw angles are in degrees
(readable); the dataclasses hold radians. An object's local frame has its origin at the centre of
its footprint on its base, ``size = (width along local x, depth along local y, height)`` and its
front facing local +y; ``yaw`` rotates local into W (yaw 0: front faces +y, so it stands against a
wall on the -y side; yaw 180: against a +y wall; yaw -90: against a -x wall; yaw 90: a +x wall).

A spec holds the ``base`` layout's objects and named layouts expressed as edits of base
(``remove`` names, ``move`` name -> new pose, ``add`` new objects), applied in that order.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import yaml


class SceneError(ValueError):
    """A scene source, spec, layout or option is malformed or unknown (the message says which)."""


@dataclass(frozen=True)
class DoorSpec:
    """A gap in a wall: centre at ``at`` metres from the wall's start, ``width`` x ``height``."""

    at: float
    width: float = 0.9
    height: float = 2.1


@dataclass(frozen=True)
class WallSpec:
    """A straight wall centred on the segment ``start`` -> ``end`` (xy), with door gaps."""

    name: str
    start: tuple[float, float]
    end: tuple[float, float]
    thickness: float = 0.1
    height: float = 2.6
    material: str = "paint:white"
    doors: tuple[DoorSpec, ...] = ()

    @property
    def length(self) -> float:
        return math.dist(self.start, self.end)


@dataclass(frozen=True)
class RoomSpec:
    """A room footprint (counter-clockwise or clockwise xy polygon) with floor and ceiling materials."""

    name: str
    polygon: tuple[tuple[float, float], ...]
    floor: str = "parquet"
    ceiling: str = "paint:white"
    kind: str = ""

    @property
    def area(self) -> float:
        """Polygon area in m2 (shoelace)."""
        pts = self.polygon
        s = sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(pts, pts[1:] + pts[:1], strict=False))
        return abs(s) / 2.0


@dataclass(frozen=True)
class ObjectSpec:
    """A placed object: a parametric primitive ``kind`` or ``kind='mesh'`` with a mesh file."""

    name: str
    kind: str
    category: str
    x: float
    y: float
    yaw: float = 0.0
    z: float = 0.0
    size: tuple[float, float, float] | None = None
    material: str | None = None
    materials: tuple[tuple[str, str], ...] = ()
    mesh: str | None = None

    def with_pose(self, x: float, y: float, yaw: float, z: float | None = None) -> ObjectSpec:
        return replace(self, x=x, y=y, yaw=yaw, z=self.z if z is None else z)


@dataclass(frozen=True)
class LayoutEdit:
    """Edits of the base layout: ``remove`` names, ``move`` name -> (x, y, yaw[rad], z), ``add`` objects."""

    remove: tuple[str, ...] = ()
    move: tuple[tuple[str, tuple[float, float, float, float]], ...] = ()
    add: tuple[ObjectSpec, ...] = ()

    @property
    def edited_names(self) -> set[str]:
        return set(self.remove) | {n for n, _ in self.move} | {o.name for o in self.add}


@dataclass(frozen=True)
class SceneSpec:
    """A whole scene: rooms, walls, base objects and edited layouts."""

    name: str
    style: str
    rooms: tuple[RoomSpec, ...]
    walls: tuple[WallSpec, ...]
    objects: tuple[ObjectSpec, ...]
    layouts: tuple[tuple[str, LayoutEdit], ...] = ()
    seed: int = 0
    source: str = "<memory>"
    base_dir: str = "."
    description: str = ""

    @property
    def layout_names(self) -> list[str]:
        return ["base"] + [n for n, _ in self.layouts]

    @property
    def floor_area(self) -> float:
        return sum(r.area for r in self.rooms)

    def edit(self, layout: str) -> LayoutEdit:
        """The edit turning base into ``layout`` (empty for base)."""
        if layout == "base":
            return LayoutEdit()
        for n, e in self.layouts:
            if n == layout:
                return e
        raise SceneError(f"scene {self.name!r} has no layout {layout!r}; allowed: {self.layout_names}")

    def layout_objects(self, layout: str = "base") -> tuple[ObjectSpec, ...]:
        """Objects of a layout: base objects with the layout's removals, moves and additions applied."""
        e = self.edit(layout)
        moves = dict(e.move)
        out = []
        for o in self.objects:
            if o.name in e.remove:
                continue
            if o.name in moves:
                x, y, yaw, z = moves[o.name]
                o = o.with_pose(x, y, yaw, z)
            out.append(o)
        return tuple(out) + e.add


# ----------------------------------------------------------------------------------------- parsing

_TOP_KEYS = {"name", "style", "description", "seed", "defaults", "rooms", "walls", "objects", "layouts"}
_DEFAULT_KEYS = {
    "wall_height",
    "wall_thickness",
    "wall_material",
    "door_height",
    "door_width",
    "floor",
    "ceiling",
}
_ROOM_KEYS = {"name", "rect", "polygon", "floor", "ceiling", "kind"}
_WALL_KEYS = {"name", "from", "to", "thickness", "height", "material", "doors"}
_DOOR_KEYS = {"at", "width", "height"}
_OBJECT_KEYS = {"name", "kind", "category", "pose", "z", "size", "material", "materials", "mesh"}
_LAYOUT_KEYS = {"remove", "move", "add"}


class _Ctx:
    """Error context: the file and the field path being parsed."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, problem: str) -> SceneError:
        return SceneError(f"{self.source}: {where}: {problem}")


def _keys(ctx: _Ctx, where: str, d: Any, allowed: set[str], required: Sequence[str] = ()) -> Mapping:
    if not isinstance(d, Mapping):
        raise ctx.fail(where, f"expected a mapping with keys from {sorted(allowed)}, got {type(d).__name__}")
    unknown = set(d) - allowed
    if unknown:
        raise ctx.fail(where, f"unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    for r in required:
        if r not in d:
            raise ctx.fail(where, f"missing required key {r!r}")
    return d


def _num(ctx: _Ctx, where: str, v: Any, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ctx.fail(where, f"expected a finite number, got {v!r}")
    if positive and v <= 0:
        raise ctx.fail(where, f"expected a positive number, got {v!r}")
    return float(v)


def _vec(ctx: _Ctx, where: str, v: Any, n: int | Sequence[int], positive: bool = False) -> tuple[float, ...]:
    ns = (n,) if isinstance(n, int) else tuple(n)
    if not isinstance(v, (list, tuple)) or len(v) not in ns:
        raise ctx.fail(where, f"expected a list of {' or '.join(map(str, ns))} numbers, got {v!r}")
    return tuple(_num(ctx, f"{where}[{i}]", x, positive) for i, x in enumerate(v))


def _str(ctx: _Ctx, where: str, v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        raise ctx.fail(where, f"expected a non-empty string, got {v!r}")
    return v.strip()


def _check_material(ctx: _Ctx, where: str, name: Any) -> str:
    from vgpnav_env.scenes.materials import MATERIAL_KINDS, parse_material_name

    name = _str(ctx, where, name)
    try:
        parse_material_name(name)
    except ValueError as e:
        raise ctx.fail(where, f"{e}; kinds: {sorted(MATERIAL_KINDS)}") from None
    return name


def _pose(ctx: _Ctx, where: str, v: Any) -> tuple[float, float, float]:
    x, y, *rest = _vec(ctx, where, v, (2, 3))
    return x, y, math.radians(rest[0]) if rest else 0.0


def _parse_object(ctx: _Ctx, where: str, d: Any) -> ObjectSpec:
    from vgpnav_env.scenes.primitives import PRIMITIVE_KINDS

    d = _keys(ctx, where, d, _OBJECT_KEYS, ("name", "pose"))
    name = _str(ctx, f"{where}.name", d["name"])
    if "/" in name:
        raise ctx.fail(f"{where}.name", f"object names may not contain '/', got {name!r}")
    mesh = d.get("mesh")
    kind = d.get("kind", "mesh" if mesh is not None else None)
    if kind is None:
        raise ctx.fail(where, f"object {name!r} needs 'kind' (one of {sorted(PRIMITIVE_KINDS)}) or 'mesh'")
    kind = _str(ctx, f"{where}.kind", kind)
    if kind == "mesh":
        if mesh is None:
            raise ctx.fail(where, f"object {name!r} of kind 'mesh' needs a 'mesh' file path")
        mesh = _str(ctx, f"{where}.mesh", mesh)
    elif kind not in PRIMITIVE_KINDS:
        raise ctx.fail(
            f"{where}.kind", f"unknown kind {kind!r}; allowed: {sorted(PRIMITIVE_KINDS) + ['mesh']}"
        )
    elif mesh is not None:
        raise ctx.fail(where, f"object {name!r} has both a primitive kind {kind!r} and a mesh; give one")
    x, y, yaw = _pose(ctx, f"{where}.pose", d["pose"])
    size = _vec(ctx, f"{where}.size", d["size"], 3, positive=True) if "size" in d else None
    if kind == "mesh" and size is None:
        raise ctx.fail(
            where, f"mesh object {name!r} needs a 'size' [width, depth, height] to fit the mesh into"
        )
    material = _check_material(ctx, f"{where}.material", d["material"]) if "material" in d else None
    mats = d.get("materials", {})
    if not isinstance(mats, Mapping):
        raise ctx.fail(f"{where}.materials", f"expected a mapping role -> material, got {mats!r}")
    materials = tuple(
        (str(k), _check_material(ctx, f"{where}.materials.{k}", v)) for k, v in sorted(mats.items())
    )
    return ObjectSpec(
        name=name,
        kind=kind,
        category=_str(ctx, f"{where}.category", d.get("category", kind if kind != "mesh" else "object")),
        x=x,
        y=y,
        yaw=yaw,
        z=_num(ctx, f"{where}.z", d.get("z", 0.0)),
        size=size,  # type: ignore[arg-type]
        material=material,
        materials=materials,
        mesh=mesh,
    )


def _parse_room(ctx: _Ctx, where: str, d: Any, defaults: Mapping) -> RoomSpec:
    d = _keys(ctx, where, d, _ROOM_KEYS, ("name",))
    name = _str(ctx, f"{where}.name", d["name"])
    if ("rect" in d) == ("polygon" in d):
        raise ctx.fail(where, f"room {name!r} needs exactly one of 'rect' [x0, y0, x1, y1] or 'polygon'")
    if "rect" in d:
        x0, y0, x1, y1 = _vec(ctx, f"{where}.rect", d["rect"], 4)
        if x1 <= x0 or y1 <= y0:
            raise ctx.fail(f"{where}.rect", f"expected x0 < x1 and y0 < y1, got {list(d['rect'])}")
        poly = ((x0, y0), (x1, y0), (x1, y1), (x0, y1))
    else:
        p = d["polygon"]
        if not isinstance(p, list) or len(p) < 3:
            raise ctx.fail(f"{where}.polygon", f"expected a list of >= 3 [x, y] points, got {p!r}")
        poly = tuple(_vec(ctx, f"{where}.polygon[{i}]", q, 2) for i, q in enumerate(p))  # type: ignore[misc]
    room = RoomSpec(
        name=name,
        polygon=poly,  # type: ignore[arg-type]
        floor=_check_material(ctx, f"{where}.floor", d.get("floor", defaults["floor"])),
        ceiling=_check_material(ctx, f"{where}.ceiling", d.get("ceiling", defaults["ceiling"])),
        kind=str(d.get("kind", "")),
    )
    if room.area < 1e-3:
        raise ctx.fail(f"{where}.polygon", f"room {name!r} has zero area")
    return room


def _parse_wall(ctx: _Ctx, where: str, d: Any, i: int, defaults: Mapping) -> WallSpec:
    d = _keys(ctx, where, d, _WALL_KEYS, ("from", "to"))
    start = _vec(ctx, f"{where}.from", d["from"], 2)
    end = _vec(ctx, f"{where}.to", d["to"], 2)
    length = math.dist(start, end)
    if length < 0.05:
        raise ctx.fail(where, f"wall is shorter than 0.05 m ({length:.3f} m)")
    height = _num(ctx, f"{where}.height", d.get("height", defaults["wall_height"]), positive=True)
    doors = []
    raw = d.get("doors", [])
    if not isinstance(raw, list):
        raise ctx.fail(f"{where}.doors", f"expected a list of doors, got {raw!r}")
    for j, dd in enumerate(raw):
        w = f"{where}.doors[{j}]"
        dd = _keys(ctx, w, dd, _DOOR_KEYS, ("at",))
        door = DoorSpec(
            at=_num(ctx, f"{w}.at", dd["at"]),
            width=_num(ctx, f"{w}.width", dd.get("width", defaults["door_width"]), positive=True),
            height=_num(ctx, f"{w}.height", dd.get("height", defaults["door_height"]), positive=True),
        )
        if door.at - door.width / 2 < -1e-6 or door.at + door.width / 2 > length + 1e-6:
            raise ctx.fail(
                w,
                f"door [{door.at - door.width / 2:.2f}, {door.at + door.width / 2:.2f}] m "
                f"does not fit on the wall of length {length:.2f} m",
            )
        if door.height > height:
            raise ctx.fail(w, f"door height {door.height} exceeds the wall height {height}")
        doors.append(door)
    doors.sort(key=lambda dr: dr.at)
    for a, b in zip(doors, doors[1:], strict=False):
        if a.at + a.width / 2 > b.at - b.width / 2:
            raise ctx.fail(f"{where}.doors", f"doors at {a.at} and {b.at} overlap")
    return WallSpec(
        name=_str(ctx, f"{where}.name", d.get("name", f"wall{i}")),
        start=start,  # type: ignore[arg-type]
        end=end,  # type: ignore[arg-type]
        thickness=_num(
            ctx, f"{where}.thickness", d.get("thickness", defaults["wall_thickness"]), positive=True
        ),
        height=height,
        material=_check_material(ctx, f"{where}.material", d.get("material", defaults["wall_material"])),
        doors=tuple(doors),
    )


def _parse_layout(ctx: _Ctx, where: str, d: Any, base: Mapping[str, ObjectSpec]) -> LayoutEdit:
    d = _keys(ctx, where, d or {}, _LAYOUT_KEYS)
    remove = d.get("remove", [])
    if not isinstance(remove, list):
        raise ctx.fail(f"{where}.remove", f"expected a list of object names, got {remove!r}")
    for n in remove:
        if n not in base:
            raise ctx.fail(f"{where}.remove", f"no base object named {n!r}; objects: {sorted(base)}")
    moves = []
    mv = d.get("move", {})
    if not isinstance(mv, Mapping):
        raise ctx.fail(f"{where}.move", f"expected a mapping name -> [x, y, yaw_deg], got {mv!r}")
    for n, v in mv.items():
        if n not in base:
            raise ctx.fail(f"{where}.move", f"no base object named {n!r}; objects: {sorted(base)}")
        if n in remove:
            raise ctx.fail(f"{where}.move", f"object {n!r} is both removed and moved")
        x, y, yaw = _pose(ctx, f"{where}.move.{n}", v)
        moves.append((str(n), (x, y, yaw, base[n].z)))
    adds = d.get("add", [])
    if not isinstance(adds, list):
        raise ctx.fail(f"{where}.add", f"expected a list of objects, got {adds!r}")
    added = tuple(_parse_object(ctx, f"{where}.add[{i}]", o) for i, o in enumerate(adds))
    for o in added:
        if o.name in base:
            raise ctx.fail(f"{where}.add", f"added object {o.name!r} clashes with a base object's name")
    return LayoutEdit(remove=tuple(map(str, remove)), move=tuple(moves), add=added)


def parse_spec(data: Any, source: str = "<memory>", base_dir: str | Path = ".") -> SceneSpec:
    """Parse a spec mapping (as loaded from YAML) into a ``SceneSpec``; ``SceneError`` names any problem."""
    ctx = _Ctx(source)
    d = _keys(ctx, "top level", data, _TOP_KEYS, ("name", "rooms", "walls"))
    defaults = {
        "wall_height": 2.6,
        "wall_thickness": 0.1,
        "wall_material": "paint:white",
        "door_height": 2.1,
        "door_width": 0.9,
        "floor": "parquet",
        "ceiling": "paint:white",
    }
    defaults.update(_keys(ctx, "defaults", d.get("defaults", {}), _DEFAULT_KEYS))
    for key in ("rooms", "walls", "objects"):
        if not isinstance(d.get(key, []), list):
            raise ctx.fail(key, f"expected a list, got {type(d[key]).__name__}")
    if not d["rooms"]:
        raise ctx.fail("rooms", "a scene needs at least one room")
    rooms = tuple(_parse_room(ctx, f"rooms[{i}]", r, defaults) for i, r in enumerate(d["rooms"]))
    walls = tuple(_parse_wall(ctx, f"walls[{i}]", w, i, defaults) for i, w in enumerate(d["walls"]))
    objects = tuple(_parse_object(ctx, f"objects[{i}]", o) for i, o in enumerate(d.get("objects", [])))
    for what, items in (("rooms", rooms), ("walls", walls), ("objects", objects)):
        names = [it.name for it in items]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ctx.fail(what, f"duplicate names {dup}")
    base = {o.name: o for o in objects}
    lays = d.get("layouts", {}) or {}
    if not isinstance(lays, Mapping):
        raise ctx.fail("layouts", f"expected a mapping layout name -> edits, got {lays!r}")
    if "base" in lays:
        raise ctx.fail("layouts", "'base' is the unedited layout and cannot be redefined")
    layouts = tuple((str(n), _parse_layout(ctx, f"layouts.{n}", e, base)) for n, e in lays.items())
    seed = d.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ctx.fail("seed", f"expected an integer, got {seed!r}")
    return SceneSpec(
        name=_str(ctx, "name", d["name"]),
        style=str(d.get("style", "custom")),
        rooms=rooms,
        walls=walls,
        objects=objects,
        layouts=layouts,
        seed=seed,
        source=source,
        base_dir=str(base_dir),
        description=str(d.get("description", "")),
    )


def read_data_file(path: Path, language: Literal["JSON", "YAML"]) -> Any:
    """The parsed JSON or YAML file ``path``; SceneError ("cannot read" / "invalid JSON|YAML") when
    it cannot be read or parsed."""
    if language == "JSON":
        loads, invalid = json.loads, json.JSONDecodeError
    else:
        loads, invalid = yaml.safe_load, yaml.YAMLError
    try:
        return loads(path.read_text())
    except OSError as e:
        raise SceneError(f"{path}: cannot read: {e}") from None
    except invalid as e:
        raise SceneError(f"{path}: invalid {language}: {e}") from None


def load_spec(path: str | Path) -> SceneSpec:
    """Read and parse a spec YAML file."""
    path = Path(path)
    return parse_spec(read_data_file(path, "YAML"), source=str(path), base_dir=path.parent)
