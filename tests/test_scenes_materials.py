"""Procedural materials: determinism, caching, tiling and the texture-level knob."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.scenes import MATERIAL_KINDS, TEXTURE_LEVELS, load_scene_spec, make_material
from vgpnav_env.scenes.materials import parse_material_name


def _grad_energy(img: np.ndarray) -> float:
    g = img.astype(np.float64).mean(axis=2)
    return float(np.mean(np.diff(g, axis=0) ** 2) + np.mean(np.diff(g, axis=1) ** 2))


def test_every_kind_and_level_builds_a_valid_image() -> None:
    for kind in sorted(MATERIAL_KINDS):
        for level in TEXTURE_LEVELS:
            m = make_material(kind, level)
            assert m.image is not None and m.image.dtype == np.uint8 and m.image.ndim == 3
            assert m.image.shape[2] == 3 and m.image.shape[0] == m.image.shape[1] in (256, 512)
            assert 0.2 <= m.tile_m <= 2.0 and m.specular <= 0.15
            assert not m.image.flags.writeable


def test_same_seed_same_image_cached_and_seeds_differ() -> None:
    a = make_material("parquet:oak", "realistic", 3)
    assert make_material("parquet:oak", "realistic", 3) is a
    make_material.cache_clear()
    b = make_material("parquet:oak", "realistic", 3)
    assert b is not a and np.array_equal(a.image, b.image)
    c = make_material("parquet:oak", "realistic", 4)
    assert np.abs(a.image.astype(int) - c.image.astype(int)).mean() > 5
    assert a.name != c.name and make_material("picture", seed=1).name != make_material("picture", seed=2).name


def test_tileable_textures_have_no_seam() -> None:
    """Opposite borders of a repeating texture continue each other like interior rows do."""
    for name in ("paint:white", "wood:oak", "carpet:grey", "fabric:blue", "linoleum:green", "marble:white"):
        img = make_material(name, "rich").image.astype(np.float64)
        seam = np.abs(img[0] - img[-1]).mean() + np.abs(img[:, 0] - img[:, -1]).mean()
        inner = np.abs(np.diff(img, axis=0)).mean() + np.abs(np.diff(img, axis=1)).mean()
        assert seam < 2.0 * inner + 1.0, (name, seam, inner)


def test_texture_levels_order_gradient_energy_on_walls_and_floors() -> None:
    spec = load_scene_spec("home")
    names = sorted({w.material for w in spec.walls} | {r.floor for r in spec.rooms})
    for name in names:
        e = {lvl: _grad_energy(make_material(name, lvl).image) for lvl in TEXTURE_LEVELS}
        assert e["rich"] > e["realistic"] > e["sparse"], (name, e)
    paint = {lvl: _grad_energy(make_material("paint:white", lvl).image) for lvl in TEXTURE_LEVELS}
    assert paint["realistic"] < 5.0 < 20.0 < paint["rich"]  # realistic walls are near blank, rich are not


def test_material_names_are_checked() -> None:
    assert parse_material_name("tiles") == ("tiles", "white")
    assert parse_material_name("wood:walnut") == ("wood", "walnut")
    with pytest.raises(ValueError, match="variants"):
        parse_material_name("wood:plastic")
    with pytest.raises(ValueError, match="unknown texture level"):
        make_material("wood", "ultra")
