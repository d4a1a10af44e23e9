"""The command's layout: one module per subcommand, heavy libraries loaded only by commands;
the installed package never imports the studies kept in pipelines/."""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys

from conftest import REPO
from plenopiv import cli

HEAVY = ("h5py", "dask", "distributed", "scipy", "skimage", "numba", "matplotlib", "tifffile")


def test_import_and_parser_load_no_heavy_library():
    """``plenopiv --help`` and argument errors answer without loading the numerical stack."""
    code = ("import sys, plenopiv.cli as c; c.build_parser(); "
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=REPO)
    assert res.stdout.strip() == ""


def test_every_subcommand_comes_from_its_own_module():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    names = list(sub.choices)
    assert names == [m.__name__.rsplit(".", 1)[1] for m in cli.COMMANDS]
    for module, name in zip(cli.COMMANDS, names, strict=True):
        func = sub.choices[name].get_default("func")
        if name == "simulate":      # the kinds are one level down
            kinds = next(a for a in sub.choices[name]._actions if a.dest == "kind").choices
            func = next(iter(kinds.values())).get_default("func")
        assert func.__module__ == module.__name__ and func.__name__ == f"cmd_{name}"


def test_the_package_never_imports_the_studies_of_pipelines():
    """The validation studies live in the repository's pipelines/, not in the wheel: no module
    of src/plenopiv imports them (``plenopiv validate`` loads them by file location)."""
    offenders = []
    for path in sorted((REPO / "src" / "plenopiv").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{path.relative_to(REPO)}:{node.lineno} {n}" for n in names
                          if n.split(".")[0] == "pipelines"]
    assert offenders == []
    assert importlib.util.find_spec("plenopiv.validation") is None
