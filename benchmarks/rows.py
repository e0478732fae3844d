"""One row of a benchmark table (``benchmarks/readme.py``), its verdict computed from the value it shows.

Every ``bench_*.py`` module lists its targets as ``rows`` in the dict its ``run`` returns, each made by
:func:`row` from a number measured in that run and the target's bound, so the verdict cannot disagree with
the figure beside it. A value that was not measured (``None``, NaN) is shown as "not measured" and misses.
"""

from __future__ import annotations

import math


def _bound(x: float) -> str:
    if abs(x) >= 1000 and float(x).is_integer():
        return f"{x:,.0f}"
    return f"{x:.4g}".replace("e-0", "e-").replace("e+0", "e")


def fmt(x: float) -> str:
    """A measured figure for a note, as ``readme.py`` shows values: ``1,234`` from a thousand up, else 3 digits."""
    return f"{x:,.0f}" if abs(x) >= 1000 else f"{x:.3g}"


def row(name: str, value: float | None, unit: str, *, le: float | None = None, ge: float | None = None,
        note: str = "") -> dict:
    """A row ``{name, target, value, unit, met, note}``: ``value`` against ``≤ le`` or ``≥ ge`` (exactly one)."""
    if (le is None) == (ge is None):
        raise ValueError("give exactly one bound: le or ge")
    value = math.nan if value is None else float(value)
    bound, sign = (le, "≤") if le is not None else (ge, "≥")
    met = value <= le if le is not None else value >= ge     # NaN: False
    target = f"{sign} {_bound(bound)} {unit}".rstrip()      # spaced as readme.py shows the value
    return {"name": name, "target": target, "value": value, "unit": unit, "met": bool(met), "note": note}
