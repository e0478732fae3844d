"""Every ``magctl`` command of docs/bring-up.md, run in order against the simulated lab as a user would type them.

Each numbered section of the page runs in a folder of its own (the sections share no file; the suite's workers
take them side by side). A ``magctl rig serve`` line starts the server in the background (on a free port: the
page's port is replaced in the lines that follow) until the section's end; every other line runs to completion and
must exit 0. The only lines not run are the install and the board's build and upload, which need a board (the
firmware's C is compiled and tested on this computer by ``test_firmware_deadline.py``).
"""

from __future__ import annotations

import re
import shlex
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from magctl.rig.server import start_server

ROOT = Path(__file__).resolve().parents[3]
PAGE = ROOT / "docs" / "bring-up.md"
NOT_RUN = ("pip install", "mkdir -p build/magcoil", "cp firmware/magcoil/", "arduino-cli ")


def _sections() -> dict[str, list[str]]:
    """The command lines of each ``## N. Title`` section of the page (``sh`` blocks, comments and prompts off)."""
    sections = {}
    for part in re.split(r"^## ", PAGE.read_text(), flags=re.M)[1:]:
        title = part.splitlines()[0].strip()
        blocks = re.findall(r"```sh\n(.*?)```", part, flags=re.S)
        lines = [line.split("  #")[0].strip() for block in blocks for line in block.splitlines()]
        lines = [line for line in lines if line and not line.startswith(("[", "#")) and "=" not in line.split()[0]]
        if lines:
            sections[title] = lines
    return sections


def _commands() -> list[str]:
    return [line for lines in _sections().values() for line in lines]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_page_has_the_commands_we_run():
    commands = _commands()
    assert [c for c in commands if not c.startswith("magctl ")] and all(
        c.startswith(NOT_RUN) for c in commands if not c.startswith("magctl ")), commands
    assert sum(c.startswith("magctl rig serve") for c in commands) == 3
    assert any(c.startswith("magctl rig calibrate camera") for c in commands)
    assert any(c.startswith("magctl rig calibrate coils") for c in commands)


RUN_SECTIONS = [title for title, lines in _sections().items() if any(line.startswith("magctl ") for line in lines)]


def test_the_sections_run_are_the_pages_steps_with_commands():
    assert [t.split(".")[0] for t in RUN_SECTIONS] == ["0", "4", "5", "6"], RUN_SECTIONS


@pytest.mark.parametrize("title", RUN_SECTIONS)
def test_every_magctl_command_of_the_page_runs(title, tmp_path):
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    servers: list[subprocess.Popen] = []
    ports: dict[str, str] = {}
    try:
        for line in _sections()[title]:
            if not line.startswith("magctl "):
                continue
            for page_port, port in ports.items():
                line = line.replace(page_port, port)
            argv = [sys.executable, "-m", "magctl", *shlex.split(line)[1:]]
            if line.startswith("magctl rig serve"):
                page_port = re.search(r"127\.0\.0\.1:(\d+)", line).group(0)
                port = f"127.0.0.1:{_free_port()}"
                ports[page_port] = port
                argv = [a.replace(page_port, port) for a in argv]
                servers.append(start_server(argv, cwd=tmp_path))
                continue
            done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=600,
                                  stdin=subprocess.DEVNULL)
            assert done.returncode == 0, f"{line}\n{done.stderr}"
    finally:
        for proc in servers:
            if proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=20)
    from magctl.rig.log import read_log

    written = {"0": ["first.jsonl"], "4": ["calibration.toml", "coils-calibration.toml"], "5": ["dry.jsonl"],
               "6": ["push.jsonl"]}[title.split(".")[0]]
    assert all((tmp_path / name).is_file() for name in written), written
    if title.startswith("6."):       # the first closed-loop push converged
        push = read_log(tmp_path / "push.jsonl")
        assert push.stop["exit_status"] == "done" and push.summary()["final_outputs"]["status"] == "converged"
