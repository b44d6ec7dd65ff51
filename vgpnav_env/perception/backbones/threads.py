"""A per-process thread pool for the classical backbone's independent work items.

OpenCV, poselib and numpy's array kernels release the GIL, so the per-reference two-view pairs and
the plane-sweep chunks run on several cores from plain threads (shared read-only inputs, nothing
pickled). The pool is created lazily in the process that uses it (a forked child makes its own)
and is shared by every backbone of the process. A call made from inside a pool thread runs its
items serially (no nested waiting on the same pool).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_key: tuple[int, int] = (-1, 0)  # (pid, size)
_inside = threading.local()


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; ``os.cpu_count()`` where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def resolve_threads(threads: int) -> int:
    """``threads`` if positive, else the available cores."""
    return threads if threads > 0 else available_cores()


def _get_pool(size: int) -> ThreadPoolExecutor:
    global _pool, _pool_key
    with _lock:
        if _pool is None or _pool_key != (os.getpid(), size):
            if _pool is not None and _pool_key[0] == os.getpid():
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(size, thread_name_prefix="vgpnav", initializer=_mark_inside)
            _pool_key = (os.getpid(), size)
        return _pool


def _mark_inside() -> None:
    _inside.active = True


def thread_map(fn: Callable[[T], R], items: Iterable[T], threads: int) -> list[R]:
    """``[fn(x) for x in items]`` in order, on up to ``threads`` threads (<= 0: all cores)."""
    items = list(items)
    n = min(resolve_threads(threads), len(items))
    if n <= 1 or getattr(_inside, "active", False):
        return [fn(x) for x in items]
    return list(_get_pool(resolve_threads(threads)).map(fn, items))
