"""Navigation agents and their registry (the ``--agent`` choices of ``vgpnav eval navigation``).

:data:`AGENTS` names every agent kind; ``vgpnav_env.eval.navigation.make_agent`` builds them. An
agent string is a name, or ``ppo:PATH`` for a trained policy (a training run directory or a model
``.zip``). Importing this package is light (no env, no torch): the command line reads the registry
to check ``--agent`` before anything runs.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class AgentKind:
    """One registered agent: ``help`` (one line); ``perception``: it drives on VGP-Nav's estimated
    pose and fused map (``--backbone`` applies); ``path``: it is written ``NAME:PATH``."""

    help: str
    perception: bool
    path: bool = False


#: name -> kind, in the order the command line lists them.
AGENTS: dict[str, AgentKind] = {
    "astar": AgentKind("A* on VGP-Nav's estimated pose and fused obstacle map (pixels only)", True),
    "oracle": AgentKind("A* on the TRUE pose and ground-truth map (the upper bound)", False),
    "ppo": AgentKind("a trained PPO policy: ppo:PATH (run directory or model .zip)", False, path=True),
}


def agent_choices() -> str:
    """The allowed ``--agent`` values, e.g. ``astar, oracle, ppo:PATH``."""
    return ", ".join(f"{name}:PATH" if kind.path else name for name, kind in AGENTS.items())


def parse_agent(text: str) -> tuple[str, str | None]:
    """(name, PATH or None) of an agent string; a one-line ValueError for an unknown name or a
    missing / unexpected ``:PATH``."""
    name, sep, path = text.partition(":")
    kind = AGENTS.get(name)
    if kind is None:
        raise ValueError(f"unknown agent {text!r}; allowed: {agent_choices()}")
    if kind.path and not path:
        raise ValueError(f"agent {name!r} needs a path: {name}:PATH")
    if not kind.path and sep:
        raise ValueError(f"agent {name!r} takes no path; allowed: {agent_choices()}")
    return name, path or None
