"""The ``magctl`` command: subcommands are the modules of :mod:`magctl.cli`.

Building the parser imports only the subcommand modules, which import their computing code
inside the commands, so ``magctl --help`` starts without python-control, scipy or matplotlib.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import pkgutil
import sys
from pathlib import Path

import magctl
from magctl.cli.common import Parser
from magctl.config import models_dir
from magctl.core.errors import MagctlError, ParameterError


def build_parser() -> Parser:
    parser = Parser(prog="magctl", description="Magnetic micro-robot pushing: analysis, simulation, rig control.")
    parser.add_argument("--version", action="version", version=f"magctl {magctl.__version__}")
    parser.add_argument("--models", metavar="DIR", default=None,
                        help="folder of parameter files to use instead of the shipped models/ (as $MAGCTL_MODELS): "
                             "a copy of it with your rig's values, e.g. one `magctl identify` wrote")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _os_error(err: OSError) -> str:
    where = f"{err.filename}: " if err.filename else ""
    return f"{where}{err.strerror or err}"


@contextlib.contextmanager
def _models_folder(folder: str | None):
    """``--models DIR``: the command reads its parameter files from ``DIR`` (``$MAGCTL_MODELS`` for the command
    and any process it starts), restored afterwards."""
    if folder is None:
        yield
        return
    path = Path(folder)
    if not path.is_dir():
        raise ParameterError(f"--models {folder}: not a folder of parameter files")
    if not any(path.glob("*.toml")):
        raise ParameterError(f"--models {folder}: holds no parameter files (*.toml); start from a copy of "
                             f"{models_dir()}")
    old = os.environ.get("MAGCTL_MODELS")
    os.environ["MAGCTL_MODELS"] = str(path.resolve())
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MAGCTL_MODELS", None)
        else:
            os.environ["MAGCTL_MODELS"] = old


def main(argv: list[str] | None = None) -> int:
    """Run ``magctl``; every failure a user can cause is one line on stderr and a non-zero exit code.

    Exit codes: 0 success, 1 the command ran but its verdict is negative (e.g. a replay that
    differs), 2 bad input or a magctl error, 130 interrupted, 141 the output pipe was closed.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help, --version, or a bad argument (its one line already printed)
        return done.code if isinstance(done.code, int) else 2
    try:
        with _models_folder(args.models):
            code = args.func(args)
        sys.stdout.flush()
    except SystemExit as done:  # a check made once the command started (parser.error): already printed
        return done.code if isinstance(done.code, int) else 2
    except BrokenPipeError:
        # the reader went away (``| head``): stop writing, and keep the interpreter's final flush quiet
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        print("magctl: error: output closed by the reader (broken pipe)", file=sys.stderr)
        return 141
    except MagctlError as err:
        print(f"magctl: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"magctl: error: {_one_line(_os_error(err))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("magctl: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
