"""vgpnav-env: monocular metric-aware navigation benchmark with VGP-Nav perception."""

import os

# Headless offscreen rendering for MuJoCo and pyrender unless the user chose otherwise.
_gl = os.environ.setdefault("MUJOCO_GL", "egl")
if _gl in ("egl", "osmesa"):
    os.environ.setdefault("PYOPENGL_PLATFORM", _gl)

__version__ = "0.1.0"
