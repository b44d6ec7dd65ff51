"""VLAD retrieval on synthetic textured views and the geometry-aware selection (paper Alg. 1)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera, camera_pose
from vgpnav_env.perception.backbones import ClassicalBackbone, ClassicalConfig, classical
from vgpnav_env.perception.backbones.classical import detect_sift
from vgpnav_env.perception.retrieval import (
    RetrievalConfig,
    TrackingConfig,
    VladConfig,
    VladIndex,
    geometric_median,
    geometric_rerank,
    nearby_cameras,
    overlapping_cameras,
    pose_guided_references,
    select_references,
    tracked_references,
    twin_references,
)

STEP = 40  # pixels between database crops of the panorama
CAMERA = PinholeCamera(320, 240, np.deg2rad(60.0))


@pytest.fixture(scope="module")
def panorama() -> np.ndarray:
    """A 240 x 1600 RGB 'world' of random shapes over smooth noise."""
    rng = np.random.default_rng(0)
    h, w = 240, 1600
    base = cv2.resize(rng.integers(0, 255, (h // 16, w // 16, 3), dtype=np.uint8), (w, h), cv2.INTER_CUBIC)
    img = np.ascontiguousarray(base)
    for _ in range(260):
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        kind = rng.integers(3)
        if kind == 0:
            cv2.rectangle(
                img, (x, y), (x + int(rng.integers(8, 50)), y + int(rng.integers(8, 50))), colour, -1
            )
        elif kind == 1:
            cv2.circle(img, (x, y), int(rng.integers(4, 25)), colour, -1)
        else:
            cv2.line(img, (x, y), (x + int(rng.integers(-60, 60)), y + int(rng.integers(-60, 60))), colour, 3)
    return img


@pytest.fixture(scope="module")
def index(panorama: np.ndarray) -> VladIndex:
    crops = [panorama[:, x : x + 320] for x in range(0, panorama.shape[1] - 320 + 1, STEP)]
    return VladIndex.fit(crops, config=VladConfig(n_words=32), seed=0, fingerprint="db-v1")


def test_descriptors_are_unit_norm_and_deterministic(index: VladIndex, panorama: np.ndarray) -> None:
    assert (
        index.database.shape == (33, 32 * 128 + 128) and index.database.dtype == np.float32
    )  # VLAD + colour
    np.testing.assert_allclose(np.linalg.norm(index.database, axis=1), 1.0, atol=1e-5)
    again = VladIndex.fit(
        [panorama[:, x : x + 320] for x in range(0, 1281, STEP)], config=VladConfig(n_words=32), seed=0
    )
    np.testing.assert_allclose(again.database, index.database, atol=1e-6)
    d = index.describe(panorama[:, :320])
    assert d.shape == (1, index.dim)
    np.testing.assert_allclose(d[0], index.database[0], atol=1e-6)


def test_query_retrieves_the_overlapping_views(index: VladIndex, panorama: np.ndarray) -> None:
    rng = np.random.default_rng(1)
    hits = 0
    offsets = range(15, 1260, 97)
    for x in offsets:
        crop = panorama[:, x : x + 320].astype(float) * 0.85 + 20 + rng.normal(0, 6, (240, 320, 3))
        sim = index.similarity(np.clip(crop, 0, 255).astype(np.uint8))
        nearest = {x // STEP, x // STEP + 1}
        hits += int(np.argmax(sim)) in nearest
    assert hits >= len(offsets) - 1, f"{hits}/{len(offsets)} queries retrieved an overlapping view"


def test_save_load_round_trip_and_fingerprint(index: VladIndex, panorama: np.ndarray, tmp_path) -> None:
    assert VladIndex.load(tmp_path / "missing") is None
    index.save(tmp_path)
    loaded = VladIndex.load(tmp_path, expected_fingerprint="db-v1")
    assert loaded is not None and loaded.fingerprint == "db-v1" and loaded.config == index.config
    np.testing.assert_array_equal(loaded.database, index.database)
    np.testing.assert_allclose(loaded.describe(panorama[:, 100:420]), index.describe(panorama[:, 100:420]))
    assert VladIndex.load(tmp_path, expected_fingerprint="db-v2") is None
    assert not list(tmp_path.glob("*.tmp"))
    (tmp_path / "vlad_index.json").write_text("{not json")
    with pytest.raises(ValueError, match="corrupt VLAD index"):
        VladIndex.load(tmp_path)


def test_sift_index_fits_from_given_features_and_shares_the_query_extraction(
    panorama: np.ndarray, tmp_path, monkeypatch
) -> None:
    crops = [np.ascontiguousarray(panorama[:, x : x + 320]) for x in range(0, 1281, STEP)]
    sift, config = ClassicalConfig(), VladConfig(local_features="sift", n_words=32)
    index = VladIndex.fit(crops, config=config, seed=0, sift=sift, threads=2)
    given = [ClassicalBackbone(sift).extract(c).descriptors for c in crops]
    fitted = VladIndex.fit(crops, config=config, seed=0, sift=sift, descriptors=given)
    np.testing.assert_array_equal(fitted.database, index.database)
    assert int(np.argmax(index.similarity(panorama[:, 200:520]))) == 5
    # The feature settings are part of the cache key.
    index.save(tmp_path)
    assert VladIndex.load(tmp_path, sift=ClassicalConfig(max_keypoints=500)) is None
    assert VladIndex.load(tmp_path, sift=sift) is not None
    # Retrieval and the backbone extract a query image once.
    detected = []
    monkeypatch.setattr(classical, "detect_sift", lambda *a: detected.append(1) or detect_sift(*a))
    query = np.ascontiguousarray(panorama[:, 333:653])
    index.similarity(query)
    ClassicalBackbone(sift)(query, [crops[8]], CAMERA, reference_keys=[8])
    assert len(detected) == 2  # the query once, the reference once


def test_geometric_rerank_puts_the_views_that_share_geometry_first(panorama: np.ndarray) -> None:
    crops = [np.ascontiguousarray(panorama[:, x : x + 320]) for x in range(0, 1281, STEP)]
    backbone = ClassicalBackbone(ClassicalConfig())
    features = [backbone.extract(c) for c in crops]
    query = backbone.extract(np.ascontiguousarray(panorama[:, 410:730]))  # overlaps crops 3..18
    # Appearance got it wrong: the far end of the panorama looks most similar.
    wrong = np.linspace(-1.0, 1.0, len(crops))
    s = geometric_rerank(wrong, query, features.__getitem__, RetrievalConfig(k=3, rerank=20))
    top = np.argsort(-s, kind="stable")
    assert set(top[:3]) <= set(range(13, 19)), top[:5]  # the overlapping crops among the 20 re-ranked
    assert np.all(s[19:] < wrong.min())  # crops 19..32 do not overlap: below every other image
    s_more = geometric_rerank(wrong, query, features.__getitem__, RetrievalConfig(rerank=33))
    best = int(np.argmax(s_more))
    assert abs(best * STEP - 410) <= STEP and s_more[best] == 2.0
    off = geometric_rerank(wrong, query, features.__getitem__, RetrievalConfig(rerank=0))
    np.testing.assert_array_equal(off, wrong)
    with pytest.raises(ValueError, match="rerank"):
        RetrievalConfig(rerank=-1)


def test_dense_extraction_on_threads_is_the_same(index: VladIndex, panorama: np.ndarray) -> None:
    crops = [panorama[:, x : x + 320] for x in range(0, 1281, STEP)]
    threaded = VladIndex.fit(crops, config=VladConfig(n_words=32), seed=0, threads=2)
    np.testing.assert_array_equal(threaded.database, index.database)
    with pytest.raises(ValueError, match="local_features"):
        VladConfig(local_features="orb")


def test_whitening_keeps_retrieval(panorama: np.ndarray) -> None:
    crops = [panorama[:, x : x + 320] for x in range(0, 1281, STEP)]
    idx = VladIndex.fit(
        crops, config=VladConfig(n_words=32, whiten=True, whiten_dim=16, colour_weight=0.0), seed=0
    )
    assert idx.database.shape == (33, 16)
    assert int(np.argmax(idx.similarity(panorama[:, 200:520]))) == 5


def _reference_alg1(sim: np.ndarray, T: np.ndarray, cfg: RetrievalConfig) -> list[int]:
    """Literal loop transcription of paper Alg. 1 (geometric median, L_scale = max valid distance)."""
    pool = sorted(range(len(sim)), key=lambda i: -sim[i])[: cfg.pool_factor * cfg.k]
    best = pool[0]
    med = geometric_median(T[pool, :3, 3])
    d = {i: np.linalg.norm(T[i, :3, 3] - med) for i in pool}
    tau = np.percentile(list(d.values()), cfg.outlier_percentile)
    valid = [i for i in pool if d[i] <= tau or i == best]
    lo, hi = min(sim[i] for i in valid), max(sim[i] for i in valid)
    s_norm = {i: (sim[i] - lo) / (hi - lo) for i in valid}
    L = max(np.linalg.norm(T[a, :3, 3] - T[b, :3, 3]) for a in valid for b in valid)
    S = [best]
    while len(S) < cfg.k and len(S) < len(valid):
        c_star, best_score = None, -np.inf
        for c in valid:
            if c in S:
                continue
            d_geo = min(
                cfg.lambda_pos * np.linalg.norm(T[c, :3, 3] - T[s, :3, 3]) / L
                + cfg.lambda_ang * np.arccos(np.clip(T[c, :3, 2] @ T[s, :3, 2], -1, 1)) / np.pi
                for s in S
            )
            if d_geo + cfg.lambda_sim * s_norm[c] > best_score:
                c_star, best_score = c, d_geo + cfg.lambda_sim * s_norm[c]
        S.append(c_star)
    return S


@pytest.mark.parametrize("seed", range(4))
def test_geometry_selection_matches_literal_algorithm(seed: int) -> None:
    rng = np.random.default_rng(seed)
    M = 120
    T = np.array(
        [
            camera_pose([*rng.uniform(0, 8, 2), 1.2], rng.uniform(-np.pi, np.pi), rng.uniform(0, 0.5))
            for _ in range(M)
        ]
    )
    sim = rng.uniform(0, 1, M)
    cfg = RetrievalConfig(k=10)
    got = select_references(sim, T, cfg)
    assert got.tolist() == _reference_alg1(sim, T, cfg)
    assert len(set(got.tolist())) == 10 and got[0] == np.argmax(sim)


def test_geometry_rejects_aliasing_and_prefers_diverse_views() -> None:
    rng = np.random.default_rng(5)
    # 30 views around (2, 2): 10 near-duplicates of the best view with top similarity, 20 diverse
    # ones slightly less similar, plus one aliased view 20 m away that is the 3rd most similar.
    dup = [
        camera_pose([2.0 + rng.normal(0, 0.01), 2.0, 1.2], 0.0 + rng.normal(0, 0.01), 0.35) for _ in range(10)
    ]
    diverse = [
        camera_pose([*rng.uniform(0.5, 3.5, 2), 1.2], rng.uniform(-np.pi, np.pi), 0.35) for _ in range(20)
    ]
    alias = [camera_pose([22.0, 2.0, 1.2], 0.0, 0.35)]
    T = np.array(dup + diverse + alias)
    sim = np.concatenate([np.linspace(0.95, 0.9, 10), np.linspace(0.85, 0.7, 20), [0.94]])
    cfg = RetrievalConfig(k=5)
    topk = select_references(sim, T, RetrievalConfig(k=5, method="topk"))
    geo = select_references(sim, T, cfg)
    assert topk.tolist() == [0, 1, 30, 2, 3]
    assert geo[0] == 0 and 30 not in geo
    assert sum(i < 10 for i in geo) == 1, "near-duplicates of the best view should not be re-selected"
    # The best match is kept even when it is the spatial outlier.
    sim_alias_best = sim.copy()
    sim_alias_best[30] = 1.0
    assert select_references(sim_alias_best, T, cfg)[0] == 30


def test_twin_references_are_the_most_similar_views_that_cannot_see_the_pose() -> None:
    # A room at (2, 2) looking +x (views 0-5), its identical twin at (8, 2) (6, 7), a view beside
    # the pose (8) and a third place (9); the references are the room's first three views.
    here = [camera_pose([2.0 + 0.1 * i, 2.0, 1.2], 0.0, 0.35) for i in range(6)]
    twin = [camera_pose([8.0 + 0.1 * i, 2.0, 1.2], 0.0, 0.35) for i in range(2)]
    beside = [camera_pose([2.5, 2.3, 1.2], 0.2, 0.35)]
    third = [camera_pose([20.0, 2.0, 1.2], 0.0, 0.35)]
    T = np.array(here + twin + beside + third)
    sim = np.array([0.95, 0.9, 0.85, 0.8, 0.75, 0.7, 0.93, 0.92, 0.99, 0.5])
    refs = [0, 1, 2]
    assert twin_references(sim, T, here[0], CAMERA, refs, 2).tolist() == [6, 7]
    # The cameras that see the pose's view (3-5, 8) and the excluded ones are never twins.
    assert twin_references(sim, T, here[0], CAMERA, refs, 5).tolist() == [6, 7, 9]
    assert twin_references(sim, T, here[0], CAMERA, [*refs, 6, 7, 9], 5).size == 0
    assert twin_references(sim, T, here[0], CAMERA, refs, 0).size == 0
    with pytest.raises(ValueError, match="twins must be"):
        RetrievalConfig(twins=-1)


def test_selection_edge_cases() -> None:
    T = np.array([camera_pose([0, 0, 1.2], 0.0, 0.3)] * 3)
    assert select_references(np.zeros(0), np.zeros((0, 4, 4))).size == 0
    assert sorted(select_references(np.array([0.5, 0.5, 0.5]), T).tolist()) == [0, 1, 2]
    with pytest.raises(ValueError, match="need similarity"):
        select_references(np.ones(3), T[:2])
    with pytest.raises(ValueError, match="method must be"):
        RetrievalConfig(method="random")


def test_pose_guided_references_rank_nearby_cameras_looking_the_same_way() -> None:
    h = 1.2
    poses = np.stack(
        [
            camera_pose([0.0, 0.0, h], 0.0, 0.0),  # the hypothesis' own camera (excluded)
            camera_pose([1.0, 0.0, h], 0.0, 0.0),  # 1 m ahead, same heading: 1/1.5 = 0.67
            camera_pose([0.5, 0.0, h], np.pi, 0.0),  # looks back: never
            camera_pose([3.0, 0.0, h], 0.0, 0.0),  # too far: never
            camera_pose([0.0, 0.2, h], np.deg2rad(20.0), 0.0),  # 0.2/1.5 + 20/35 = 0.70
            camera_pose([0.0, 5.0, h], np.pi / 2, 0.0),  # the second hypothesis' neighbour
        ]
    )
    first = camera_pose([0.0, 0.0, h], 0.0, 0.0)
    got = pose_guided_references(poses, first[None], 10, exclude=[0])
    assert got.tolist() == [1, 4]
    second = camera_pose([0.0, 4.5, h], np.pi / 2, 0.0)
    # Hypotheses take turns; n caps the count; no index twice.
    assert pose_guided_references(poses, np.stack([first, second]), 2, exclude=[0]).tolist() == [1, 5]
    assert pose_guided_references(poses, np.stack([first, first]), 10).tolist() == [0, 1, 4]
    with pytest.raises(ValueError, match="radius"):
        pose_guided_references(poses, first[None], 3, radius=0.0)
    # The shared test: centre distance in [min, max] metres, optical axes within the angle.
    near = nearby_cameras(poses, first, 1.5, 35.0)
    assert near.index.tolist() == [0, 1, 4]
    np.testing.assert_allclose(near.distance, [0.0, 1.0, 0.2])
    np.testing.assert_allclose(near.cos_angle, [1.0, 1.0, np.cos(np.deg2rad(20.0))])
    assert nearby_cameras(poses, first, 1.5, 35.0, min_distance=0.5).index.tolist() == [1]
    assert nearby_cameras(poses, first, 1.5, 19.0).index.tolist() == [0, 1]


def test_tracking_without_near_cameras_takes_those_that_see_the_predicted_view() -> None:
    """A predicted pose with no database camera within 2 m / 45 deg (home:2's frames 21-24): the
    cameras within 4 m whose images hold the predicted view join the pool; one 3 m behind looking
    the same way sees it, one beside it facing away, one 3 m ahead looking back and one 6 m behind
    do not (angle, overlap, distance)."""
    h = 1.2
    predicted = camera_pose([0.0, 0.0, h], 0.0, 0.0)
    poses = np.stack(
        [
            camera_pose([-3.0, 0.0, h], 0.0, 0.0),  # 3 m behind, same heading: sees the view
            camera_pose([-2.8, 0.4, h], np.deg2rad(-10.0), 0.0),  # 2.8 m behind, 10 deg: sees it
            camera_pose([-2.9, -0.3, h], np.deg2rad(15.0), 0.0),  # likewise
            camera_pose([0.5, 0.5, h], np.deg2rad(120.0), 0.0),  # near, facing away: angle
            camera_pose([3.0, 0.0, h], np.pi, 0.0),  # ahead, looking back: angle
            camera_pose([-6.0, 0.0, h], 0.0, 0.0),  # too far
            camera_pose([-1.0, 3.5, h], 0.0, 0.0),  # 3.6 m aside, same heading: sees little of it
        ]
    )
    config = TrackingConfig()
    assert len(nearby_cameras(poses, predicted, config.radius, config.max_angle_deg).index) == 0
    got = overlapping_cameras(
        poses, predicted, CAMERA, 4.0, 45.0, config.overlap_depths_m, config.min_overlap
    )
    assert got.tolist() == [0, 1, 2]
    sims = np.linspace(1.0, 0.5, len(poses))
    refs = tracked_references(sims, poses, predicted, CAMERA, RetrievalConfig(k=3), config)
    assert set(refs.tolist()) <= {0, 1, 2} and refs[0] == 0 and len(refs) >= 2  # Alg. 1 over the pool
    # Too few overlapping cameras: none, the caller relocalizes.
    few = poses[[0, 1, 3, 4, 5]]
    assert len(tracked_references(sims[:5], few, predicted, CAMERA, RetrievalConfig(k=3), config)) == 0
    with pytest.raises(ValueError, match="overlap"):
        TrackingConfig(overlap_radius=1.0)
