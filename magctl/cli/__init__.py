"""The ``magctl`` command: subcommands are the modules of :mod:`magctl.cli`."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import magctl
import magctl.cli
from magctl.core.errors import MagctlError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magctl", description="Magnetic micro-robot pushing: analysis, simulation, rig control."
    )
    parser.add_argument("--version", action="version", version=f"magctl {magctl.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
    except MagctlError as err:
        print(f"magctl: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("magctl: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
