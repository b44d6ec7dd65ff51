"""Scene -> MuJoCo model: geoms, groups, contacts, textures, lights, clip planes."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

from vgpnav_env.scenes.model import (
    COLLISION_GROUP,
    RENDER_CAMERA,
    VISUAL_GROUP,
    ZNEAR_M,
    build_mjspec,
    build_model,
)


def test_geoms_groups_and_contacts_flags(tiny_scene):
    model = build_model(tiny_scene)
    n_visual = len(tiny_scene.meshes)
    n_collision = sum(len(m.collision) for m in tiny_scene.meshes)
    groups = model.geom_group
    assert (groups == VISUAL_GROUP).sum() == n_visual
    assert (groups == COLLISION_GROUP).sum() == n_collision
    visual = groups == VISUAL_GROUP
    assert np.all(model.geom_contype[visual] == 0) and np.all(model.geom_conaffinity[visual] == 0)
    assert np.all(model.geom_contype[~visual] == 1) and np.all(model.geom_conaffinity[~visual] == 1)
    # The tiny scene's collision parts are boxes: they become box primitives, not meshes.
    assert np.all(model.geom_type[~visual] == mujoco.mjtGeom.mjGEOM_BOX)
    assert np.all(model.geom_type[visual] == mujoco.mjtGeom.mjGEOM_MESH)


def test_collision_boxes_match_parts(tiny_scene):
    model = build_model(tiny_scene)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "col_box_a_0")
    np.testing.assert_allclose(data.geom_xpos[gid], [1.0, 1.5, 0.4], atol=1e-9)
    # Box half sizes are the part's half extents, in some axis order (the OBB may permute axes).
    np.testing.assert_allclose(np.sort(model.geom_size[gid]), np.sort([0.3, 0.4, 0.4]), atol=1e-9)


def test_textures_and_uvs(tiny_scene):
    model = build_model(tiny_scene)
    textured = {m.material.name for m in tiny_scene.meshes if m.material.image is not None}
    assert model.ntex == len(textured)
    assert model.nmeshtexcoord > 0
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MESH, "vis_floor")
    assert model.mesh_texcoordnum[floor] > 0


def test_lights_clip_planes_and_camera(tiny_scene):
    model = build_model(tiny_scene)
    assert model.nlight >= 1 and not np.any(model.light_castshadow)
    assert np.all(model.light_specular == 0)
    extent = model.stat.extent
    assert model.vis.map.znear * extent == pytest.approx(ZNEAR_M, rel=1e-6)
    diagonal = float(np.linalg.norm(np.subtract(*tiny_scene.bounds[::-1])))
    assert model.vis.map.zfar * extent > diagonal
    assert (model.vis.global_.offwidth, model.vis.global_.offheight) == (640, 480)
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, RENDER_CAMERA) >= 0
    assert model.vis.quality.offsamples == 0


def test_unknown_lighting_is_a_clear_error(tiny_scene):
    scene = dataclasses.replace(tiny_scene, lighting="disco")
    with pytest.raises(ValueError, match="unknown lighting 'disco'"):
        build_mjspec(scene)


def test_model_cache(tiny_scene):
    assert build_model(tiny_scene) is build_model(tiny_scene)
    assert build_model(tiny_scene, max_image_size=(800, 600)) is not build_model(tiny_scene)


def _with_ball(scene, xyz):
    """Scene spec plus a free ball of radius 0.2 m at ``xyz`` (as the env adds its robot)."""
    spec = build_mjspec(scene)
    body = spec.worldbody.add_body(name="ball", pos=xyz)
    body.add_freejoint()
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.2, 0, 0], group=COLLISION_GROUP)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def test_walls_and_boxes_collide_floor_does_not(tiny_scene):
    _, data = _with_ball(tiny_scene, [2.0, 2.5, 0.15])  # overlaps only the (visual) floor
    assert data.ncon == 0
    _, data = _with_ball(tiny_scene, [0.1, 2.5, 1.0])  # overlaps the west wall (inner face x = 0)
    assert data.ncon >= 1
    _, data = _with_ball(tiny_scene, [1.0, 1.5 - 0.5, 0.4])  # 0.1 m into box_a's south face
    assert data.ncon >= 1
