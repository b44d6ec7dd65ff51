"""MkDocs hook: the source tree mkdocstrings reads for the API reference.

The distribution maps three top-level folders into the package (``agents/`` ->
``vgpnav_env.agents``, ``eval/`` -> ``vgpnav_env.eval``, ``scenes/`` -> ``vgpnav_env.scenes``;
``[tool.setuptools] package-dir`` in pyproject.toml). Griffe reads packages from folders, so this
hook lays out ``build/api-src/vgpnav_env`` as the installed package looks: symbolic links to the
files of ``vgpnav_env/`` and to the three mapped folders.
"""

from __future__ import annotations

import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
API_SRC = ROOT / "build" / "api-src"
MAPPED = {"agents": "agents", "eval": "eval", "scenes": "scenes"}


def on_startup(*, command: str, dirty: bool) -> None:
    """Before any plugin's config event: mkdocstrings reads its search paths there."""
    package = API_SRC / "vgpnav_env"
    if API_SRC.exists():
        shutil.rmtree(API_SRC)
    package.mkdir(parents=True)
    for entry in (ROOT / "vgpnav_env").iterdir():
        if entry.name != "__pycache__":
            (package / entry.name).symlink_to(entry)
    for name, folder in MAPPED.items():
        (package / name).symlink_to(ROOT / folder)
