"""A protocol's independent tasks on this process, on worker processes or on a Ray cluster.

Every evaluation protocol (navigation episodes, query frames, ablation configurations) describes
its work as

- ``setup``: a picklable zero-argument callable (a frozen dataclass instance or a top-level
  function) that builds what every task needs -- the env and the agent, or the database, the
  backbone and the perceiver. It runs **once per worker process** and its result (the worker's
  *state*) is kept between tasks, so renderers, databases and feature caches are built once per
  worker, not once per task;
- ``task(state, item) -> result``: a picklable top-level function; ``item`` and ``result`` are
  picklable plain data (records, arrays, PNG bytes: a Ray cluster's nodes share no files).

:class:`Workers` runs ``[task(state, item) for item in items]`` and returns the results in the
order of ``items``, whichever worker ran them:

- ``workers=1`` (and no Ray): in this process, ``setup`` called once per distinct setup;
- ``workers=N``: a ``concurrent.futures.ProcessPoolExecutor`` of up to N processes (started on
  demand) with the ``spawn`` context (a GL context or a thread pool does not survive ``fork``);
  each process builds its state on its first task of a setup. Worker ``i`` runs on the ``i``-th
  share of this process's cores (CPU affinity, Linux) and sizes every native thread pool to it at
  its start (:func:`~vgpnav_env.perception.backbones.threads.configure_threads`), so N workers on
  N cores do not oversubscribe them;
- ``ray=ADDRESS``: one Ray task per item (``ray.init(address)``; ``"local"`` starts a local
  instance with ``workers`` CPUs), each task on one CPU (its process's pools sized to one thread).
  Ray reuses its worker processes between tasks, and the state is cached in each of them the same
  way. Every node needs ``vgpnav-env`` installed and the same builds (database directories) at the
  same paths.

``cost`` (optional, one number per item, e.g. an episode's geodesic distance): items are started
in decreasing cost, so that the last worker does not run a long task alone; results keep the
order of ``items``.

A running task may call :func:`note` (e.g. ``"episode 2: step 40"``): the note is shown beside
its map's progress bar, from this process or from worker processes (through a queue; notes from
Ray tasks are not shown), so that tasks of a minute or more show what they are doing.
Cores follow the work: once fewer tasks are left than worker processes, the running ones share the
idle workers' cores (affinity and every pool resized by
:func:`~vgpnav_env.perception.backbones.threads.configure_threads`), picked up when a task starts
and at each :func:`note`; a new map starts from the even shares again. Thread counts do not change
results.

Identical results: a task's result may depend only on ``setup`` and its ``item`` -- seeds are
part of the items (episode seeds, per-frame seeds), never a random stream shared across tasks.
Protocols that carry state along a sequence (the ground anchor of the query-frame protocols)
compute that state first and pass it in the items (see :mod:`vgpnav_env.eval.perception_runs`).

``Workers.cpu_seconds`` is the CPU time (``time.process_time`` of the worker processes, all their
threads, setup included) the tasks used outside this process; reports add it to this process's.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import pickle
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from queue import Empty
from typing import Any, TypeVar

from tqdm import tqdm

from vgpnav_env.perception.backbones.threads import available_cores, configure_threads, cpu_share

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")
Setup = Callable[[], Any]
Task = Callable[[Any, Any], Any]
#: Called with (item index, result) as each task finishes.
Done = Callable[[int, Any], None]

#: ``--ray`` without an address: start a local Ray instance with ``--workers`` CPUs.
LOCAL_RAY = "local"
RAY_MISSING = "--ray needs the optional dependency ray: pip install 'vgpnav-env[distributed]'"

#: The state of this process's current setup: (setup key, state); one at a time.
_STATE: tuple[str, Any] | None = None
#: Where :func:`note` sends a running task's note: (process id, text or None when the task ended).
_NOTES: Callable[[tuple[int, str | None]], None] | None = None
#: Seconds between looks at the notes while waiting for worker processes.
NOTE_POLL_S = 0.5
#: The process whose thread pools :func:`_run` sized (a Ray worker's).
_THREADS_PID = -1
#: A worker process's cores: (all the pool's cores, its own even share, the shared Value holding
#: how many cores each running task may use now); None outside worker processes.
_CORES: tuple[tuple[int, ...], tuple[int, ...], Any] | None = None


def note(text: str) -> None:
    """Show ``text`` beside the progress bar of the :meth:`Workers.map` that runs the calling task
    (a no-op outside one, and on Ray)."""
    if _NOTES is not None:
        _NOTES((os.getpid(), text))
    _follow_share()


def running_share(cores: int, workers: int, left: int) -> int:
    """Cores each of ``left`` unfinished tasks may use on ``workers`` processes over ``cores`` cores:
    the even share while every worker has a task, the idle workers' cores spread over the running
    tasks once fewer are left."""
    even = max(1, cores // workers)
    return max(even, cores // left) if 0 < left < workers else even


def _follow_share() -> None:
    """In a worker process: take the share the pool's owner set (module docstring), if it changed."""
    if _CORES is None:
        return
    cores, own, shared = _CORES
    share = min(int(shared.value), len(cores))
    if share == cpu_share():
        return
    os.sched_setaffinity(0, own if share <= len(own) else cores)
    configure_threads(threads=share)


def default_workers() -> int:
    """The cores this process may run on (the default ``--workers``)."""
    return available_cores()


def _close(state: Any) -> None:
    close = getattr(state, "close", None)
    if callable(close):
        close()


def _state(key: str, setup: Setup) -> Any:
    """This process's state for ``setup`` (built on first use; a new setup replaces the old)."""
    global _STATE
    if _STATE is None or _STATE[0] != key:
        if _STATE is not None:
            _close(_STATE[1])
            _STATE = None
        _STATE = (key, setup())
    return _STATE[1]


def _run(key: str, setup: Setup, task: Task, item: Any, threads: int | None = None) -> tuple[Any, float]:
    """Worker side of one task: (result, CPU seconds this process spent on it, setup included);
    ``threads``: size this process's thread pools to that many threads first (once per process)."""
    global _THREADS_PID
    if threads is not None and _THREADS_PID != os.getpid():
        configure_threads(threads=threads)
        _THREADS_PID = os.getpid()
    _follow_share()
    cpu = time.process_time()
    try:
        result = task(_state(key, setup), item)
    finally:
        if _NOTES is not None:
            _NOTES((os.getpid(), None))
    return result, time.process_time() - cpu


def _init_worker(
    notes: Any, counter: Any, workers: int, cores: tuple[int, ...] | None, share: Any = None
) -> None:
    """Worker process initializer: send notes to ``notes`` (a queue) and, given ``cores``, run on
    the ``i``-th share of them (``i`` counts started workers), so that N single-share workers do not
    each start thread pools over every core; ``share`` (a shared Value) says how many cores a
    running task may use once others are idle (module docstring)."""
    global _NOTES, _CORES
    _NOTES = notes.put
    if cores is not None:
        with counter.get_lock():
            i = counter.value
            counter.value += 1
        n = min(workers, len(cores))
        own = cores[i % n :: n]
        os.sched_setaffinity(0, own)
        if share is not None:
            _CORES = (cores, own, share)
    configure_threads()


def _drain(notes: Any) -> list[tuple[int, str | None]]:
    """The notes waiting in the queue ``notes``."""
    out = []
    while True:
        try:
            out.append(notes.get_nowait())
        except Empty:
            return out


def _show_notes(bar: tqdm, notes: dict[int, str], pid: int, text: str | None) -> None:
    """Record one worker's note (None: its task ended) and show all current ones on ``bar``."""
    if text is None:
        notes.pop(pid, None)
    else:
        notes[pid] = text
    bar.set_postfix_str("; ".join(notes[p] for p in sorted(notes)))


def _key(setup: Setup) -> str:
    return hashlib.blake2b(pickle.dumps(setup), digest_size=16).hexdigest()


class Workers:
    """Runs tasks (module docstring) on ``workers`` processes or a Ray cluster; a context manager
    that shuts the pool (and a Ray instance it started) down on exit.

    ``workers``: processes (1 = this process);
    ``ray``: a Ray address (``"auto"``, ``"ray://host:10001"``) or :data:`LOCAL_RAY`; ``progress``
    shows a progress bar per :meth:`map`.
    """

    def __init__(self, workers: int = 1, ray: str | None = None, progress: bool = True) -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = int(workers)
        self.ray_address = ray
        self.progress = progress
        self.cpu_seconds = 0.0
        self._pool: ProcessPoolExecutor | None = None
        self._notes: Any = None  # the worker processes' note queue
        self._share: Any = None  # cores per running task (module docstring)
        self._ray: Any = None
        self._ray_started = False
        self._local: tuple[str, Any] | None = None

    @property
    def where(self) -> str:
        """Where tasks run, for reports: ``"this process"``, ``"N processes"`` or ``"Ray (...)"``."""
        if self.ray_address is not None:
            return f"Ray ({self.ray_address})"
        return "this process" if self.workers == 1 else f"{self.workers} processes"

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._local is not None:
            _close(self._local[1])
            self._local = None
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
            self._notes.close()
            self._notes = self._share = None
        if self._ray_started:
            self._ray.shutdown()
            self._ray_started = False

    def map(
        self,
        setup: Setup,
        task: Task,
        items: Sequence[Any],
        desc: str | None = None,
        cost: Sequence[float] | None = None,
        on_result: Done | None = None,
    ) -> list[Any]:
        """``[task(state, item) for item in items]`` with one state per worker, started in decreasing
        ``cost`` when given (module docstring). ``on_result(i, result)`` is called in this process
        as each task finishes (in the order they finish; ``i`` indexes ``items``), e.g. to write a
        record before the others are done."""
        items = list(items)
        if not items:
            return []
        if cost is not None and len(cost) != len(items):
            raise ValueError(f"got {len(cost)} costs for {len(items)} items")
        order = list(range(len(items))) if cost is None else sorted(range(len(items)), key=lambda i: -cost[i])
        key = _key(setup)
        bar = tqdm(total=len(items), desc=desc, disable=not self.progress, unit="task")
        ordered = [items[i] for i in order]

        def done_ordered(j: int, result: Any) -> None:
            if on_result is not None:
                on_result(order[j], result)

        try:
            if self.ray_address is not None:
                out = self._map_ray(key, setup, task, ordered, bar, done_ordered)
            elif self.workers == 1:
                out = self._map_here(key, setup, task, ordered, bar, done_ordered)
            else:
                out = self._map_processes(key, setup, task, ordered, bar, done_ordered)
        finally:
            bar.close()
        results: list[Any] = [None] * len(items)
        for i, result in zip(order, out, strict=True):
            results[i] = result
        return results

    def _map_here(
        self, key: str, setup: Setup, task: Task, items: list[Any], bar: tqdm, done: Done
    ) -> list[Any]:
        global _NOTES
        if self._local is None or self._local[0] != key:
            if self._local is not None:
                _close(self._local[1])
                self._local = None
            self._local = (key, setup())
        results = []
        shown: dict[int, str] = {}

        def show(n: tuple[int, str | None]) -> None:
            _show_notes(bar, shown, *n)

        _NOTES = show
        try:
            for i, item in enumerate(items):
                results.append(task(self._local[1], item))
                done(i, results[-1])
                bar.update()
        finally:
            _NOTES = None
        return results

    def _map_processes(
        self, key: str, setup: Setup, task: Task, items: list[Any], bar: tqdm, done: Done
    ) -> list[Any]:
        if self._pool is None:  # processes start on demand, at most one per pending task
            context = get_context("spawn")
            cores = tuple(sorted(os.sched_getaffinity(0))) if hasattr(os, "sched_setaffinity") else None
            self._notes = context.Queue()
            self._share = context.Value("i", 1)
            init = (self._notes, context.Value("i", 0), self.workers, cores, self._share)
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=context, initializer=_init_worker, initargs=init
            )
        n_cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else self.workers
        self._share.value = running_share(n_cores, self.workers, len(items))
        futures: dict[Future, int] = {
            self._pool.submit(_run, key, setup, task, x): i for i, x in enumerate(items)
        }
        results: list[Any] = [None] * len(items)
        pending = set(futures)
        shown: dict[int, str] = {}
        try:
            while pending:
                finished, pending = wait(pending, timeout=NOTE_POLL_S, return_when=FIRST_COMPLETED)
                self._share.value = running_share(n_cores, self.workers, len(pending))
                for pid, text in _drain(self._notes):
                    _show_notes(bar, shown, pid, text)
                for future in finished:
                    results[futures[future]], cpu = future.result()
                    self.cpu_seconds += cpu
                    done(futures[future], results[futures[future]])
                    bar.update()
        except BaseException:
            for future in pending:
                future.cancel()
            raise
        return results

    def _map_ray(
        self, key: str, setup: Setup, task: Task, items: list[Any], bar: tqdm, done: Done
    ) -> list[Any]:
        ray = self._connect_ray()
        remote = ray.remote(num_cpus=1)(_run)
        setup_ref = ray.put(setup)
        refs = [remote.remote(key, setup_ref, task, x, 1) for x in items]
        index = {ref: i for i, ref in enumerate(refs)}
        results: list[Any] = [None] * len(items)
        pending = list(refs)
        try:
            while pending:
                finished, pending = ray.wait(pending, num_returns=1)
                for ref in finished:
                    results[index[ref]], cpu = ray.get(ref)
                    self.cpu_seconds += cpu
                    done(index[ref], results[index[ref]])
                    bar.update()
        except BaseException:
            for ref in pending:
                ray.cancel(ref)
            raise
        return results

    def _connect_ray(self) -> Any:
        if self._ray is not None:
            return self._ray
        try:
            import ray
        except ImportError as e:
            raise ValueError(RAY_MISSING) from e
        if not ray.is_initialized():
            if self.ray_address == LOCAL_RAY:
                ray.init(num_cpus=self.workers, include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=self.ray_address, log_to_driver=False)
            self._ray_started = True
        self._ray = ray
        return ray


def add_worker_arguments(parser: Any) -> None:
    """``--workers N`` (default: this machine's cores) and ``--ray [ADDRESS]``; read them with
    :func:`workers_from_args`."""
    from vgpnav_env.arguments import positive_int_arg

    cores = default_workers()
    parser.add_argument(
        "--workers",
        type=positive_int_arg,
        default=cores,
        metavar="N",
        help=f"processes that run episodes / frames in parallel (default: the machine's cores, {cores})",
    )
    parser.add_argument(
        "--ray",
        nargs="?",
        const=LOCAL_RAY,
        default=None,
        metavar="ADDRESS",
        help="run the tasks on a Ray cluster (e.g. auto, ray://host:10001); without ADDRESS a local "
        "Ray instance with --workers CPUs (needs the extra vgpnav-env[distributed])",
    )


def workers_from_args(args: Any, progress: bool = True) -> Workers:
    """The :class:`Workers` of ``--workers`` / ``--ray`` (a one-line ValueError for ``--ray``
    without the ``ray`` package)."""
    if args.ray is not None and importlib.util.find_spec("ray") is None:
        raise ValueError(RAY_MISSING)
    return Workers(args.workers, args.ray, progress=progress)
