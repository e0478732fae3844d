"""Output helpers shared by the ``magctl`` subcommands: ``--json`` documents and readable summaries."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np


def to_jsonable(obj: Any) -> Any:
    """numpy scalars/arrays and nested containers → plain JSON types; non-finite floats → None."""
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
