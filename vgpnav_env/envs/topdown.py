"""Fast top-down map drawing with OpenCV (north-up: +y points up in the image, +x right).

Colours (RGB): obstacles dark grey, free floor light grey, navigable floor white, unknown black;
fused obstacles red, planned path blue, true pose green, estimated pose orange, goal magenta,
start cyan, travelled trajectory dark green (:data:`LEGEND`). :func:`legend_panel` draws that
legend and :func:`text_panel` lines of text, as strips to put under a rendered frame.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.grid import GridSpec

_UNKNOWN = (20, 20, 20)
_OBSTACLE = (90, 90, 90)
_FREE = (190, 190, 190)
_NAVIGABLE = (250, 250, 250)
_FUSED = (220, 40, 40)
_PATH = (40, 90, 230)
_TRUE = (20, 170, 60)
_ESTIMATE = (255, 150, 0)
_GOAL = (220, 0, 220)
_START = (0, 190, 210)
_TRAJECTORY = (0, 110, 40)


class TopDownMap:
    """Draws poses, paths and obstacles over a ground-truth map background of fixed pixel height."""

    def __init__(
        self,
        spec: GridSpec,
        free: NDArray[np.bool_],
        obstacle: NDArray[np.bool_],
        navigable: NDArray[np.bool_],
        height_px: int,
    ) -> None:
        if height_px <= 0:
            raise ValueError(f"top-down map height must be positive pixels, got {height_px}")
        self.spec = spec
        rows, cols = spec.shape
        self.scale = height_px / rows  # pixels per cell
        self.size = (max(1, round(cols * self.scale)), height_px)  # (width, height)
        bg = np.empty((rows, cols, 3), np.uint8)
        bg[:] = _UNKNOWN
        bg[free] = _FREE
        bg[navigable] = _NAVIGABLE
        bg[obstacle] = _OBSTACLE
        self.background = cv2.resize(bg[::-1], self.size, interpolation=cv2.INTER_NEAREST)

    def to_pixels(self, xy: ArrayLike) -> NDArray[np.int32]:
        """Image pixel (u, v) of world points (..., 2)."""
        xy = np.asarray(xy, float)
        s = self.scale / self.spec.resolution
        u = (xy[..., 0] - self.spec.origin[0]) * s
        v = self.size[1] - (xy[..., 1] - self.spec.origin[1]) * s
        return np.stack([u, v], axis=-1).round().astype(np.int32)

    def _pose(self, img: NDArray[np.uint8], pose: ArrayLike, color: tuple[int, int, int]) -> None:
        x, y, yaw = np.asarray(pose, float)
        r = max(3, round(0.2 * self.scale / self.spec.resolution))
        c = tuple(int(v) for v in self.to_pixels([x, y]))
        tip = tuple(int(v) for v in self.to_pixels([x + 0.5 * np.cos(yaw), y + 0.5 * np.sin(yaw)]))
        cv2.circle(img, c, r, color, 2, cv2.LINE_AA)
        cv2.line(img, c, tip, color, 2, cv2.LINE_AA)

    def draw(
        self,
        true_pose: ArrayLike | None = None,
        goal: ArrayLike | None = None,
        start: ArrayLike | None = None,
        estimated_pose: ArrayLike | None = None,
        path: ArrayLike | None = None,
        obstacles: ArrayLike | None = None,
        trajectory: ArrayLike | None = None,
    ) -> NDArray[np.uint8]:
        """Map image (H, W, 3) uint8 with everything given drawn on top.

        Poses are (x, y, yaw); ``path``, ``obstacles`` and ``trajectory`` are world (N, 2) points.
        """
        img = self.background.copy()
        if obstacles is not None and len(obstacles):
            px = self.to_pixels(np.asarray(obstacles, float).reshape(-1, 2))
            ok = (px[:, 0] >= 0) & (px[:, 0] < self.size[0]) & (px[:, 1] >= 0) & (px[:, 1] < self.size[1])
            mask = np.zeros(img.shape[:2], np.uint8)
            mask[px[ok, 1], px[ok, 0]] = 1
            k = max(1, round(self.scale))  # one map cell
            mask = cv2.dilate(mask, np.ones((k, k), np.uint8))
            img[mask > 0] = _FUSED
        for pts, color in ((trajectory, _TRAJECTORY), (path, _PATH)):
            if pts is not None and len(pts) > 1:
                cv2.polylines(
                    img, [self.to_pixels(np.asarray(pts, float)[:, :2])], False, color, 1, cv2.LINE_AA
                )
        r = max(3, round(0.25 * self.scale / self.spec.resolution))
        for point, color in ((start, _START), (goal, _GOAL)):
            if point is not None:
                c = tuple(int(v) for v in self.to_pixels(np.asarray(point, float)[:2]))
                cv2.drawMarker(img, c, color, cv2.MARKER_CROSS, 2 * r, 2)
        if estimated_pose is not None:
            self._pose(img, estimated_pose, _ESTIMATE)
        if true_pose is not None:
            self._pose(img, true_pose, _TRUE)
        return img


#: What the top-down map's colours mean: (label, colour, how it is drawn), in legend order.
LEGEND: tuple[tuple[str, tuple[int, int, int], str], ...] = (
    ("true pose", _TRUE, "pose"),
    ("estimated pose", _ESTIMATE, "pose"),
    ("goal", _GOAL, "cross"),
    ("start", _START, "cross"),
    ("travelled", _TRAJECTORY, "line"),
    ("planned path", _PATH, "line"),
    ("fused obstacles", _FUSED, "box"),
    ("obstacle", _OBSTACLE, "box"),
    ("navigable", _NAVIGABLE, "box"),
    ("free (too close to walls)", _FREE, "box"),
)
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_TEXT = (235, 235, 235)
_PANEL = (35, 35, 35)


def text_panel(lines: list[str], width: int, scale: float = 0.5) -> NDArray[np.uint8]:
    """A dark strip ``width`` pixels wide with one line of light text per entry of ``lines``."""
    line_h = round(32 * scale) + 6
    img = np.empty((line_h * len(lines) + 6, width, 3), np.uint8)
    img[:] = _PANEL
    for i, line in enumerate(lines):
        cv2.putText(img, line, (8, (i + 1) * line_h), _FONT, scale, _TEXT, 1, cv2.LINE_AA)
    return img


def legend_panel(width: int, scale: float = 0.45) -> NDArray[np.uint8]:
    """The :data:`LEGEND` as swatches with labels, wrapped into rows ``width`` pixels wide."""
    sw, pad, row_h = round(28 * scale), 8, round(34 * scale) + 6
    entries, x, row = [], pad, 0
    for label, colour, kind in LEGEND:
        w = sw + 6 + cv2.getTextSize(label, _FONT, scale, 1)[0][0] + 3 * pad
        if x + w > width and x > pad:
            x, row = pad, row + 1
        entries.append((x, row, label, colour, kind))
        x += w
    img = np.empty(((row + 1) * row_h + pad, width, 3), np.uint8)
    img[:] = _PANEL
    for x, r, label, colour, kind in entries:
        y0 = pad + r * row_h
        c = (x + sw // 2, y0 + sw // 2)
        if kind == "box":
            cv2.rectangle(img, (x, y0), (x + sw, y0 + sw), colour, -1)
        elif kind == "line":
            cv2.line(img, (x, c[1]), (x + sw, c[1]), colour, 2, cv2.LINE_AA)
        elif kind == "cross":
            cv2.drawMarker(img, c, colour, cv2.MARKER_CROSS, sw, 2)
        else:
            cv2.circle(img, c, sw // 2 - 1, colour, 2, cv2.LINE_AA)
            cv2.line(img, c, (x + sw, c[1]), colour, 2, cv2.LINE_AA)
        cv2.putText(img, label, (x + sw + 6, y0 + sw - 2), _FONT, scale, _TEXT, 1, cv2.LINE_AA)
    return img
