"""A corpus of InternScenes-like mesh-scene directories made of third-party furniture and textures.

``python -m vgpnav_env.scenes.corpus [--out DIR] [--debs DIR] [--scene NAME]`` writes the scenes of
``corpus.yaml`` (default into ``$VGPNAV_CACHE/corpus/<name>``): the Debian packages named there
(Sweet Home 3D's default catalogue and its furniture libraries) are fetched with ``apt-get
download`` into ``--debs`` (default ``$VGPNAV_CACHE/corpus/debs``) unless already there, and
unpacked with ``dpkg-deb``. Nothing of them is kept in git.

Each directory holds what a user's own scene would (see ``mesh_scene.py``):

- ``structure.obj`` + ``structure.mtl`` + ``textures/*.jpg``: floors, ceilings and walls with door
  gaps from the recipe's spec (the geometry of ``meshes.build_scene``), UVs so one texture image
  covers its catalogue size; ceilings plain. Either each part's category is in ``layout.json`` or
  the loader classifies them; either the MTL names textures by relative paths or, like exports
  from another machine, by absolute Windows paths in another letter case (the images sit in
  ``textures/``).
- ``objects/<model>/``: each model's OBJ + MTL + textures copied unchanged from its library (the
  vertex lines rotated to z up in a z-up scene), with whatever its author left in them: absolute
  texture paths, missing textures, flat parts (a TV screen, the soil of a pot), glass (``d`` < 1).
- ``layout.json`` (base) and ``layout_changed.json``: objects as bboxes in the files' frame and units.
- ``LICENSES.md``: source, creator and licence of every file; ``corpus.json``: what built it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import re
import shutil
import subprocess
import sys
import tarfile
import uuid
import zipfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vgpnav_env.runs import default_cache_dir
from vgpnav_env.scenes.meshes import build_scene, planar_uv
from vgpnav_env.scenes.spec import SceneError, SceneSpec, parse_spec

logger = logging.getLogger(__name__)

CORPUS_FILE = Path(__file__).parent / "corpus.yaml"
CORPUS_VERSION = 1
UNITS = {"m": 1.0, "cm": 0.01}
_Y_TO_Z = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # file (y up) -> W (z up)
CEILING_KD = (0.93, 0.93, 0.91)


def load_recipes(path: Path = CORPUS_FILE) -> dict[str, Any]:
    """The parsed corpus recipe file (``sources``, ``textures``, ``scenes``)."""
    return yaml.safe_load(path.read_text())


def default_corpus_dir() -> Path:
    """``$VGPNAV_CACHE/corpus`` (or ``~/.cache/vgpnav/corpus``)."""
    return default_cache_dir() / "corpus"


def _deb(debs: Path, package: str, fetch: bool) -> Path:
    """The newest ``<package>_*.deb`` in ``debs``, downloaded with ``apt-get download`` if absent."""
    found = sorted(debs.glob(f"{package}_*.deb"))
    if not found and not fetch:
        raise FileNotFoundError(
            f"no {package}_*.deb in {debs} (python -m vgpnav_env.scenes.corpus fetches it)"
        )
    if not found:
        debs.mkdir(parents=True, exist_ok=True)
        logger.info("fetching Debian package %s into %s", package, debs)
        try:
            subprocess.run(["apt-get", "download", package], cwd=debs, check=True, capture_output=True)
        except (OSError, subprocess.CalledProcessError) as e:
            err = getattr(e, "stderr", b"") or b""
            raise SceneError(
                f"cannot fetch Debian package {package!r} with 'apt-get download' ({e}; "
                f"{err.decode(errors='replace').strip()}); run 'apt-get update' or put the .deb into {debs}"
            ) from None
        found = sorted(debs.glob(f"{package}_*.deb"))
    return found[-1]


def _extract(deb: Path, members: set[str], cache: Path) -> dict[str, Path]:
    """Files ``members`` of a .deb's data, extracted (once, in one pass) below ``cache / <deb stem>``."""
    out = {m: cache / deb.stem / m for m in members}
    todo = {m for m, p in out.items() if not p.is_file()}
    if todo:
        proc = subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE)
        with tarfile.open(fileobj=proc.stdout, mode="r|") as tar:
            for info in tar:  # read to the end: dpkg-deb must not block on a full pipe
                name = info.name.removeprefix("./")
                if name in todo and info.isfile():
                    out[name].parent.mkdir(parents=True, exist_ok=True)
                    tmp = out[name].with_name(out[name].name + ".part")
                    tmp.write_bytes(tar.extractfile(info).read())  # type: ignore[union-attr]
                    tmp.replace(out[name])
        if proc.wait() != 0:
            raise SceneError(f"dpkg-deb could not unpack {deb}")
    lost = sorted(m for m, p in out.items() if not p.is_file())
    if lost:
        raise SceneError(f"{deb.name} has no file(s) {lost}")
    return out


class _Source:
    """One model/texture archive (a Sweet Home 3D .sh3f library or the application's .jar)."""

    def __init__(self, key: str, spec: dict[str, Any], deb: Path, archive: Path, copyright: Path) -> None:
        self.key, self.spec, self.deb, self.copyright = key, spec, deb, copyright
        self.zip = zipfile.ZipFile(archive)
        self.root = spec["root"]
        self.creators = self._creators()

    def _creators(self) -> dict[str, str]:
        """Model folder -> creator, from a furniture library's catalogue (empty for the .jar)."""
        try:
            text = self.zip.read("PluginFurnitureCatalog.properties").decode("latin-1")
        except KeyError:
            return {}
        fields: dict[str, dict[str, str]] = {}
        for line in text.splitlines():
            m = re.match(r"(\w+)#(\d+)=(.*)", line)
            if m:
                fields.setdefault(m[2], {})[m[1]] = m[3].strip()
        out = {}
        for f in fields.values():
            parts = f.get("model", "").strip("/").split("/")
            if len(parts) >= 2:
                out[parts[-2]] = f.get("creator", "")
        return out

    def read(self, name: str) -> bytes:
        try:
            return self.zip.read(self.root + name)
        except KeyError:
            raise SceneError(
                f"{self.spec['member']} in {self.deb.name} has no file {self.root + name!r}"
            ) from None

    def folder(self, folder: str) -> dict[str, bytes]:
        prefix = f"{self.root}{folder}/"
        files = {n[len(prefix) :]: self.zip.read(n) for n in self.zip.namelist() if n.startswith(prefix)}
        files = {n: b for n, b in files.items() if n and not n.endswith("/")}
        if not files:
            raise SceneError(f"{self.spec['member']} in {self.deb.name} has no model folder {prefix!r}")
        return files


def _sources(specs: dict[str, dict[str, Any]], debs: Path, fetch: bool) -> dict[str, _Source]:
    """Open every source archive, fetching and unpacking its package first if needed."""
    by_package: dict[str, set[str]] = {}
    for spec in specs.values():
        by_package.setdefault(spec["package"], {_copyright(spec["package"])}).add(spec["member"])
    files = {}
    for package, members in by_package.items():
        deb = _deb(debs, package, fetch)
        files.update({(package, m): (deb, p) for m, p in _extract(deb, members, debs / "extracted").items()})
    return {
        k: _Source(
            k, v, *files[(v["package"], v["member"])], files[(v["package"], _copyright(v["package"]))][1]
        )
        for k, v in specs.items()
    }


def _copyright(package: str) -> str:
    return f"usr/share/doc/{package}/copyright"


def _to_file(points: np.ndarray, up: str, scale: float) -> np.ndarray:
    """W (metres, z up) -> the scene files' frame and units."""
    return (points @ _Y_TO_Z if up == "y" else points) / scale


def _obj_to_z_up(text: str) -> str:
    """An OBJ with its ``v`` and ``vn`` lines rotated from y up to z up, everything else unchanged."""

    def turn(m: re.Match) -> str:
        x, y, z = (float(v) for v in m.group(2, 3, 4))
        return f"{m.group(1)} {x:.6g} {-z:.6g} {y:.6g}{m.group(5)}"

    return re.sub(r"^(vn?)\s+(\S+)\s+(\S+)\s+(\S+)(.*)$", turn, text, flags=re.MULTILINE)


def _write_structure(
    spec: SceneSpec, recipe: dict, textures: dict, sh3d: _Source, out: Path, up: str, scale: float
) -> tuple[dict[str, str], set[str]]:
    """structure.obj/.mtl + textures/; returns (part name -> category, texture files used)."""
    scene = build_scene(replace(spec, objects=(), layouts=()), texture="sparse")
    (out / "textures").mkdir()
    obj = [
        "# structure of " + spec.name + " (units: " + recipe["units"] + f", {up} up)",
        "mtllib structure.mtl",
    ]
    mtl = []
    categories: dict[str, str] = {}
    used: set[str] = set()
    nv = 0
    for sm in scene.meshes:
        if sm.category == "trim":
            continue
        kind, _, room = sm.name.partition("/")
        part = f"{kind}_{room}"
        categories[part] = kind
        tex = None
        if kind == "floor":
            tex = recipe["floors"][room]
        elif kind == "wall":
            tex = recipe["walls"].get(room, recipe["walls"]["default"])
        vertices, faces, uv = planar_uv(sm.mesh, 1.0)
        mtl.append(f"newmtl {part}")
        if tex is None:
            mtl.append("Kd {:.3f} {:.3f} {:.3f}".format(*CEILING_KD))
        else:
            t = textures[tex]
            uv = uv / np.asarray(t["size"], float)
            fname = Path(t["file"]).name
            used.add(t["file"])
            if not (out / "textures" / fname).exists():
                (out / "textures" / fname).write_bytes(sh3d.read(t["file"]))
            author = f"C:\\Users\\designer\\My Textures\\{fname.upper()}"
            ref = author if recipe["author_paths"] else f"textures/{fname}"
            mtl += ["Kd 1.000 1.000 1.000", f"map_Kd {ref}"]
        mtl.append("")
        obj += [f"o {part}", f"usemtl {part}"]
        obj += ["v {:.6g} {:.6g} {:.6g}".format(*p) for p in _to_file(vertices, up, scale)]
        obj += [f"vt {u:.6g} {v:.6g}" for u, v in uv]
        obj += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in faces + 1 + nv]
        nv += len(vertices)
    (out / "structure.obj").write_text("\n".join(obj) + "\n")
    (out / "structure.mtl").write_text("\n".join(mtl))
    return categories, used


def _bbox(o: Any, up: str, scale: float) -> dict[str, list[float]]:
    """An object's bbox in the files' frame; Sweet Home 3D models face +z (y up), i.e. W -y: yaw + 180."""
    w, d, h = o.size
    centre = _to_file(np.array([[o.x, o.y, o.z + h / 2]]), up, scale)[0]
    yaw = math.remainder(o.yaw + math.pi, 2 * math.pi)
    if up == "y":
        return {
            "centre": centre.tolist(),
            "size": [w / scale, h / scale, d / scale],
            "euler": [0.0, yaw, 0.0],
        }
    return {"centre": centre.tolist(), "size": [w / scale, d / scale, h / scale], "euler": [0.0, 0.0, yaw]}


def _licences(name: str, used: dict[str, set[str]], sources: dict[str, _Source]) -> str:
    lines = [
        f"# Licences of {name}",
        "",
        "Assembled by vgpnav_env.scenes.corpus from Debian packages; every file keeps its licence.",
        "",
    ]
    for key in sorted(used):
        src = sources[key]
        lines += [
            f"## {key}: {src.deb.name} ({src.spec['member']})",
            "",
            f"Licence: {src.spec['licence']}. Copyright: {src.spec['copyright']}.",
            f"Full texts: licences/{src.spec['package']}.copyright (the package's Debian copyright file).",
            "",
        ]
        for item in sorted(used[key]):
            creator = src.creators.get(item, "")
            lines.append(f"- {item}" + (f" (creator: {creator})" if creator else ""))
        lines.append("")
    return "\n".join(lines)


def _write_scene(name: str, recipe: dict, recipes: dict, sources: dict[str, _Source], out: Path) -> None:
    up, scale = recipe["up"], UNITS[recipe["units"]]
    spec = parse_spec(recipe["spec"], source=f"{CORPUS_FILE.name}: scenes.{name}")
    categories, textures = _write_structure(
        spec, recipe, recipes["textures"], sources["sh3d"], out, up, scale
    )
    used: dict[str, set[str]] = {"sh3d": textures}
    copied: set[str] = set()
    for layout in spec.layout_names:
        objects = []
        for o in spec.layout_objects(layout):
            key, _, folder = str(o.mesh).partition(":")
            if key not in sources:
                raise SceneError(
                    f"{CORPUS_FILE.name}: {o.name!r}: unknown source {key!r}; allowed: {sorted(sources)}"
                )
            used.setdefault(key, set()).add(folder)
            files = sources[key].folder(folder)
            if folder not in copied:
                for fname, data in files.items():
                    dest = out / "objects" / folder / fname
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    if up == "z" and fname.lower().endswith(".obj"):
                        data = _obj_to_z_up(data.decode("latin-1")).encode("latin-1")
                    dest.write_bytes(data)
                copied.add(folder)
            obj = next(f for f in files if f.lower().endswith(".obj") and "/" not in f)
            objects.append(
                {
                    "name": o.name,
                    "category": o.category,
                    "mesh": f"objects/{folder}/{obj}",
                    "bbox": _bbox(o, up, scale),
                }
            )
        data: dict[str, Any] = {"objects": objects}
        if layout == "base":
            data = {"name": name, "structure": "structure.obj", "up": up, "scale": scale, **data}
            if recipe["categories"]:
                data["structure_categories"] = categories
        fname = "layout.json" if layout == "base" else f"layout_{layout}.json"
        (out / fname).write_text(json.dumps(data, indent=1) + "\n")
    (out / "LICENSES.md").write_text(_licences(name, used, sources))
    (out / "licences").mkdir()
    for key in used:
        shutil.copyfile(
            sources[key].copyright, out / "licences" / f"{sources[key].spec['package']}.copyright"
        )


def _stamp(recipe: dict, sources: dict[str, _Source]) -> dict[str, Any]:
    text = json.dumps(recipe, sort_keys=True)
    return {
        "format": "vgpnav-corpus-scene",
        "version": CORPUS_VERSION,
        "recipe_sha256": hashlib.sha256(text.encode()).hexdigest(),
        "builder_sha256": hashlib.sha256(Path(__file__).read_bytes()).hexdigest(),
        "packages": sorted({s.deb.name for s in sources.values()}),
    }


def build_corpus(
    out: Path | str | None = None,
    debs: Path | str | None = None,
    names: list[str] | None = None,
    fetch: bool = True,
) -> list[Path]:
    """Write the corpus scenes ``names`` (default all) below ``out``; return their directories.

    ``fetch`` False: raise ``FileNotFoundError`` instead of running ``apt-get download`` for a
    package that is not in ``debs`` yet.

    A directory whose ``corpus.json`` matches the recipe and packages is kept as it is; others are
    written to a temporary sibling and swapped in (only directories holding a ``corpus.json`` are
    ever replaced).
    """
    out = Path(out) if out is not None else default_corpus_dir()
    debs = Path(debs) if debs is not None else out / "debs"
    recipes = load_recipes()
    names = list(recipes["scenes"]) if names is None else names
    unknown = sorted(set(names) - set(recipes["scenes"]))
    if unknown:
        raise SceneError(f"unknown corpus scene(s) {unknown}; allowed: {sorted(recipes['scenes'])}")
    sources = _sources(recipes["sources"], debs, fetch)
    dirs = []
    for name in names:
        recipe = recipes["scenes"][name]
        target = out / name
        stamp = {**_stamp(recipe, sources), "textures": recipes["textures"]}
        marker = target / "corpus.json"
        if marker.is_file() and json.loads(marker.read_text()) == stamp:
            dirs.append(target)
            continue
        if target.exists() and not marker.is_file():
            raise SceneError(f"refusing to replace {target}: it is not a corpus scene (no corpus.json)")
        tmp = out / f".{name}.tmp-{uuid.uuid4().hex[:8]}"
        tmp.mkdir(parents=True)
        try:
            _write_scene(name, recipe, recipes, sources, tmp)
            (tmp / "corpus.json").write_text(json.dumps(stamp, indent=1) + "\n")
            if target.exists():
                shutil.rmtree(target)
            tmp.replace(target)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp)
        logger.info("wrote corpus scene %s", target)
        dirs.append(target)
    return dirs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m vgpnav_env.scenes.corpus", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--out", type=Path, help="corpus directory (default $VGPNAV_CACHE/corpus)")
    parser.add_argument("--debs", type=Path, help="where the .deb files are or go (default OUT/debs)")
    parser.add_argument("--scene", action="append", help="only this scene (repeatable; default all)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        dirs = build_corpus(args.out, args.debs, args.scene)
    except SceneError as e:
        sys.stderr.write(f"corpus: error: {e}\n")
        return 2
    sys.stdout.write("\n".join(str(d) for d in dirs) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
