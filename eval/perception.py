"""Metric perception protocol: Acc / Comp / Overall of VGP-Nav's metric points (paper Table III).

``vgpnav eval perception SCENE [SCENE ...] --backbone B [--no-scale-recovery]
[--retrieval geometry|topk] [--averaging weighted|single] [--k 10] [--queries N]
[--perception-mode paper|temporal] --out DIR [--build DIR]``

Per query frame the predicted metric world points (confident pixels) are compared with the true
visible surface of that frame (see :mod:`vgpnav_env.eval.perception_runs`): Acc = mean
nearest-neighbour distance predicted -> true, Comp = true -> predicted; Overall = their mean.
Mean (``acc_m``, ``comp_m``, ``overall_m``) and median (``*_median_m``) over the frames that
localized (``n_frames``); lost frames are counted (``n_lost``, ``lost_rate``), and the localization
metrics (gross errors, recalls) stand beside them, since a gross pose error is what makes Acc /
Comp large. The ground anchor is initialised on the first query frame with that frame's camera
height as the calibrated height and kept for the run. ``report.md`` adds a top-down figure of
predicted vs true points of one frame (``points.png``), the error CDF and the worst frames.
Several scenes: one report per scene plus a table across them. ``--perception-mode temporal``:
the frames in order with the state estimate (tracking; its metrics are added,
:func:`~vgpnav_env.eval.perception_runs.temporal_metrics`).
"""

from __future__ import annotations

import argparse
from dataclasses import asdict
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from vgpnav_env.eval.perception_runs import (
    FrameRecord,
    QueryFrame,
    QueryRun,
    add_perception_mode_argument,
    add_pipeline_arguments,
    add_scene_arguments,
    perceive_queries,
    perception_metrics,
    temporal_metrics,
)
from vgpnav_env.eval.query_reports import localization_summary, run_scenes
from vgpnav_env.eval.report import markdown_table
from vgpnav_env.eval.workers import Workers, add_worker_arguments
from vgpnav_env.grid import GridSpec
from vgpnav_env.map_measures import map_score
from vgpnav_env.perception.occupancy import LogOddsMap, OccupancyConfig
from vgpnav_env.robot import OBSTACLE_MIN, ROBOT_HEIGHT

#: Paper Table III (Acc, Comp, Overall in metres) for comparison.
PAPER = {
    "VGP-Nav Home": (0.08, 0.03, 0.05),
    "VGP-Nav Hospital": (0.10, 0.08, 0.09),
    "MoGe-2 Home": (0.18, 0.15, 0.16),
    "MapAnything Home": (0.10, 0.07, 0.08),
}
#: The table across scenes.
COLUMNS = (
    "n_queries",
    "acc_m",
    "acc_median_m",
    "comp_m",
    "comp_median_m",
    "overall_m",
    "overall_median_m",
    "n_frames",
    "lost_rate",
    "gross_rate",
    "recall_5cm_5deg",
    "map_precision",
    "map_recall",
    "map_iou",
    "cpu_s_per_frame",
)


def points_figure(example: QueryFrame | None, max_points: int = 6000, seed: int = 0) -> Figure:
    """Top-down (x, y) view of one frame's predicted (orange) and true (blue) points with both cameras."""
    fig = Figure(figsize=(5.5, 5.0))
    ax = fig.subplots()
    rng = np.random.default_rng(seed)
    if example is not None:
        for p, colour, label in (
            (example.surface, "tab:blue", "true surface"),
            (example.result.points_w, "tab:orange", "predicted"),
        ):
            if len(p) > max_points:
                p = p[rng.choice(len(p), max_points, replace=False)]
            ax.scatter(p[:, 0], p[:, 1], s=1, c=colour, alpha=0.5, label=label)
        for T, marker, label in (
            (example.T_true, "o", "true camera"),
            (example.result.T_wc, "x", "estimated camera"),
        ):
            ax.plot(*T[:2, 3], marker, c="k", label=label)
            ax.arrow(*T[:2, 3], *(0.4 * T[:2, 2]), head_width=0.05, color="k")
        ax.set_title(f"query frame {example.record.frame} (top-down, metres)")
        ax.legend(loc="best", fontsize=7, markerscale=4)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    return fig


class FusedMapScore:
    """The map measures (:mod:`vgpnav_env.map_measures`) of the query frames' fused map.

    The localized frames' metric points are fused, in frame order, as the perceiver fuses them
    (``config``) into a log-odds map (no database prior: the layout changed) of ``resolution`` m
    cells, sight lines from the estimated camera; the truth is the true visible surface of every
    frame: its cells with a point in the obstacle band (:data:`~vgpnav_env.robot.OBSTACLE_MIN` to
    the robot height) are true obstacles, its cells with a point below the robot height are observed
    (lost frames' too: what the map missed there counts).
    """

    def __init__(self, config: OccupancyConfig | None = None, resolution: float = 0.05) -> None:
        self.config = config or OccupancyConfig()
        self.resolution = float(resolution)
        self._spec = GridSpec((0.0, 0.0), self.resolution, (1, 1))  # cell indices only, unbounded
        self.observed: set[tuple[int, int]] = set()
        self.truth: set[tuple[int, int]] = set()
        self.frames: list[tuple[NDArray[np.float64], float, float, NDArray[np.float64]]] = []

    def _cells(self, xy: NDArray[np.float64]) -> set[tuple[int, int]]:
        return set(map(tuple, np.unique(self._spec.world_to_cell(xy), axis=0).tolist()))

    def add(self, frame: QueryFrame) -> None:
        surface = frame.surface[frame.surface[:, 2] <= ROBOT_HEIGHT]
        self.observed |= self._cells(surface[:, :2])
        self.truth |= self._cells(surface[surface[:, 2] >= OBSTACLE_MIN, :2])
        r = frame.result
        z = float("nan") if r.z_ground is None else float(r.z_ground)
        if r.localized and r.T_wc is not None and r.points_w is not None and np.isfinite(z):
            height = float(r.T_wc[2, 3] - z)
            self.frames.append((np.asarray(r.points_w, float), z, height, r.T_wc[:2, 3].copy()))

    def metrics(self) -> dict[str, Any]:
        """``map_precision``, ``map_recall``, ``map_iou`` (None when undefined)."""
        if not self.observed:
            return {"map_precision": None, "map_recall": None, "map_iou": None}
        cells = np.array(sorted(self.observed))
        lo = cells.min(axis=0) - 2
        shape = tuple(int(v) for v in cells.max(axis=0) - lo + 3)
        spec = GridSpec((lo[1] * self.resolution, lo[0] * self.resolution), self.resolution, shape)
        c = self.config
        fused = LogOddsMap(spec, c.l_free, c.l_occ, c.clamp)
        for points, z_ground, height, camera_xy in self.frames:
            fused.update(
                points, z_ground, height, camera_xy=camera_xy, free_tol=c.free_tol,
                obstacle_min=c.obstacle_min, clear_height=c.clear_height, min_cell_points=c.min_cell_points,
                max_obstacle_range=c.max_obstacle_range, protect_free=c.protect_free,
            )  # fmt: skip

        def grid(found: set[tuple[int, int]]) -> NDArray[np.bool_]:
            out = np.zeros(shape, bool)
            rc = np.array(sorted(found), int).reshape(-1, 2) - lo
            out[rc[:, 0], rc[:, 1]] = True
            return out

        score = map_score(fused.occupied(), grid(self.truth), grid(self.observed))
        return {"map_precision": score.precision, "map_recall": score.recall, "map_iou": score.iou}


def evaluate_perception(
    run: QueryRun, *, workers: Workers | None = None, progress: bool = True
) -> tuple[dict[str, Any], QueryFrame | None]:
    """(metrics dict, the localized frame with the most points for :func:`points_figure`);
    ``workers`` (default: this process) perceive the frames. The metrics include the fused map's
    (:class:`FusedMapScore`)."""
    records: list[FrameRecord] = []
    example: QueryFrame | None = None
    fused = FusedMapScore(run.config.occupancy)
    for frame in perceive_queries(run, workers=workers, progress=progress):
        records.append(frame.record)
        fused.add(frame)
        if frame.result.localized and (example is None or frame.record.n_points > example.record.n_points):
            example = frame
    metrics = {**localization_summary(records), **perception_metrics(records), **temporal_metrics(records)}
    metrics |= fused.metrics()
    return {**metrics, "records": [asdict(r) for r in records]}, example


def _evaluate(run: QueryRun, workers: Workers) -> tuple[dict[str, Any], dict[str, Figure]]:
    metrics, example = evaluate_perception(run, workers=workers)
    return metrics, {"points.png": points_figure(example, seed=run.seed)}


def headline(scene: str, m: dict[str, Any]) -> str:
    fused = " / ".join(
        f"{m.get(k):.2f}" if m.get(k) is not None else "n/a" for k in ("map_precision", "map_recall")
    )
    return (
        f"perception {scene}: Acc {m['acc_m']:.3f} m, Comp {m['comp_m']:.3f} m, Overall "
        f"{m['overall_m']:.3f} m (means; medians {m['acc_median_m']:.3f} / {m['comp_median_m']:.3f} m) "
        f"over {m['n_frames']} of {m['n_queries']} frames, lost {m['lost_rate']:.0%}; fused map "
        f"precision / recall {fused}"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=50, several=True)
    add_pipeline_arguments(parser)
    parser.add_argument(
        "--no-scale-recovery",
        action="store_true",
        help="ablation: keep the backbone's unknown scale (no ground-anchored scale recovery)",
    )
    add_perception_mode_argument(parser, default="paper")
    add_worker_arguments(parser)


def _sections(metrics: dict[str, Any]) -> list[str]:
    return [
        "## Paper Table III (m)\n\n"
        + markdown_table(["method", "Acc", "Comp", "Overall"], [(k, *v) for k, v in PAPER.items()], ".2f"),
        "Acc / Comp are the mean (`acc_m`, `comp_m`) and median (`acc_median_m`, ...) over the frames "
        "that localized (n_frames); lost frames have no points and are counted in `lost_rate`. Points "
        "farther than 5 m from the camera are left out of both sets. `map_precision` / `map_recall` / "
        "`map_iou`: the localized frames' points fused into one log-odds map (5 cm cells, no prior) "
        "against the true visible surface's obstacle cells over the cells the frames saw, one cell of "
        "tolerance (vgpnav_env.map_measures).",
    ]


def run(args: argparse.Namespace) -> int:
    return run_scenes(
        args, "Metric perception", _evaluate, COLUMNS, headline, _sections, scale=not args.no_scale_recovery
    )
