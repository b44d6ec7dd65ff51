"""Pictures of the navigation protocol: one per episode, one across episodes (matplotlib, Agg).

:func:`episode_figure` shows what happened in an episode: the true and estimated trajectories on
the ground-truth map with lost frames and collisions marked, the fused obstacle map and the plan
the agent had at the first collision burst (when there was one) and at the end -- phantoms and
missed obstacles coloured against the true map (:mod:`vgpnav_env.map_measures`) -- and the pose
error over time with the lost stretches shaded. :func:`summary_figure`:
the pose-error CDF over all frames of all episodes and the lost fraction of every episode.
Figures are built with ``matplotlib.figure.Figure`` (no pyplot state), so workers can draw them.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from vgpnav_env.eval.report import plot_cdf
from vgpnav_env.grid import GridSpec

if TYPE_CHECKING:
    from vgpnav_env.eval.navigation import EpisodeRecord

_TRUE, _ESTIMATE, _LOST, _GOAL, _START = "tab:green", "tab:orange", "tab:red", "tab:purple", "tab:cyan"


def _ground_truth_panel(ax: Any, env: gym.Env, record: EpisodeRecord) -> None:
    base = env.unwrapped
    gt, spec = base.ground_truth, base.ground_truth.spec
    img = np.full(spec.shape, 0.15)
    img[gt.free] = 0.75
    img[base.world.navigable] = 1.0
    img[gt.obstacle] = 0.4
    (x0, y0), (x1, y1) = spec.bounds
    ax.imshow(
        img, cmap="gray", vmin=0, vmax=1, origin="lower", extent=(x0, x1, y0, y1), interpolation="nearest"
    )
    traj = np.asarray(record.trajectory)
    ax.plot(traj[:, 0], traj[:, 1], "-", color=_TRUE, lw=1.5, label="true")
    if record.estimated_trajectory:
        est = np.asarray(record.estimated_trajectory)
        have = ~np.asarray(record.frames.get("no_estimate", [False] * len(est)), bool)
        lost = ~np.asarray(record.frames.get("localized", [True] * len(est)), bool) & have
        est_line = est[have]
        ax.plot(est_line[:, 0], est_line[:, 1], "--", color=_ESTIMATE, lw=1.0, label="estimated")
        if lost.any():
            ax.plot(est[lost, 0], est[lost, 1], ".", color=_LOST, ms=3, label="lost (odometry)")
    if record.collision_steps:
        hits = traj[np.asarray(record.collision_steps) + 1]
        ax.plot(hits[:, 0], hits[:, 1], "x", color="k", ms=5, label="collision")
    ax.plot(*record.start[:2], "o", color=_START, label="start")
    ax.plot(*record.goal, "*", color=_GOAL, ms=12, label="goal")
    ax.add_patch(_circle(record.goal, base.success_distance))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0)


def _circle(centre: Any, radius: float) -> Any:
    from matplotlib.patches import Circle

    return Circle(centre, radius, fill=False, ls=":", color=_GOAL)


@dataclass(frozen=True)
class MapSnapshot:
    """The fused map and the plan at one step: ``occupied`` and ``free`` cells over ``spec``, the
    ``truth`` and the ``observed`` cells of :class:`~vgpnav_env.map_measures.MapTracker`, the agent's ``path``
    (world (N, 2) or None), the ``estimate`` and ``true`` poses (x, y, yaw)."""

    step: int
    spec: GridSpec
    occupied: np.ndarray
    free: np.ndarray
    truth: np.ndarray
    observed: np.ndarray
    path: np.ndarray | None
    estimate: np.ndarray | None
    true: np.ndarray

    @classmethod
    def of(cls, env: gym.Env, policy: Any, step: int) -> MapSnapshot | None:
        """The snapshot of ``env`` (a perception wrapper; None without a fused map) now."""
        try:
            fused = env.get_wrapper_attr("fused_map")
            tracker = env.get_wrapper_attr("map_tracker")
        except AttributeError:
            return None
        path = getattr(getattr(policy, "agent", None), "path", None)
        estimate = getattr(env.get_wrapper_attr("pose_state"), "estimate", None)
        return cls(
            step,
            fused.spec,
            fused.occupied(),
            fused.free(),
            tracker.truth.copy(),
            tracker.observed.copy(),
            None if path is None else np.asarray(path, float).copy(),
            None if estimate is None else np.asarray(estimate, float).copy(),
            np.asarray(env.unwrapped.pose, float).copy(),
        )


def _map_panel(ax: Any, env: gym.Env, record: EpisodeRecord, snap: MapSnapshot, title: str) -> None:
    """The fused map of ``snap``: free white, unknown grey, occupied near a true obstacle black,
    phantoms (no true obstacle within the score's tolerance) red, observed true obstacles the map
    misses blue; the plan, the estimated and true poses, the trajectory up to the step."""
    from vgpnav_env.map_measures import TOLERANCE_CELLS, phantom_cells

    img = np.full((*snap.spec.shape, 3), 0.6)
    phantom = phantom_cells(snap.occupied, snap.truth)
    missed = phantom_cells(snap.truth & snap.observed, snap.occupied, TOLERANCE_CELLS)
    img[snap.free] = 1.0
    img[snap.occupied] = (0.1, 0.1, 0.1)
    img[phantom] = (0.9, 0.1, 0.1)
    img[missed] = (0.1, 0.35, 0.95)
    (x0, y0), (x1, y1) = snap.spec.bounds
    ax.imshow(img, origin="lower", extent=(x0, x1, y0, y1), interpolation="nearest")
    traj = np.asarray(record.trajectory)[: snap.step + 2]
    ax.plot(traj[:, 0], traj[:, 1], "-", color=_TRUE, lw=1.0)
    if snap.path is not None:
        ax.plot(snap.path[:, 0], snap.path[:, 1], "-", color="magenta", lw=1.2, label="plan")
    for pose, colour in ((snap.true, _TRUE), (snap.estimate, _ESTIMATE)):
        if pose is not None:
            ax.plot(*pose[:2], "o", color=colour, ms=5)
            ax.arrow(*pose[:2], *(0.4 * np.array([np.cos(pose[2]), np.sin(pose[2])])), head_width=0.1,
                     color=colour)  # fmt: skip
    ax.plot(*record.goal, "*", color=_GOAL, ms=10)
    (gx0, gy0), (gx1, gy1) = env.unwrapped.ground_truth.spec.bounds
    ax.set_xlim(gx0, gx1)
    ax.set_ylim(gy0, gy1)
    ax.set_title(title, fontsize=8)
    ax.set_xlabel("x (m)")
    ax.set_aspect("equal")


def _stretches(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index pairs of the runs of True in ``mask`` (end exclusive)."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _error_panel(ax: Any, record: EpisodeRecord, success_distance: float) -> None:
    errors = np.asarray(record.frames["localization_error_m"], float)
    lost = ~np.asarray(record.frames.get("localized", [True] * len(errors)), bool)
    steps = np.arange(len(errors))
    for a, b in _stretches(lost):
        ax.axvspan(a - 0.5, b - 0.5, color=_LOST, alpha=0.15, lw=0)
    ax.plot(steps, errors, "-", color=_ESTIMATE, lw=1.2, label="pose error")
    ax.axhline(
        success_distance, color="grey", ls="--", lw=0.8, label=f"success radius {success_distance:g} m"
    )
    if record.collision_steps:
        ax.plot(record.collision_steps, np.zeros(len(record.collision_steps)), "|", color="k", ms=8,
                label="collision")  # fmt: skip
    ax.plot([], [], "s", color=_LOST, alpha=0.3, label="lost (shaded)")
    ax.set_xlabel("step")
    ax.set_ylabel("horizontal pose error (m)")
    ax.set_xlim(-0.5, max(len(errors), 1) - 0.5)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0)


def episode_figure(
    env: gym.Env, record: EpisodeRecord, policy: Any = None, burst: MapSnapshot | None = None
) -> Figure:
    """The picture of one finished episode in ``env`` (module docstring): the fused map and the plan
    of ``policy`` at the end and, with ``burst``, at the first collision burst; agents without a
    pose estimate get the trajectory panel only."""
    success_distance = env.unwrapped.success_distance
    outcome = record.failure or "success"
    m = record.metrics
    title = (
        f"episode {record.index} (seed {record.seed}): {outcome}, SPL {m['spl']:.2f}, {m['steps']} steps, "
        f"{m['collisions']} collisions"
    )
    end = MapSnapshot.of(env, policy, len(record.trajectory) - 2) if record.frames else None
    if end is None:
        fig = Figure(figsize=(7.5, 6))
        _ground_truth_panel(fig.subplots(), env, record)
        fig.suptitle(title, fontsize=9)
        return fig
    lost = m.get("lost_fraction")
    error = m["localization_error_m"]
    title += f"; lost {lost:.0%} of frames, mean pose error " + (
        "none" if error is None else f"{error:.2f} m"
    )
    if m.get("map_precision") is not None or m.get("map_recall") is not None:
        title += "\nmap precision {} / recall {}, {} phantom cells on the true path".format(
            *(f"{m.get(k):.2f}" if m.get(k) is not None else "n/a" for k in ("map_precision", "map_recall")),
            m.get("path_phantom_cells"),
        )
    (x0, y0), (x1, y1) = env.unwrapped.ground_truth.spec.bounds
    n_maps = 2 if burst is None else 3
    maps_height = (13.0 / n_maps) * (y1 - y0) / (x1 - x0) + 0.8
    fig = Figure(figsize=(13 if burst is None else 18, maps_height + 3.0))
    grid = fig.add_gridspec(2, n_maps, height_ratios=(maps_height, 2.6))
    _ground_truth_panel(fig.add_subplot(grid[0, 0]), env, record)
    legend = "black occupied, red phantom, blue missed, white free, grey unknown; magenta plan"
    if burst is not None:
        _map_panel(fig.add_subplot(grid[0, 1]), env, record, burst,
                   f"fused map + plan at the collision burst (step {burst.step})")  # fmt: skip
    _map_panel(fig.add_subplot(grid[0, n_maps - 1]), env, record, end,
               f"fused map + plan at the end ({outcome})\n{legend}")  # fmt: skip
    _error_panel(fig.add_subplot(grid[1, :]), record, success_distance)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def episode_png(
    env: gym.Env, record: EpisodeRecord, policy: Any = None, burst: MapSnapshot | None = None
) -> bytes:
    """:func:`episode_figure` as PNG bytes (drawn where the episode ran; written by the caller)."""
    buffer = io.BytesIO()
    episode_figure(env, record, policy, burst).savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    return buffer.getvalue()


def summary_figure(records: list[EpisodeRecord], success_distance: float) -> Figure:
    """Left: CDF of the pose error over all frames of all episodes; right: each episode's lost
    fraction, green for a success and red for a failure."""
    fig = Figure(figsize=(10, 3.6))
    left, right = fig.subplots(1, 2)
    errors = [e for r in records for e in r.frames.get("localization_error_m", [])]
    plot_cdf(left, errors)
    left.axvline(success_distance, color="grey", ls="--", lw=0.8)
    left.set_xlabel("horizontal pose error (m), all frames")
    left.set_ylabel("fraction of frames")
    lost = [r.metrics.get("lost_fraction") or 0.0 for r in records]
    colours = ["tab:green" if r.failure is None else "tab:red" for r in records]
    right.bar([r.index for r in records], lost, color=colours)
    right.xaxis.set_major_locator(MaxNLocator(integer=True))
    right.set_xlabel("episode (green success, red failure)")
    right.set_ylabel("lost fraction of frames")
    right.set_ylim(0, 1)
    right.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return fig
