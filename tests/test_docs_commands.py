"""Every complete `cpgjax` command line in README.md and docs/ still parses with today's parser and passes the
checks that span options (no option of the other robot or mode): a renamed, removed or refused option in a
documented command fails here. The commands are parsed, not run (their files need not exist: the file-reading
option types are replaced by plain paths); command lines with placeholders (`<out>`, `FILE`, `N`, `...`) are
skipped."""

import pathlib
import re
import shlex

import pytest

from cpgjax import cli

ROOT = pathlib.Path(__file__).resolve().parent.parent
PLACEHOLDER = re.compile(r"<|\[|\||\.\.\.|…|\b(FILE|N|NAME|DIR|FOLDER|CALIBRATION)\b")


def documented_commands() -> list[tuple[str, str]]:
    """(file, command line) of every `cpgjax <command> <option>…` in a code span or block of the docs."""
    found = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text()
        spans = re.findall(r"```(?:bash)?\n(.*?)```", text, re.S) + re.findall(r"`([^`\n]+)`", text)
        for span in spans:
            for line in span.splitlines():
                line = line.split("#")[0].strip().removesuffix("&").strip()
                m = re.match(r"^(?:\.venv/bin/)?cpgjax (walk|study|optimize|show|demo|deploy)(?=\s|$)(.*)$", line)
                if m and m.group(2).strip() not in ("", "calibrate") and not PLACEHOLDER.search(line):
                    found.append((path.name, line.removeprefix(".venv/bin/")))
    return sorted(set(found))


COMMANDS = documented_commands()


def test_the_docs_name_commands():
    assert len(COMMANDS) >= 15 and any("deploy --robot sim --optimize" in c for _, c in COMMANDS)


@pytest.mark.parametrize("doc, command", COMMANDS, ids=[c for _, c in COMMANDS])
def test_a_documented_command_parses(doc, command, monkeypatch, capsys):
    monkeypatch.setattr(cli, "_params_file", pathlib.Path)
    monkeypatch.setattr(cli, "_calibration_file", pathlib.Path)
    monkeypatch.setattr(cli, "_output_path", pathlib.Path)
    argv = shlex.split(command)[1:]
    try:
        args = cli.build_parser().parse_args(argv)
    except SystemExit:
        pytest.fail(f"{doc}: `{command}` is refused: {capsys.readouterr().err.strip()}")
    if args.command == "deploy" and getattr(args, "robot", None) is not None:
        problem = cli._inapplicable(args, calibrating=args.func is cli._calibrate)
        assert problem is None, f"{doc}: `{command}`: {problem}"
