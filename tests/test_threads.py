"""The backbone's per-process thread pool."""

from __future__ import annotations

import threading
import time

import pytest

from vgpnav_env.perception.backbones.threads import available_cores, resolve_threads, thread_map


def test_thread_map_keeps_the_order_and_uses_threads():
    names = set()

    def work(x: int) -> int:
        names.add(threading.current_thread().name)
        return x * x

    assert thread_map(work, range(20), 2) == [x * x for x in range(20)]
    assert any(name.startswith("vgpnav") for name in names)
    names.clear()
    assert thread_map(work, range(5), 1) == [0, 1, 4, 9, 16]
    assert names == {threading.current_thread().name}


def test_nested_calls_run_serially_inside_the_pool():
    def outer(x: int) -> list[str]:
        return thread_map(lambda _: threading.current_thread().name, range(3), 2)

    for inner in thread_map(outer, range(4), 2):
        assert len(set(inner)) == 1  # the calling pool thread did all the inner items


def test_zero_threads_means_every_available_core():
    assert resolve_threads(0) == available_cores() >= 1
    assert resolve_threads(3) == 3


def test_an_exception_propagates_after_every_call_finished():
    finished = []

    def work(x: int) -> int:
        if x == 0:
            raise OSError("disk full (simulated)")
        time.sleep(0.2)
        finished.append(x)
        return x

    with pytest.raises(OSError, match="simulated"):
        thread_map(work, range(4), 2)
    assert sorted(finished) == [1, 2, 3]  # nothing still running when the caller cleans up
