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
