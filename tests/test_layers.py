"""No import runs upward: every module of magctl imports only from its own layer or the layers below, and no
modules of magctl import one another round a cycle.

The layer order is the one drawn in docs/architecture.md; imports inside functions count too (a cycle an import
inside a function closes is a cycle: it only hides until the function runs).
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


def imports_of(path: Path, here: str | None = None, modules=None) -> list[tuple[int, str]]:
    """(line, module) of every magctl import in the file (module ``here``), at any depth. With ``modules`` (the
    names of magctl's modules) ``from package import name`` is an import of ``package.name`` where that is a module."""
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
            elif modules is not None:
                out += [(node.lineno, f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod) for a in node.names]
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
                     "def f():\n    from magctl.stability.iteration import side_attempt_map\n")
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


# --- no cycles ------------------------------------------------------------------------------------------------
def package_modules() -> dict[str, Path]:
    """Every module of magctl by name (a package by its ``__init__.py``)."""
    return {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def import_graph(modules: dict[str, Path]) -> dict[str, dict[str, int]]:
    """Module → {module it imports: the line of the first such import}, over ``modules`` only: every import at any
    depth (inside functions too), ``from package import module`` an import of that module. The packages an import
    runs first (``magctl.control`` before ``magctl.control.servo``) are not edges: a package's ``__init__`` gathering
    its modules' names is no cycle with them."""
    names = set(modules)
    graph: dict[str, dict[str, int]] = {}
    for me, path in modules.items():
        edges = graph.setdefault(me, {})
        for line, mod in imports_of(path, me, modules=names):
            if mod in names and mod != me:
                edges.setdefault(mod, line)
    return graph


def import_cycles(graph: dict[str, dict[str, int]]) -> list[str]:
    """One cycle of every strongly connected group of modules, shortest through the group's first module, written
    ``a (line 12) -> b (line 30) -> a`` with the line of each import."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    out = []
    for group in groups:  # breadth first from the group's first module, inside the group, until an import of it
        start, inside = group[0], set(group)
        parent: dict[str, str | None] = {start: None}
        queue, last = [start], None
        for v in queue:
            if start in graph[v]:
                last = v
                break
            for w in sorted(graph[v]):
                if w in inside and w not in parent:
                    parent[w] = v
                    queue.append(w)
        path = [last]
        while parent[path[-1]] is not None:
            path.append(parent[path[-1]])
        cycle = [*reversed(path), start]
        out.append(" -> ".join(f"{u} (line {graph[u][w]})" for u, w in zip(cycle, cycle[1:], strict=False))
                   + f" -> {start}")
    return out


def test_no_import_cycle():
    """A cycle (a imports b, b imports a, perhaps inside a function) means neither can be read, tested or moved
    without the other; the lower module's piece the higher one needs belongs below both."""
    cycles = import_cycles(import_graph(package_modules()))
    assert cycles == [], "import cycles among magctl's modules:\n" + "\n".join(cycles)


def test_the_checker_sees_import_cycles(tmp_path):
    """Two probe modules importing each other (one of the imports inside a function, one as ``from package import
    module``) are a cycle; one importing the other is not."""
    a, b, c = tmp_path / "probe_a.py", tmp_path / "probe_b.py", tmp_path / "probe_c.py"
    a.write_text("from magctl.probe import probe_b\nfrom magctl.core.block import Block\n")
    b.write_text("import numpy as np\n\n\ndef f():\n    from magctl.probe.probe_a import g\n")
    c.write_text("from magctl.probe.probe_a import g\n")
    modules = {"magctl.probe.probe_a": a, "magctl.probe.probe_b": b, "magctl.probe.probe_c": c}
    graph = import_graph(modules)
    assert graph == {"magctl.probe.probe_a": {"magctl.probe.probe_b": 1},
                     "magctl.probe.probe_b": {"magctl.probe.probe_a": 5},
                     "magctl.probe.probe_c": {"magctl.probe.probe_a": 1}}
    assert import_cycles(graph) == ["magctl.probe.probe_a (line 1) -> magctl.probe.probe_b (line 5) -> "
                                    "magctl.probe.probe_a"]
    b.write_text("import numpy as np\n")
    assert import_cycles(import_graph(modules)) == []
