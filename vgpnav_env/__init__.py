"""vgpnav-env: monocular metric-aware navigation benchmark with VGP-Nav perception."""

import os

# Headless offscreen rendering for MuJoCo and pyrender unless the user chose otherwise.
_gl = os.environ.setdefault("MUJOCO_GL", "egl")
if _gl in ("egl", "osmesa"):
    os.environ.setdefault("PYOPENGL_PLATFORM", _gl)

__version__ = "0.1.0"


def _register_envs() -> None:
    import gymnasium

    if "VGPNav/PointGoal-v0" not in gymnasium.registry:
        gymnasium.register("VGPNav/PointGoal-v0", entry_point="vgpnav_env.envs.pointgoal:PointGoalEnv")
    from vgpnav_env.tasks import register_tasks

    register_tasks()  # VGPNav/PointNav-v1, ...: vgpnav_env.tasks


_register_envs()

from vgpnav_env.make import make_env  # noqa: E402 (after the GL platform is chosen)

__all__ = ["make_env"]
