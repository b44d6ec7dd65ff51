"""Threads of a process: its CPU share, every native pool sized to it, and the backbone's own pool.

:func:`configure_threads` is the one place that sizes the native thread pools of a process to its
CPU share (the cores of its CPU affinity divided by the worker processes that share them; a worker
of :mod:`vgpnav_env.eval.workers` already runs on its own share): OpenMP and numexpr through their
environment variables (read when a library loads: effective for libraries not loaded yet and for
child processes) and ``threadpoolctl`` (when installed) for pools already loaded, torch's intra-op
pool (inter-op 1) when torch is loaded (a module that loads torch later calls
:func:`pin_torch_threads`), and ``OMP_WAIT_POLICY=PASSIVE``: an idle OpenMP thread sleeps instead of
spinning on a core another worker needs (with spinning, a torch pair took 1-7 s instead of 40-60 ms
on 2 shared cores). BLAS (OpenBLAS, MKL, Accelerate) and OpenCV get ONE thread: the perception's
matrices are small, the backbone parallelizes over pairs and plane chunks itself (below), and their
pools spin-wait between the small calls (OpenBLAS's pthreads ignore the OpenMP wait policy). The CLI
calls it once, each worker process at its start. :func:`thread_report` says what a process uses.

The backbone's pool: OpenCV, poselib and numpy's array kernels release the GIL, so the
per-reference two-view pairs and the plane-sweep chunks run on several cores from plain threads
(shared read-only inputs, nothing pickled). The pool is created lazily in the process that uses it
(a forked child makes its own) and is shared by every backbone of the process; its size follows the
process's share (``threads`` <= 0) unless a config gives one. A call made from inside a pool thread
runs its items serially (no nested waiting on the same pool).
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_key: tuple[int, int] = (-1, 0)  # (pid, size)
_inside = threading.local()
#: This process's share of cores set by :func:`configure_threads` (pid, threads); else its affinity.
_share: tuple[int, int] = (-1, 0)
#: Environment variables native libraries read their thread count from when they load.
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
)
#: Of those, the BLAS pools: one thread whatever the share (module docstring).
BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; ``os.cpu_count()`` where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def cpu_share() -> int:
    """Threads this process's pools may use: set by :func:`configure_threads`, else its cores."""
    return _share[1] if _share[0] == os.getpid() else available_cores()


def resolve_threads(threads: int) -> int:
    """``threads`` if positive, else this process's :func:`cpu_share`."""
    return threads if threads > 0 else cpu_share()


def configure_threads(workers: int = 1, threads: int | None = None) -> int:
    """Size the native thread pools of this process to its CPU share (module docstring; BLAS and
    OpenCV get one thread): the cores of its affinity divided by ``workers`` processes sharing them
    (at least 1), or ``threads`` when given (e.g. a Ray task's CPUs). Returns the share."""
    global _share
    if workers < 1 or (threads is not None and threads < 1):
        raise ValueError(f"workers and threads must be >= 1, got {workers}, {threads}")
    share = threads if threads is not None else max(1, available_cores() // workers)
    _share = (os.getpid(), share)
    for name in THREAD_VARIABLES:
        os.environ[name] = "1" if name in BLAS_VARIABLES else str(share)
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1, user_api="blas")
        threadpool_limits(share, user_api="openmp")
    except ImportError:  # pragma: no cover - optional: the variables above size BLAS loaded later
        pass
    import cv2

    cv2.setNumThreads(1)
    pin_torch_threads()
    return share


def pin_torch_threads(threads: int | None = None) -> None:
    """Size torch's intra-op pool to ``threads`` (default: this process's :func:`cpu_share`;
    inter-op 1) when torch is loaded; never imports it (loading torch costs a second). A module
    that loads torch calls it after the import (:mod:`~vgpnav_env.perception.backbones.xfeat`
    asks for 1: its small networks run on the backbone's pair threads instead)."""
    torch = sys.modules.get("torch")
    if torch is None:
        return
    torch.set_num_threads(threads if threads is not None else cpu_share())
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already set, or torch's inter-op pool already ran
        pass


def thread_report() -> dict[str, Any]:
    """The thread counts this process uses: its cores and share, the backbone pool's size, OpenCV,
    torch (when loaded), each loaded BLAS / OpenMP library (``threadpoolctl``, when installed) and
    the thread environment variables."""
    import cv2

    report: dict[str, Any] = {
        "cores": available_cores(),
        "share": cpu_share(),
        "backbone_pool": resolve_threads(0),
        "opencv": cv2.getNumThreads(),
    }
    torch = sys.modules.get("torch")
    report["torch"] = (
        f"{torch.get_num_threads()} intra-op, {torch.get_num_interop_threads()} inter-op"
        if torch is not None
        else "not loaded"
    )
    try:
        from threadpoolctl import threadpool_info

        pools = threadpool_info()
        report["native"] = {f"{i['internal_api']} ({i['prefix']})": i["num_threads"] for i in pools}
    except ImportError:  # pragma: no cover - optional
        report["native"] = "threadpoolctl not installed"
    report["environment"] = {k: os.environ.get(k, "") for k in (*THREAD_VARIABLES, "OMP_WAIT_POLICY")}
    return report


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
    """``[fn(x) for x in items]`` in order, on up to ``threads`` threads (<= 0: the process's share).
    If a call raises, the first exception (in item order) propagates only after every call has
    finished, so no call still runs (e.g. writes into a directory the caller then deletes)."""
    items = list(items)
    n = min(resolve_threads(threads), len(items))
    if n <= 1 or getattr(_inside, "active", False):
        return [fn(x) for x in items]
    pool = _get_pool(resolve_threads(threads))
    futures = [pool.submit(fn, x) for x in items]
    wait(futures)
    return [f.result() for f in futures]
