"""The package's import graph: no cycles, and the numerics never import the plots or the report.

The graph is read from the source with :mod:`ast`, not by importing: every
``import`` and ``from ... import`` anywhere in a module counts, inside
functions too (a lazy import is still a dependency, only a later one).  The
root package's lazily exported names (``comest_bayes.__getattr__``) count as
imports of their modules.  Importing a submodule also runs its parent
package's ``__init__``; those implicit edges are left out, since every module
would otherwise depend on the root and the root's front door on every module.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import comest_bayes
from conftest import REPO_ROOT

PACKAGE_DIR = Path(comest_bayes.__file__).resolve().parent

#: Modules outside ``comest_bayes.report`` that may import it: the layers on top
#: (CLI, front door and its lazy ``write_report``), and the two commands that draw a figure of their own
#: result (``comest-bayes fit``: ``pipeline.fits.fit_outcome_file``; ``comest-bayes lf``: ``lf.fit.run_lf``).
#: The test also fails when a module here no longer needs its place, so the list only shrinks.
MAY_IMPORT_PLOTS = {"comest_bayes", "comest_bayes.cli", "comest_bayes.api", "comest_bayes.pipeline.fits",
                    "comest_bayes.lf.fit"}


def module_names(root: Path) -> dict[str, Path]:
    """Dotted name -> file of every module of the package in ``root`` (a package is named by its folder)."""
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = (root.name, *path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module of a ``from ... import`` (relative levels resolved against ``module``)."""
    if not node.level:
        return node.module or ""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    parts = package.split(".")
    if node.level > 1:
        parts = parts[: len(parts) - (node.level - 1)]
    return ".".join(parts + ([node.module] if node.module else []))


def _lazy_exports(tree: ast.Module, module: str) -> set[str]:
    """Modules named by the root's lazy-export tables (``_EXPORTS``: name -> module, ``_RENAMED``: name -> (module, attr))."""
    out = set()
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id in ("_EXPORTS", "_RENAMED")
                                                for t in node.targets):
            table = ast.literal_eval(node.value)
            for value in table.values():
                out.add(f"{module}.{value if isinstance(value, str) else value[0]}")
    return out


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports anywhere in its source."""
    names = module_names(root)
    top = root.name
    graph = {}
    for module, path in names.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                deps.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(module, path, node)
                for alias in node.names:
                    full = f"{base}.{alias.name}"
                    deps.add(full if full in names else base)
        if path.name == "__init__.py" and module == top:
            deps |= _lazy_exports(tree, module)
        graph[module] = {d for d in deps if d in names and d != module and (d == top or d.startswith(top + "."))}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan), each as a closed path through it."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
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
                found.append(_closed_path(graph, set(component)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _closed_path(graph, component: set[str]) -> list[str]:
    """A path inside ``component`` from its first module back to it (breadth-first), for the message."""
    start = min(component)
    previous, frontier = {start: None}, [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & component):
                if w == start:
                    path = [v]
                    while previous[path[-1]] is not None:
                        path.append(previous[path[-1]])
                    return [start, *reversed(path[:-1]), start] if len(path) > 1 else [start, v, start]
                if w not in previous:
                    previous[w] = v
                    nxt.append(w)
        frontier = nxt
    return sorted(component)  # pragma: no cover - a component always closes


@pytest.fixture(scope="module")
def graph():
    return import_graph(PACKAGE_DIR)


def test_the_package_has_no_import_cycle(graph):
    found = cycles(graph)
    assert not found, "import cycles: " + "; ".join(" -> ".join(c) for c in found)


def test_numerics_never_import_the_plots_or_the_report(graph):
    def drawing(name):
        return name == "comest_bayes.report" or name.startswith("comest_bayes.report.")

    importers = {m for m, deps in graph.items() if not drawing(m) and any(drawing(d) for d in deps)}
    assert importers - MAY_IMPORT_PLOTS == set(), \
        f"these modules import comest_bayes.report.plots or report: {sorted(importers - MAY_IMPORT_PLOTS)}"
    assert MAY_IMPORT_PLOTS - importers == set(), \
        f"no longer importing plots or report, remove from MAY_IMPORT_PLOTS: {sorted(MAY_IMPORT_PLOTS - importers)}"


def test_the_graph_sees_top_level_lazy_and_relative_imports(graph):
    # the reader would pass the tests above on an empty graph; here it finds imports of every form
    assert "comest_bayes.detect.sep_backend" in graph["comest_bayes.pipeline.stages"]  # top of the file
    assert "comest_bayes.report.html" in graph["comest_bayes.cli"]  # inside a function only
    assert "comest_bayes.detect.base" in graph["comest_bayes.detect.sextractor"]
    assert "comest_bayes.report.plots" in graph["comest_bayes.report.plots.lf"]  # `from . import COLORS` in a subpackage
    assert "comest_bayes.io.rundir" in graph["comest_bayes.report.plots"]  # `from ..rundir import ...`
    assert "comest_bayes.ratios.binned" in graph["comest_bayes.bayes.fit"]  # `from . import ratios as R`
    assert {"comest_bayes.api", "comest_bayes.lf.fit", "comest_bayes.bayes.posterior"} <= graph["comest_bayes"]  # lazy exports
    assert "comest_bayes.detect.sextractor" not in graph["comest_bayes.detect.base"]
    assert len(graph) == len(list(PACKAGE_DIR.rglob("*.py")))


def test_a_cycle_through_a_function_level_import_is_found(tmp_path):
    pkg = tmp_path / "toy"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import f\n")
    (pkg / "b.py").write_text("def f():\n    from .sub import c\n    return c\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "c.py").write_text("import os\n\ndef g():\n    from ..a import f\n")
    (pkg / "d.py").write_text("from . import a\nfrom .sub import c\n")
    found = cycles(import_graph(pkg))
    assert found == [["toy.a", "toy.b", "toy.sub.c", "toy.a"]]
    # without the function-level import the cycle is gone
    (pkg / "sub" / "c.py").write_text("import os\n")
    assert cycles(import_graph(pkg)) == []


def test_float64_is_switched_on_in_one_place_only():
    # JAX's precision is process-wide: one module (jaxnum) sets it, the numerics import JAX through it, and the
    # front door does not import it.
    import ast

    root = REPO_ROOT / "comest_bayes"
    setters = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and node.value == "jax_enable_x64":
                setters.append(path.name)
    assert setters == ["jaxnum.py"]
