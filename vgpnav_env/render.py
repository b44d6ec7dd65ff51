"""Renderer backends behind one camera contract.

``renderer.render(T_wc) -> Frame``: ``T_wc`` is an OpenCV camera pose (camera -> world,
x right, y down, z forward) and the renderer's ``PinholeCamera`` fixes size and fovy.
``Frame.rgb`` is uint8 (H, W, 3); ``Frame.depth`` is float32 (H, W) metric z-depth along the
optical axis, ``np.inf`` where nothing is hit.

- ``MujocoRenderer`` (default): one OpenGL context + ``MjrContext`` reused for every frame;
  RGB and depth come from the same draw. Geom group 3 (collision parts, the robot) is hidden.
  Fork safety: before the process forks (``os.register_at_fork``), every live renderer frees its
  GL context and MuJoCo's EGL display is terminated (Mesa's llvmpipe threads and locks do not
  survive ``fork``: a child creating a context would hang); parent and child then recreate their
  own context on their next draw. So Gymnasium's ``AsyncVectorEnv`` and SB3's ``SubprocVecEnv``
  may fork after an env rendered in the parent.
- ``PyrenderRenderer``: pyrender over the scene's trimesh meshes, for mesh scenes whose
  materials MuJoCo cannot show (several or PBR materials); pyrender is imported lazily.
"""

from __future__ import annotations

import logging
import os
import sys
import weakref
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.geometry import PinholeCamera, mujoco_from_opencv
from vgpnav_env.scenes.model import (
    COLLISION_GROUP,
    RENDER_CAMERA,
    build_model,
    lighting_for,
    scene_lights,
)
from vgpnav_env.scenes.scene import Scene

logger = logging.getLogger(__name__)

BACKENDS = ("mujoco", "pyrender")


@dataclass(frozen=True)
class Frame:
    """One rendered view: ``rgb`` uint8 (H, W, 3), ``depth`` float32 (H, W) z-depth (inf = no hit)."""

    rgb: NDArray[np.uint8]
    depth: NDArray[np.float32]


class Renderer(Protocol):
    camera: PinholeCamera

    def render(self, T_wc: ArrayLike) -> Frame: ...

    def close(self) -> None: ...


def _check_pose(T_wc: ArrayLike) -> NDArray[np.float64]:
    T = np.asarray(T_wc, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_wc must be a finite 4x4 camera->world pose, got shape {T.shape}")
    return T


_C = TypeVar("_C", bound="_Closing")


class _Closing:
    """Context manager and finalizer that call ``close()`` (idempotent in subclasses)."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self: _C) -> _C:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown may have torn GL down already
            pass


class MujocoRenderer(_Closing):
    """Renders a MuJoCo model (or a ``Scene``, compiled with ``build_model``) from OpenCV poses.

    ``data``: an ``MjData`` of the model whose state is drawn (e.g. the environment's robot);
    by default a private one (static scene). The model must contain ``RENDER_CAMERA``; its
    pose and fovy are set on every call, so several renderers may share one model.
    """

    def __init__(self, model_or_scene: mujoco.MjModel | Scene, camera: PinholeCamera, *, data=None) -> None:
        if isinstance(model_or_scene, Scene):
            size = (max(640, camera.width), max(480, camera.height))
            model = build_model(model_or_scene, max_image_size=size)
        elif isinstance(model_or_scene, mujoco.MjModel):
            model = model_or_scene
        else:
            raise TypeError(
                f"MujocoRenderer needs a mujoco.MjModel or a Scene, got {type(model_or_scene).__name__}"
            )
        off = (model.vis.global_.offwidth, model.vis.global_.offheight)
        if camera.width > off[0] or camera.height > off[1]:
            raise ValueError(
                f"image {camera.width}x{camera.height} exceeds the model's offscreen buffer "
                f"{off[0]}x{off[1]}; build the model with a larger max_image_size"
            )
        self.camera = camera
        self.model = model
        self.data = data if data is not None else mujoco.MjData(model)
        if not isinstance(self.data, mujoco.MjData):
            raise TypeError(f"data must be a mujoco.MjData, got {type(self.data).__name__}")
        self._cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, RENDER_CAMERA)
        if self._cam_id < 0:
            raise ValueError(
                f"model has no camera named {RENDER_CAMERA!r} (build it with vgpnav_env.scenes.model)"
            )
        if data is None:
            mujoco.mj_kinematics(model, self.data)
            mujoco.mj_camlight(model, self.data)  # world light directions; without it lights are dark
        self._gl: Any = None
        self._ctx: mujoco.MjrContext | None = None
        self._closed = False
        self._open_gl()
        _LIVE.add(self)
        self._scene = mujoco.MjvScene(model, maxgeom=max(1000, 2 * model.ngeom))
        self._option = mujoco.MjvOption()
        self._option.geomgroup[:] = 0
        self._option.geomgroup[:COLLISION_GROUP] = 1
        self._mjcam = mujoco.MjvCamera()
        self._mjcam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._mjcam.fixedcamid = self._cam_id
        self._rect = mujoco.MjrRect(0, 0, camera.width, camera.height)
        self._rgb = np.empty((camera.height, camera.width, 3), np.uint8)
        self._zbuf = np.empty((camera.height, camera.width), np.float32)

    def _open_gl(self) -> None:
        off = (self.model.vis.global_.offwidth, self.model.vis.global_.offheight)
        self._gl = mujoco.GLContext(off[0], off[1])
        self._gl.make_current()
        self._ctx = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._ctx)
        self._ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR

    def _free_gl(self) -> None:
        if self._ctx is not None:
            self._gl.make_current()
            self._ctx.free()
            self._ctx = None
            self._gl.free()
            self._gl = None

    def _draw(self, T_wc: ArrayLike, data) -> None:
        if self._closed:
            raise RuntimeError("render called after close()")
        if self._ctx is None:  # freed before a fork: this process makes its own context
            self._open_gl()
        T = _check_pose(T_wc)
        data = self.data if data is None else data
        R_mj = mujoco_from_opencv(T[:3, :3])
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, R_mj.reshape(-1))
        m, c = self.model, self._cam_id
        m.cam_pos[c] = T[:3, 3]
        m.cam_quat[c] = quat
        m.cam_fovy[c] = np.degrees(self.camera.fovy)
        # The camera lives in the world body: its world pose is its model pose.
        data.cam_xpos[c] = T[:3, 3]
        data.cam_xmat[c] = R_mj.reshape(-1)
        self._gl.make_current()
        mujoco.mjv_updateScene(
            m, data, self._option, None, self._mjcam, mujoco.mjtCatBit.mjCAT_ALL, self._scene
        )
        mujoco.mjr_render(self._rect, self._scene, self._ctx)

    def _depth_from_buffer(self) -> NDArray[np.float32]:
        # Reverse-Z depth buffer (mjDEPTH_ZEROFAR): 0 at the far plane, 1 at the near plane.
        extent = self.model.stat.extent
        near = np.float32(self.model.vis.map.znear * extent)
        far = np.float32(self.model.vis.map.zfar * extent)
        c = np.float32(-0.5) * (-(far + near) / (far - near)) - np.float32(0.5)
        d = np.float32(-0.5) * (-(np.float32(2) * far * near) / (far - near))
        z = self._zbuf.astype(np.float64)
        with np.errstate(divide="ignore"):
            depth = (float(d) / (z + float(c))).astype(np.float32)
        depth[z <= 0.0] = np.inf
        return depth

    def render(self, T_wc: ArrayLike, data=None) -> Frame:
        """RGB and z-depth from one draw; ``data`` overrides the renderer's ``MjData``."""
        self._draw(T_wc, data)
        mujoco.mjr_readPixels(self._rgb, self._zbuf, self._rect, self._ctx)
        return Frame(np.flipud(self._rgb).copy(), np.flipud(self._depth_from_buffer()).copy())

    def render_rgb(self, T_wc: ArrayLike, data=None) -> NDArray[np.uint8]:
        self._draw(T_wc, data)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, self._ctx)
        return np.flipud(self._rgb).copy()

    def render_depth(self, T_wc: ArrayLike, data=None) -> NDArray[np.float32]:
        self._draw(T_wc, data)
        mujoco.mjr_readPixels(None, self._zbuf, self._rect, self._ctx)
        return np.flipud(self._depth_from_buffer()).copy()

    def close(self) -> None:
        self._closed = True
        self._free_gl()
        _LIVE.discard(self)


_LIVE: weakref.WeakSet[MujocoRenderer] = weakref.WeakSet()


def _release_gl_before_fork() -> None:
    """Free every renderer's GL context and terminate MuJoCo's EGL display (see the module doc)."""
    for renderer in list(_LIVE):
        renderer._free_gl()
    egl = sys.modules.get("mujoco.egl")
    if egl is not None and egl.EGL_DISPLAY is not None:
        display, egl.EGL_DISPLAY = egl.EGL_DISPLAY, None
        EGL = egl.EGL
        EGL.eglMakeCurrent(display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
        EGL.eglTerminate(display)
        EGL.eglReleaseThread()


os.register_at_fork(before=_release_gl_before_fork)


#: pyrender writes gamma-encoded colour, about texture * light^(1/2.2), where MuJoCo writes
#: texture * light. Scaling pyrender's lights by L^1.2 at a typical total light L = 0.8 makes
#: mid-tones agree (an approximation: the two shading models differ).
_LIGHT_SCALE = 0.8**1.2


def _import_pyrender():
    """Import pyrender (lazily) with single-sample framebuffers.

    pyrender hard-codes 4x MSAA; the resolved depth is then one sample's depth, ~0.3 px away
    from the pixel centre, which biases back-projected geometry. Storing its multisample
    renderbuffers with one sample makes depth exact at pixel centres (as ``MujocoRenderer``).
    """
    import pyrender
    import pyrender.renderer
    from OpenGL import GL

    def single_sample_storage(target, samples, internalformat, width, height):
        GL.glRenderbufferStorage(target, internalformat, width, height)

    pyrender.renderer.glRenderbufferStorageMultisample = single_sample_storage
    return pyrender


class PyrenderRenderer(_Closing):
    """pyrender backend over the scene's trimesh meshes with the same camera contract.

    Materials: a mesh whose trimesh visual carries a PBR material (e.g. from a GLB) keeps it;
    otherwise the ``SceneMesh.material`` (texture image, rgba) is used, as in MuJoCo. Lights
    mirror the MuJoCo lights (ambient, directional lights; the headlight is a
    directional light attached to the camera), so colours roughly agree with MuJoCo.
    """

    def __init__(self, scene: Scene, camera: PinholeCamera) -> None:
        self._offscreen = None
        pyrender = _import_pyrender()
        self.camera = camera
        self._pyrender = pyrender
        preset = lighting_for(scene.lighting)
        ambient = _LIGHT_SCALE * np.asarray(preset.ambient, float)
        self._scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=ambient)
        self._add_meshes(scene)
        for light in scene_lights(scene):
            self._add_directional(light.direction, light.diffuse)
        K = camera.K
        # pyrender maps (cx, cy) to window coordinates, where pixel centres sit at +0.5; K's
        # principal point is in pixel indices (centre of pixel 0 = 0), hence the half-pixel shift.
        cam = pyrender.IntrinsicsCamera(
            fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.5, cy=K[1, 2] + 0.5, znear=0.05, zfar=1000.0
        )
        self._cam_node = self._scene.add(cam, pose=np.eye(4))
        head_color = np.asarray(preset.headlight_diffuse, float)
        head = pyrender.DirectionalLight(
            color=head_color / max(float(head_color.max()), 1e-9),
            intensity=_LIGHT_SCALE * np.pi * float(head_color.max()),
        )
        self._head_node = self._scene.add(head, pose=np.eye(4))
        self._offscreen = pyrender.OffscreenRenderer(camera.width, camera.height)

    def _add_meshes(self, scene: Scene) -> None:
        """One primitive per scene ``Material`` (merged geometry: pyrender's cost is per draw call);
        meshes carrying their own PBR material (mesh files) are added as they are."""
        from trimesh.visual.material import PBRMaterial

        pyrender = self._pyrender
        groups: dict[int, list] = {}
        for sm in scene.meshes:
            own = getattr(sm.mesh.visual, "material", None)
            if isinstance(own, PBRMaterial) and sm.material.image is None:
                self._scene.add(pyrender.Mesh.from_trimesh(sm.mesh, smooth=False))
            else:
                groups.setdefault(id(sm.material), []).append(sm)
        primitives = []
        for members in groups.values():
            material = members[0].material
            tris = np.concatenate([m.mesh.triangles.reshape(-1, 3) for m in members])
            normals = np.concatenate([np.repeat(m.mesh.face_normals, 3, axis=0) for m in members])
            uv = None
            if material.image is not None:
                uv = np.concatenate(
                    [np.asarray(m.mesh.visual.uv)[m.mesh.faces].reshape(-1, 2) for m in members]
                )
            texture = None
            if material.image is not None:
                texture = pyrender.Texture(source=np.ascontiguousarray(material.image), source_channels="RGB")
            pbr = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=np.asarray(material.rgba, float),
                baseColorTexture=texture,
                metallicFactor=0.0,
                roughnessFactor=1.0,
                doubleSided=True,
            )
            primitives.append(
                pyrender.Primitive(
                    positions=tris.astype(np.float32),
                    normals=normals.astype(np.float32),
                    texcoord_0=None if uv is None else uv.astype(np.float32),
                    material=pbr,
                )
            )
        if primitives:
            self._scene.add(pyrender.Mesh(primitives))

    def _add_directional(self, direction, diffuse) -> None:
        # pyrender lights shine along their node's -z; Lambertian 1/pi is undone by the pi.
        z = -np.asarray(direction, float)
        x = np.cross([0.0, 0.0, 1.0], z) if abs(z[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
        color = np.asarray(diffuse, float)
        peak = max(float(color.max()), 1e-9)
        light = self._pyrender.DirectionalLight(color=color / peak, intensity=_LIGHT_SCALE * np.pi * peak)
        self._scene.add(light, pose=pose)

    def render(self, T_wc: ArrayLike) -> Frame:
        if self._offscreen is None:
            raise RuntimeError("render called after close()")
        T = _check_pose(T_wc)
        pose_gl = T.copy()
        pose_gl[:3, :3] = mujoco_from_opencv(T[:3, :3])  # OpenGL camera axes = MuJoCo camera axes
        self._scene.set_pose(self._cam_node, pose_gl)
        self._scene.set_pose(self._head_node, pose_gl)
        rgb, depth = self._offscreen.render(self._scene, flags=self._pyrender.RenderFlags.SKIP_CULL_FACES)
        depth = depth.astype(np.float32)
        depth[depth <= 0.0] = np.inf
        return Frame(np.ascontiguousarray(rgb[..., :3]), depth)

    def close(self) -> None:
        if self._offscreen is None:
            return
        offscreen, self._offscreen = self._offscreen, None
        display = getattr(offscreen._platform, "_egl_display", None)
        if display is None:
            offscreen.delete()
            return
        # pyrender's delete() calls eglTerminate on the EGL display, which is shared with
        # MuJoCo's contexts in this process and would break them: free only our context.
        from OpenGL import EGL

        platform = offscreen._platform
        platform.make_current()
        offscreen._renderer.delete()
        EGL.eglMakeCurrent(display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
        EGL.eglDestroyContext(display, platform._egl_context)
        # Disarm pyrender's own finalizers (they would terminate the shared display).
        platform._egl_context = platform._egl_display = None
        offscreen._renderer = offscreen._platform = None


def make_renderer(
    scene: Scene, camera: PinholeCamera, backend: str = "mujoco"
) -> MujocoRenderer | PyrenderRenderer:
    """Renderer of ``scene`` for ``camera`` with the named backend (``BACKENDS``)."""
    if backend == "mujoco":
        return MujocoRenderer(scene, camera)
    if backend == "pyrender":
        return PyrenderRenderer(scene, camera)
    raise ValueError(f"unknown render backend {backend!r}; allowed: {list(BACKENDS)}")
