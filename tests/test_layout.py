"""The package's shape (issue 10): imports flow one way, the public API and the old paths work.

The import graph is read from the source (``ast``), so a cycle is caught even when deferred
imports inside functions would hide it at run time. Imports under ``if TYPE_CHECKING:`` are
for annotations only and are left out; the old-path shims of ``stablecues._compat`` import by
name (``importlib``), on purpose, and so add no edge.
"""

from __future__ import annotations

import ast
import importlib
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

import stablecues
from stablecues import _compat

SRC = Path(stablecues.__file__).resolve().parent


def _module_files() -> dict[str, Path]:
    out = {}
    for path in SRC.rglob("*.py"):
        parts = ["stablecues", *path.relative_to(SRC).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _module_files()


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import statement, at any depth, except those under ``if TYPE_CHECKING:``."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and _is_type_checking(node):
            yield from (n for child in node.orelse for n in _imports(ast.Module([child], [])))
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        yield from _imports(node)


def _targets(module: str, node: ast.Import | ast.ImportFrom) -> Iterator[str]:
    if isinstance(node, ast.Import):
        yield from (a.name for a in node.names if a.name.split(".")[0] == "stablecues")
        return
    if node.level:
        base = module.split(".")
        if MODULES[module].name != "__init__.py":
            base = base[:-1]
        base = base[: len(base) - (node.level - 1)]
        name = ".".join(base + ([node.module] if node.module else []))
    else:
        name = node.module or ""
    if name.split(".")[0] != "stablecues":
        return
    for alias in node.names:
        sub = f"{name}.{alias.name}"
        yield sub if sub in MODULES else name


def _with_parents(name: str, importer: str) -> Iterator[str]:
    """Importing ``a.b.c`` runs ``a.b`` and ``a`` first, unless the importer lives inside them
    (a package's own modules run while it is being imported)."""
    parts = name.split(".")
    for k in range(1, len(parts) + 1):
        parent = ".".join(parts[:k])
        if k == len(parts) or not (importer + ".").startswith(parent + "."):
            yield parent


def import_graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for module, path in MODULES.items():
        deps: set[str] = set()
        for node in _imports(ast.parse(path.read_text(encoding="utf-8"))):
            for target in _targets(module, node):
                deps.update(t for t in _with_parents(target, module) if t in MODULES and t != module)
        graph[module] = deps
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a path, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                return stack[stack.index(dep):] + [dep]
            if dep not in state and (cycle := visit(dep)) is not None:
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)) is not None:
            return cycle
    return None


def _unit(module: str) -> str:
    """The top-level unit a module belongs to: ``stablecues.X``."""
    return ".".join(module.split(".")[:2])


def package_graph() -> dict[str, set[str]]:
    units: dict[str, set[str]] = {}
    for module, deps in import_graph().items():
        units.setdefault(_unit(module), set()).update(_unit(d) for d in deps if _unit(d) != _unit(module))
    return units


def test_cycle_finder_finds_a_planted_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_relative_imports_are_resolved() -> None:
    graph = import_graph()
    assert "stablecues.errors" in graph["stablecues.types"]
    assert "stablecues.detection.prepare" in graph["stablecues.detection.detector"]
    assert "stablecues.geometry" in graph["stablecues.detection.prepare"]  # parent of geometry.camera


def test_no_import_cycle_between_modules() -> None:
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_no_import_cycle_between_packages() -> None:
    cycle = find_cycle(package_graph())
    assert cycle is None, "packages import each other: " + " -> ".join(cycle or [])


def test_evaluation_is_a_pure_consumer() -> None:
    users = sorted(unit for unit, deps in package_graph().items() if "stablecues.evaluation" in deps)
    # the command line, the demo and the sweeps on a cluster (which evaluate each run) drive it
    assert set(users) <= {"stablecues.cli", "stablecues.demo", "stablecues.distributed"}, users


def test_shared_values_come_from_the_bottom() -> None:
    """types, errors, imageio, trajectory, groundtruth and runs import no stage above them."""
    stages = {"detection", "verification", "database", "datasets", "evaluation", "semantics", "mav",
              "synthetic", "cli", "demo"}
    graph = package_graph()
    for unit in ("types", "errors", "imageio", "trajectory", "groundtruth", "runs"):
        above = {d.split(".")[1] for d in graph.get(f"stablecues.{unit}", set())} & stages
        assert not above, f"stablecues.{unit} imports {sorted(above)}"


@pytest.mark.parametrize("name", sorted(stablecues._API))
def test_public_api(name: str) -> None:
    value = getattr(stablecues, name)
    module = importlib.import_module(f"stablecues.{stablecues._API[name]}")
    assert value is getattr(module, name)


def test_public_api_is_listed_once() -> None:
    assert set(stablecues.__all__) == set(stablecues._API) | {"__version__"}
    with pytest.raises(AttributeError):
        _ = stablecues.NoSuchThing  # type: ignore[attr-defined]


@pytest.mark.parametrize(("old", "new"), sorted(_compat.MOVED.items()))
def test_old_module_paths_still_import(old: str, new: str) -> None:
    for name in (old, new):
        sys.modules.pop(name, None)
    with pytest.warns(DeprecationWarning, match="moved to"):
        old_module = importlib.import_module(old)
    assert old_module is importlib.import_module(new)


@pytest.mark.parametrize(
    ("package", "name"),
    [(p, n) for p, names in sorted(_compat.DEPRECATED_NAMES.items()) for n in sorted(names)],
)
def test_old_names_still_resolve(package: str, name: str) -> None:
    module_name, attr = _compat.DEPRECATED_NAMES[package][name].split(":")
    with pytest.warns(DeprecationWarning, match="moved to"):
        value = getattr(importlib.import_module(package), name)
    assert value is getattr(importlib.import_module(module_name), attr)


def test_frame_is_one_type() -> None:
    from stablecues.datasets import Frame as DatasetsFrame
    from stablecues.datasets.base import Frame as BaseFrame

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # these old paths are plain re-exports: no warning
        assert BaseFrame is DatasetsFrame is stablecues.Frame


PACKAGES = sorted(name for name in MODULES if name.count(".") == 1 and MODULES[name].name == "__init__.py")


@pytest.mark.parametrize("package", PACKAGES)
def test_every_name_a_package_lists_resolves(package: str) -> None:
    """Package namespaces import their names on first use (``stablecues._lazy``): each name of
    ``__all__`` must still come from the module that gives it, and show in ``dir()``."""
    mod = importlib.import_module(package)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not through a deprecated alias
        for name in getattr(mod, "__all__", []):
            assert getattr(mod, name) is not None, f"{package}.{name}"
            assert name in dir(mod), f"{package}.{name}"
    with pytest.raises(AttributeError):
        _ = mod.no_such_name_here
