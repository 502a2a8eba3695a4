"""The code's shape: no import cycles, functions a reader can hold, one version, private names kept private.

Each check reads the source with :mod:`ast`, so it counts every import,
those inside functions included, without importing anything.
"""

from __future__ import annotations

import ast
import importlib.metadata
from pathlib import Path

import pytest

import octcl

REPOSITORY = Path(__file__).absolute().parents[1]
#: Source folders and the package each installs as (setup.cfg's package_dir).
SOURCES = {"octcl": "octcl", "host": "octcl.host"}
#: Lines a function may have without its docstring; the argument parser is the one exception.
MAX_FUNCTION_LINES = 100
LONG_BY_NATURE = {("octcl/cli.py", "build_parser")}


def modules() -> dict[str, tuple[Path, bool]]:
    """{dotted name: (file, whether it is a package's ``__init__``)} of every module of octcl."""
    found = {}
    for folder, package in SOURCES.items():
        for path in sorted((REPOSITORY / folder).rglob("*.py")):
            parts = list(path.relative_to(REPOSITORY / folder).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            name = ".".join([package, *(parts[:-1] if is_package else parts)])
            found[name] = (path, is_package)
    return found


def import_edges(known: dict[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    """Module → the octcl modules it imports anywhere in its file.

    ``from P import n`` is an import of module ``P.n`` where that is a module,
    else of ``P`` (a name its ``__init__`` defines).
    """
    edges = {name: set() for name in known}
    for name, (path, is_package) in known.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                edges[name] |= {alias.name for alias in node.names if alias.name in known}
            elif isinstance(node, ast.ImportFrom):
                base = name.split(".") if is_package else name.split(".")[:-1]
                source = (".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
                          if node.level else node.module)
                for alias in node.names:
                    target = f"{source}.{alias.name}"
                    edges[name] |= {target} if target in known else ({source} if source in known else set())
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import graph's strongly connected components of more than one module (Tarjan's algorithm)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(module):
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for target in sorted(edges[module]):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in on_stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            component = []
            while not component or component[-1] != module:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1 or module in edges[module]:
                found.append(sorted(component))

    for module in sorted(edges):
        if module not in index:
            visit(module)
    return found


def test_no_import_cycle_among_octcls_modules():
    assert cycles(import_edges(modules())) == []


def test_the_cycle_finder_finds_a_cycle():
    """The check above can fail: a two-module loop and a self-import are found, a chain is not."""
    assert cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]
    assert cycles({"a": {"a"}}) == [["a"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_imports_inside_functions_count():
    known = modules()
    edges = import_edges(known)
    # octcl.invert imports the pipeline inside its body, to keep `import octcl` light.
    assert "octcl.host.pipeline.invert" in edges["octcl"]


def function_lengths(path: Path) -> list[tuple[str, int]]:
    """(name, lines without the docstring) of every function and method in ``path``."""
    lengths = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.body[0]
            docstring = (first.end_lineno - first.lineno + 1
                         if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                         and isinstance(first.value.value, str) else 0)
            start = node.decorator_list[0].lineno if node.decorator_list else node.lineno
            lengths.append((node.name, node.end_lineno - start + 1 - docstring))
    return lengths


def test_no_function_over_a_hundred_lines():
    long = [f"{path.relative_to(REPOSITORY).as_posix()}:{name} ({lines} lines)"
            for path, _ in modules().values() for name, lines in function_lengths(path)
            if lines > MAX_FUNCTION_LINES and (path.relative_to(REPOSITORY).as_posix(), name) not in LONG_BY_NATURE]
    assert long == []


def test_one_version_read_from_one_place():
    """``octcl.__version__`` is the installed metadata's version (setup.cfg reads it from octcl/__init__.py)."""
    assert octcl.__version__ == importlib.metadata.version("octcl")
    assert "version = attr: octcl.__version__" in (REPOSITORY / "setup.cfg").read_text(encoding="utf-8")


@pytest.mark.parametrize("folder", sorted(SOURCES))
def test_no_private_name_imported_across_modules(folder):
    """A leading underscore means "this module's own": no other module imports such a name (private
    modules such as ``octcl._io`` are octcl's own, and importing them is how they are used)."""
    crossing = []
    for path in sorted((REPOSITORY / folder).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("octcl")):
                crossing += [f"{path.relative_to(REPOSITORY).as_posix()}:{node.lineno} {alias.name}"
                             for alias in node.names
                             if alias.name.startswith("_") and not alias.name.startswith("__")
                             and not (REPOSITORY / "octcl" / f"{alias.name}.py").exists()]
    assert crossing == []


def test_no_private_name_read_through_an_imported_module():
    """``module._name`` where ``module`` is one of octcl's, imported by name: the same rule, by attribute."""
    crossing = []
    for folder in SOURCES:
        for path in sorted((REPOSITORY / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            modules_here = set()
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("octcl")):
                    modules_here |= {alias.asname or alias.name for alias in node.names}
                elif isinstance(node, ast.Import):
                    modules_here |= {alias.asname or alias.name for alias in node.names if alias.name.startswith("octcl")}
            crossing += [f"{path.relative_to(REPOSITORY).as_posix()}:{node.lineno} {node.value.id}.{node.attr}"
                         for node in ast.walk(tree)
                         if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                         and node.value.id in modules_here and node.attr.startswith("_")
                         and not node.attr.startswith("__")]
    assert crossing == []
