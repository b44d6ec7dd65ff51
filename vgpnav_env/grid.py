"""The one 2D grid type over the floor plane of W (metres), shared by ground truth and maps.

Cell (row, col) covers x in [x0 + col*res, x0 + (col+1)*res) and y in [y0 + row*res, ...):
rows grow along +y, columns along +x (so ``array[row, col]``; flip rows to draw north-up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class GridSpec:
    """Geometry of a 2D grid: ``origin`` = world (x, y) of the corner of cell (0, 0)."""

    origin: tuple[float, float]
    resolution: float
    shape: tuple[int, int]  # (rows along y, cols along x)

    def __post_init__(self) -> None:
        if self.resolution <= 0:
            raise ValueError(f"grid resolution must be positive metres, got {self.resolution}")
        if min(self.shape) <= 0:
            raise ValueError(f"grid shape must be positive, got {self.shape}")

    @classmethod
    def covering(cls, xy_min: ArrayLike, xy_max: ArrayLike, resolution: float, margin: float = 0.0) -> GridSpec:
        """Smallest grid with the given resolution covering the box [xy_min, xy_max] + margin."""
        lo = np.asarray(xy_min, float) - margin
        hi = np.asarray(xy_max, float) + margin
        cols, rows = np.maximum(np.ceil((hi - lo) / resolution).astype(int), 1)
        return cls((float(lo[0]), float(lo[1])), float(resolution), (int(rows), int(cols)))

    def world_to_cell(self, xy: ArrayLike) -> NDArray[np.int64]:
        """Integer (row, col) of world points (..., 2); may be out of bounds (see ``contains``)."""
        xy = np.asarray(xy, float)
        col = np.floor((xy[..., 0] - self.origin[0]) / self.resolution)
        row = np.floor((xy[..., 1] - self.origin[1]) / self.resolution)
        return np.stack([row, col], axis=-1).astype(np.int64)

    def cell_to_world(self, cells: ArrayLike) -> NDArray[np.float64]:
        """World (x, y) of cell centres for (..., 2) integer (row, col)."""
        rc = np.asarray(cells, float)
        x = self.origin[0] + (rc[..., 1] + 0.5) * self.resolution
        y = self.origin[1] + (rc[..., 0] + 0.5) * self.resolution
        return np.stack([x, y], axis=-1)

    def contains(self, cells: ArrayLike) -> NDArray[np.bool_]:
        """Whether (..., 2) integer (row, col) lie inside the grid."""
        rc = np.asarray(cells)
        return (rc[..., 0] >= 0) & (rc[..., 0] < self.shape[0]) & (rc[..., 1] >= 0) & (rc[..., 1] < self.shape[1])

    def centres(self) -> NDArray[np.float64]:
        """World (x, y) of every cell centre, shape (rows, cols, 2)."""
        rows, cols = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return self.cell_to_world(np.stack([rows, cols], axis=-1))
