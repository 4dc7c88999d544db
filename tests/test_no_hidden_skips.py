"""A broken install fails the suite; it does not skip it (issue 41).

Every package a test imports is a declared dependency or in the ``test`` extra (pyproject.toml), so no test
may skip when one is missing: ``pytest.importorskip``, an ``except ImportError`` around an import, or a
``find_spec`` probe in a test file turns a missing or broken package into skipped tests that CI reports as
passing. The skips that remain are for what a machine may lack by design (a CUDA device, the third-party
data of TEXSTREAM_DATA, a second GPU), and none of them goes through an import.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TEST_FILES = sorted((ROOT / "tests").glob("*.py"))
IMPORT_ERRORS = {"ImportError", "ModuleNotFoundError"}


def hidden_skips(source: str, name: str) -> list[str]:
    """``file:line: what`` for each way ``source`` can turn a missing package into a skip or a silent pass."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if called in ("importorskip", "find_spec", "find_loader"):
                found.append(f"{name}:{node.lineno}: {called}")
        elif isinstance(node, ast.ExceptHandler) and node.type is not None:
            caught = node.type.elts if isinstance(node.type, ast.Tuple) else [node.type]
            if any(getattr(c, "id", getattr(c, "attr", None)) in IMPORT_ERRORS for c in caught):
                found.append(f"{name}:{node.lineno}: except ImportError")
    return found


def test_the_scanner_finds_each_way_of_hiding_a_missing_package():
    """The check below would pass vacuously if the scanner missed a pattern: each one is found here."""
    cases = ['import pytest\ncv2 = pytest.importorskip("cv2")',
             'from pytest import importorskip\nimportorskip("ray", reason="optional")',
             'try:\n    import trimesh\nexcept ImportError:\n    trimesh = None',
             'try:\n    import ray\nexcept (OSError, ModuleNotFoundError):\n    pass',
             ('import importlib.util\nimport pytest\n'
              '@pytest.mark.skipif(importlib.util.find_spec("torch") is None, reason="no torch")\n'
              'def test(): pass')]
    for source in cases:
        assert len(hidden_skips(source, "case.py")) == 1, source
    assert hidden_skips('try:\n    x = 1 / 0\nexcept ZeroDivisionError:\n    pass', "case.py") == []


def test_no_test_skips_on_a_missing_package():
    assert len(TEST_FILES) > 50  # the glob found the suite
    found = [hit for p in TEST_FILES for hit in hidden_skips(p.read_text(), p.name)]
    assert not found, ("a missing package must fail the tests, not skip them: import it plainly (declared in "
                       "pyproject.toml's dependencies or test extra) instead of:\n" + "\n".join(found))


def distribution_key(requirement: str) -> str:
    """PEP 503 normalised distribution name of a requirement string ("OpenImageIO>=3.0" -> "openimageio")."""
    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9._-]+", requirement).group(0)).lower()


def imported_top_modules(path: Path) -> set[str]:
    tops = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            tops.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            tops.add(node.module.split(".")[0])
    return tops


def distribution_named(module: str) -> list[str]:
    """The installed distribution called like ``module``: a package that is one extension module (xatlas)
    lists no .py file, from which packages_distributions() would infer its module name."""
    try:
        return [importlib.metadata.distribution(module).metadata["Name"]]
    except importlib.metadata.PackageNotFoundError:
        return []


def test_every_package_a_test_imports_is_declared():
    """A test may import the standard library, texstream, the test helpers beside it (and the peers of
    benchmarks/peers/, which test_peers_quick.py puts on the path), and declared packages only."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = project["dependencies"] + project["optional-dependencies"]["test"]
    declared = {distribution_key(r) for r in requirements}
    local = {p.stem for p in TEST_FILES} | {p.stem for p in (ROOT / "benchmarks" / "peers").glob("*.py")}
    installed = importlib.metadata.packages_distributions()
    undeclared = {}
    for path in TEST_FILES:
        for top in imported_top_modules(path) - set(sys.stdlib_module_names) - local - {"texstream"}:
            dists = {distribution_key(d) for d in installed.get(top, []) or distribution_named(top)}
            if not dists & declared:
                undeclared.setdefault(top, []).append(path.name)
    assert "cv2" not in local and "warp" not in local  # the local names are the helpers, not packages
    assert not undeclared, ("imported by tests but neither a dependency nor in the test extra (or not "
                            f"installed): {undeclared}")
