"""Per-module timings of the VGP-Nav perception math (retrieval, motion averaging, scale, occupancy).

    python benchmarks/perception_modules.py [--build DIR] [--repeats N]

Without ``--build`` the inputs are synthetic (textured noise images, random poses, a ray-cast
floor). With ``--build`` (a directory written by ``vgpnav_env.build.build_runs``) the VLAD
index is fitted on the database run and every query image is retrieved; retrieval quality
is reported as the fraction of queries whose best match lies within 1.5 m and 45 deg, and
the modules are chained on every third query with the PRIVILEGED simulated backbone (1 deg
rotation, 2 deg direction, 2 % depth noise, 10 % outlier references) to compare the
ablations: geometry-aware vs top-k retrieval, weighted vs single-reference motion
averaging, ground from the query alone vs the whole reconstruction with a ray-scale prior.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import cv2
import numpy as np

from vgpnav_env.geometry import PinholeCamera, camera_pose, invert_pose, rotation_angle
from vgpnav_env.grid import GridSpec
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig, average_motion
from vgpnav_env.perception.occupancy import LogOddsMap
from vgpnav_env.perception.retrieval import RetrievalConfig, VladIndex, select_references
from vgpnav_env.perception.scale_recovery import (
    GroundAnchor,
    ground_peak,
    reconstruction_points,
    recover_metric_points,
)


def timed(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time (ms) of ``fn`` over ``repeats`` calls after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def synthetic_images(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for _ in range(n):
        img = cv2.resize(rng.integers(0, 255, (30, 40, 3), dtype=np.uint8), (320, 240), cv2.INTER_CUBIC)
        out.append(img)
    return out


def bench_retrieval(rng: np.random.Generator, repeats: int, build: str | None) -> None:
    if build:
        from vgpnav_env.runs import load_build

        b = load_build(build)
        db_images, db_poses = b.database.images, b.database.poses
        q_images, q_poses = b.query.images, b.query.poses
    else:
        db_images = np.array(synthetic_images(200, rng))
        db_poses = np.array(
            [camera_pose([*rng.uniform(0, 10, 2), 1.5], rng.uniform(-3, 3), 0.3) for _ in db_images]
        )
        q_images, q_poses = db_images[:10], db_poses[:10]
    t = time.perf_counter()
    index = VladIndex.fit(list(db_images), seed=0)
    fit_s = time.perf_counter() - t
    print(f"retrieval: fit on {len(db_images)} images {db_images.shape[1:3]}: {fit_s:.2f} s, D = {index.dim}")
    ms = timed(lambda: index.similarity(q_images[0]), repeats)
    print(f"retrieval: describe + similarity, one query: {ms:.1f} ms")
    sim = index.similarity(q_images[0])
    cfg = RetrievalConfig()
    ms = timed(lambda: select_references(sim, db_poses, cfg), repeats)
    print(f"retrieval: select_references (M = {len(sim)}): {ms:.2f} ms")
    if build:
        top1 = 0
        near = {"geometry": [], "topk": []}
        for img, T_wq in zip(q_images, q_poses, strict=True):
            sim = index.similarity(img)
            best = int(np.argmax(sim))
            d = np.linalg.norm(db_poses[best, :3, 3] - T_wq[:3, 3])
            ang = np.rad2deg(np.arccos(np.clip(db_poses[best, :3, 2] @ T_wq[:3, 2], -1, 1)))
            top1 += int(d < 1.5 and ang < 45)
            for method, frac in near.items():
                sel = select_references(sim, db_poses, RetrievalConfig(method=method))
                frac.append(np.mean(np.linalg.norm(db_poses[sel, :3, 3] - T_wq[:3, 3], axis=1) < 3.0))
        print(f"retrieval: best match within 1.5 m / 45 deg for {top1}/{len(q_images)} queries")
        for method, frac in near.items():
            print(f"retrieval: {method}: {100 * np.mean(frac):.0f}% of the selected references within 3 m")
        chain_eval(build, index)


def chain_eval(build: str, index: VladIndex) -> None:
    """Retrieval -> simulated backbone -> motion averaging -> scale on a build's query run."""
    from vgpnav_env.perception.backbones.base import Privileged
    from vgpnav_env.perception.backbones.simulated import SimulatedBackbone, SimulatedConfig
    from vgpnav_env.runs import load_build, load_run_depth

    b = load_build(build)
    db_depth = load_run_depth(b.path / "database")
    q_depth = load_run_depth(b.path / "query")
    cam = b.query.camera
    noise = SimulatedConfig(
        rotation_noise_deg=1.0, direction_noise_deg=2.0, depth_noise=0.02, outlier_fraction=0.1
    )
    rows: dict[str, list[tuple[float, float]]] = {}
    scale_err: dict[str, list[float]] = {"query only": [], "reconstruction + prior": []}
    for i in range(0, len(b.query), 3):
        T_wq = b.query.poses[i]
        sim = index.similarity(b.query.images[i])
        for method in ("geometry", "topk"):
            sel = select_references(sim, b.database.poses, RetrievalConfig(method=method))
            backbone = SimulatedBackbone(noise, seed=i)
            priv = Privileged(T_wq, b.database.poses[sel], q_depth[i], db_depth[sel])
            out = backbone(b.query.images[i], list(b.database.images[sel]), cam, priv)
            T_wi = b.database.poses[sel]
            for mode in ("weighted", "single"):
                res = average_motion(
                    T_wi,
                    out.T_qi,
                    out.confidence,
                    MotionAveragingConfig(method=mode),
                    scale_valid=out.scale_valid,
                )
                t_err = np.linalg.norm(res.T_wq[:3, 3] - T_wq[:3, 3]) if res.ok else np.inf
                r_err = np.rad2deg(rotation_angle(res.T_wq[:3, :3], T_wq[:3, :3])) if res.ok else np.inf
                rows.setdefault(f"{method:8s} + {mode}", []).append((t_err, r_err))
                if method == "geometry" and mode == "weighted" and res.ok:
                    anchor = GroundAnchor()
                    anchor.initialize([(T_wq, None)], float(T_wq[2, 3]))
                    true_scale = 1.0 / backbone.last_scale
                    P, w = reconstruction_points(cam, out.query_depth, out.query_depth_confidence)
                    g = ground_peak(P, res.T_wq[:3, :3], w)
                    scale_err["query only"].append(anchor.scale_for(res.T_wq, g).scale / true_scale - 1)
                    P, w = reconstruction_points(
                        cam,
                        out.query_depth,
                        out.query_depth_confidence,
                        out.T_qi,
                        out.reference_depths,
                        out.confidence * out.scale_valid,
                    )
                    prior = anchor.expected_height_b(res.T_wq, res.scale_from_rays)
                    g = ground_peak(P, res.T_wq[:3, :3], w, prior_height_b=prior)
                    scale_err["reconstruction + prior"].append(
                        anchor.scale_for(res.T_wq, g).scale / true_scale - 1
                    )
    n = len(rows["geometry + weighted"])
    print(f"chain ({n} queries, simulated backbone): median position / rotation error")
    for name, errs in rows.items():
        e = np.array(errs)
        t, r = np.median(e[:, 0]), np.median(e[:, 1])
        print(f"  {name}: {t:.3f} m / {r:.2f} deg, failures {np.isinf(e[:, 0]).sum()}")
    for name, errs in scale_err.items():
        e = np.abs(np.array(errs))
        ok = np.isfinite(e)
        print(
            f"  scale, {name}: found {ok.sum()}/{len(e)}, median |error| {100 * np.median(e[ok]):.2f} %, "
            f"> 5 %: {(e[ok] > 0.05).sum()}"
        )


def bench_motion(rng: np.random.Generator, repeats: int) -> None:
    T_wq = camera_pose([1.0, 2.0, 1.2], 0.3, 0.35)
    T_wi = np.array(
        [camera_pose(T_wq[:3, 3] + [*rng.normal(0, 2, 2), 0.3], rng.uniform(-3, 3), 0.3) for _ in range(10)]
    )
    T_qi = np.array([invert_pose(T_wq) @ T for T in T_wi])
    T_qi[:, :3, 3] *= 0.37
    conf = rng.uniform(0.5, 1.0, 10)
    res = average_motion(T_wi, T_qi, conf)
    err = np.linalg.norm(res.T_wq[:3, 3] - T_wq[:3, 3])
    ms = timed(lambda: average_motion(T_wi, T_qi, conf), repeats)
    print(f"motion averaging (k = 10): {ms:.2f} ms, error {err:.1e} m")


def bench_scale_and_occupancy(rng: np.random.Generator, repeats: int) -> None:
    cam = PinholeCamera(320, 240, np.deg2rad(60))
    T_wc = camera_pose([0.0, 0.0, 1.2], 0.0, np.deg2rad(20))
    rays = cam.rays().reshape(-1, 3) @ T_wc[:3, :3].T
    with np.errstate(divide="ignore"):
        t_floor = np.where(rays[:, 2] < 0, -1.2 / rays[:, 2], np.inf)
    depth = np.minimum(t_floor, 5.0).reshape(cam.height, cam.width)  # floor, else a wall 5 m away
    pts_b = cam.backproject(0.37 * depth * np.exp(rng.normal(0, 0.02, depth.shape)))
    g = ground_peak(pts_b, T_wc[:3, :3])
    ms = timed(lambda: ground_peak(pts_b, T_wc[:3, :3]), repeats)
    scale = 1.2 / -g.height_b
    print(
        f"scale: ground_peak ({cam.width}x{cam.height} points): {ms:.2f} ms, scale {scale:.4f} (true 2.7027)"
    )
    P_w = recover_metric_points(pts_b, T_wc, 1.2 / -g.height_b).reshape(-1, 3)
    P_w = P_w[rng.choice(len(P_w), 20000, replace=False)]
    P_w[:5000, 2] = rng.uniform(0.2, 1.0, 5000)  # some obstacle points
    spec = GridSpec.covering((-10, -10), (10, 10), 0.05)
    m = LogOddsMap(spec)
    ms = timed(lambda: m.update(P_w, 0.0, 1.2, camera_xy=(0, 0)), repeats)
    print(f"occupancy: update 20k points + ray carving: {ms:.2f} ms")
    ms = timed(lambda: m.egocentric_crop(0.0, 0.0, 0.3, 128), repeats)
    print(f"occupancy: egocentric crop 128x128: {ms:.2f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--build", help="build directory (vgpnav build) for retrieval on rendered images")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    bench_retrieval(rng, args.repeats, args.build)
    bench_motion(rng, args.repeats)
    bench_scale_and_occupancy(rng, args.repeats)


if __name__ == "__main__":
    main()
