"""Shared by the ``magctl`` subcommands: the one-line-error parser, argument types checked at parse time,
``--json`` documents and readable summaries.

Every value the user types is checked when the command line is parsed, so a bad one stops the
command before any work with one line on stderr naming the option (``magctl study: error: argument
--trials: must be an integer >= 1, got '0'``) and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line on stderr (no usage block), exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())}\n")


def _number(text: str, kind: type, what: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def _bounded(text: str, kind: type, what: str, ok) -> int | float:
    value = _number(text, kind, what)
    if not ok(value):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer ≥ 1 (trials, ticks, workers)."""
    return _bounded(text, int, "an integer >= 1", lambda v: v >= 1)


def nonneg_int(text: str) -> int:
    """An integer ≥ 0."""
    return _bounded(text, int, "an integer >= 0", lambda v: v >= 0)


def seed(text: str) -> int:
    """A root seed: an integer ≥ 0 (what ``numpy.random.SeedSequence`` takes)."""
    return _bounded(text, int, "an integer >= 0 (a root seed)", lambda v: v >= 0)


def finite_float(text: str) -> float:
    """Any finite number (no nan, no inf)."""
    return _number(text, float, "a finite number")


def positive_float(text: str) -> float:
    """A finite number > 0."""
    return _bounded(text, float, "a finite number > 0", lambda v: v > 0)


def nonneg_float(text: str) -> float:
    """A finite number ≥ 0."""
    return _bounded(text, float, "a finite number >= 0", lambda v: v >= 0)


def bounded_float(low: float, high: float, what: str):
    """A type for a finite number in ``[low, high]``: the range that keeps the computation it feeds finite and
    meaningful (gains, distances, scales), stated in the error (``what`` names the kind of quantity)."""
    def parse(text: str) -> float:
        return _bounded(text, float, f"{what} from {low:g} to {high:g}", lambda v: low <= v <= high)
    return parse


def bounded_int(low: int, high: int, what: str):
    """A type for an integer in ``[low, high]``."""
    def parse(text: str) -> int:
        return _bounded(text, int, f"{what} from {low} to {high}", lambda v: low <= v <= high)
    return parse


def existing_file(text: str) -> Path:
    """A path to a file that exists (not a folder)."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{text}: is {'a folder' if path.is_dir() else 'not a regular file'}, "
                                         f"not a file")
    if not os.access(path, os.R_OK):
        raise argparse.ArgumentTypeError(f"{text}: cannot be read (permission denied)")
    return path


def existing_dir(text: str) -> Path:
    """A path to a folder that exists."""
    path = Path(text)
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {'is not a folder' if path.exists() else 'no such folder'}")
    return path


def output_dir(text: str) -> Path:
    """A folder that exists or can be created (checked by creating it, then removing what was created)."""
    path = Path(text)
    if path.exists():
        if not path.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: exists and is not a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise argparse.ArgumentTypeError(f"{text}: folder is not writable")
        return path
    missing = []
    probe = path.absolute()
    while not probe.exists():
        missing.append(probe)
        probe = probe.parent
    if not probe.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: cannot create it, {probe} is a file")
    try:
        path.mkdir(parents=True)
    except OSError as err:
        raise argparse.ArgumentTypeError(f"{text}: cannot create folder ({err.strerror or err})") from None
    for made in missing:  # deepest first: leave nothing behind until the command writes into it
        made.rmdir()
    return path


def output_file(text: str) -> Path:
    """A file that can be written: its folder exists and is writable, and it is not itself a folder."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a folder, not a file")
    parent = path.absolute().parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: folder {parent} is not writable")
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: file is not writable")
    return path


def rig_address(text: str) -> str:
    """``sim``, a lab file ``*.toml`` that exists (an in-process rig of its devices) or a ZeroMQ TCP endpoint
    ``tcp://HOST:PORT`` with a port from 1 to 65535 (its form only; the client reaches it)."""
    if text == "sim":
        return text
    if text.endswith(".toml"):
        if not Path(text).is_file():
            raise argparse.ArgumentTypeError(f"no such lab file {text!r}")
        return text
    host, sep, port = text.removeprefix("tcp://").rpartition(":")
    if not text.startswith("tcp://") or not sep or not host:
        raise argparse.ArgumentTypeError(f"must be 'sim', a lab file (lab.toml) or tcp://HOST:PORT, got {text!r}")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"port must be an integer from 1 to 65535, got {port!r} in {text!r}")
    return text


def scheduler_address(text: str) -> str:
    """``serial``, ``processes`` or a Dask address (its form only; :func:`contact_scheduler` reaches it)."""
    from magctl.sweep import SchedulerError, executor_kind

    try:
        executor_kind(text)
    except SchedulerError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def contact_scheduler(parser: argparse.ArgumentParser, address: str | None) -> None:
    """Reach a Dask ``--scheduler`` (and one of its workers) before any work; a parse error otherwise."""
    from magctl.sweep import SchedulerError, connect_dask, executor_kind

    if address is None or executor_kind(address) != "dask":
        return
    try:
        client = connect_dask(address)
    except SchedulerError as err:
        parser.error(f"argument --scheduler: {err}")
    client.close()


def to_jsonable(obj: Any) -> Any:
    """numpy scalars/arrays and nested containers → plain JSON types; non-finite floats → None."""
    import numpy as np

    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, complex | np.complexfloating):
        return {"re": to_jsonable(obj.real), "im": to_jsonable(obj.imag)}
    return obj


def emit(args, result: dict, summary: Callable[[dict], str]) -> None:
    """Print ``result`` as one JSON document with ``--json``, otherwise the readable summary."""
    if getattr(args, "json", False):
        print(json.dumps(to_jsonable(result), indent=2))
    else:
        print(summary(result))


def add_json(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")
