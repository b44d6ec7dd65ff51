"""The on-disk run format: round trip, atomic saves, clear errors on damaged directories."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera, camera_pose
from vgpnav_env.runs import (
    RUN_FORMAT,
    Run,
    RunFormatError,
    load_run,
    load_run_depth,
    read_run_meta,
    run_fingerprint,
    save_run,
    write_run,
)


def make_run(n: int = 4, seed: int = 0, kind: str = "database") -> tuple[Run, np.ndarray]:
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(32, 24, np.deg2rad(60.0))
    images = rng.integers(0, 256, (n, 24, 32, 3), dtype=np.uint8)
    poses = np.stack([camera_pose(rng.uniform(0, 5, 3), rng.uniform(-3, 3), 0.3) for _ in range(n)])
    depth = rng.uniform(0.5, 8.0, (n, 24, 32)).astype(np.float32)
    depth[:, 0, 0] = np.inf
    meta = {
        "scene": "tiny",
        "layout": "base",
        "kind": kind,
        "seed": seed,
        "texture": "checker",
        "lighting": "default",
    }
    return Run(images, poses, cam, meta), depth


def test_round_trip(tmp_path: Path) -> None:
    run, depth = make_run()
    path = save_run(tmp_path / "run", run, depth)
    loaded = load_run(path)
    assert np.array_equal(loaded.images, run.images)  # PNG is lossless, RGB order kept
    assert np.array_equal(loaded.poses, run.poses)
    assert loaded.camera == run.camera
    assert np.allclose(json.loads((path / "intrinsics.json").read_text())["K"], run.camera.K)
    meta = loaded.metadata
    assert meta["format"] == RUN_FORMAT and meta["version"] == 1
    assert (meta["n_frames"], meta["width"], meta["height"]) == (4, 32, 24)
    assert meta["fovy_deg"] == pytest.approx(60.0)
    assert {k: meta[k] for k in run.metadata} == run.metadata
    d = load_run_depth(path)
    assert d.dtype == np.float32 and d.shape == depth.shape
    assert np.isinf(d[:, 0, 0]).all()
    finite = np.isfinite(depth)
    assert np.allclose(d[finite], depth[finite], rtol=1e-3)  # float16 storage
    assert sorted(p.name for p in path.iterdir()) == [
        "groundtruth",
        "images",
        "intrinsics.json",
        "meta.json",
        "poses.npy",
    ]
    assert not list(tmp_path.glob(".*"))  # no temp directory left behind


def test_write_run_reports_each_image_as_it_is_written(tmp_path: Path) -> None:
    run, depth = make_run(n=5)
    (tmp_path / "run").mkdir()
    written = []  # images on disk at each call (images are written on several threads)
    write_run(tmp_path / "run", run, depth, lambda: written.append(len(list(tmp_path.rglob("*.png")))))
    assert len(written) == 5 and all(n >= i + 1 for i, n in enumerate(sorted(written)))
    assert np.array_equal(load_run(tmp_path / "run").images, run.images)


def test_run_without_depth_and_validation(tmp_path: Path) -> None:
    run, _ = make_run()
    path = save_run(tmp_path / "run", run)
    with pytest.raises(RunFormatError, match="no ground-truth depth"):
        load_run_depth(path)
    with pytest.raises(ValueError, match="depth shape"):
        save_run(tmp_path / "bad", run, np.zeros((3, 24, 32)))
    assert not (tmp_path / "bad").exists()
    with pytest.raises(ValueError, match="metadata lacks"):
        save_run(tmp_path / "bad", Run(run.images, run.poses, run.camera, {"scene": "x"}))
    with pytest.raises(ValueError, match="uint8"):
        Run(run.images[:2], run.poses, run.camera, run.metadata)
    with pytest.raises(ValueError, match="kind"):
        Run(run.images, run.poses, run.camera, {**run.metadata, "kind": "train"})


def test_fingerprint_tracks_content(tmp_path: Path) -> None:
    run, _ = make_run()
    a = save_run(tmp_path / "a", run)
    b = save_run(tmp_path / "b", run)
    assert run_fingerprint(a) == run_fingerprint(b)
    images = run.images.copy()
    images[2, 5, 5] ^= 1
    c = save_run(tmp_path / "c", Run(images, run.poses, run.camera, run.metadata))
    poses = run.poses.copy()
    poses[0, 0, 3] += 1e-6
    d = save_run(tmp_path / "d", Run(run.images, poses, run.camera, run.metadata))
    assert len({run_fingerprint(p) for p in (a, c, d)}) == 3


def test_interrupted_save_keeps_previous_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    old, _ = make_run(seed=0)
    path = save_run(tmp_path / "run", old)
    new, depth = make_run(n=6, seed=1)

    import vgpnav_env.runs as runs

    calls = {"n": 0}
    real = runs._write_bytes

    def failing(p: Path, data: bytes, sync: bool = True) -> None:
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError("disk full (simulated)")
        real(p, data, sync)

    monkeypatch.setattr(runs, "_write_bytes", failing)
    with pytest.raises(OSError, match="simulated"):
        save_run(path, new, depth)
    monkeypatch.undo()
    kept = load_run(path)
    assert np.array_equal(kept.images, old.images)
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # temp directory cleaned up
    # A fresh save into a new path that fails leaves nothing at all.
    monkeypatch.setattr(runs, "_write_bytes", failing)
    calls["n"] = 0
    with pytest.raises(OSError):
        save_run(tmp_path / "fresh", new)
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    monkeypatch.undo()
    # A successful save replaces the old run.
    save_run(path, new, depth)
    assert len(load_run(path)) == 6


def _damage(path: Path, how: str) -> None:
    if how == "no_meta":
        (path / "meta.json").unlink()
    elif how == "foreign":
        (path / "meta.json").write_text(json.dumps({"format": "colmap", "version": 1}))
    elif how == "future":
        meta = json.loads((path / "meta.json").read_text())
        (path / "meta.json").write_text(json.dumps({**meta, "version": 99}))
    elif how == "bad_json":
        (path / "meta.json").write_text("{not json")
    elif how == "missing_image":
        (path / "images" / "000002.png").unlink()
    elif how == "extra_image":
        shutil.copy(path / "images" / "000000.png", path / "images" / "000004.png")
    elif how == "no_poses":
        (path / "poses.npy").unlink()
    elif how == "bad_poses":
        np.save(path / "poses.npy", np.zeros((4, 3, 4)))
    elif how == "corrupt_image":
        (path / "images" / "000001.png").write_bytes(b"not a png")
    elif how == "wrong_image_size":
        import cv2

        cv2.imwrite(str(path / "images" / "000001.png"), np.zeros((10, 10, 3), np.uint8))
    elif how == "no_intrinsics":
        (path / "intrinsics.json").unlink()


@pytest.mark.parametrize(
    ("how", "message"),
    [
        ("no_meta", "missing meta.json"),
        ("foreign", "format is 'colmap'"),
        ("future", "version 99 is not supported"),
        ("bad_json", "unreadable run metadata"),
        ("missing_image", r"holds 3 frames but poses.npy has 4; missing \['000002.png'\]"),
        ("extra_image", "unexpected"),
        ("no_poses", "missing poses.npy"),
        ("bad_poses", r"\(4, 4, 4\)"),
        ("corrupt_image", "unreadable PNG"),
        ("wrong_image_size", "image shape"),
        ("no_intrinsics", "missing intrinsics.json"),
    ],
)
def test_damaged_directories_raise(tmp_path: Path, how: str, message: str) -> None:
    run, _ = make_run()
    path = save_run(tmp_path / "run", run)
    _damage(path, how)
    with pytest.raises(RunFormatError, match=message) as err:
        load_run(path)
    assert str(tmp_path) in str(err.value)  # the message names the directory


def test_not_a_directory(tmp_path: Path) -> None:
    with pytest.raises(RunFormatError, match="no such run directory"):
        read_run_meta(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunFormatError, match="missing meta.json"):
        load_run(tmp_path / "empty")


def test_save_never_replaces_foreign_directories(tmp_path: Path) -> None:
    run, _ = make_run()
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "holiday.jpg").write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="refusing to replace .*photos.*not a vgpnav run"):
        save_run(foreign, run)
    assert [p.name for p in foreign.iterdir()] == ["holiday.jpg"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(FileExistsError, match="refusing"):
        save_run(tmp_path / "file", run)
    (tmp_path / "empty").mkdir()
    assert len(load_run(save_run(tmp_path / "empty", run))) == 4  # empty directories are fine
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "file", "photos"]
