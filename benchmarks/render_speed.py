"""Render and ground-truth speed on a built-in scene (prints numbers; not a test).

    python benchmarks/render_speed.py [--scene home] [--frames 50]

Poses: random database-like views (1.4-1.6 m, 15-30 deg down) on navigable cells.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vgpnav_env.geometry import PinholeCamera, camera_pose
from vgpnav_env.groundtruth import ground_truth_map
from vgpnav_env.render import MujocoRenderer, PyrenderRenderer
from vgpnav_env.scenes import load_scene
from vgpnav_env.scenes.model import build_model


def poses(gt, n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    cells = np.argwhere(gt.navigable)
    picks = cells[rng.choice(len(cells), n)]
    xy = gt.spec.cell_to_world(picks)
    views = []
    for x, y in xy:
        height, yaw, pitch = (
            rng.uniform(1.4, 1.6),
            rng.uniform(-np.pi, np.pi),
            np.radians(rng.uniform(15, 30)),
        )
        views.append(camera_pose([x, y, height], yaw, pitch))
    return views


def fps(render, views) -> float:
    render(views[0])  # warm-up (texture upload, first draw)
    t0 = time.perf_counter()
    for T in views:
        render(T)
    return len(views) / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="home")
    parser.add_argument("--frames", type=int, default=50)
    args = parser.parse_args()

    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    print(f"load_scene({args.scene!r}): {time.perf_counter() - t0:.2f} s, {len(scene.meshes)} meshes")
    t0 = time.perf_counter()
    model = build_model(scene)
    print(f"build_model: {time.perf_counter() - t0:.2f} s, {model.ngeom} geoms, {model.ntex} textures")
    t0 = time.perf_counter()
    gt = ground_truth_map(scene)
    print(
        f"ground_truth_map (0.05 m): {time.perf_counter() - t0:.2f} s, "
        f"navigable {gt.area_m2(gt.navigable):.1f} m2 of floor {gt.area_m2(gt.floor):.1f} m2"
    )
    views = poses(gt, args.frames)
    for w, h in ((320, 240), (640, 480)):
        cam = PinholeCamera(w, h, np.radians(60.0))
        with MujocoRenderer(model, cam) as r:
            print(
                f"MuJoCo {w}x{h}: RGB+depth {fps(r.render, views):.0f} fps, "
                f"RGB {fps(r.render_rgb, views):.0f} fps, depth {fps(r.render_depth, views):.0f} fps"
            )
        t0 = time.perf_counter()
        with PyrenderRenderer(scene, cam) as r:
            setup = time.perf_counter() - t0
            print(f"pyrender {w}x{h}: RGB+depth {fps(r.render, views[:20]):.0f} fps (setup {setup:.1f} s)")


if __name__ == "__main__":
    main()
