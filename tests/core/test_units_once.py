"""Every unit constant is defined once, in magctl/core/units.py, with one meaning.

``UM`` used to be defined in some twenty modules, as one micrometre in metres (1e-6) in most and as the metres → µm
factor (1e6) in a few. Now a module that needs a unit imports it from :mod:`magctl.core.units`; this test fails when
any source under magctl/, analysis/, benchmarks/ or tests/ binds a name that units.py defines at module level
(assigns it, or imports it from anywhere else or under another name).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
UNITS = ROOT / "magctl" / "core" / "units.py"
SCANNED = ("magctl", "analysis", "benchmarks", "tests")
UNITS_MODULE = "magctl.core.units"


def _targets(node: ast.AST):
    """The names an assignment target binds (unpacking included)."""
    if isinstance(node, ast.Name):
        yield node
    elif isinstance(node, (ast.Tuple, ast.List)):
        for elt in node.elts:
            yield from _targets(elt)
    elif isinstance(node, ast.Starred):
        yield from _targets(node.value)


def _module_level(body):
    """The module's statements, into ``if``/``try``/``with``/loops but not into functions or classes."""
    for stmt in body:
        yield stmt
        if isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        for field in ("body", "orelse", "finalbody"):
            yield from _module_level(getattr(stmt, field, []))
        for handler in getattr(stmt, "handlers", []):
            yield from _module_level(handler.body)


def defined_names(tree: ast.Module) -> set[str]:
    """The names a module assigns at module level."""
    names = set()
    for stmt in _module_level(tree.body):
        if isinstance(stmt, ast.Assign):
            names.update(t.id for target in stmt.targets for t in _targets(target))
        elif isinstance(stmt, (ast.AnnAssign, ast.AugAssign)):
            names.update(t.id for t in _targets(stmt.target))
    return names


def redefinitions(tree: ast.Module, names: set[str]) -> list[tuple[int, str, str]]:
    """``(line, name, how)`` for every module-level binding of one of ``names`` other than
    ``from magctl.core.units import <name>``."""
    found = []
    for stmt in _module_level(tree.body):
        bound = []
        if isinstance(stmt, ast.Assign):
            bound = [(t.id, "assigned") for target in stmt.targets for t in _targets(target)]
        elif isinstance(stmt, (ast.AnnAssign, ast.AugAssign)):
            bound = [(t.id, "assigned") for t in _targets(stmt.target)]
        elif isinstance(stmt, (ast.For, ast.AsyncFor)):
            bound = [(t.id, "a loop variable") for t in _targets(stmt.target)]
        elif isinstance(stmt, (ast.With, ast.AsyncWith)):
            bound = [(t.id, "bound by with") for item in stmt.items if item.optional_vars
                     for t in _targets(item.optional_vars)]
        elif isinstance(stmt, ast.Import):
            bound = [(alias.asname or alias.name.split(".")[0], f"import {alias.name}") for alias in stmt.names]
        elif isinstance(stmt, ast.ImportFrom):
            module = "." * stmt.level + (stmt.module or "")
            bound = [(alias.asname or alias.name, f"from {module} import {alias.name}") for alias in stmt.names
                     if not (module == UNITS_MODULE and alias.asname in (None, alias.name))]
        found += [(stmt.lineno, name, how) for name, how in bound if name in names]
    return found


NAMES = defined_names(ast.parse(UNITS.read_text(encoding="utf-8")))

PROBE = '''
import numpy as np
UM = 1e6  # m -> um, the other meaning
if np.pi > 3:
    MM: float = 1e-3
from magctl.core.units import UM_PER_M as UM
from magctl.plant.fluid import fem_box as UM_PER_M
from magctl.core.units import MM, UM, UM_PER_M  # allowed: the one definition


def f():
    UM = 2  # a local: not the module's name


class C:
    MM = 1  # a class attribute
'''


def test_units_defines_the_names_checked():
    assert {"UM", "MM", "UM_PER_M"} <= NAMES


def test_the_check_finds_a_probe_module_s_own_unit_names():
    """The probe binds UM twice and MM and UM_PER_M once each at module level: the check names all four lines,
    and none of the import from units.py, the function's local or the class attribute."""
    found = redefinitions(ast.parse(PROBE), NAMES)
    assert [(line, name) for line, name, _ in found] == [(3, "UM"), (5, "MM"), (6, "UM"), (7, "UM_PER_M")]
    assert redefinitions(ast.parse("from magctl.core.units import UM\nx = 3 * UM\n"), NAMES) == []


def test_no_module_defines_a_unit_of_its_own():
    sources = sorted(p for top in SCANNED for p in (ROOT / top).rglob("*.py") if "__pycache__" not in p.parts)
    assert len(sources) > 100 and UNITS in sources
    offenders = [f"{p.relative_to(ROOT)}:{line}: {name} {how}"
                 for p in sources if p != UNITS
                 for line, name, how in redefinitions(ast.parse(p.read_text(encoding="utf-8"), str(p)), NAMES)]
    assert not offenders, ("import these from magctl.core.units (add a name there for a new meaning) instead of "
                           "defining them:\n" + "\n".join(offenders))
