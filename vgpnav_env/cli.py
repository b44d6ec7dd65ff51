"""The ``vgpnav`` command line: ``vgpnav build | eval <protocol> | calibrate | train <algo> | report``.

Commands live in their own modules, listed in :data:`COMMANDS` and imported only when invoked
(so ``vgpnav --help`` stays fast and one broken command cannot break the others). A command
module exposes::

    add_arguments(parser: argparse.ArgumentParser) -> None
    run(args: argparse.Namespace) -> int            # exit code

To add a command, add one line to :data:`COMMANDS`: ``"eval localization": ("module", "help")``
(two words = a command inside a group). Shared argument types (``size_arg``, ``seed_arg``) are in
:mod:`vgpnav_env.arguments`, so command modules never import this dispatcher. Errors in user
input exit with status 2 and one line ``vgpnav: error: ...`` on stderr; ``-v`` / ``-vv`` log
progress / debug details to stderr.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from typing import NoReturn

#: Command name ("build", or "group name") -> (module path, one-line help).
COMMANDS: dict[str, tuple[str, str]] = {
    "build": ("vgpnav_env.build", "render and save a scene's database and query runs"),
    "eval localization": ("vgpnav_env.eval.localization", "median pose error and recall of VGP-Nav"),
    "eval perception": ("vgpnav_env.eval.perception", "metric perception Acc / Comp / Overall"),
    "eval timing": ("vgpnav_env.eval.timing", "seconds per frame of every perception module"),
    "eval ablations": ("vgpnav_env.eval.ablations", "paper Tables IV and V: retrieval, averaging, scale"),
    "eval navigation": (
        "vgpnav_env.eval.navigation",
        "point-goal success rate, SPL and soft SPL of an agent",
    ),
    "calibrate": (
        "vgpnav_env.eval.calibrate",
        "fit the privileged 'model' perception (RL at speed) to a classical localization run",
    ),
    "train ppo": ("vgpnav_env.agents.ppo", "train PPO (stable-baselines3) on VGP-Nav observations"),
    "report": ("vgpnav_env.eval.compare", "put several eval runs side by side (tables and plots)"),
    "episodes generate": ("vgpnav_env.tasks.episodes", "write a task split's fixed episode file"),
    "bench": ("vgpnav_env.eval.bench", "run a versioned task's split: one results file (vgpnav report)"),
}
#: One-line help of command groups.
GROUPS: dict[str, str] = {
    "eval": "run a benchmark protocol and write its report",
    "train": "train a navigation policy",
    "episodes": "a benchmark task's fixed episode datasets",
}
PROG = "vgpnav"


class CliError(Exception):
    """A user-facing error: the CLI prints ``vgpnav: error: <message>`` and exits with ``code``."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one line on stderr: ``vgpnav: error: ...`` (exit 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{PROG}: error: {message} (see '{self.prog} --help')\n")


def _command_help(group: str | None) -> dict[str, str]:
    """Commands (leaf names) directly under ``group`` (None: top level), with their help."""
    out: dict[str, str] = {}
    for name, (_, help_text) in COMMANDS.items():
        words = name.split()
        if group is None and len(words) == 1:
            out[words[0]] = help_text
        elif group is not None and len(words) == 2 and words[0] == group:
            out[words[1]] = help_text
    return out


def _selected(argv: Sequence[str]) -> str | None:
    """The registered command named by the leading positional words of ``argv``, if any."""
    words = [a for a in argv if not a.startswith("-")][:2]
    for n in (2, 1):
        name = " ".join(words[:n])
        if len(words) >= n and name in COMMANDS:
            return name
    return None


def _add_command(action: argparse._SubParsersAction, name: str, selected: str | None) -> None:
    module, help_text = COMMANDS[name]
    sub = action.add_parser(name.split()[-1], help=help_text, description=help_text)
    sub.set_defaults(_command=name)
    if name == selected:
        try:
            imported = importlib.import_module(module)
        except ImportError as e:
            sub.error(f"command {name!r} is unavailable: cannot import {module} ({e})")
        imported.add_arguments(sub)


def build_parser(argv: Sequence[str] = ()) -> argparse.ArgumentParser:
    """The ``vgpnav`` parser; only the command selected by ``argv`` gets its arguments (imported)."""
    parser = _Parser(prog=PROG, description="vgpnav-env: monocular metric-aware navigation benchmark.")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="log to stderr (-v info, -vv debug)"
    )
    top = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    selected = _selected(argv)
    for name in COMMANDS:  # top-level commands first, then the groups
        if " " not in name:
            _add_command(top, name, selected)
    leaves: dict[str, argparse._SubParsersAction] = {}
    for group, help_text in GROUPS.items():
        if _command_help(group):
            sub = top.add_parser(group, help=help_text, description=help_text)
            leaves[group] = sub.add_subparsers(dest="subcommand", metavar="NAME", required=True)
    for name in COMMANDS:
        if " " in name:
            _add_command(leaves[name.split()[0]], name, selected)
    return parser


def _configure_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity == 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vgpnav`` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser(argv).parse_args(argv)
    _configure_logging(args.verbose)
    from vgpnav_env.perception.backbones.threads import configure_threads

    configure_threads()  # this process's pools; worker processes size theirs at their start
    module = importlib.import_module(COMMANDS[args._command][0])
    try:
        return int(module.run(args))
    except CliError as e:
        code, message = e.code, str(e)
    except ValueError as e:  # bad input found while running (unknown scene, malformed spec, ...)
        code, message = 2, str(e)
    except OSError as e:
        code, message = 1, f"{e.strerror or e}: {e.filename}" if e.filename else str(e)
    except KeyboardInterrupt:
        code, message = 130, "interrupted"
    logging.getLogger(__name__).debug("command failed", exc_info=True)
    sys.stderr.write(f"{PROG}: error: {' '.join(message.split())}\n")
    return code


if __name__ == "__main__":
    sys.exit(main())
