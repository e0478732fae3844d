"""Generated numba modules: written once under a hash of their text, imported, cached by numba on disk.

The compiled engine (:mod:`magctl.core.compiled`) and the per-block kernel driver
(:mod:`magctl.core.kernel_driver`) both generate Python source that imports kernels and loops over
trials; numba caches machine code beside a source file, so the source must live in a file whose name
changes when its text does. The text includes a fingerprint of the kernel modules it imports
(:func:`fingerprint`), so an edited kernel gets a new file.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import os
import sys
from pathlib import Path

import numpy as np

JIT = '@numba.njit(cache=True, nogil=True, error_model="numpy", _nrt=False)'
"""Decorator of the generated functions. Without numba's reference counting (``_nrt=False``): they and the
kernels inlined into them only take views of the arrays they are given and never allocate, and the counts
numba would keep on every array a kernel names cost atomic operations each call that its pruning cannot
remove from kernels with loops and branches (two to four times the time of the step)."""


def cache_dir() -> Path:
    """Where generated sources (and numba's cache of them) live: ``$MAGCTL_COMPILED_CACHE``, else
    ``compiled`` under ``$MAGCTL_CACHE`` or ``~/.cache/magctl``."""
    own = os.environ.get("MAGCTL_COMPILED_CACHE")
    if own:
        return Path(own)
    root = os.environ.get("MAGCTL_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "magctl") / "compiled"


def kernel_modules(modules) -> set[str]:
    """The named modules and every ``magctl`` module they take functions or modules from, transitively: the
    sources a compiled kernel may inline."""
    import inspect

    seen: set[str] = set()
    todo = list(modules)
    while todo:
        name = todo.pop()
        if name in seen or not name.startswith("magctl"):
            continue
        seen.add(name)
        module = sys.modules.get(name) or importlib.import_module(name)
        for obj in vars(module).values():
            source = obj.__name__ if inspect.ismodule(obj) else getattr(
                getattr(obj, "py_func", obj), "__module__", None)
            if isinstance(source, str) and source.startswith("magctl") and source not in seen:
                todo.append(source)
    return seen


def fingerprint(modules) -> str:
    """A hash of the source files of the named modules and of every magctl module they draw on
    (:func:`kernel_modules`), with numba's version: numba's cache of a generated module checks only that
    module's file, and a kernel inlines functions of other modules, so an edit to any of them must change the
    generated text."""
    import numba

    h = hashlib.sha256(numba.__version__.encode())
    for mod in sorted(kernel_modules(modules)):
        path = getattr(sys.modules.get(mod), "__file__", None)
        if path:
            h.update(Path(path).read_bytes())
    return h.hexdigest()[:16]


def load(source: str, prefix: str = "magctl_gen"):
    """The module of ``source``, written to :func:`cache_dir` under a hash of its text and imported once
    per process."""
    digest = hashlib.sha256(source.encode()).hexdigest()[:20]
    name = f"{prefix}_{digest}"
    mod = sys.modules.get(name)
    if mod is not None:
        return mod
    folder = cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.py"
    if not path.exists():
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(source)
        os.replace(tmp, path)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def kernel_name(fn) -> tuple[str, str]:
    """``(module, qualified name)`` of a numba-compiled kernel function."""
    from magctl.core.errors import MagctlError

    py = getattr(fn, "py_func", None)
    if py is None:
        raise MagctlError(f"kernel function {fn!r} is not a numba dispatcher")
    return py.__module__, py.__qualname__


def is_record(value) -> bool:
    """A named tuple (a kernel's parameter record, read by field name in the kernel)."""
    return isinstance(value, tuple) and hasattr(type(value), "_fields")


def param_value(value):
    """A kernel parameter as generated code takes it: a contiguous array, a Python scalar, or a named tuple of
    those."""
    if is_record(value):
        return type(value)(*(param_value(v) for v in value))
    if isinstance(value, np.ndarray) and value.ndim > 0:
        return np.ascontiguousarray(value)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    arr = np.asarray(value)
    return int(arr) if arr.dtype.kind in "iu" else float(arr) if arr.dtype.kind == "f" else value
