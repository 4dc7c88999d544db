"""The size rule: no package module over 800 lines, no function (nested ones included) over 120.

A module past 800 lines mixes concerns that want their own files; a function past 120 lines runs
phases that want their own names. The check reads the source with :mod:`ast` (a function's length
is ``end_lineno - lineno + 1``, decorators excluded) and lists every offender, so a failure says
what to split.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = ("core", "render", "capture", "calib", "geometry", "fit", "pipelines")
MAX_FILE_LINES = 800
MAX_FUNCTION_LINES = 120


def size_offenders(root: Path = ROOT) -> list[str]:
    """One line per module over :data:`MAX_FILE_LINES` and per function over :data:`MAX_FUNCTION_LINES`."""
    bad = []
    for folder in FOLDERS:
        for path in sorted((root / folder).rglob("*.py")):
            source = path.read_text()
            name = path.relative_to(root).as_posix()
            lines = len(source.splitlines())
            if lines > MAX_FILE_LINES:
                bad.append(f"{name}: {lines} lines")
            for node in ast.walk(ast.parse(source)):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    length = node.end_lineno - node.lineno + 1
                    if length > MAX_FUNCTION_LINES:
                        bad.append(f"{name}:{node.lineno}: {node.name} {length} lines")
    return bad


def test_no_module_or_function_is_too_long():
    offenders = size_offenders()
    assert offenders == [], "split these:\n" + "\n".join(offenders)


def test_the_check_catches_a_long_module_and_a_long_nested_function(tmp_path):
    (tmp_path / "fit").mkdir()
    (tmp_path / "fit" / "long.py").write_text("x = 1\n" * (MAX_FILE_LINES + 1))
    inner = "    def inner():\n" + "        y = 1\n" * MAX_FUNCTION_LINES
    (tmp_path / "core").mkdir()
    (tmp_path / "core" / "nested.py").write_text("def outer():\n" + inner + "    return inner\n")
    assert size_offenders(tmp_path) == [f"core/nested.py:1: outer {MAX_FUNCTION_LINES + 3} lines",
                                        f"core/nested.py:2: inner {MAX_FUNCTION_LINES + 1} lines",
                                        f"fit/long.py: {MAX_FILE_LINES + 1} lines"]
