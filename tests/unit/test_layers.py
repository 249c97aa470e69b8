"""The package's imports point one way: contracts at the bottom, commands on top.

Walks every module of ``openfusion`` (both source roots) with ``ast``, including imports inside
functions and under ``TYPE_CHECKING``, and fails on

- any import cycle between modules;
- a module importing one of a higher layer (``LAYERS``, lowest first), e.g. the map core
  importing the bus or a command, or library code importing ``openfusion.app``;
- Zenoh imported outside the packages that talk to the bus;
- a package of the library importing another package of the same layer that it may not.

Entry scripts (``__main__.py``) may import anything: they are programs, not library code.
docs/ARCHITECTURE.md draws the same layers.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
SOURCE_ROOTS = {"openfusion": ROOT / "shared" / "openfusion", "openfusion.services": ROOT / "services"}

#: Lowest first. A module may import modules of its own layer (same package) or of lower layers.
LAYERS: list[tuple[str, ...]] = [
    ("openfusion", "openfusion.errors"),
    ("openfusion.frame", "openfusion.poses", "openfusion.blas"),
    ("openfusion.wire",),
    ("openfusion.config",),
    ("openfusion.bus",),
    ("openfusion.io",),
    ("openfusion.mapping",),
    ("openfusion.encoders",),
    ("openfusion.sources",),
    ("openfusion.eval", "openfusion.viz"),
    ("openfusion.shard_client",),
    ("openfusion.client",),
    ("openfusion.services",),
    ("openfusion.app",),
    ("openfusion.testing",),
]

#: Packages that may import zenoh (they talk to the bus); everything else must not.
ZENOH_ALLOWED = ("openfusion.config", "openfusion.bus", "openfusion.sources.ros2", "openfusion.client",
                 "openfusion.shard_client",
                 "openfusion.services", "openfusion.app", "openfusion.testing")


def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for package, folder in SOURCE_ROOTS.items():
        for path in folder.rglob("*.py"):
            rel = path.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([package, *parts]) if parts else package
            out[name] = path
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Modules of ours that ``name`` imports (a ``from X import y`` of a submodule names X.y)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
            subs: list[str] = []
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [module]
            subs = [f"{module}.{alias.name}" for alias in node.names]
        else:
            continue
        for target in targets:
            if not target.startswith("openfusion"):
                continue
            hit = [s for s in subs if s in known]
            if hit:
                found.update(hit)
                if len(hit) < len(subs) and target in known:
                    found.add(target)
            elif target in known:
                found.add(target)
            else:
                raise AssertionError(f"{name} imports {target}, which is no module of the package")
    found.discard(name)
    return found


def _layer_of(module: str) -> int:
    best, rank = -1, -1
    for i, layer in enumerate(LAYERS):
        for prefix in layer:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, rank = len(prefix), i
    assert rank >= 0, f"{module} is in no layer: add it to LAYERS (and docs/ARCHITECTURE.md)"
    return rank


def _package_of(module: str) -> str:
    parts = module.split(".")
    if parts[:2] == ["openfusion", "services"]:
        return "openfusion.services"
    return ".".join(parts[:2])


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles() -> None:
    """No two modules import each other, directly or through others (function-level imports count)."""
    cycles = _cycles(_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_no_module_imports_a_higher_layer() -> None:
    """Contracts never import the bus, the library never imports services or commands, nothing
    but tests imports openfusion.testing."""
    wrong = []
    for module, targets in sorted(_graph().items()):
        if module.endswith("__main__"):
            continue
        for target in sorted(targets):
            if _layer_of(target) > _layer_of(module):
                wrong.append(f"{module} -> {target}")
    assert not wrong, "imports that run up the layers:\n" + "\n".join(wrong)


def test_library_packages_of_one_layer_do_not_import_each_other() -> None:
    """eval and viz sit on one layer: neither imports the other."""
    wrong = []
    for module, targets in sorted(_graph().items()):
        for target in targets:
            same_layer = _layer_of(target) == _layer_of(module)
            if same_layer and _package_of(target) != _package_of(module) and _layer_of(module) > 1:
                wrong.append(f"{module} -> {target}")
    assert not wrong, "\n".join(wrong)


def test_zenoh_only_where_the_bus_is_spoken() -> None:
    """The map core, encoders, evaluation, pictures and wire contracts never import zenoh."""
    wrong = []
    for name, path in sorted(_modules().items()):
        if any(name == p or name.startswith(p + ".") for p in ZENOH_ALLOWED):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            mods = ([a.name for a in node.names] if isinstance(node, ast.Import)
                    else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            if any(m == "zenoh" or m.startswith("zenoh.") for m in mods):
                wrong.append(name)
    assert not wrong, f"zenoh imported outside the bus layers: {wrong}"


def test_the_walker_sees_function_level_imports(tmp_path: Path) -> None:
    """The checks above would pass vacuously if imports inside functions were missed."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from openfusion.app import cli\n    return cli\n")
    assert _imports("openfusion.mapping.m", src, {"openfusion.app", "openfusion.app.cli"}) == {"openfusion.app.cli"}
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
