"""The package's layout is its data flow: the layer rule and no import cycle (docs/design.md).

Every ``import`` and ``from ... import`` of a module counts, those inside functions too.
"""

import ast
import graphlib
from pathlib import Path

import pytest

import plenopiv

PACKAGE = Path(plenopiv.__file__).resolve().parent

#: The stages in the order data moves; a stage imports only the stages before it.
STAGES = ("camera", "synthetic", "calibration", "preprocess", "lightfield", "reconstruction",
          "particles", "piv", "tracking")
#: What every stage may import besides the stages before it.
SHARED = ("errors", "conventions", "settings", "products", "resources", "_threads",
          "_median")
#: The layers that compose the stages; no stage imports them.
COMPOSING = ("workflow", "batch", "cli", "config")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(path: Path, modules: set[str], name: str | None = None) -> set[str]:
    """The plenopiv modules that the file at ``path`` imports, resolved to existing modules."""
    name = module_name(path) if name is None else name
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            targets = [f"{prefix}.{a.name}" for a in node.names] + [prefix]
        else:
            continue
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target.startswith("plenopiv") and target != name:
                out.add(target)
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    files = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(f) for f in files}
    return {module_name(f): imported(f, modules) for f in files}


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_the_package_has_no_import_cycle(graph):
    # a submodule's import of its own package's __init__ is not an edge back (Python runs the
    # package first); every other edge counts
    edges = {m: {d for d in deps if not m.startswith(d + ".")} for m, deps in graph.items()}
    try:
        tuple(graphlib.TopologicalSorter(edges).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle: {' -> '.join(exc.args[1])}")


def test_a_stage_imports_only_the_stages_before_it(graph):
    wrong = []
    for module, deps in graph.items():
        own = layer(module)
        if own not in STAGES:
            continue
        for dep in deps:
            other = layer(dep)
            if other == own or other in SHARED or other == "":
                continue
            if other in COMPOSING:
                wrong.append(f"{module} imports {dep} (a stage never imports {other}/)")
            elif other in STAGES and STAGES.index(other) > STAGES.index(own):
                wrong.append(f"{module} imports {dep}, a later stage")
            elif other not in STAGES:
                wrong.append(f"{module} imports {dep}, outside the stages and shared modules")
    assert not wrong, "\n".join(sorted(wrong))


@pytest.mark.parametrize(("lower", "upper"), [
    (("errors", "conventions", "settings", "resources", "_threads"),
     COMPOSING + ("products",) + STAGES),
    (("products",), COMPOSING),
    (("workflow",), ("batch", "cli")),
    (("batch",), ("cli",)),
])
def test_lower_layers_do_not_import_the_ones_that_use_them(graph, lower, upper):
    wrong = sorted(f"{m} imports {d}" for m, deps in graph.items() if layer(m) in lower
                   for d in deps if layer(d) in upper)
    assert not wrong, "\n".join(wrong)


def test_every_module_belongs_to_a_known_layer(graph):
    known = set(STAGES) | set(SHARED) | set(COMPOSING) | {"", "__main__"}
    assert {layer(m) for m in graph} <= known, sorted({layer(m) for m in graph} - known)


def test_imports_inside_functions_and_relative_imports_are_seen(tmp_path):
    modules = {"plenopiv", "plenopiv.camera", "plenopiv.camera.model", "plenopiv.workflow",
               "plenopiv.workflow.pair", "plenopiv.camera.grid"}
    probe = tmp_path / "probe.py"
    probe.write_text("import numpy\nfrom . import grid\n\n\ndef f():\n"
                     "    from plenopiv.workflow.pair import correlate\n")
    assert imported(probe, modules, name="plenopiv.camera.probe") == {
        "plenopiv.camera", "plenopiv.camera.grid", "plenopiv.workflow.pair"}


# ---- the source reads as reference, not as a notebook --------------------------------------

#: A module's docstring says what it is for and links the methods page; the physics is there.
MAX_MODULE_DOCSTRING_LINES = 13
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 100
#: Dated figures, machine loads and history belong to docs/performance.md and the commit log.
NOTEBOOK = (r"\b20\d\d-\d\d-\d\d\b", r"\btwo cores\b", r"\b2-core\b", r"\bidle machine\b",
            r"\bprevious defaults?\b", r"\bissue #?\d+", r"\bthis project's\b")


def source_files():
    return sorted(PACKAGE.rglob("*.py"))


def test_no_lab_notebook_lines_in_the_source():
    import re

    found = [f"{p.relative_to(PACKAGE)}:{i}: {line.strip()}" for p in source_files()
             for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             for pattern in NOTEBOOK if re.search(pattern, line, re.IGNORECASE)]
    assert not found, "\n".join(found)


def test_modules_and_functions_stay_small_and_module_docstrings_short():
    long = []
    for p in source_files():
        text = p.read_text(encoding="utf-8")
        tree = ast.parse(text)
        if len(text.splitlines()) > MAX_MODULE_LINES:
            long.append(f"{p.relative_to(PACKAGE)}: {len(text.splitlines())} lines")
        doc = ast.get_docstring(tree, clean=False)
        if doc and len(doc.splitlines()) > MAX_MODULE_DOCSTRING_LINES:
            long.append(f"{p.relative_to(PACKAGE)}: module docstring of "
                        f"{len(doc.splitlines())} lines")
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{p.relative_to(PACKAGE)}: {node.name} has {n} lines")
    assert not long, "\n".join(long)
