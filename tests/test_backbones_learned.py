"""Learned-backbone adapter: a tiny fake VGGT-contract model with weights saved by the test."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vgpnav_env.geometry import PinholeCamera, camera_pose, invert_pose
from vgpnav_env.perception.backbones import make_backbone
from vgpnav_env.perception.backbones.learned import LearnedBackbone, vggt_confidence

CAMERA = PinholeCamera(16, 12, np.deg2rad(60.0))
S = 4


class FakeVGGT(torch.nn.Module):
    """Returns stored extrinsics; depth = depth_scale * (1 + mean image intensity); conf = 1 + u."""

    def __init__(self, batch_axis: bool = False) -> None:
        super().__init__()
        self.extrinsic = torch.nn.Parameter(torch.zeros(S, 3, 4, dtype=torch.float64))
        self.depth_scale = torch.nn.Parameter(torch.zeros(()))
        self.batch_axis = batch_axis

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        assert images.dtype == torch.float32 and images.ndim == 4 and images.shape[1] == 3
        assert 0.0 <= float(images.min()) and float(images.max()) <= 1.0
        n, _, h, w = images.shape
        depth = self.depth_scale * (1.0 + images.mean(dim=1))
        conf = 1.0 + torch.arange(n, dtype=torch.float32)[:, None, None].expand(n, h, w)
        out = {"extrinsic": self.extrinsic[:n], "depth": depth[..., None], "depth_conf": conf}
        return {key: v[None] for key, v in out.items()} if self.batch_axis else out


@pytest.fixture()
def truth(tmp_path):
    """Camera-from-world extrinsics with world = a frame that is NOT the query (checks re-expression)."""
    rng = np.random.default_rng(0)
    T_wc = np.stack([camera_pose([*rng.uniform(0, 2, 2), 1.3], rng.uniform(-3, 3), 0.3) for _ in range(S)])
    model = FakeVGGT()
    with torch.no_grad():
        model.extrinsic.copy_(torch.from_numpy(invert_pose(T_wc)[:, :3, :]))
        model.depth_scale.fill_(2.0)
    path = tmp_path / "fake.pt"
    torch.save(model.state_dict(), path)
    images = [np.full((12, 16, 3), 255 * i // (S - 1), np.uint8) for i in range(S)]
    return {"T_wc": T_wc, "path": path, "images": images}


def test_fake_model_round_trip(truth):
    backbone = LearnedBackbone(FakeVGGT, truth["path"])
    out = backbone(truth["images"][0], truth["images"][1:], CAMERA)
    T_qi_true = invert_pose(truth["T_wc"][0]) @ truth["T_wc"][1:]
    np.testing.assert_allclose(out.T_qi, T_qi_true, atol=1e-9)
    # depth = 2 * (1 + mean intensity): the query is black, the last reference white.
    np.testing.assert_allclose(out.query_depth, 2.0)
    np.testing.assert_allclose(out.reference_depths[-1], 4.0, rtol=1e-6)
    # conf of image n is 1 + n, mapped by 1 - 1/c.
    np.testing.assert_allclose(out.query_depth_confidence, 0.0)
    np.testing.assert_allclose(out.confidence, [0.5, 2 / 3, 0.75], rtol=1e-6)
    assert out.name == "learned" and out.scale == "model" and out.scale_valid.all()


def test_batch_axis_resizing_and_wrapped_checkpoints(truth, tmp_path):
    state = torch.load(truth["path"], weights_only=True)
    wrapped = tmp_path / "wrapped.pt"
    torch.save({"model": state}, wrapped)
    backbone = make_backbone(
        "learned", model=lambda: FakeVGGT(batch_axis=True), weights_path=wrapped, input_size=(8, 6)
    )
    out = backbone(truth["images"][0], truth["images"][1:], CAMERA)
    assert out.query_depth.shape == (12, 16) and out.reference_depths.shape == (S - 1, 12, 16)
    np.testing.assert_allclose(out.T_qi, invert_pose(truth["T_wc"][0]) @ truth["T_wc"][1:], atol=1e-9)


def test_missing_weights_and_bad_specs_fail_clearly(tmp_path):
    with pytest.raises(FileNotFoundError, match="never downloads"):
        LearnedBackbone(FakeVGGT, tmp_path / "absent.pt")
    with pytest.raises(ValueError, match="module:factory"):
        LearnedBackbone("no_colon_here", tmp_path / "absent.pt")
    np.testing.assert_allclose(vggt_confidence(np.array([0.5, 1.0, 4.0])), [0.0, 0.0, 0.75])
