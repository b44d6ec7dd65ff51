"""argparse argument types shared by the ``vgpnav`` commands (light: no heavy imports).

A type raises ``argparse.ArgumentTypeError`` with one line saying what was wrong and what is
allowed; the CLI turns it into ``vgpnav: error: ...`` and exit code 2.
"""

from __future__ import annotations

import argparse
import math

#: Largest image (width, height) in pixels a build or an env camera may have.
MAX_IMAGE_SIZE = (1920, 1080)


def size_arg(text: str) -> tuple[int, int]:
    """argparse type for ``WxH`` image sizes (1 <= W <= 1920, 1 <= H <= 1080)."""
    parts = text.lower().split("x")
    max_w, max_h = MAX_IMAGE_SIZE
    allowed = f"allowed: WxH with integers 1 <= W <= {max_w}, 1 <= H <= {max_h}, e.g. 320x240"
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise argparse.ArgumentTypeError(f"malformed size {text!r}; {allowed}")
    w, h = (int(p) for p in parts)
    if not (1 <= w <= max_w and 1 <= h <= max_h):
        raise argparse.ArgumentTypeError(f"size {text!r} out of range; {allowed}")
    return w, h


def seed_arg(text: str) -> int:
    """argparse type for seeds: non-negative integers."""
    try:
        seed = int(text)
    except ValueError:
        seed = -1
    if seed < 0:
        raise argparse.ArgumentTypeError(f"seed must be a non-negative integer, got {text!r}")
    return seed


def _int_at_least(text: str, low: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = low - 1
    if value < low:
        raise argparse.ArgumentTypeError(f"must be {what} integer, got {text!r}")
    return value


def positive_int_arg(text: str) -> int:
    """argparse type for counts that must be at least 1 (episodes, steps, workers, references)."""
    return _int_at_least(text, 1, "a positive")


def positive_float_arg(text: str) -> float:
    """argparse type for a finite number above 0 (rates, thresholds)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def unit_interval_arg(text: str) -> float:
    """argparse type for a share: a number from 0 to 1."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a number from 0 to 1, got {text!r}")
    return value


def count_arg(text: str) -> int:
    """argparse type for counts where 0 means "all" (e.g. ``--queries``): non-negative integers."""
    return _int_at_least(text, 0, "a non-negative")
