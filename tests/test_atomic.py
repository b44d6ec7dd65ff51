"""Atomic writes: a failed write leaves the previous file intact and no temporary files behind."""

from __future__ import annotations

import pytest

from vgpnav_env.atomic import atomic_write, atomic_write_text


def test_write_replaces_and_failure_keeps_previous(tmp_path) -> None:
    path = tmp_path / "sub" / "report.json"
    atomic_write_text(path, "first")
    assert path.read_text() == "first"

    def crash(f) -> None:
        f.write(b"half of the sec")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(path, crash)
    assert path.read_text() == "first"
    assert [p.name for p in path.parent.iterdir()] == ["report.json"]
    atomic_write_text(path, "second")
    assert path.read_text() == "second"
    assert path.stat().st_mode & 0o777 == 0o644
