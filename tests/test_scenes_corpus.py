"""The corpus of third-party scenes (scenes/corpus.yaml): load, compile, render with their
textures, ground truth, runs and the oracle.

The corpus is assembled from Debian packages that ``python -m vgpnav_env.scenes.corpus`` (and
``.ci/run``) fetch; without them these tests skip, unless ``VGPNAV_REQUIRE_CORPUS=1`` (CI), when
they fail.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from vgpnav_env.build import build_runs
from vgpnav_env.geometry import PinholeCamera, camera_pose
from vgpnav_env.groundtruth import ground_truth_map
from vgpnav_env.render import MujocoRenderer
from vgpnav_env.runs import load_build
from vgpnav_env.scenes import load_scene
from vgpnav_env.scenes.corpus import build_corpus
from vgpnav_env.scenes.mesh_scene import load_mesh_scene
from vgpnav_env.scenes.meshes import STRUCTURE_CATEGORIES
from vgpnav_env.scenes.model import build_model


@pytest.fixture(scope="session")
def corpus() -> dict[str, str]:
    """Name -> directory of every corpus scene (built once from the fetched packages)."""
    try:
        dirs = build_corpus(fetch=False)
    except FileNotFoundError as e:
        if os.environ.get("VGPNAV_REQUIRE_CORPUS") == "1":
            raise
        pytest.skip(f"corpus packages not fetched: {e}")
    return {d.name: str(d) for d in dirs}


@pytest.mark.parametrize(
    ("name", "missing", "fixes", "glass"),
    [
        (
            "sh3d_apartment",
            ("Living room rug.jpg", "WoodFine0031_10_S.jpg"),
            ("little_plant/Mutt", "plant_big/ground"),
            ("table", 0.65),
        ),
        ("sh3d_office", ("tree.jpg",), ("plant/Mutt", "cabinet/ovenGlass"), ("cabinet", 0.8)),
        ("sh3d_studio", (), ("cabinet_1/cabinetBaseboard", "oven/verde_led"), ("shelves", 0.55)),
        (
            "sh3d_bedsit",
            ("Living room rug.jpg",),
            ("wardrobe/Door_Reflect_Right", "sink/cabinetBaseboard"),
            ("shower", 0.3),
        ),
        ("sh3d_lounge", (), ("pool_table/cueTip", "speaker_w/matte_black"), ("shelves", 0.4)),
    ],
)
def test_corpus_scene_loads_compiles_and_renders_textures(corpus, name, missing, fixes, glass) -> None:
    scene, report = load_mesh_scene(corpus[name], report=True)
    assert scene.texture == "native"
    for m in missing:  # the authors' own broken texture references are reported, not fatal
        assert any(m in line for line in report.missing), m
    for f in fixes:  # flat parts (a pot's soil, an oven's glass) got thin boxes
        assert any(line.startswith(f"{f}: flat part -> thin box") for line in report.fixes), f
    cats = {m.category for m in scene.meshes}
    assert {"floor", "ceiling", "wall", "chair", "table"} <= cats
    lo, hi = scene.bounds
    assert lo[2] == pytest.approx(0.0, abs=0.05) and 2.5 < hi[2] < 3.0  # metres, z up, floor at 0
    obj, alpha = glass  # MTL "d" of a glass part reaches the MuJoCo material
    assert alpha in {round(m.material.rgba[3], 3) for m in scene.meshes if m.name.split("/")[0] == obj}
    model = build_model(scene)
    assert np.isclose(model.mat_rgba[:, 3], alpha).any() and model.ntex >= 10
    textured = [m for m in scene.meshes if m.material.image is not None]
    assert {"floor", "wall"} <= {m.category for m in textured}
    # Looking straight down at bare floor (0.5 m above, in a room, farthest from objects): texture,
    # not a flat colour.
    camera = PinholeCamera(96, 72, np.deg2rad(60.0))
    boxes = np.array([m.mesh.bounds[:, :2] for m in scene.meshes if m.category not in STRUCTURE_CATEGORIES])
    spots = []
    for floor in (m.mesh.bounds for m in scene.meshes if m.category == "floor"):
        axes = [np.arange(floor[0, i] + 1, floor[1, i] - 1, 0.1) for i in (0, 1)]
        spots.append(np.stack(np.meshgrid(*axes), -1).reshape(-1, 2))
    grid = np.concatenate(spots)
    gap = np.maximum(boxes[None, :, 0] - grid[:, None], grid[:, None] - boxes[None, :, 1])
    x, y = grid[np.argmax(gap.max(axis=2).min(axis=1))]
    with MujocoRenderer(model, camera) as r:
        frame = r.render(camera_pose([x, y, 0.5], 0.0, np.deg2rad(90.0)))
    assert np.allclose(frame.depth, 0.5, atol=0.01) and frame.rgb.std(axis=(0, 1)).max() > 8.0


def test_corpus_build_ground_truth_and_oracle(corpus, tmp_path) -> None:
    from vgpnav_env.eval.navigation import evaluate_navigation

    src = corpus["sh3d_apartment"]
    gt = ground_truth_map(load_scene(src, "changed"))
    assert 15.0 < gt.area_m2(gt.navigable) < 30.0
    summary = build_runs(src, tmp_path / "build", size=(48, 36), progress=False)
    build = load_build(tmp_path / "build")
    assert summary["texture"] == "native" and summary["database_frames"] > 150
    assert len(build.query) == summary["query_frames"] > 30
    # With navigable cells in contact with hulls, 3 of these 5 office episodes were impossible. The
    # apartment's episode 0 timed out while the oracle planned on the inflated free floor alone
    # (hulls reach past their floor cells); it keeps to navigable cells now (measured at 320x240:
    # apartment 20/20, office 20/20 over seeds 0-19).
    for scene, episodes, successes in ((src, 3, 3), (corpus["sh3d_office"], 5, 5)):
        report = evaluate_navigation(
            scene, agent="oracle", episodes=episodes, seed=0, size=(48, 36), progress=False
        )
        assert round(report["success_rate"] * episodes) >= successes, scene
