"""Light setups and tasks for the worker tests (spawned workers import this module, so it imports
nothing heavy)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class CountingSetup:
    """A setup whose state records the process that built it and a fresh token."""

    tag: str

    def __call__(self) -> dict:
        return {"pid": os.getpid(), "token": os.urandom(8).hex(), "tag": self.tag}


def tagged_task(state: dict, item: int) -> tuple[int, int, str, str]:
    return item * item, state["pid"], state["token"], state["tag"]


def failing_task(state: dict, item: int) -> int:
    raise ValueError(f"bad item {item}")


def affinity_task(state: dict, item: int) -> tuple[int, list[int]]:
    return os.getpid(), sorted(os.sched_getaffinity(0))


def noting_task(state: dict, item: int) -> int:
    from vgpnav_env.eval.workers import note

    note(f"item {item} running")
    time.sleep(0.3)  # a task that takes a while: the note is sent long before its result
    return item * item


def threads_task(state: dict, item: int) -> dict:
    """The worker process's thread pools (:func:`thread_report`) and its pid."""
    from vgpnav_env.perception.backbones.threads import thread_report

    return {"pid": os.getpid(), **thread_report()}


def share_task(state: dict, item: int) -> dict:
    """The worker's cores and pool sizes after a note, the point where a task takes a new share."""
    from vgpnav_env.eval.workers import note
    from vgpnav_env.perception.backbones.threads import thread_report

    note(f"item {item}")
    return {"affinity": sorted(os.sched_getaffinity(0)), **thread_report()}


def ordered_task(state: dict, item: int) -> tuple[int, int, int]:
    """(item, pid, how many tasks this worker ran before it): the order tasks started in."""
    started = state.setdefault("started", [])
    started.append(item)
    return item, os.getpid(), len(started) - 1
