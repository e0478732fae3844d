"""Every ``magctl`` command the README shows parses: its subcommand and options exist and its values pass their checks.

The commands are read from the README's fenced blocks (``;``-separated commands split, comments dropped) and given to
the real parser in a scratch folder that holds what the commands name as inputs (a run log, the examples folder),
so a renamed option, a removed subcommand or a value its check now refuses fails here, not in a new user's hands.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from magctl.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def readme_commands(text: str) -> list[list[str]]:
    out = []
    for lang, body in re.findall(r"```(\w*)\n(.*?)```", text, flags=re.S):
        if lang:
            continue
        for line in body.splitlines():
            for part in line.split("#", 1)[0].split(";"):
                words = shlex.split(part.strip().rstrip("&").strip())
                if words[:1] == ["magctl"]:
                    out.append(words[1:])
    return out


COMMANDS = readme_commands((ROOT / "README.md").read_text())


def test_the_readme_shows_the_commands_this_test_reads():
    heads = {" ".join(c[:2]) for c in COMMANDS}
    assert {"stability servo", "study --list", "rig run", "log view", "rig serve"} <= heads
    assert len(COMMANDS) >= 12


@pytest.mark.parametrize("argv", COMMANDS, ids=[" ".join(c[:3]) for c in COMMANDS])
def test_a_readme_command_parses(argv, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.jsonl").write_text("")
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as done:
        if argv == ["--help"] and done.code == 0:    # the help, printed: what `magctl --help` does
            return
        pytest.fail(f"magctl {' '.join(argv)}: the parser refused it (exit {done.code})")
    assert callable(args.func)


def test_a_stale_option_is_caught():
    with pytest.raises(SystemExit):
        build_parser().parse_args(["stability", "servo", "--no-such-option"])
    assert readme_commands("```\nmagctl a b  # c\nmagctl x; magctl y &\n```\n") == [["a", "b"], ["x"], ["y"]]
