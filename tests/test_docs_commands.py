"""Every complete `cpgjax` command line in README.md and docs/ still works.

- **Parsed**: each parses with today's parser and passes the checks that span options (no option of the other robot
  or mode), its files replaced by plain paths: a renamed, removed or refused option fails here.
- **Run**: each is then run, in the order its document gives it, in a fresh folder per document, where the files
  the document shows (a TOML block whose first line is `# file: NAME`) are saved first (so a command that
  reads what an earlier one wrote, `deploy --params sim-opt/best_params.json` after `deploy --optimize --log-dir
  sim-opt`, finds it or fails), made short by options appended after the documented ones (the last given
  wins): a study with `--dry-run` (every check of the run, its output folder included, without computing: the paper
  studies take minutes to hours); `deploy --robot sim` in lockstep pacing, a replay of 1 s, `--optimize` with 2
  trials of 0.2 + 0.3 s, `calibrate` with stands of a few tenths of a second; `walk` with 1 trial. A command that
  would reach a real Go1 (any `deploy` without `--robot sim`) is parsed, never run. Command lines with placeholders
  (`<out>`, `FILE`, `N`, `...`) are skipped. A command whose shortened form is one already run in the same folder
  (`deploy --robot sim --duration-s 10` and `--duration-s 9.5` both become a 1 s replay) is not run again.
"""

import os
import pathlib
import re
import shlex
import subprocess
import sys

import pytest

from cpgjax import cli
from cpgjax.deployment import deploy
from cpgjax.deployment.options import CalibrateOptions, DeployOptions

ROOT = pathlib.Path(__file__).resolve().parent.parent
PLACEHOLDER = re.compile(r"<|\[|\||\.\.\.|…|\b(FILE|N|NAME|DIR|FOLDER|CALIBRATION)\b")


def commands_in_order(path: pathlib.Path) -> list[str]:
    """Every complete `cpgjax <command> <option>…` of one document, in the order the document gives them (in a code
    block or a code span), without repeats."""
    found = []
    for span in re.finditer(r"```[a-z]*\n(.*?)```|`([^`\n]+)`", path.read_text(), re.S):
        for line in (span.group(1) or span.group(2)).splitlines():
            line = line.split("#")[0].strip().removesuffix("&").strip()
            m = re.match(r"^(?:\.venv/bin/)?cpgjax (walk|study|optimize|show|demo|deploy)(?=\s|$)(.*)$", line)
            if m and m.group(2).strip() not in ("", "calibrate") and not PLACEHOLDER.search(line):
                command = line.removeprefix(".venv/bin/")
                if command not in found:
                    found.append(command)
    return found


def files_in(path: pathlib.Path) -> dict[str, str]:
    """The files a document writes out for its commands: each TOML block whose first line is `# file: NAME`."""
    return {m.group(1): m.group(2) for m in re.finditer(r"```toml\n# file: (\S+)\n(.*?)```", path.read_text(), re.S)}


DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
COMMANDS = sorted({(path.name, c) for path in DOCS for c in commands_in_order(path)})


def test_the_docs_name_commands():
    assert len(COMMANDS) >= 15 and any("deploy --robot sim --optimize" in c for _, c in COMMANDS)


def _files_as_plain_paths(monkeypatch) -> None:
    """The parser's file arguments taken as plain paths: nothing is read or checked on disk while parsing."""
    for name in ("_params_file", "_calibration_file", "_output_path"):
        monkeypatch.setattr(cli, name, pathlib.Path)


@pytest.mark.parametrize("doc, command", COMMANDS, ids=[c for _, c in COMMANDS])
def test_a_documented_command_parses(doc, command, monkeypatch, capsys):
    _files_as_plain_paths(monkeypatch)
    argv = shlex.split(command)[1:]
    try:
        args = cli.build_parser().parse_args(argv)
    except SystemExit:
        pytest.fail(f"{doc}: `{command}` is refused: {capsys.readouterr().err.strip()}")
    if args.command == "deploy" and getattr(args, "robot", None) is not None:
        args.command_line = command
        try:  # the rules that span options; a file named stands for a good one
            if args.func is cli._calibrate:
                cli._options_of(CalibrateOptions, args)
            else:
                cli._options_of(
                    DeployOptions,
                    args,
                    params=None,
                    params_path=None,
                    calibration=None if args.calibration is None else deploy.sim_calibration(),
                )
        except ValueError as err:
            pytest.fail(f"{doc}: `{command}`: {err}")


def shortened(argv: list[str]) -> list[str] | None:
    """The documented command's arguments with the options that make it short appended (the module docstring), or
    None for a command that would reach a real robot."""
    command = argv[0]
    if command == "study":
        return [*argv, "--dry-run"]
    if command == "walk":
        return [*argv, "--trials", "1"]
    if command == "deploy":
        if "--robot" not in argv or argv[argv.index("--robot") + 1] != "sim":
            return None
        short = ["--sim-pacing", "lockstep"]
        if "calibrate" in argv:
            return [*argv, *short, "--air-s", "0.2", "--stand-s", "0.3", "--settle-s", "0.2"]
        if "--optimize" in argv:
            return [*argv, *short, "--trials", "2", "--transition-s", "0.2", "--steady-s", "0.3"]
        return [*argv, *short, "--duration-s", "1"]
    return argv


@pytest.mark.slow
@pytest.mark.parametrize("doc", [d for d in DOCS if commands_in_order(d)], ids=lambda d: d.name)
def test_the_documented_commands_run_in_a_fresh_folder(doc, tmp_path, monkeypatch):
    _files_as_plain_paths(monkeypatch)
    # One parser for every line: what it makes of two lines that differ only in an option
    # given again later (the last given wins) compares equal.
    parser = cli.build_parser()
    for name, text in files_in(doc).items():  # a study file the document shows, as its reader would save it
        (tmp_path / name).write_text(text)
    ran, run_options = [], []
    for command in commands_in_order(doc):
        argv = shortened(shlex.split(command)[1:])
        if argv is None:
            continue
        options = vars(parser.parse_args(argv))
        if options in run_options:  # shortened to a command already run in this folder
            continue
        run_options.append(options)
        proc = subprocess.run(
            [sys.executable, "-m", "cpgjax.cli", *argv],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
            env=dict(os.environ, JAX_PLATFORMS="cpu"),
        )
        assert proc.returncode == 0, (
            f"{doc.name}: `{command}` (run as `cpgjax {shlex.join(argv)}` in a fresh "
            f"folder, after {ran}) exited {proc.returncode}: {proc.stderr[-1500:]}"
        )
        ran.append(command)
    assert ran, f"{doc.name}: no documented command was run"
