"""Convex collision parts for meshes made by other people, decided by a shape check.

Every part gets a shape from the principal extents of its vertices (a PCA frame, metres in W):

- ``solid``: all three extents >= ``FLAT_M`` -> its convex hull (or, if that hull encloses less
  than ``MIN_HULL_FILL`` of the principal box, the oriented box: qhull output is never trusted
  unchecked);
- ``flat`` (a TV screen, a soil disc, a rug): the thinnest extent < ``FLAT_M`` -> a thin box
  (``THIN_BOX_M``) over the part's minimum-area rectangle in its plane;
- ``line`` (a wire, a pole drawn as a polyline) or ``empty`` (no finite vertex) -> degenerate:
  the part is covered by the hull of its whole object instead;
- ``tiny``: every extent < ``TINY_M`` -> no collision (nothing that small stops a robot).

MuJoCo then only sees boxes and full-dimensional hulls, so compiling never fails on coplanar
or collinear vertices. Each decision other than a plain hull is returned as a note
(``"flat part -> thin box 0.02 m"``) for the loader's report.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

FLAT_M = 0.005
TINY_M = 0.01
THIN_BOX_M = 0.02
MIN_HULL_FILL = 1e-3
WALL_SKIN_M = 0.05


@dataclass(frozen=True)
class Shape:
    """Principal frame of a point set: ``kind``, ``centre`` (3,), ``axes`` (3, 3) rows = directions
    of decreasing extent, ``extents`` (3,) sizes along them (metres)."""

    kind: str
    centre: NDArray[np.float64]
    axes: NDArray[np.float64]
    extents: NDArray[np.float64]


def shape_of(points: NDArray) -> Shape:
    """Classify a point set (N, 3) as ``solid``, ``flat``, ``line``, ``tiny`` or ``empty``."""
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) == 0:
        return Shape("empty", np.zeros(3), np.eye(3), np.zeros(3))
    mean = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - mean, full_matrices=False)
    axes = np.eye(3) if vt.shape[0] < 3 else vt
    axes = axes.copy()
    axes[2] = np.cross(axes[0], axes[1])  # right-handed
    local = (p - mean) @ axes.T
    lo, hi = local.min(axis=0), local.max(axis=0)
    extents = hi - lo
    centre = mean + ((lo + hi) / 2) @ axes
    if extents.max() < TINY_M:
        kind = "tiny"
    elif extents[1] < FLAT_M:
        kind = "line"
    elif extents[2] < FLAT_M:
        kind = "flat"
    else:
        kind = "solid"
    return Shape(kind, centre, axes, extents)


def _box(centre: NDArray, axes: NDArray, extents: NDArray) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, :3] = axes.T
    T[:3, 3] = centre
    return trimesh.creation.box(extents=extents, transform=T)


def thin_box(points: NDArray, shape: Shape) -> trimesh.Trimesh:
    """A ``THIN_BOX_M`` box over the minimum-area rectangle of flat points in their plane."""
    local = (np.asarray(points, float) - shape.centre) @ shape.axes[:2].T
    T2, size2 = trimesh.bounds.oriented_bounds_2D(local)
    # T2 maps the points into the rectangle's frame (centred): invert for its axes and centre.
    inv = np.linalg.inv(T2)
    u = inv[:2, 0] @ shape.axes[:2]
    v = inv[:2, 1] @ shape.axes[:2]
    centre = shape.centre + inv[:2, 2] @ shape.axes[:2]
    axes = np.stack([u, v, np.cross(u, v)])
    return _box(centre, axes, np.array([size2[0], size2[1], THIN_BOX_M]))


def solid_hull(points: NDArray, shape: Shape) -> tuple[trimesh.Trimesh, str | None]:
    """Convex hull of solid points, or their principal box if the hull is not a proper volume."""
    hull = trimesh.convex.convex_hull(np.asarray(points, float))
    box_volume = float(np.prod(shape.extents))
    if hull.is_volume and hull.volume >= MIN_HULL_FILL * box_volume:
        return hull, None
    return _box(shape.centre, shape.axes, shape.extents), "hull not a proper volume -> oriented box"


def part_collision(mesh: trimesh.Trimesh) -> tuple[list[trimesh.Trimesh], str, str | None]:
    """(convex parts, shape kind, note) for one part; degenerate kinds return no parts.

    ``note`` is None for a plain hull, else what was done (for the load report).
    """
    points = np.asarray(mesh.vertices, float)[np.unique(np.asarray(mesh.faces))]
    shape = shape_of(points)
    if shape.kind == "solid":
        hull, note = solid_hull(points, shape)
        return [hull], shape.kind, note
    if shape.kind == "flat":
        return [thin_box(points, shape)], shape.kind, f"flat part -> thin box {THIN_BOX_M:g} m"
    if shape.kind == "tiny":
        return [], shape.kind, f"tiny part (< {TINY_M:g} m) -> no collision"
    return [], shape.kind, f"degenerate part ({shape.kind}) -> covered by the object's hull"


def object_collision(parts: list[trimesh.Trimesh]) -> list[trimesh.Trimesh]:
    """One convex part for a whole object (all its parts' vertices): hull, thin box, or none."""
    points = np.concatenate([np.asarray(m.vertices, float)[np.unique(np.asarray(m.faces))] for m in parts])
    shape = shape_of(points)
    if shape.kind == "solid":
        return [solid_hull(points, shape)[0]]
    if shape.kind == "flat":
        return [thin_box(points, shape)]
    return []


def is_convex_solid(m: trimesh.Trimesh) -> bool:
    """Whether ``m`` is a closed solid that its convex hull fits within 3 % (checked, not assumed)."""
    if not m.is_watertight or m.volume <= 0 or shape_of(m.vertices).kind != "solid":
        return False
    hull = trimesh.convex.convex_hull(m.vertices)
    return bool(hull.is_volume and abs(m.volume) >= 0.97 * hull.volume)


def facet_boxes(m: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """Thin convex solids behind the vertical surfaces of a (possibly open, non-convex) wall mesh:
    a ``WALL_SKIN_M`` box behind each rectangular vertical facet, a thin prism per triangle otherwise."""
    out = []
    vertical = np.abs(m.face_normals[:, 2]) < 0.3
    groups = [list(f) for f in m.facets] + [
        [i] for i in set(range(len(m.faces))) - {i for f in m.facets for i in f}
    ]
    for faces in groups:
        if not vertical[faces[0]]:
            continue
        n = m.face_normals[faces[0]]
        t1 = np.cross([0.0, 0.0, 1.0], n)
        t1 /= np.linalg.norm(t1)
        pts = m.vertices[m.faces[faces].ravel()]
        u, z = pts @ t1, pts[:, 2]
        area = float(m.area_faces[faces].sum())
        rect = (u.max() - u.min()) * (z.max() - z.min())
        if area < 1e-4:
            continue
        if area >= 0.95 * rect:
            centre = t1 * (u.max() + u.min()) / 2 + n * float(pts[0] @ n - WALL_SKIN_M / 2)
            centre[2] = (z.max() + z.min()) / 2
            axes = np.stack([t1, n, [0.0, 0.0, 1.0]])
            out.append(_box(centre, axes, np.array([u.max() - u.min(), WALL_SKIN_M, z.max() - z.min()])))
        else:
            for f in faces:
                tri = m.vertices[m.faces[f]]
                prism = np.concatenate([tri, tri - n * WALL_SKIN_M])
                shape = shape_of(prism)
                if shape.kind == "solid":  # sliver triangles cover nothing
                    out.append(solid_hull(prism, shape)[0])
    return out
