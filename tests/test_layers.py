"""The import direction between the product packages (STYLE.md "Where a part goes (the seams)").

A fit reads one way: scene -> rays -> estimator -> field -> renderer -> losses -> fit loop -> run
folder -> report, and nothing below imports anything above it. The rules below are that order as
today's code can already keep it, read from the source with ``ast``: every import counts, also one
inside a function, so a loop cannot hide in a lazy import.

Two rules of the seams are not checked yet, because issue 13's other parts are changing that code:

- a field knows nothing of rays, samplers or compositing (``fields/`` still imports ``render/``
  and ``data.scene.RayBatch``: each backbone samples and composites its own rays until the
  Field / Estimator / Renderer split lands);
- the run folder does not import the report (``fit/run.py`` still draws its PSNR plots and
  snapshot renders through ``report.plots`` / ``report.snapshots``). The fit modules below the run
  folder are held to it, and the report never imports the run folder or the loop back.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("nerfmeta", "classifier", "pretrain")

CLI = ("nerfmeta.__main__", "nerfmeta.cli", "nerfmeta.commands")
WIRING = ("nerfmeta.route", "nerfmeta.demo", *CLI, "classifier", "pretrain")
"""Modules that wire the library into the classify-and-fit pipeline and the commands."""
ABOVE_LOOP = ("nerfmeta.fit.run", "nerfmeta.init", "nerfmeta.zoo", "nerfmeta.report", "nerfmeta.collection",
              "nerfmeta.inspect", *WIRING)
"""What sits above the fit loop: the run folder, saved initialisations, the zoo, reports, generated
collections, scene inspection and the wiring."""
FIT_BELOW_RUN = ("nerfmeta.fit.loop", "nerfmeta.fit.evaluate", "nerfmeta.fit.sampler", "nerfmeta.fit.guard",
                 "nerfmeta.fit.checkpoint")

RULES: list[tuple[tuple[str, ...], tuple[str, ...], str]] = [
    (("nerfmeta.errors", "nerfmeta.io", "nerfmeta.compat", "nerfmeta.metrics"),
     ("nerfmeta.data", "nerfmeta.render", "nerfmeta.fields", "nerfmeta.fit", *ABOVE_LOOP),
     "errors, file IO and metrics are leaves every layer may use"),
    (("nerfmeta.render",), ("nerfmeta.fields", "nerfmeta.fit", *ABOVE_LOOP),
     "rendering and sampling maths are below every field and the fit"),
    (("nerfmeta.data",), ("nerfmeta.fields", "nerfmeta.fit", *ABOVE_LOOP),
     "a scene is read before anything is fitted to it"),
    (("nerfmeta.fields",), ("nerfmeta.fit", *ABOVE_LOOP), "a field knows nothing of the fit that trains it"),
    (FIT_BELOW_RUN, ABOVE_LOOP, "the fit loop writes no run folder and draws no report"),
    (("nerfmeta.report",), ("nerfmeta.fit.run", "nerfmeta.fit.loop", *WIRING),
     "the report reads run folders' files; it never runs a fit"),
    (("nerfmeta",), ("classifier", "pretrain"), "only the wiring uses the classifier and pretraining"),
    (("nerfmeta",), CLI, "the CLI is a thin layer above the library"),
]


def _within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def module_name(path: Path, root: Path = ROOT) -> str:
    """``nerfmeta/fit/run.py`` -> ``nerfmeta.fit.run``; a package's ``__init__.py`` -> the package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(source: str, module: str, is_package: bool) -> set[str]:
    """Every dotted name ``source`` imports, anywhere in the file; relative imports made absolute.

    ``from a.b import c`` gives ``a.b.c``: the module ``c`` of package ``a.b``, or a name in module ``a.b``.
    """
    package = module.split(".") if is_package else module.split(".")[:-1]
    names: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            stem = ".".join(base + ([node.module] if node.module else []))
            names.update(f"{stem}.{alias.name}" for alias in node.names)
    return {n for n in names if n}


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Product module -> the product modules it imports (a name resolved to the longest known module)."""
    files = {module_name(p, root): p for pkg in PRODUCT for p in (root / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        targets = set()
        for name in imported_names(path.read_text(encoding="utf-8"), module, path.name == "__init__.py"):
            parts = name.split(".")
            found = next((".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in files), None)
            if found is not None and found != module:
                targets.add(found)
        graph[module] = targets
    return graph


def violations(graph: dict[str, set[str]]) -> list[str]:
    """``importer -> imported (why)`` for every import that breaks a rule of :data:`RULES` (the wiring is exempt)."""
    out = []
    for importers, forbidden, why in RULES:
        for module, targets in sorted(graph.items()):
            if not _within(module, importers) or _within(module, WIRING):
                continue
            out += [f"{module} -> {t} ({why})" for t in sorted(targets) if _within(t, forbidden)]
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import loops of ``graph``: each strongly connected set of two or more modules, sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
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
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_nothing_below_imports_anything_above(graph):
    assert violations(graph) == []


def test_no_import_loops(graph):
    assert cycles(graph) == []


def test_no_product_module_imports_test_or_benchmark_code():
    bad = []
    for pkg in PRODUCT:
        for path in (ROOT / pkg).rglob("*.py"):
            module = module_name(path)
            names = imported_names(path.read_text(encoding="utf-8"), module, path.name == "__init__.py")
            bad += [f"{module} -> {n}" for n in sorted(names) if n.split(".")[0] in ("benchlib", "tests", "conftest", "scripts")]
    assert bad == []


def test_the_reader_sees_lazy_and_relative_imports_and_the_checks_catch_them(tmp_path):
    (tmp_path / "nerfmeta" / "report").mkdir(parents=True)
    (tmp_path / "nerfmeta" / "fit").mkdir()
    for init in ("nerfmeta", "nerfmeta/report", "nerfmeta/fit"):
        (tmp_path / init / "__init__.py").write_text("")
    (tmp_path / "nerfmeta" / "report" / "compare.py").write_text("def f():\n    from ..fit.run import read_metrics\n")
    (tmp_path / "nerfmeta" / "fit" / "run.py").write_text("from nerfmeta.report import compare\n")
    graph = import_graph(tmp_path)
    assert graph["nerfmeta.report.compare"] == {"nerfmeta.fit.run"}
    assert graph["nerfmeta.fit.run"] == {"nerfmeta.report.compare"}
    assert cycles(graph) == [["nerfmeta.fit.run", "nerfmeta.report.compare"]]
    assert violations(graph) == [
        "nerfmeta.report.compare -> nerfmeta.fit.run (the report reads run folders' files; it never runs a fit)"]
