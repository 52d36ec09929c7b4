"""The run directory's file table (:mod:`comest_bayes.io.layout`) is the only place a run file is named."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import comest_bayes
from comest_bayes.io import layout

PACKAGE_DIR = Path(comest_bayes.__file__).resolve().parent

#: Modules that write files of the same name somewhere else than a run directory.
OTHER_DIRECTORIES = {
    "detect/sextractor.py": "the SExtractor binary's scratch folder (its check images and catalog)",
    "__init__.py": "names modules, not files: report.html is the module comest_bayes.report.html",
}


def _run_file_names() -> set[str]:
    names = {v for k, v in vars(layout).items() if k.isupper() and isinstance(v, str) and "." in v}
    names |= {layout.LF_POSTERIOR, layout.LF_JSON}
    return names


def _literals(tree: ast.AST) -> list[tuple[int, str]]:
    """String constants of a module (docstrings and f-string pieces included, but not comments)."""
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                docstrings.add(id(first.value))
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings]


def test_layout_names_are_unique_and_relative():
    names = [v for k, v in vars(layout).items() if k.isupper() and isinstance(v, str)]
    assert len(names) == len(set(names))
    assert all(not n.startswith("/") for n in names)
    assert layout.catalog("point", "matched") == "catalogs/point_matched.fits"
    assert layout.posterior("buldisk", "purity") == "posterior/buldisk_purity.npz"
    assert layout.realization("point", 7) == "point/r00007.fits"
    assert Path("sims", layout.realization("point", 7)).match(str(Path("sims", layout.realization_glob("point"))))


def test_no_other_module_spells_a_run_file_name():
    names = _run_file_names()
    found = []
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        rel = path.relative_to(PACKAGE_DIR).as_posix()
        if rel == "io/layout.py" or rel in OTHER_DIRECTORIES:
            continue
        for line, text in _literals(ast.parse(path.read_text())):
            hits = [n for n in names if re.search(r"(?<![\w.])" + re.escape(n), text)]
            if hits:
                found.append(f"{rel}:{line}: {text!r}")
    assert not found, "run file names spelled outside comest_bayes/io/layout.py:\n" + "\n".join(found)


def test_the_check_sees_a_spelled_name(tmp_path):
    # the scan above would pass on a package without any literal; here a planted one is found
    tree = ast.parse('def f(run):\n    """Reads summary.json."""\n    return run / "summary.json"\n')
    assert [t for _, t in _literals(tree)] == ["summary.json"]
