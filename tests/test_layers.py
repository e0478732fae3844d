"""No import runs upward: every module of magctl imports only from its own layer or the layers below.

The layer order is the one drawn in docs/architecture.md; imports inside functions count too.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import magctl

PACKAGE = Path(magctl.__file__).parent
ARCHITECTURE = PACKAGE.parent / "docs" / "architecture.md"


def layer_order() -> list[str]:
    """The layers, bottom first, as listed in docs/architecture.md's "Layers" table."""
    text = ARCHITECTURE.read_text(encoding="utf-8")
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\|\s*(\d+)\s*\|\s*`([\w./]+)`", section, flags=re.M)
    assert rows, "docs/architecture.md has no layer table"
    return [name.rstrip("/").removesuffix(".py") for _, name in sorted(rows, key=lambda r: int(r[0]))]


def layer_of(module: str, layers: list[str]) -> int:
    parts = module.split(".")
    if parts[0] != "magctl":
        raise ValueError(module)
    top = parts[1] if len(parts) > 1 else "__init__"
    if top in ("__init__", "__main__"):
        return -1 if top == "__init__" else len(layers)
    return layers.index(top)


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports_of(path: Path, here: str | None = None) -> list[tuple[int, str]]:
    """(line, module) of every magctl import in the file (module ``here``), at any depth."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    here = here or module_name(path)
    package = here if path.name == "__init__.py" else here.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "magctl"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "magctl":
                continue
            if mod == "magctl":  # ``from magctl import x``: x is a module (its layer) or a root constant
                out += [(node.lineno, f"magctl.{a.name}" if (PACKAGE / a.name).exists()
                         or (PACKAGE / f"{a.name}.py").exists() else "magctl") for a in node.names]
            else:
                out.append((node.lineno, mod))
    return out


def test_every_top_level_module_has_a_layer():
    layers = layer_order()
    tops = {p.stem for p in PACKAGE.glob("*.py")} | {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    tops -= {"__init__", "__main__"}
    assert sorted(tops - set(layers)) == [], "add these to the layer table of docs/architecture.md"
    assert sorted(set(layers) - tops) == [], "the layer table names modules that do not exist"


def upward_imports(path: Path, layers: list[str], here: str | None = None) -> list[str]:
    me = here or module_name(path)
    mine = layer_of(me, layers)
    return [f"{path.name}:{line} ({me}) imports {mod}" for line, mod in imports_of(path, me)
            if mod != "magctl" and layer_of(mod, layers) > mine]


def allowed_layers() -> dict[str, set[str]]:
    """Each layer's "what it may use" column of docs/architecture.md, read as layer names: a layer it names
    (``plant models`` is plant), ``X and below`` (X and every layer under it), ``everything above`` /
    ``everything`` (every layer under it); third-party names are not layers and are skipped. A layer may always
    use itself."""
    text = ARCHITECTURE.read_text(encoding="utf-8")
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\|\s*(\d+)\s*\|\s*`([\w./]+)`\s*\|([^|]*)\|", section, flags=re.M)
    layers = layer_order()
    out = {}
    for _, name, uses in rows:
        me = name.rstrip("/").removesuffix(".py")
        below = set(layers[: layers.index(me)])
        allowed = {me}
        for item in (part.strip() for part in uses.split(",")):
            words = re.sub(r"\(.*?\)", "", item).split()
            if not words:
                continue
            if words[0] == "everything":
                allowed |= below
            elif item.endswith("and below"):
                allowed |= set(layers[: layers.index(words[0]) + 1])
            elif words[0] in layers:
                allowed.add(words[0])
        out[me] = allowed
    return out


def forbidden_imports(path: Path, layers: list[str], allowed: dict[str, set[str]], here: str | None = None):
    me = here or module_name(path)
    mine = layer_of(me, layers)
    if mine < 0 or mine >= len(layers):
        return []
    ok = allowed[layers[mine]]
    return [f"{path.name}:{line} ({me}) imports {mod}" for line, mod in imports_of(path, me)
            if mod != "magctl" and 0 <= layer_of(mod, layers) < len(layers) and layers[layer_of(mod, layers)] not in ok]


def test_every_import_is_one_the_table_allows():
    """The "what it may use" column, not only the order: sweep uses core only, rig uses loops and below, …"""
    layers, allowed = layer_order(), allowed_layers()
    found = [line for path in sorted(PACKAGE.rglob("*.py")) for line in forbidden_imports(path, layers, allowed)]
    assert found == []


def test_the_may_use_column_is_read_and_enforced(tmp_path):
    """rig → stability is below rig in the order but not in its column; sweep → plant likewise; rig → loops and
    rig → sensing (below loops) are allowed."""
    layers, allowed = layer_order(), allowed_layers()
    assert allowed["sweep"] == {"sweep", "core"} and allowed["cli"] == set(layers[: layers.index("cli") + 1])
    probe = tmp_path / "probe.py"
    probe.write_text("from magctl.loops import controller\nfrom magctl.sensing.camera import field_of_view\n"
                     "def f():\n    from magctl.stability.iteration import front_report\n")
    found = forbidden_imports(probe, layers, allowed, here="magctl.rig.probe")
    assert [line.split(" imports ")[1] for line in found] == ["magctl.stability.iteration"]
    probe.write_text("from magctl.plant.sphere import Spheres\n")
    assert forbidden_imports(probe, layers, allowed, here="magctl.sweep") != []


def test_no_import_runs_upward():
    layers = layer_order()
    upward = [line for path in sorted(PACKAGE.rglob("*.py")) for line in upward_imports(path, layers)]
    assert upward == []


def test_the_checker_sees_upward_imports(tmp_path):
    """An import inside a function, a relative one and ``from magctl import x`` are all ranked."""
    layers = layer_order()
    probe = tmp_path / "probe.py"
    probe.write_text("from magctl.core.block import Block\nfrom ..control import servo\nfrom magctl import loops\n"
                     "def f():\n    from magctl.rig.server import RigServer\n")
    found = upward_imports(probe, layers, here="magctl.plant.probe")
    assert [line.split(" imports ")[1] for line in found] == ["magctl.control", "magctl.loops", "magctl.rig.server"]
