"""Fixtures of the device tests: the coil board's firmware built for this computer, a board behind its pty, and the
``magctl rig calibrate`` commands through their own parser."""

from __future__ import annotations

import pytest

from magctl.cli.common import Parser
from magctl.cli.rig_calibrate import add_parsers
from magctl.rig.devices.firmware import HostBoard, build_host


@pytest.fixture(scope="module")
def exe(tmp_path_factory):
    """The host build of the firmware (cached by its sources' hash)."""
    return str(build_host(tmp_path_factory.mktemp("fw")))


@pytest.fixture
def board(exe):
    """The firmware running behind its pseudo-terminal, its clock driven by the test."""
    with HostBoard(exe=exe) as b:
        yield b


@pytest.fixture(scope="session")
def calibrate():
    """``magctl rig calibrate …`` through the commands' own parser (errors: MagctlError, one line)."""
    def run(*argv: str) -> int:
        parser = Parser(prog="magctl rig")
        add_parsers(parser.add_subparsers(dest="rig_command"))
        args = parser.parse_args(["calibrate", *argv])
        return args.func(args)

    return run
