"""Unit constants: lengths and speeds are SI inside magctl; these convert the paper's units."""

UM = 1e-6
"""One micrometre in metres."""
MM = 1e-3
"""One millimetre in metres."""
UM_PER_M = 1e6
"""Micrometres in one metre: ``x * UM_PER_M`` is the length ``x`` (m) in µm, for output. Not ``x / UM``, which
can differ from it in the last bit; dividing a length in µm by it gives the double nearest that length in metres
(``25 / UM_PER_M == 25e-6``, where ``25 * UM`` is one bit off)."""
