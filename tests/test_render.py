"""Renderer contract: OpenCV poses, metric z-depth, pixel-exact projection, backend agreement."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from conftest import MARKER, ROOM_X, ROOM_Y
from matplotlib.path import Path
from scipy.spatial import ConvexHull

from vgpnav_env.geometry import PinholeCamera, camera_pose
from vgpnav_env.render import BACKENDS, Frame, MujocoRenderer, PyrenderRenderer, make_renderer
from vgpnav_env.scenes.model import COLLISION_GROUP, build_mjspec

CAM = PinholeCamera(160, 120, np.radians(60.0))
CAM_MID = PinholeCamera(320, 240, np.radians(60.0))


def random_poses(n: int, seed: int, margin: float = 0.6) -> list[np.ndarray]:
    """Camera poses inside the tiny room: height 1.2-1.6 m, pitch 15-30 deg down, yaw within
    60 deg of the direction to the room centre (so that the floor fills part of the view)."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(n):
        xy = rng.uniform([margin, margin], [ROOM_X - margin, ROOM_Y - margin])
        z = rng.uniform(1.2, 1.6)
        to_centre = np.arctan2(ROOM_Y / 2 - xy[1], ROOM_X / 2 - xy[0])
        yaw = to_centre + rng.uniform(-1.0, 1.0)
        poses.append(camera_pose([*xy, z], yaw, np.radians(rng.uniform(15, 30))))
    return poses


@pytest.fixture(scope="module")
def mj_empty(empty_room):
    with MujocoRenderer(empty_room, CAM) as r:
        yield r


@pytest.fixture(scope="module")
def mj_tiny(tiny_scene):
    with MujocoRenderer(tiny_scene, CAM_MID) as r:
        yield r


def floor_mask(camera: PinholeCamera, T_wc: np.ndarray, inset: float = 0.05) -> np.ndarray:
    """Pixels whose ray hits the floor inside the (convex, empty) room, away from the walls."""
    d_w = camera.rays() @ T_wc[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -T_wc[2, 3] / d_w[..., 2]
    hit = T_wc[:3, 3] + t[..., None] * d_w
    inside = (hit[..., 0] > inset) & (hit[..., 0] < ROOM_X - inset)
    inside &= (hit[..., 1] > inset) & (hit[..., 1] < ROOM_Y - inset)
    return (d_w[..., 2] < 0) & inside


def test_frame_contract(mj_empty):
    frame = mj_empty.render(random_poses(1, 0)[0])
    assert isinstance(frame, Frame)
    assert frame.rgb.shape == (CAM.height, CAM.width, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (CAM.height, CAM.width) and frame.depth.dtype == np.float32
    assert np.all((frame.depth > 0) | np.isinf(frame.depth))


def test_floor_backprojects_to_z0(mj_empty):
    """>= 10 random database-like poses: every floor pixel lands within 1 cm of z = 0."""
    for T_wc in random_poses(12, seed=1):
        frame = mj_empty.render(T_wc)
        mask = floor_mask(CAM, T_wc)
        assert mask.sum() > 0.1 * mask.size
        z = CAM.backproject_world(frame.depth, T_wc, mask)[:, 2]
        assert len(z) == mask.sum(), "floor pixels must have finite depth"
        assert np.abs(z).max() < 0.01, f"floor back-projection off by {np.abs(z).max():.4f} m"


def test_depth_is_planar_z_not_ray_length(mj_empty):
    T_wc = camera_pose([2.0, 0.8, 1.5], np.pi / 2, np.radians(25))
    frame = mj_empty.render(T_wc)
    mask = floor_mask(CAM, T_wc)
    d_w = CAM.rays() @ T_wc[:3, :3].T
    expected = -T_wc[2, 3] / d_w[..., 2]  # z-depth: the rays have unit z in the camera frame
    np.testing.assert_allclose(frame.depth[mask], expected[mask], rtol=1e-4)


def test_sky_is_inf(mj_empty):
    frame = mj_empty.render(camera_pose([2.0, 2.5, 1.5], 0.0, np.radians(-80)))  # looking up, no ceiling
    assert np.isinf(frame.depth).mean() > 0.5


def _marker_silhouette(camera: PinholeCamera, T_wc: np.ndarray) -> np.ndarray:
    centre, extents = np.asarray(MARKER[0]), np.asarray(MARKER[1])
    corners = centre + 0.5 * extents * np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    )
    uv, z = camera.project_world(T_wc, corners)
    assert np.all(z > 0)
    hull = Path(uv[ConvexHull(uv).vertices])
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    return hull.contains_points(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(camera.height, camera.width)


@pytest.mark.parametrize("yaw_deg", [30.0, 75.0])
def test_known_point_projects_where_rendered(mj_tiny, yaw_deg):
    """The red marker cube's projected silhouette matches its rendered pixels (centroid < 0.25 px)."""
    T_wc = camera_pose([0.2, 0.4, 1.5], np.radians(yaw_deg), np.radians(30))
    rgb = mj_tiny.render(T_wc).rgb.astype(int)
    red = (rgb[..., 0] > 40) & (rgb[..., 1] < 8) & (rgb[..., 2] < 8)  # the marker is pure red
    predicted = _marker_silhouette(CAM_MID, T_wc)
    assert predicted.sum() > 100
    iou = (red & predicted).sum() / (red | predicted).sum()
    assert iou > 0.85
    centroid = np.argwhere(red).mean(axis=0)
    expected = np.argwhere(predicted).mean(axis=0)
    assert np.abs(centroid - expected).max() < 0.25, (centroid, expected)


def test_box_top_depth(mj_tiny):
    """Pixels just inside box_b's top face near its corner: depth = the ray's hit on z = 0.5."""
    T_wc = camera_pose([2.0, 1.0, 1.5], np.radians(60), np.radians(25))
    corner = np.array([2.6, 3.25, 0.5])  # box_b: centre (3, 3.5, .25), extents (.8, .5, .5)
    inside = corner + np.array([[0.03, 0.03, 0.0], [0.1, 0.05, 0.0], [0.05, 0.2, 0.0]])
    uv, _ = CAM_MID.project_world(T_wc, inside)
    u, v = np.round(uv).astype(int).T
    d_w = CAM_MID.rays()[v, u] @ T_wc[:3, :3].T
    expected = (0.5 - T_wc[2, 3]) / d_w[:, 2]
    np.testing.assert_allclose(mj_tiny.render(T_wc).depth[v, u], expected, rtol=1e-4)


def test_deterministic(mj_tiny):
    T_wc = random_poses(1, 5)[0]
    a, b = mj_tiny.render(T_wc), mj_tiny.render(T_wc)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(mj_tiny.render_rgb(T_wc), a.rgb)
    np.testing.assert_array_equal(mj_tiny.render_depth(T_wc), a.depth)


def test_hidden_group_and_added_bodies(tiny_scene):
    """Bodies added to the MjSpec render; group-3 geoms (robot, collision) stay invisible."""
    T_wc = camera_pose([2.0, 0.5, 1.5], np.pi / 2, np.radians(20))
    spec = build_mjspec(tiny_scene)
    for name, group, y in (("hidden", COLLISION_GROUP, 1.5), ("shown", 0, 3.0)):
        body = spec.worldbody.add_body(name=name, pos=[2.0, y, 1.0])
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.3, 0, 0], group=group, rgba=[0, 1, 0, 1])
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with MujocoRenderer(model, CAM, data=data) as r:
        centre = CAM.project_world(T_wc, np.array([[2.0, 1.5, 1.0], [2.0, 3.0, 1.0]]))
        uv = np.round(centre[0]).astype(int)
        depth = r.render(T_wc).depth
        assert depth[uv[0, 1], uv[0, 0]] > centre[1][0] + 0.5  # hidden sphere: see past it
        assert depth[uv[1, 1], uv[1, 0]] == pytest.approx(centre[1][1] - 0.3, abs=0.05)  # sphere front
        data.qpos[:] = 0  # no joints: moving the visible body goes through the model, not data
        model.body_pos[model.body("shown").id] = [2.0, 3.0, 2.8]
        mujoco.mj_kinematics(model, data)
        assert r.render(T_wc).depth[uv[1, 1], uv[1, 0]] > centre[1][1] + 0.5


def test_backends_agree(tiny_scene, mj_tiny):
    """pyrender vs MuJoCo: depth median |diff| < 1 cm on pixels hit by both; RGB roughly agrees."""
    before = mj_tiny.render(random_poses(1, 7)[0])
    with PyrenderRenderer(tiny_scene, CAM_MID) as pr:
        depth_err, rgb_err = [], []
        for T_wc in random_poses(3, 7):
            a, b = mj_tiny.render(T_wc), pr.render(T_wc)
            both = np.isfinite(a.depth) & np.isfinite(b.depth)
            assert both.mean() > 0.9
            depth_err.append(np.median(np.abs(a.depth - b.depth)[both]))
            rgb_err.append(np.abs(a.rgb.astype(float) - b.rgb).mean())
    print(f"backends: depth median {max(depth_err) * 1000:.3f} mm, RGB mean |diff| {np.mean(rgb_err):.1f}")
    assert max(depth_err) < 0.01
    assert np.mean(rgb_err) < 20.0
    # MuJoCo still renders (identically) after pyrender used its own GL context in this process.
    after = mj_tiny.render(random_poses(1, 7)[0])
    assert np.array_equal(before.rgb, after.rgb) and np.array_equal(before.depth, after.depth)


def test_pyrender_floor_exact(empty_room):
    with make_renderer(empty_room, CAM, backend="pyrender") as pr:
        for T_wc in random_poses(3, 11):
            mask = floor_mask(CAM, T_wc)
            z = CAM.backproject_world(pr.render(T_wc).depth, T_wc, mask)[:, 2]
            assert len(z) == mask.sum() > 0.1 * mask.size
            assert np.abs(z).max() < 0.01


def test_bad_inputs(tiny_scene, mj_tiny):
    with pytest.raises(ValueError, match="unknown render backend 'vulkan'"):
        make_renderer(tiny_scene, CAM, backend="vulkan")
    assert BACKENDS == ("mujoco", "pyrender")
    with pytest.raises(ValueError, match="4x4"):
        mj_tiny.render(np.eye(3))
    with pytest.raises(ValueError, match="offscreen buffer"):
        from vgpnav_env.scenes.model import build_model

        MujocoRenderer(build_model(tiny_scene), PinholeCamera(1280, 960, 1.0))
    with pytest.raises(TypeError, match="MjModel or a Scene"):
        MujocoRenderer("home", CAM)


def test_home_database_view():
    """A database-like view in the built-in home (1.5 m, 20 deg down): textured, closed, floor at z = 0."""
    from vgpnav_env.scenes import load_scene

    T_wc = camera_pose([0.8, 0.6, 1.5], np.radians(30), np.radians(20))
    with MujocoRenderer(load_scene("home"), CAM) as r:
        frame = r.render(T_wc)
    assert frame.rgb.std() > 20.0
    assert np.isfinite(frame.depth).all()  # walls and ceiling close the view
    z = CAM.backproject_world(frame.depth, T_wc)[:, 2]
    assert z.min() > -0.01  # nothing is seen below the floor
    assert (np.abs(z) < 0.01).mean() > 0.15  # the floor is a good part of the view


def test_pyrender_finalizer_keeps_mujoco_alive(empty_room):
    """A pyrender renderer dropped without close() must not tear down MuJoCo's EGL display."""
    import gc

    pr = PyrenderRenderer(empty_room, CAM)
    pr.render(random_poses(1, 3)[0])
    del pr
    gc.collect()
    with MujocoRenderer(empty_room, CAM) as r:
        assert np.isfinite(r.render(random_poses(1, 3)[0]).depth).any()
