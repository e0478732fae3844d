"""Readable numpy forms of magctl's kernelled blocks: the references the library's kernels are tested against.

The library writes each numeric block's behaviour once, as its per-trial kernel; both engines run it. The
batched numpy forms here are written independently of that code, from the same equations, one subclass per
block overriding ``output``/``update``/``step`` (ports, state declarations and parameters come from the
library block). ``tests/core/test_kernels.py`` runs every kernelled block against its reference
(:data:`REFERENCES`) through both engines.
"""

from reference.core_blocks import CORE_REFERENCES

REFERENCES = {**CORE_REFERENCES}
"""Library block class → its numpy reference subclass."""


def reference_of(block):
    """``block`` running its numpy reference instead of its kernel (same parameters; None when its class has
    no reference)."""
    import copy

    cls = REFERENCES.get(type(block))
    if cls is None:
        return None
    ref = copy.copy(block)
    ref.__dict__.pop("_kernel_driver", None)
    ref.__class__ = cls
    return ref
