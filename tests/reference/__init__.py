"""Readable numpy forms of magctl's kernelled blocks: the references the library's kernels are tested against.

The library writes each numeric block's behaviour once, as its per-trial kernel; both engines run it. The
batched numpy forms here are written from the same equations, one subclass per block overriding
``output``/``update``/``step`` (ports, state declarations and parameters come from the library block; the
:class:`~reference.core_blocks.NumpyForm` base switches the kernel off). Each ``*_blocks.py`` module of this
folder holds one layer's references in a dict ``REFERENCES`` (library class → reference subclass); a reference
of a block that steps others (a push task's learning law, a task run inside another) steps their references.
``tests/core/test_kernels.py`` runs every kernelled block against its reference through both engines.
"""

import importlib
from pathlib import Path

REFERENCES = {}
"""Library block class → its numpy reference subclass, from every ``*_blocks.py`` module here."""
for _path in sorted(Path(__file__).parent.glob("*_blocks.py")):
    REFERENCES.update(importlib.import_module(f"reference.{_path.stem}").REFERENCES)


def reference_of(block):
    """``block`` running its numpy reference instead of its kernel (same parameters; None when its class has
    no reference)."""
    import copy

    cls = REFERENCES.get(type(block))
    if cls is None:
        return None
    ref = copy.copy(block)
    ref.__class__ = cls
    return ref
