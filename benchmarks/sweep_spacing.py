"""How far apart the plane sweeps' planes lie in disparity, in the sweep's own pixels.

    python benchmarks/sweep_spacing.py [SCENE] [--queries 30]

Runs ``vgpnav eval timing SCENE --perception-mode temporal --queries N`` in this process and
records every :func:`~vgpnav_env.perception.backbones.stereo.plane_sweep` call: the classical
backbone's sweep (80x60 at 320x240) and the map's posed sweep (160x120). For each call and
reference, a 15x15 grid of query pixels is placed at the two ends of the swept inverse-depth
range (the sparse-depth range, without the coarser near planes) and projected into the reference;
over the pixels that land inside the reference at both ends, the largest displacement is that
reference's disparity range. Printed per sweep kind: the number of planes and, at the widest and
at the second-widest reference, the pixels of disparity between neighbouring planes (percentiles
over the calls). About one pixel or less is what a 5x5 (3x3) NCC window resolves; much less
oversamples, much more skips matches.
"""

from __future__ import annotations

import argparse
import tempfile

import numpy as np
from numpy.typing import NDArray

import vgpnav_env.perception.backbones.classical as classical
import vgpnav_env.perception.backbones.stereo as stereo
import vgpnav_env.perception.posed_depth as posed_depth
from vgpnav_env.geometry import PinholeCamera


def disparity_ranges(
    T_iq: NDArray[np.float64], camera: PinholeCamera, inv_range: tuple[float, float], grid: int = 15
) -> NDArray[np.float64]:
    """(k,) pixels the query pixels seen in reference i move between the two inverse depths
    ``inv_range`` (the largest over a ``grid`` x ``grid`` lattice of query pixels inside reference i
    at both ends; 0 when none is)."""
    w, h, K = camera.width, camera.height, camera.K
    us, vs = np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid))
    rays = np.linalg.inv(K) @ np.stack([us.ravel(), vs.ravel(), np.ones(us.size)])
    out = np.zeros(len(T_iq))
    for i, T in enumerate(T_iq):
        ends, ok = [], np.ones(us.size, bool)
        for rho in inv_range:  # the point x / rho moved into reference i, times rho
            P = K @ (T[:3, :3] @ rays + T[:3, 3, None] * rho)
            ok &= P[2] > 1e-9
            p = P[:2] / np.where(ok, P[2], 1.0)
            ok &= (p[0] >= 0) & (p[0] <= w - 1) & (p[1] >= 0) & (p[1] <= h - 1)
            ends.append(p)
        if ok.any():
            out[i] = float(np.linalg.norm(ends[0] - ends[1], axis=0)[ok].max())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", nargs="?", default="home")
    parser.add_argument("--queries", type=int, default=30)
    args = parser.parse_args()

    calls: list[tuple[str, int, NDArray[np.float64]]] = []
    sweep = stereo.plane_sweep

    def spy(query, references, T_iq, camera, sparse_depths, config=None, **kwargs):
        cfg = config or stereo.SweepConfig()
        w, h = max(8, round(camera.width * cfg.scale)), max(8, round(camera.height * cfg.scale))
        lo, hi = np.percentile(sparse_depths, cfg.depth_range_percentiles)
        inv_range = (1.0 / (lo * cfg.depth_range_margin[0]), 1.0 / (hi * cfg.depth_range_margin[1]))
        moved = disparity_ranges(np.asarray(T_iq, float), camera.resized(w, h), inv_range)
        kind = f"{w}x{h}"
        planes = len(stereo.sweep_planes(sparse_depths, cfg))
        calls.append((kind, planes, np.sort(moved)[::-1] / (cfg.planes - 1)))
        return sweep(query, references, T_iq, camera, sparse_depths, config, **kwargs)

    classical.plane_sweep = spy
    posed_depth.plane_sweep = spy
    from vgpnav_env.cli import main as cli

    with tempfile.TemporaryDirectory() as out:
        cli(["eval", "timing", args.scene, "--perception-mode", "temporal", "--queries", str(args.queries),
             "--out", out])  # fmt: skip
    print(f"\n{args.scene}, {args.queries} temporal frames: disparity between neighbouring planes (pixels)")
    print("| sweep | calls | planes (median) | widest reference p10 / p50 / p90 | second p10 / p50 / p90 |")
    print("| --- | --- | --- | --- | --- |")
    for kind in sorted({c[0] for c in calls}):
        mine = [c for c in calls if c[0] == kind]
        first = np.array([c[2][0] for c in mine])
        second = np.array([c[2][1] for c in mine if len(c[2]) > 1])
        cells = [" / ".join(f"{v:.2f}" for v in np.percentile(a, [10, 50, 90])) for a in (first, second)]
        print(f"| {kind} | {len(mine)} | {np.median([c[1] for c in mine]):.0f} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
