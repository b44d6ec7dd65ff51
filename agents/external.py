"""Agents from outside the package: ``--agent MODULE:FACTORY`` (bring your own policy).

``MODULE`` is an importable module (on ``sys.path``: installed, or the working directory) and
``FACTORY`` a callable in it -- a class or a function. The protocol calls it once per worker and
scene as ``FACTORY(env)`` if it takes a parameter, else ``FACTORY()``, and drives what it returns:

- ``act(obs) -> action`` (required): ``obs`` is the observation of the env the agent acts in -- the
  raw point-goal observation ``{"rgb", "goal"}``, or with ``--perception pixels`` VGP-Nav's
  ``{"pose", "goal_rel", "map", "localized"}`` (see ``docs/benchmark.md`` and
  :class:`~vgpnav_env.tasks.env.TaskEnv`); ``action`` an ``int`` of
  :class:`~vgpnav_env.robot.Action` (0 stop, 1 forward, 2 turn left, 3 turn right);
- ``reset(seed=None)`` (optional): called before every episode with the episode's seed (draw any
  randomness from it, so an episode's actions do not depend on the worker that ran it).

``env`` is given for its spaces, the bump sensor (``env.unwrapped.bumped``) and, with perception,
the wrapper's ``fused_map`` and ``pose_state`` (``env.get_wrapper_attr``). An entry must not read
the env's ``info``, true pose, ground-truth map or depth: they are for evaluation.
"""

from __future__ import annotations

import importlib
import inspect
import re
from collections.abc import Callable
from typing import Any

_SPEC = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")


def is_factory_spec(text: str) -> bool:
    """Whether ``text`` is written ``MODULE:FACTORY`` (a dotted module path and a name)."""
    return bool(_SPEC.match(text))


def load_factory(spec: str) -> Callable[..., Any]:
    """The callable ``FACTORY`` of ``MODULE:FACTORY``; ValueError in one line when the module does
    not import or has no such callable."""
    if not is_factory_spec(spec):
        raise ValueError(f"agent {spec!r} is not MODULE:FACTORY (e.g. mypkg.agents:MyAgent)")
    module_name, name = spec.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise ValueError(f"agent {spec!r}: cannot import {module_name} ({e})") from e
    factory = getattr(module, name, None)
    if not callable(factory):
        raise ValueError(f"agent {spec!r}: {module_name} has no callable {name!r}")
    return factory


class ExternalPolicy:
    """The object ``FACTORY`` made, behind the protocol's ``reset(seed)`` / ``act(obs)``."""

    def __init__(self, spec: str, env: Any) -> None:
        factory = load_factory(spec)
        try:
            takes_env = bool(inspect.signature(factory).parameters)
        except (TypeError, ValueError):  # a builtin without a signature
            takes_env = False
        self.agent = factory(env) if takes_env else factory()
        if not callable(getattr(self.agent, "act", None)):
            raise TypeError(f"agent {spec!r} made a {type(self.agent).__name__} without act(obs)")
        self._reset = getattr(self.agent, "reset", None)

    def reset(self, seed: int | None = None) -> None:
        if callable(self._reset):
            try:
                takes_seed = bool(inspect.signature(self._reset).parameters)
            except (TypeError, ValueError):
                takes_seed = False
            self._reset(seed) if takes_seed else self._reset()

    def act(self, obs: Any) -> Any:
        return self.agent.act(obs)
