"""The layering of the library (docs/architecture.md), read from the code.

Every import in ``torchhand/`` (module level and function level) is parsed with ``ast``;
a module may import from its own layer or a lower one, never from a higher one. No two
modules or packages of the product (``torchhand/``, ``train/``, ``eval/``,
``datasets/``) share a name.
"""

from __future__ import annotations

import ast
from collections import Counter
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "torchhand"

#: lowest first (docs/architecture.md)
LAYERS = ["core", "optim", "io", "geometry", "model", "data", "salient", "tracking", "reconstruction", "scoring", "app"]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path):
    """(line, absolute module) of every torchhand import in a file."""
    return _imports_of(path.read_text(), _module_name(path), path.name == "__init__.py")


def _imports_of(source: str, module: str, is_package: bool):
    tree = ast.parse(source)
    me = module.split(".")
    package = me if is_package else me[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "torchhand":
                    yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] == "torchhand":
                if mod == "torchhand":  # `from torchhand import x`: x is a layer package or a top-level name
                    for a in node.names:
                        yield node.lineno, f"torchhand.{a.name}"
                else:
                    yield node.lineno, mod


def _layer(module: str):
    parts = module.split(".")
    if len(parts) < 2 or parts[1] not in LAYERS:
        return None
    return LAYERS.index(parts[1])


def _library_files():
    return sorted(p for p in PKG.rglob("*.py"))


def test_every_module_lives_in_a_layer():
    stray = [str(p.relative_to(REPO)) for p in _library_files()
             if p.parent == PKG and p.name != "__init__.py"
             or p.parent != PKG and p.relative_to(PKG).parts[0] not in LAYERS]
    assert stray == [], f"modules outside the layer packages {LAYERS}: {stray}"


def test_no_module_imports_from_a_higher_layer():
    bad = []
    for path in _library_files():
        if path.parent == PKG:
            continue  # torchhand/__init__.py re-exports the entry points
        mine = _layer(_module_name(path))
        for line, mod in _imports(path):
            theirs = _layer(mod)
            if theirs is not None and theirs > mine:
                bad.append(f"{path.relative_to(REPO)}:{line} ({LAYERS[mine]}) imports {mod} ({LAYERS[theirs]})")
    assert bad == [], "imports from a higher layer:\n" + "\n".join(bad)


def test_the_import_reader_sees_every_form():
    src = ("import torchhand.geometry.camera\nfrom torchhand.app import cli\n"
           "def f():\n    from ..tracking.tracker import Tracker\n    from . import scene\n")
    found = [m for _, m in _imports_of(src, "torchhand.model.motion", False)]
    assert found == ["torchhand.geometry.camera", "torchhand.app", "torchhand.tracking.tracker", "torchhand.model"]
    assert [_layer(m) > _layer("torchhand.model.motion") for m in found] == [False, True, True, False]


def test_the_library_never_imports_scripts():
    bad = []
    for path in _library_files():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            bad += [f"{path.relative_to(REPO)}:{node.lineno} imports {n}" for n in names
                    if n.split(".")[0] in ("train", "eval", "tests", "datasets")]
    assert bad == []


def test_no_two_modules_share_a_name():
    names = []
    for root in ("torchhand", "train", "eval", "datasets"):
        for p in (REPO / root).rglob("*.py"):
            if p.name == "__init__.py":
                if p.parent != REPO / root:
                    names.append((p.parent.name, p.parent))
            elif not p.name.startswith("_"):
                names.append((p.stem, p))
    counts = Counter(n for n, _ in names)
    clashes = {n: sorted(str(p.relative_to(REPO)) for m, p in names if m == n) for n, c in counts.items() if c > 1}
    assert clashes == {}, f"modules sharing a name: {clashes}"


@pytest.mark.parametrize("layer", LAYERS)
def test_layer_packages_import_alone(layer):
    """Each layer package imports without pulling in a higher one (catches cycles)."""
    import importlib
    import subprocess
    import sys

    code = (f"import sys, importlib; importlib.import_module('torchhand.{layer}'); "
            f"L = {LAYERS!r}; mine = L.index({layer!r}); "
            "up = sorted(m for m in sys.modules if m.startswith('torchhand.') and m.split('.')[1] in L "
            "and L.index(m.split('.')[1]) > mine); print(up); sys.exit(1 if up else 0)")
    importlib.invalidate_caches()
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert res.returncode == 0, f"importing torchhand.{layer} loaded higher layers: {res.stdout} {res.stderr[-2000:]}"


def test_the_equation_table_names_existing_code():
    """Every `module:name` of docs/architecture.md's equation table can be imported."""
    import importlib
    import re

    text = (REPO / "docs" / "architecture.md").read_text()
    table = text[text.index("## Equations and where they live"):]
    refs = re.findall(r"`(torchhand(?:\.\w+)+):(\w+)`", table)
    assert len(refs) >= 20, refs
    missing = []
    for module, name in refs:
        try:
            if not hasattr(importlib.import_module(module), name):
                missing.append(f"{module}:{name}")
        except ImportError as err:
            missing.append(f"{module}:{name} ({err})")
    assert missing == [], missing
    covered = set()
    for first, last in re.findall(r"^\| Thesis 4\.(\d+)(?:–4\.(\d+))?", table, re.M):
        covered |= set(range(int(first), int(last or first) + 1))
    assert covered == set(range(1, 20)), f"thesis equations missing from the table: {set(range(1, 20)) - covered}"
    ballan = {int(n) for n in re.findall(r"Ballan (\d)\b", table)}
    assert ballan == {1, 2, 3}, ballan


#: module and function sizes (lines, docstrings included) past which a unit is split by
#: concept; the exempt functions are generated kernel sources and argument parsers
MAX_MODULE_LINES, MAX_FUNCTION_LINES = 600, 80
EXEMPT_FUNCTIONS = {("torchhand/geometry/warp_kernels.py", "_kernels"), ("torchhand/app/cli.py", "build_parser")}


def test_modules_and_functions_stay_small():
    too_long = []
    for path in _library_files():
        rel = path.relative_to(REPO).as_posix()
        source = path.read_text()
        if source.count("\n") > MAX_MODULE_LINES:
            too_long.append(f"{rel}: {source.count(chr(10))} lines")
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and (rel, node.name) not in EXEMPT_FUNCTIONS:
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    too_long.append(f"{rel}:{node.lineno} {node.name}: {n} lines")
    assert not too_long, "split these by concept:\n" + "\n".join(too_long)
