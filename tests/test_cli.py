"""The ``vgpnav`` command line: plug-in registry, one-line errors, nothing half-written."""

from __future__ import annotations

import argparse
import subprocess
import sys
import types
from pathlib import Path

import pytest

from vgpnav_env import cli
from vgpnav_env.arguments import size_arg


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    try:
        code = cli.main(argv)
    except SystemExit as e:
        code = int(e.code)
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("vgpnav: error: ")
    return lines[0]


def test_help_lists_commands_without_importing_them(capsys: pytest.CaptureFixture[str]) -> None:
    sys.modules.pop("vgpnav_env.build", None)
    code, out, _ = _run(["--help"], capsys)
    assert code == 0
    assert "build" in out
    assert "vgpnav_env.build" not in sys.modules  # commands are imported only when invoked


def test_registered_command_group(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    module = types.ModuleType("vgpnav_fake_protocol")

    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--episodes", type=int, default=3)

    def run(args: argparse.Namespace) -> int:
        sys.stdout.write(f"ran {args._command} with {args.episodes}\n")
        return 0 if args.episodes > 0 else 1

    module.add_arguments, module.run = add_arguments, run
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setitem(cli.COMMANDS, "eval fake", (module.__name__, "a fake protocol"))
    assert _run(["eval", "fake", "--episodes", "5"], capsys)[:2] == (0, "ran eval fake with 5\n")
    assert _run(["-v", "eval", "fake", "--episodes", "0"], capsys)[0] == 1
    code, out, _ = _run(["eval", "--help"], capsys)
    assert code == 0 and "fake" in out and "a fake protocol" in out
    code, _, err = _run(["eval", "nope"], capsys)
    assert code == 2 and "invalid choice: 'nope'" in _one_error_line(err)


def test_value_errors_from_commands_are_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    module = types.ModuleType("vgpnav_fake_failing")
    module.add_arguments = lambda parser: None

    def run(args: argparse.Namespace) -> int:
        raise ValueError("bad thing\n  spread over lines")

    module.run = run
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setitem(cli.COMMANDS, "train fake", (module.__name__, "fails"))
    code, _, err = _run(["train", "fake"], capsys)
    assert code == 2
    assert _one_error_line(err) == "vgpnav: error: bad thing spread over lines"


@pytest.mark.parametrize(
    "text", ["32x", "0x240", "4000x3000", "320x0", "abc", "320*240", "-3x2", "320x240x3"]
)
def test_bad_size(text: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(["build", "home", "--out", str(tmp_path / "out"), f"--size={text}"], capsys)
    line = _one_error_line(err)
    assert code == 2
    assert "--size" in line and repr(text) in line
    assert "1 <= W <= 1920, 1 <= H <= 1080" in line
    assert not (tmp_path / "out").exists()


def test_size_arg_parses() -> None:
    assert size_arg("320x240") == (320, 240)
    assert size_arg("1920X1080") == (1920, 1080)


def test_command_modules_do_not_import_the_dispatcher() -> None:
    script = (
        "import argparse, importlib, sys\n"
        "from vgpnav_env.cli import COMMANDS\n"
        "del sys.modules['vgpnav_env.cli']\n"
        "for module, _ in COMMANDS.values():\n"
        "    importlib.import_module(module).add_arguments(argparse.ArgumentParser())\n"
        "assert 'vgpnav_env.cli' not in sys.modules, 'a command module imports vgpnav_env.cli'\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True)


@pytest.mark.parametrize("text", ["-1", "1.5", "abc", ""])
def test_bad_seed(text: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(["build", "home", "--out", str(tmp_path / "out"), f"--seed={text}"], capsys)
    line = _one_error_line(err)
    assert code == 2 and "seed must be a non-negative integer" in line and repr(text) in line
    assert not (tmp_path / "out").exists()


def test_unknown_texture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(["build", "home", "--out", str(tmp_path / "out"), "--texture", "shiny"], capsys)
    line = _one_error_line(err)
    assert code == 2 and "'shiny'" in line and "realistic" in line
    assert not (tmp_path / "out").exists()


def test_unknown_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(["build", "nosuchscene", "--out", str(tmp_path / "out")], capsys)
    line = _one_error_line(err)
    assert code == 2 and "'nosuchscene'" in line and "home" in line and "hospital" in line
    assert list(tmp_path.iterdir()) == []  # nothing written, not even a temp directory


def test_malformed_spec_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = tmp_path / "broken.yaml"
    spec.write_text("name: broken\nrooms:\n  - name: a\n    rect: [0, 0, oops]\n")
    out = tmp_path / "out"
    code, _, err = _run(["build", str(spec), "--out", str(out), "--quiet"], capsys)
    line = _one_error_line(err)
    assert code == 2 and "broken" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.yaml"]


def test_console_script_error_is_one_line(tmp_path: Path) -> None:
    """The installed entry point: real stderr, real exit code."""
    proc = subprocess.run(
        [sys.executable, "-m", "vgpnav_env.cli", "build", "home", "--size", "0x240"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    _one_error_line(proc.stderr)
    assert proc.stdout == ""


def test_build_refuses_foreign_out_dir(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    code, _, err = _run(["build", "home", "--out", str(out), "--quiet"], capsys)
    line = _one_error_line(err)
    assert code == 1 and "refusing to replace" in line and str(out) in line
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_unimportable_command_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(cli.COMMANDS, "eval missing", ("vgpnav_env.eval.no_such_module", "not written yet"))
    code, _, err = _run(["eval", "missing"], capsys)
    assert code == 2 and "command 'eval missing' is unavailable" in _one_error_line(err)


QUERY_PROTOCOLS = ("localization", "perception", "timing", "ablations")
#: (command line, a phrase the one error line must hold); MISSING / EMPTY are replaced by a missing
#: path and an empty directory; every line gets ``--out OUT``.
BAD_INPUTS = [
    ("build home --size 0x240", "--size"),
    ("build home --seed -1", "seed must be a non-negative integer"),
    ("build home --texture shiny", "'shiny'"),
    ("build nosuchscene", "'nosuchscene'"),
    *((f"eval {p} home --k 0", "--k: must be a positive integer") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --queries -1", "--queries: must be a non-negative integer") for p in QUERY_PROTOCOLS),
    *((f"eval {p} nosuchscene", "'nosuchscene'") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --build MISSING", "no such build directory") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --build EMPTY", "summary.json") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --backbone nope", "invalid choice: 'nope'") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --backbone learned", "needs --model") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --model m:f", "for --backbone learned") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --size 10", "--size") for p in QUERY_PROTOCOLS),
    *((f"eval {p} home --workers 0", "--workers: must be a positive integer") for p in QUERY_PROTOCOLS[:2]),
    ("eval ablations home --workers 0", "--workers: must be a positive integer"),
    ("eval localization home --fallback-min-pairs 0", "--fallback-min-pairs: must be a positive integer"),
    ("eval localization home --switch-share 1.5", "--switch-share: must be a number from 0 to 1"),
    (
        "eval localization home --backbone learned --model m:f --weights MISSING --fallback-min-pairs 5",
        "are for --backbone classical",
    ),
    ("eval localization home --retrieval nope", "invalid choice: 'nope'"),
    ("eval localization home --averaging nope", "invalid choice: 'nope'"),
    ("eval perception home --texture shiny", "invalid choice: 'shiny'"),
    ("eval navigation home --agent greedy", "unknown agent 'greedy'; allowed: astar, oracle, ppo:PATH"),
    ("eval navigation home --agent ppo:MISSING", "no PPO model"),
    ("eval navigation home --agent ppo", "needs a path"),
    ("eval navigation home --agent oracle:x", "takes no path"),
    ("eval navigation home --episodes 0", "--episodes: must be a positive integer"),
    ("eval navigation home --max-steps 0", "--max-steps: must be a positive integer"),
    ("eval navigation home --workers 0", "--workers: must be a positive integer"),
    ("eval navigation home --backbone nope", "invalid choice: 'nope'"),
    ("eval navigation home --seed -2", "seed must be a non-negative integer"),
    ("eval navigation nosuchscene --agent oracle", "'nosuchscene'"),
    ("eval navigation home --database MISSING", "no such build directory"),
    ("train ppo home --steps 0", "--steps: must be a positive integer"),
    ("train ppo home --envs 0", "--envs: must be a positive integer"),
    ("train ppo nosuchscene --steps 10", "'nosuchscene'"),
    ("train ppo home --perception learned", "PPO trains with --perception model, classical or simulated"),
    ("train ppo home --perception nope", "invalid choice: 'nope'"),
    ("train ppo home --perception simulated --database MISSING", "no such build directory"),
    ("train ppo home --guidance path", "--guidance needs --perception"),
    ("train ppo home --perception model --pretrain -1", "--pretrain needs --perception"),
    ("train ppo home --randomize", "--randomize needs --perception model"),
    ("train ppo home --perception model --init MISSING", "no PPO model"),
    ("train ppo home --perception model --init MISSING --resume", "--init starts a new run"),
    ("train ppo home --perception model --learning-rate 0", "--learning-rate: must be a positive number"),
    ("train ppo home --perception model --target-kl nan", "--target-kl: must be a positive number"),
    ("train ppo home --perception model --resume --target-kl 0.02", "saved PPO settings"),
    ("eval navigation home --perception nope", "invalid choice: 'nope'"),
    ("eval navigation home --actions nope", "invalid choice: 'nope'"),
    ("eval navigation home --agent oracle --actions sampled", "applies to ppo:PATH agents"),
    ("calibrate home", "--out must be a .json file"),
    ("calibrate home --backbone nope", "invalid choice: 'nope'"),
    ("report MISSING", "no report.json"),
    ("report EMPTY", "no report.json"),
    ("bench nonesuch-v9", "unknown task 'nonesuch-v9'"),
    ("bench pointnav-v1 --split dev", "invalid choice: 'dev'"),
    ("bench pointnav-v1 --agent no_such_module_xyz:Agent", "cannot import no_such_module_xyz"),
    ("bench pointnav-v1 --agent bench_agents:Nothing", "has no callable 'Nothing'"),
    ("bench pointnav-v1 --limit 0", "--limit: must be a positive integer"),
    ("bench pointnav-v1 --database home=MISSING", "expected SCENE=DIR"),
    ("episodes generate nonesuch-v9 --split test", "unknown task 'nonesuch-v9'"),
    ("episodes generate pointnav-v1", "--split"),
    ("train ppo --steps 10", "give one or more SCENEs or --task"),
    ("train ppo home --task pointnav-v1", "SCENEs or --task, not both"),
]


@pytest.mark.parametrize(("line", "phrase"), BAD_INPUTS, ids=[line for line, _ in BAD_INPUTS])
def test_every_command_refuses_bad_input_in_one_line_and_writes_nothing(
    line: str,
    phrase: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    cache, empty, out = tmp_path / "cache", tmp_path / "empty", tmp_path / "out"
    monkeypatch.setenv("VGPNAV_CACHE", str(cache))
    empty.mkdir()
    words = line.replace("MISSING", str(tmp_path / "missing")).replace("EMPTY", str(empty)).split()
    code, stdout, err = _run([*words, "--out", str(out)], capsys)
    assert code == 2, err
    assert phrase in _one_error_line(err)
    assert stdout == ""
    assert not out.exists() and not cache.exists() and list(empty.iterdir()) == []


def test_every_command_is_in_the_bad_input_table() -> None:
    groups = ("eval", "train", "episodes")
    tested = {" ".join(line.split()[:2]) if line.startswith(groups) else line.split()[0]
              for line, _ in BAD_INPUTS}  # fmt: skip
    assert tested == set(cli.COMMANDS)


def test_fallback_flags_reach_the_classical_backbone_and_its_report_line() -> None:
    from eval.perception_runs import add_backbone_arguments, backbone_options, classical_features

    parser = argparse.ArgumentParser()
    add_backbone_arguments(parser)
    options = backbone_options(parser.parse_args(["--fallback-pairs", "6", "--fallback-min-pairs", "5"]))
    assert options == {"fallback_pairs": 6, "fallback_min_pairs": 5}
    assert backbone_options(parser.parse_args(["--switch-share", "0"])) == {"switch_share": 0.0}
    text = classical_features(options)
    assert text == "rootsift + nearest, XFeat + LighterGlue fallback (6 pairs when fewer than 5 pass)"
    assert "fallback" not in classical_features({"fallback_pairs": 0})
