"""Dense query depth (plane sweep) on synthetic views with known depth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.perception.backbones.stereo import SweepConfig, best_mean, plane_sweep

CAMERA = PinholeCamera(320, 240, np.deg2rad(60.0))


def test_best_mean_matches_a_sorted_reference():
    rng = np.random.default_rng(0)
    values = rng.random((4, 5, 6)).astype(np.float32)
    values[rng.random(values.shape) < 0.4] = np.nan
    for keep in (1, 2, 3, 4, 5):
        expected = np.full(values.shape[1:], np.nan, np.float32)
        for idx in np.ndindex(values.shape[1:]):
            column = values[(slice(None), *idx)]
            top = np.sort(column[np.isfinite(column)])[::-1][:keep]
            if len(top):
                expected[idx] = top.mean()
        np.testing.assert_allclose(best_mean(values, keep), expected, rtol=1e-6)


def _shifted_plane_views(shift_px: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Query and reference of a textured fronto-parallel plane; the reference is the query moved
    ``shift_px`` pixels to the right (``x_ref = x_query + shift``), fresh texture where unseen."""
    rng = np.random.default_rng(seed)
    width = CAMERA.width + 2 * int(abs(shift_px)) + 4
    texture = rng.integers(0, 256, (CAMERA.height, width), np.uint8).astype(np.float32)
    texture = np.clip(cv2.GaussianBlur(texture, (0, 0), 1.5) * 2.0 - 128.0, 0, 255).astype(np.uint8)
    x0 = int(abs(shift_px)) + 2
    query = texture[:, x0 : x0 + CAMERA.width]
    ref = texture[:, x0 - int(shift_px) : x0 - int(shift_px) + CAMERA.width]
    return np.repeat(query[..., None], 3, axis=2), np.repeat(ref[..., None], 3, axis=2)


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_plane_sweep_sees_the_whole_overlap_whichever_side_leaves_the_view(direction):
    # A reference translated along x: the query pixels it does not see lie on the left or the right.
    # NaN outside the warped reference must stay local (box filters run sums along rows).
    depth, f = 1.0, CAMERA.K[0, 0]
    shift = round(f * 0.1 / depth)
    query, ref = _shifted_plane_views(direction * shift)
    T_iq = np.eye(4)
    T_iq[0, 3] = direction * shift / f * depth
    est, conf = plane_sweep(query, [ref, ref], np.stack([T_iq, T_iq]), CAMERA, np.array([0.8, 1.25]))
    cols = slice(shift + 8, CAMERA.width - 8) if direction < 0 else slice(8, CAMERA.width - shift - 8)
    confident = conf[8:-8, cols] > 0.3
    assert confident.mean() > 0.8
    assert np.median(np.abs(est[8:-8, cols][confident] - depth)) < 0.02 * depth


def test_bad_sweep_config_is_rejected():
    with pytest.raises(ValueError, match="scale"):
        SweepConfig(scale=0.0)
    with pytest.raises(ValueError, match="odd"):
        SweepConfig(ncc_window=4)
