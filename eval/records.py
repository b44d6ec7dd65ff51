"""The benchmark's on-disk records: the episode log (JSON lines) and the versioned results file.

Episode log ``episodes.jsonl``: line 1 is a header (``{"header": {...}}``: the run's identity --
task, split, episode file checksum, agent and perception settings); every further line is one
finished episode's record, appended and flushed as the episode ends. A run that was stopped
loses at most the line being written (a torn last line is ignored on reading), and
``--resume`` skips the episodes the log holds when its header matches.

Results file ``report.json`` (:data:`RESULTS_SCHEMA`, ``schema_version``
:data:`SCHEMA_VERSION`): the task, split, episode file, package version, git commit, settings,
summary metrics (top level, as every ``vgpnav eval`` report, so ``vgpnav report`` compares them),
per-scene summaries and per-episode records, plus ``run`` (workers, wall and CPU time, dates:
how it ran, not what it measured). ``digest`` is the SHA-256 of the canonical JSON of everything
but ``run`` and ``digest``: two runs gave the same results exactly when their digests are equal
(e.g. a resumed run against an uninterrupted one, ``--workers 2`` against ``--workers 1``).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

SCHEMA = "vgpnav-bench-results"
SCHEMA_VERSION = 1
LOG_NAME = "episodes.jsonl"
#: Top-level keys left out of :func:`results_digest` (how the run went, not what it measured).
UNCOMPARED = ("run", "digest")

_NUMBER_OR_NULL = {"type": ["number", "null"]}
_EPISODE = {
    "type": "object",
    "required": ["index", "episode_id", "scene_id", "seed", "status"],
    "properties": {
        "index": {"type": "integer", "minimum": 0},
        "episode_id": {"type": "string"},
        "scene_id": {"type": "string"},
        "seed": {"type": "integer", "minimum": 0},
        "status": {"enum": ["ok", "error"]},
        "error": {"type": ["string", "null"]},
        "success": {"type": ["boolean", "number", "null"]},
        "spl": _NUMBER_OR_NULL,
        "soft_spl": _NUMBER_OR_NULL,
        "failure": {"type": ["string", "null"]},
        "trajectory_sha256": {"type": ["string", "null"]},
    },
}
#: JSON Schema (draft 2020-12 subset) of the results file.
RESULTS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "vgpnav bench results",
    "type": "object",
    "required": [
        "schema",
        "schema_version",
        "task",
        "split",
        "episode_file",
        "package_version",
        "git_commit",
        "settings",
        "complete",
        "episodes",
        "errors",
        "success_rate",
        "spl",
        "soft_spl",
        "scenes",
        "records",
        "run",
        "digest",
    ],  # fmt: skip
    "properties": {
        "schema": {"const": SCHEMA},
        "schema_version": {"const": SCHEMA_VERSION},
        "task": {
            "type": "object",
            "required": ["name", "version", "sha256"],
            "properties": {
                "name": {"type": "string"},
                "version": {"type": "integer"},
                "sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
            },
        },
        "split": {"enum": ["train", "val", "test"]},
        "episode_file": {
            "type": "object",
            "required": ["sha256", "episodes"],
            "properties": {"sha256": {"type": "string"}, "episodes": {"type": "integer"}},
        },
        "package_version": {"type": "string"},
        "git_commit": {"type": ["string", "null"]},
        "settings": {"type": "object", "required": ["agent", "backbone"]},
        "complete": {"type": "boolean"},
        "limit": {"type": ["integer", "null"]},
        "episodes": {"type": "integer", "minimum": 0},
        "errors": {"type": "integer", "minimum": 0},
        "success_rate": _NUMBER_OR_NULL,
        "spl": _NUMBER_OR_NULL,
        "soft_spl": _NUMBER_OR_NULL,
        "scenes": {"type": "object"},
        "records": {"type": "array", "items": _EPISODE},
        "run": {"type": "object", "required": ["workers", "wall_s", "cpu_s"]},
        "digest": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
    },
}


def canonical(data: Any) -> bytes:
    """The canonical JSON bytes of ``data`` (sorted keys, no spaces, shortest float repr)."""
    return json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def json_safe(data: Any) -> Any:
    """``data`` with every non-finite float (nan: a frame without an estimate) as None, so that
    it is standard JSON."""
    if isinstance(data, float) and not math.isfinite(data):
        return None
    if isinstance(data, dict):
        return {k: json_safe(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_safe(v) for v in data]
    return data


def results_digest(results: dict[str, Any]) -> str:
    """SHA-256 of the compared part of a results file (module docstring)."""
    return hashlib.sha256(canonical({k: v for k, v in results.items() if k not in UNCOMPARED})).hexdigest()


class SchemaError(ValueError):
    """A results file does not follow :data:`RESULTS_SCHEMA`."""


def validate_results(results: Any) -> None:
    """Raise :class:`SchemaError` (one line: where and what) unless ``results`` follows
    :data:`RESULTS_SCHEMA` and its ``digest`` matches; uses ``jsonschema`` when installed, else
    the subset of JSON Schema the schema uses (type, const, enum, required, properties, items,
    minimum, pattern)."""
    try:
        import jsonschema
    except ImportError:
        _check(results, RESULTS_SCHEMA, "$")
    else:
        error = jsonschema.exceptions.best_match(
            jsonschema.Draft202012Validator(RESULTS_SCHEMA).iter_errors(results)
        )
        if error is not None:
            where = "$" + "".join(f"[{p!r}]" for p in error.absolute_path)
            raise SchemaError(f"{where}: {error.message}")
    if results["digest"] != results_digest(results):
        raise SchemaError("$['digest']: does not match the file's content (edited after the run?)")


_TYPES = {
    "object": dict,
    "array": list,
    "string": str,
    "integer": int,
    "number": (int, float),
    "boolean": bool,
    "null": type(None),
}


def _is(value: Any, name: str) -> bool:
    if name in ("integer", "number") and isinstance(value, bool):
        return False
    return isinstance(value, _TYPES[name])


def _check(value: Any, schema: dict[str, Any], where: str) -> None:
    """The JSON Schema subset of :func:`validate_results` without ``jsonschema``."""
    import re

    types = schema.get("type")
    if types is not None and not any(_is(value, t) for t in ([types] if isinstance(types, str) else types)):
        raise SchemaError(f"{where}: {value!r} is not of type {types}")
    if "const" in schema and value != schema["const"]:
        raise SchemaError(f"{where}: {value!r} is not {schema['const']!r}")
    if "enum" in schema and value not in schema["enum"]:
        raise SchemaError(f"{where}: {value!r} is not one of {schema['enum']}")
    if "minimum" in schema and value < schema["minimum"]:
        raise SchemaError(f"{where}: {value!r} is less than {schema['minimum']}")
    if "pattern" in schema and not re.search(schema["pattern"], value):
        raise SchemaError(f"{where}: {value!r} does not match {schema['pattern']!r}")
    if isinstance(value, dict):
        for key in schema.get("required", []):
            if key not in value:
                raise SchemaError(f"{where}: {key!r} is a required property")
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                _check(value[key], sub, f"{where}[{key!r}]")
    if isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            _check(item, schema["items"], f"{where}[{i}]")


class EpisodeLog:
    """The append-only episode log of a run directory (module docstring)."""

    def __init__(self, directory: Path) -> None:
        self.path = Path(directory) / LOG_NAME

    def read(self) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
        """(header or None, records) of the log; a torn last line is left out."""
        if not self.path.is_file():
            return None, []
        header, records = None, []
        for line in self.path.read_text().splitlines():
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                continue  # the line being written when the run stopped
            if "header" in entry:
                header = entry["header"]
            else:
                records.append(entry)
        return header, records

    def start(self, header: dict[str, Any], resume: bool) -> list[dict[str, Any]]:
        """Begin a run: with ``resume`` the finished records of a log with the same header (a
        one-line ValueError if it has another); without, a new log (ValueError if one exists)."""
        old_header, records = self.read()
        if self.path.is_file() and not resume:
            raise ValueError(
                f"{self.path} exists: add --resume to continue that run, or choose another --out"
            )
        if resume and old_header is not None:
            if canonical(old_header) != canonical(header):
                changed = sorted(k for k in {*header, *old_header} if header.get(k) != old_header.get(k))
                raise ValueError(f"--resume: {self.path} is a run with other settings ({', '.join(changed)})")
            self._rewrite(header, records)  # drops a torn last line
            return records
        self._rewrite(header, [])
        return []

    def _rewrite(self, header: dict[str, Any], records: list[dict[str, Any]]) -> None:
        from vgpnav_env.atomic import atomic_write

        self.path.parent.mkdir(parents=True, exist_ok=True)
        lines = [canonical({"header": header}), *(canonical(r) for r in records)]
        atomic_write(self.path, lambda f: f.write(b"".join(line + b"\n" for line in lines)))

    def append(self, record: dict[str, Any]) -> None:
        """Append one record and flush it to disk."""
        with self.path.open("ab") as f:
            f.write(canonical(record) + b"\n")
            f.flush()
            os.fsync(f.fileno())
