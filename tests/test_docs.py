"""The documentation runs: the README's Python example, its commands, and every docs page's code.

- The README's Python example runs as written, on the session's ``home`` build (``conftest``): the
  cache points at it and the wrapper opens the session's database.
- Every ``vgpnav`` command the README names prints its ``--help``; every full ``vgpnav`` command
  line in its shell blocks parses.
- Every ``python`` block of ``docs/*.md`` runs, page by page (one namespace per page, in order), in
  one fresh process: pages may register measures and write files, which must not leak into this one.
- Every relative link of the README, ``docs/`` and ``benchmarks/`` pages names a file or folder
  that exists, and its ``#anchor``, if any, a heading of a Markdown target.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vgpnav_env import cli

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
PAGES = sorted((ROOT / "docs").glob("*.md"))
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def blocks(text: str, language: str) -> list[str]:
    """The contents of the fenced code blocks of ``language`` in ``text``, in order."""
    return [body for lang, body in FENCE.findall(text) if lang == language]


def readme_commands() -> list[list[str]]:
    """Each ``vgpnav`` command the README names (``eval navigation``, ``build``, ...), once."""
    groups = "|".join(cli.GROUPS)
    found = re.findall(rf"`vgpnav ((?:{groups}) [a-z]+|[a-z]+)\b", README)
    return [name.split() for name in dict.fromkeys(found)]


def readme_command_lines() -> list[list[str]]:
    """The full ``vgpnav`` command lines of the README: those of its shell blocks (after any
    ``&&``), then the inline ones with an ``--out`` (the results table's; ``ppo:PATH`` agents need a
    trained policy to parse and are left out)."""
    lines = [line for body in blocks(README, "bash") for line in body.splitlines()]
    parts = [part for line in lines for part in line.split("&&")]
    parts += [span for span in re.findall(r"`(vgpnav [^`]*--out[^`]*)`", README) if "ppo:" not in span]
    return [words[1:] for words in (shlex.split(p, comments=True) for p in parts) if words[:1] == ["vgpnav"]]


LINK = re.compile(r"\]\(([^)\s]+)\)")


def anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def markdown_anchors(path: Path) -> set[str]:
    return {anchor(h) for h in re.findall(r"^#+ (.*)$", FENCE.sub("", path.read_text()), re.M)}


@pytest.mark.parametrize(
    "page",
    [ROOT / "README.md", *PAGES, *sorted((ROOT / "benchmarks").glob("**/*.md"))],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_relative_links_resolve(page: Path) -> None:
    broken, text = [], FENCE.sub("", page.read_text())
    assert LINK.findall(text) or "](" not in text, "the link pattern found none of the page's links"
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto
        path, _, fragment = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(target)
        elif fragment and file.suffix == ".md" and fragment not in markdown_anchors(file):
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: broken links {broken}"


def test_readme_is_short_and_names_every_command() -> None:
    assert len(README.encode()) <= 15_000
    assert {" ".join(c) for c in readme_commands()} == set(cli.COMMANDS)
    assert ["eval", "navigation", "home", "--episodes", "3"] == readme_command_lines()[0][:5]
    assert "python -m pytest -q\n" in blocks(README, "bash")[0]


def test_readme_leaderboard_is_the_bench_results_files(capsys) -> None:
    """The README's leaderboard is what ``vgpnav report ... --leaderboard`` prints for the results
    files it cites, row for row."""
    table = re.search(r"<!-- leaderboard:begin -->\n(.*?)\n<!-- leaderboard:end -->", README, re.S)
    assert table is not None
    bench = ROOT / "benchmarks" / "pointnav-v1"
    runs = sorted(str(d) for d in bench.glob("*/") if (d / "report.json").exists())
    assert len(runs) >= 3
    assert cli.main(["report", *runs, "--leaderboard"]) == 0
    printed = capsys.readouterr().out.strip()
    assert printed == table.group(1).strip()
    assert len(printed.splitlines()) == len(runs) + 2


def test_report_leaderboard_refuses_runs_without_bench_results(tmp_path, capsys) -> None:
    (tmp_path / "report.json").write_text('{"settings": {}}')
    assert cli.main(["report", str(tmp_path), "--leaderboard"]) == 2
    assert "none of the directories holds a vgpnav bench results file" in capsys.readouterr().err


@pytest.mark.parametrize("command", readme_commands(), ids=" ".join)
def test_readme_command_help(command: list[str]) -> None:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exit_:
        cli.main([*command, "--help"])
    assert exit_.value.code == 0
    assert out.getvalue().startswith(f"usage: vgpnav {' '.join(command)}")


@pytest.mark.parametrize("argv", readme_command_lines(), ids=" ".join)
def test_readme_command_lines_parse(argv: list[str]) -> None:
    args = cli.build_parser(argv).parse_args(argv)
    assert args._command == (" ".join(argv[:2]) if argv[0] in cli.GROUPS else argv[0])


@pytest.mark.slow
def test_readme_python_example(home_build, home_database, monkeypatch, tmp_path, capsys) -> None:
    """The example as written; ``home_build`` is the cached build of its scene and image size."""
    import vgpnav_env.wrappers

    (example,) = blocks(README, "python")
    assert "image_size=(240, 180)" in example  # conftest.HOME_SIZE: the session's home build
    monkeypatch.setenv("VGPNAV_CACHE", str(home_build.parent))
    monkeypatch.setattr(vgpnav_env.wrappers, "open_database", lambda path, config=None: home_database)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(example, "README.md", "exec"), namespace)
    env, obs, info, frame = (namespace[k] for k in ("env", "obs", "info", "frame"))
    try:
        assert set(obs) == {"pose", "goal_rel", "map", "localized"}
        assert frame.ndim == 3 and frame.dtype == np.uint8
        # The estimate tracks the robot: within 0.5 m of the true position after the loop.
        assert np.linalg.norm(obs["pose"][:2] - np.asarray(info["pose"])[:2]) < 0.5
        assert "estimated pose" in capsys.readouterr().out
    finally:
        env.close()


RUNNER = """
import os, sys, traceback
os.chdir(sys.argv[1])
failed = 0
for page in sys.argv[2:]:
    text = open(page).read()
    import re
    fence = re.compile(r"^```(\\w*)[^\\n]*\\n(.*?)^```", re.S | re.M)
    namespace = {"__name__": "__docs__"}
    for i, (lang, body) in enumerate(fence.findall(text)):
        if lang != "python":
            continue
        try:
            exec(compile(body, f"{page} block {i}", "exec"), namespace)
        except Exception:
            failed += 1
            print(f"FAILED: {page} block {i}", file=sys.stderr)
            traceback.print_exc()
sys.exit(1 if failed else 0)
"""


@pytest.mark.slow
def test_docs_pages_code_runs(tmp_path) -> None:
    pages = [str(p) for p in PAGES if blocks(p.read_text(), "python")]
    assert len(pages) >= 4
    done = subprocess.run(
        [sys.executable, "-c", RUNNER, str(tmp_path), *pages], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-4000:]
    assert (tmp_path / "room_01" / "layout.json").is_file()  # the scenes page's worked example
