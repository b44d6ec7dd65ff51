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
    "external": AgentKind(
        "your own agent: MODULE:FACTORY making an object with act(obs) (vgpnav_env.agents.external)",
        False,
        path=True,
    ),
}
#: How an ``external`` agent is written on the command line.
EXTERNAL_FORM = "MODULE:FACTORY"


def agent_choices() -> str:
    """The allowed ``--agent`` values, e.g. ``astar, oracle, ppo:PATH, MODULE:FACTORY``."""
    return ", ".join(
        EXTERNAL_FORM if name == "external" else f"{name}:PATH" if kind.path else name
        for name, kind in AGENTS.items()
    )


def parse_agent(text: str) -> tuple[str, str | None]:
    """(name, PATH or None) of an agent string -- ``("external", "MODULE:FACTORY")`` for an agent
    from outside the package --; a one-line ValueError for an unknown name or a missing /
    unexpected ``:PATH``."""
    from vgpnav_env.agents.external import is_factory_spec

    name, sep, path = text.partition(":")
    kind = AGENTS.get(name)
    if (kind is None or name == "external") and is_factory_spec(text):
        return "external", text
    if kind is None or name == "external":
        raise ValueError(f"unknown agent {text!r}; allowed: {agent_choices()}")
    if kind.path and not path:
        raise ValueError(f"agent {name!r} needs a path: {name}:PATH")
    if not kind.path and sep:
        raise ValueError(f"agent {name!r} takes no path; allowed: {agent_choices()}")
    return name, path or None
