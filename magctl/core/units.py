"""Unit constants: lengths and speeds are SI inside magctl; these convert the paper's units."""

UM = 1e-6
"""One micrometre in metres."""
MM = 1e-3
"""One millimetre in metres."""
