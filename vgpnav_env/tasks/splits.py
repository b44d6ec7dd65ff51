"""Scene splits of the benchmark tasks and the perception's tuning scenes (``splits.yaml``).

A scene id is a scene source as ``vgpnav build`` takes it (``home``, ``home:7``) or
``corpus:NAME``: a real-furniture mesh-scene directory of ``scenes/corpus.yaml``, built into
``$VGPNAV_CACHE/corpus/NAME`` by ``python -m vgpnav_env.scenes.corpus`` (:func:`scene_source`
resolves it). ``STYLE:A..B`` in the file stands for the seeds A to B inclusive.

What may be fitted where is stated at the top of ``splits.yaml``: navigation agents on ``train``,
model selection on ``val``, ``test`` only reported; perception thresholds only on
:func:`perception_tuning_scenes`, every other scene held out (:func:`perception_split`).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path

import yaml

SPLITS_FILE = Path(__file__).parent / "splits.yaml"
SPLIT_NAMES: tuple[str, ...] = ("train", "val", "test")
CORPUS_PREFIX = "corpus:"
_RANGE = re.compile(r"^(?P<style>[a-z]+):(?P<first>\d+)\.\.(?P<last>\d+)$")


def expand_scenes(entries: list[str]) -> tuple[str, ...]:
    """Scene ids of a split's entries (``STYLE:A..B`` expanded), in order; ValueError on a repeat."""
    out: list[str] = []
    for entry in entries:
        m = _RANGE.match(str(entry))
        if m:
            first, last = int(m["first"]), int(m["last"])
            if last < first:
                raise ValueError(f"scene range {entry!r} is empty")
            out += [f"{m['style']}:{seed}" for seed in range(first, last + 1)]
        else:
            out.append(str(entry))
    repeated = sorted({s for s in out if out.count(s) > 1})
    if repeated:
        raise ValueError(f"scenes listed twice in a split: {repeated}")
    return tuple(out)


@lru_cache(maxsize=8)
def _load(path: Path = SPLITS_FILE) -> dict:
    return yaml.safe_load(path.read_text())


def split_sets() -> tuple[str, ...]:
    """The names of the split sets in ``splits.yaml`` (e.g. ``v1``)."""
    return tuple(_load()["splits"])


def scene_splits(name: str | Mapping[str, list[str]]) -> dict[str, tuple[str, ...]]:
    """Split name -> scene ids of the split set ``name`` of ``splits.yaml`` (or of a mapping of
    split name -> entries, a task's own splits); ValueError if unknown, if a scene is in two splits
    or if a split is missing."""
    sets = _load()["splits"]
    if isinstance(name, Mapping):
        entries, name = name, "of the task"
    elif name in sets:
        entries = sets[name]
    else:
        raise ValueError(f"unknown scene split set {name!r}; allowed: {list(sets)}")
    splits = {split: expand_scenes(entries.get(split) or []) for split in SPLIT_NAMES}
    missing = [s for s, scenes in splits.items() if not scenes]
    if missing:
        raise ValueError(f"scene split set {name!r} has no scenes in {missing}")
    for i, a in enumerate(SPLIT_NAMES):
        for b in SPLIT_NAMES[i + 1 :]:
            both = sorted(set(splits[a]) & set(splits[b]))
            if both:
                raise ValueError(f"scene split set {name!r}: {both} in both {a} and {b}")
    return splits


def perception_tuning_scenes() -> tuple[str, ...]:
    """The scenes whose frames perception thresholds and models may be fitted on (issue 28)."""
    return expand_scenes(_load()["perception"]["tuning"])


def perception_split(scene: str) -> str:
    """``"tuning"`` for a perception tuning scene (its id, its build's name: ``home-2`` for
    ``home:2``, or for ``corpus:NAME`` the corpus directory :func:`scene_source` gives), else
    ``"held-out"`` (any other source, including a user's mesh directory)."""
    tuning = perception_tuning_scenes()
    names = set(tuning) | {s.replace(":", "-") for s in tuning}
    if scene in names:
        return "tuning"
    corpus = [s for s in tuning if s.startswith(CORPUS_PREFIX)]
    if corpus and Path(scene).is_dir():
        from vgpnav_env.scenes.corpus import default_corpus_dir

        here = Path(scene).resolve()
        if any(here == (default_corpus_dir() / s[len(CORPUS_PREFIX) :]).resolve() for s in corpus):
            return "tuning"
    return "held-out"


def scene_source(scene: str) -> str:
    """The scene source the env loads for a scene id: ``corpus:NAME`` -> its directory (ValueError
    in one line if it is not built), anything else unchanged."""
    if not scene.startswith(CORPUS_PREFIX):
        return scene
    from vgpnav_env.scenes.corpus import default_corpus_dir

    name = scene[len(CORPUS_PREFIX) :]
    path = default_corpus_dir() / name
    if not (path / "layout.json").is_file():
        raise ValueError(
            f"corpus scene {name!r} is not built at {path}: "
            f"run python -m vgpnav_env.scenes.corpus --scene {name}"
        )
    return str(path)
