"""Mesh files made by other people: their parts, their materials and the files they name.

:func:`load_parts` reads any trimesh format (OBJ + MTL, GLB/GLTF, PLY, STL, ...) as named parts,
one per scene node -- an OBJ with several materials gives one part per material -- each with its
own :class:`~vgpnav_env.scenes.scene.Material`:

- Texture image + UVs kept as authored (``tile_m`` 1). Textured MTL materials show their image
  as is (rgba 1, 1, 1, opacity), as Blender and Sweet Home 3D show them; glTF multiplies its
  ``baseColorFactor`` in, as MuJoCo does. Untextured parts take ``Kd`` / ``baseColorFactor`` /
  vertex colours. Parts sharing one image and colour share one Material (one MuJoCo texture).
- Opacity from MTL ``d`` (else ``1 - Tr``) or a glTF ``BLEND`` factor's alpha. An opacity of 0
  is taken as opaque (exporters that write ``Tr`` as opacity make whole objects vanish otherwise).

Files named inside mesh files (an OBJ's ``mtllib``, an MTL's ``map_*`` textures, a glTF's
buffers and images) are found by :func:`resolve_asset`, which accepts what authors' exports hold:
relative paths, absolute paths from another machine (``C:\\Users\\me\\tex\\Wood.JPG``), MTL
options before the name (``-s 1 1 1 a.jpg``), another letter case, or only the file's name
beside the mesh / MTL or below its folder. Each name it cannot find is returned in
``LoadedMesh.missing`` (the caller warns once per name); the part keeps its plain colour.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray

from vgpnav_env.scenes.scene import Material
from vgpnav_env.scenes.spec import SceneError

#: MTL statements whose argument is a file (the digest covers them all; only map_Kd is rendered).
MTL_FILE_KEYS = ("map_ka", "map_kd", "map_ks", "map_ns", "map_d", "map_bump", "bump", "disp", "decal", "norm")
_MTL_OPTION = re.compile(
    r"^\s*(?:-(?:o|s|t)(?:\s+[-+]?[\d.]+(?:e[-+]?\d+)?){1,3}\s+|-mm\s+\S+\s+\S+\s+"
    r"|-(?:blendu|blendv|cc|clamp|bm|boost|texres|imfchan|type)\s+\S+\s+)*",
    re.IGNORECASE,
)
#: Parts with less area than this (in the file's units squared) are dropped.
MIN_AREA = 1e-12
#: Give up searching a folder tree for a file's name beyond this many entries.
_MAX_SEARCH = 5000


@dataclass
class MeshPart:
    """One named part of a mesh file in the file's own frame, with its material."""

    name: str
    mesh: trimesh.Trimesh
    material: Material


@dataclass
class LoadedMesh:
    """A mesh file's parts, the files it named and found (``assets``), and the names it did not find."""

    parts: list[MeshPart]
    assets: list[Path] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def asset_name(text: str) -> str:
    """The file name of an MTL map statement's argument (options such as ``-s 1 1 1`` removed)."""
    return text[_MTL_OPTION.match(text).end() :].strip().strip("\"'")  # type: ignore[union-attr]


def _child(folder: Path, name: str) -> Path | None:
    """``folder / name``, matched case-insensitively if the exact name is not there."""
    exact = folder / name
    if exact.exists():
        return exact
    if not folder.is_dir():
        return None
    low = name.lower()
    matches = sorted(p for p in folder.iterdir() if p.name.lower() == low)
    return matches[0] if matches else None


def _walk(folder: Path, parts: tuple[str, ...]) -> Path | None:
    for part in parts:
        if part in ("", "."):
            continue
        nxt = folder.parent if part == ".." else _child(folder, part)
        if nxt is None:
            return None
        folder = nxt
    return folder if folder.is_file() else None


def _below(folder: Path, name: str) -> Path | None:
    low = name.lower()
    found = []
    for i, p in enumerate(folder.rglob("*")):
        if i >= _MAX_SEARCH:
            break
        if p.name.lower() == low and p.is_file():
            found.append(p)
    return min(found, key=lambda p: (len(p.parts), str(p))) if found else None


def resolve_asset(name: str, *folders: Path) -> Path | None:
    """The file an author's reference ``name`` means, searched from ``folders`` in order; None if absent.

    Tried in order: the absolute path if it exists here; the path relative to each folder (any
    letter case, ``\\`` read as ``/``); the bare file name beside each folder (any case); the
    file name anywhere below each folder (the shallowest match).
    """
    raw = asset_name(name)
    if not raw:
        return None
    norm = raw.replace("\\", "/")
    p = Path(norm)
    if p.is_absolute() and p.is_file():
        return p
    rel = tuple(c for c in norm.split("/") if c)
    basename = rel[-1] if rel else ""
    if not basename:
        return None
    for folder in folders:
        if not re.match(r"^[A-Za-z]:$", rel[0]) and not norm.startswith("/"):
            hit = _walk(folder, rel)
            if hit is not None:
                return hit
        hit = _child(folder, basename)
        if hit is not None and hit.is_file():
            return hit
    for folder in folders:
        hit = _below(folder, basename)
        if hit is not None:
            return hit
    return None


class _Resolver(trimesh.resolvers.FilePathResolver):
    """trimesh resolver over :func:`resolve_asset` that records what it found and what it did not."""

    def __init__(self, path: Path) -> None:
        super().__init__(str(path))
        self.folders = [path.parent]
        self.assets: list[Path] = []
        self.missing: list[str] = []

    def get(self, name: str) -> bytes:
        found = resolve_asset(name, *self.folders)
        if found is None:
            self.missing.append(asset_name(name))
            raise FileNotFoundError(name)
        if found.suffix.lower() == ".mtl" and found.parent not in self.folders:
            self.folders.insert(0, found.parent)
        self.assets.append(found)
        return found.read_bytes()


def _first_float(value: object) -> float | None:
    items = value if isinstance(value, (list, tuple)) else [value]
    try:
        return float(items[0])  # type: ignore[index, arg-type]
    except (TypeError, ValueError, IndexError):
        return None


def _opacity(mat: trimesh.visual.material.Material) -> float:
    """Opacity of a trimesh material: MTL ``d`` (else 1 - ``Tr``) or a glTF BLEND factor's alpha."""
    if isinstance(mat, trimesh.visual.material.PBRMaterial):
        if str(mat.alphaMode or "OPAQUE").upper() != "BLEND" or mat.baseColorFactor is None:
            return 1.0
        alpha = float(np.asarray(mat.baseColorFactor, float).ravel()[3]) / 255.0
    else:
        kwargs = getattr(mat, "kwargs", {}) or {}
        d = _first_float(kwargs.get("d"))
        tr = _first_float(kwargs.get("tr"))
        alpha = d if d is not None else 1.0 - tr if tr is not None else 1.0
    alpha = float(np.clip(alpha, 0.0, 1.0))
    return 1.0 if alpha <= 0.0 else alpha


def _colour(rgba_u8: object) -> tuple[float, float, float]:
    c = np.asarray(rgba_u8, float).ravel()
    return (float(c[0]) / 255.0, float(c[1]) / 255.0, float(c[2]) / 255.0)


def _appearance(
    mesh: trimesh.Trimesh,
) -> tuple[NDArray[np.uint8] | None, tuple[float, float, float, float], str]:
    """(texture image or None, rgba, note) of a loaded part's visual."""
    vis = mesh.visual
    if isinstance(vis, trimesh.visual.TextureVisuals) and vis.material is not None:
        mat = vis.material
        alpha = _opacity(mat)
        pbr = isinstance(mat, trimesh.visual.material.PBRMaterial)
        img = mat.baseColorTexture if pbr else getattr(mat, "image", None)
        factor = mat.baseColorFactor if pbr else getattr(mat, "diffuse", None)
        rgb = _colour(factor) if factor is not None else (1.0, 1.0, 1.0)
        if img is not None:
            image = np.asarray(img.convert("RGB"), dtype=np.uint8)
            if vis.uv is not None and len(vis.uv) == len(mesh.vertices):
                return image, ((*rgb, alpha) if pbr else (1.0, 1.0, 1.0, alpha)), ""
            mean = image.reshape(-1, 3).mean(axis=0) / 255.0
            rgb = tuple(float(m * c) for m, c in zip(mean, rgb, strict=True))  # type: ignore[assignment]
            return None, (*rgb, alpha), "texture without per-vertex UVs -> its mean colour"
        return None, (*rgb, alpha), ""
    if isinstance(vis, trimesh.visual.ColorVisuals) and vis.kind is not None:
        c = np.asarray(vis.main_color, float) / 255.0
        return None, (float(c[0]), float(c[1]), float(c[2]), float(c[3])), ""
    return None, Material("default").rgba, ""


def _geometries(loaded: object, path: Path) -> list[tuple[str, trimesh.Trimesh]]:
    if isinstance(loaded, trimesh.Trimesh):
        return [(path.stem, loaded)]
    if not isinstance(loaded, trimesh.Scene):
        return []
    out, seen = [], set()
    for node in loaded.graph.nodes_geometry:
        T, geom = loaded.graph[node]
        g = loaded.geometry[geom]
        if isinstance(g, trimesh.Trimesh) and len(g.faces):
            # Each part is a mesh of its own (callers transform parts in place).
            own = geom not in seen and np.allclose(T, np.eye(4))
            out.append((str(node), g if own else g.copy().apply_transform(T)))
            seen.add(geom)
    return out


def load_parts(path: str | Path, what: str, material_prefix: str = "") -> LoadedMesh:
    """Parts of a mesh file (file frame, units as stored; largest area first) with materials named
    ``<prefix><part>``.

    ``SceneError`` (naming ``what`` and the file) if it is missing, unreadable or has no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{what}: mesh file {path} does not exist")
    resolver = _Resolver(path)
    try:
        loaded = trimesh.load(str(path), resolver=resolver, process=False)
    except Exception as e:  # trimesh raises many exception types for bad files
        raise SceneError(f"{what}: cannot load mesh file {path}: {e}") from None
    geoms = _geometries(loaded, path)
    if not geoms:
        raise SceneError(f"{what}: mesh file {path} holds no triangles")
    if all(float(m.area) <= MIN_AREA for _, m in geoms):
        raise SceneError(f"{what}: mesh file {path} has no surface area")
    out = LoadedMesh(
        [], assets=list(dict.fromkeys(resolver.assets)), missing=list(dict.fromkeys(resolver.missing))
    )
    shared: dict[tuple[str, tuple[float, ...]], Material] = {}
    for name, mesh in sorted(geoms, key=lambda g: -float(g[1].area)):
        if float(mesh.area) <= MIN_AREA:
            out.notes.append(f"{name}: no surface area -> dropped")
            continue
        image, rgba, note = _appearance(mesh)
        if note:
            out.notes.append(f"{name}: {note}")
        key = (hashlib.sha1(image.tobytes()).hexdigest() if image is not None else "", rgba)
        material = shared.get(key)
        if material is None:
            material = Material(name=f"{material_prefix}{name}", rgba=rgba, image=image, tile_m=1.0)
            shared[key] = material
        out.parts.append(MeshPart(name, mesh, material))
    return out


def _mtl_files(mtl: Path, folders: list[Path]) -> tuple[list[Path], list[str]]:
    found, missing = [], []
    for line in mtl.read_text(errors="replace").splitlines():
        key, _, arg = line.strip().partition(" ")
        if key.lower() in MTL_FILE_KEYS and arg.strip():
            hit = resolve_asset(arg, mtl.parent, *folders)
            (found.append(hit) if hit is not None else missing.append(asset_name(arg)))
    return found, missing


def referenced_files(path: str | Path) -> tuple[list[Path], list[str]]:
    """(files, unresolved names) that a mesh file names: an OBJ's MTL libraries and their textures,
    a glTF's buffers and images. Read as text, without loading the geometry (cheap: for digests)."""
    path = Path(path)
    found: list[Path] = []
    missing: list[str] = []
    suffix = path.suffix.lower()
    if suffix == ".obj":
        for line in path.read_text(errors="replace").splitlines():
            if line.startswith("mtllib"):
                name = line[len("mtllib") :].strip()
                mtl = resolve_asset(name, path.parent)
                if mtl is None:
                    missing.append(name)
                    continue
                files, lost = _mtl_files(mtl, [path.parent])
                found += [mtl, *files]
                missing += lost
    elif suffix == ".gltf":
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            return found, missing
        for item in data.get("buffers", []) + data.get("images", []):
            uri = item.get("uri", "") if isinstance(item, dict) else ""
            if uri and not uri.startswith("data:"):
                hit = resolve_asset(uri, path.parent)
                (found.append(hit) if hit is not None else missing.append(uri))
    return list(dict.fromkeys(found)), list(dict.fromkeys(missing))
