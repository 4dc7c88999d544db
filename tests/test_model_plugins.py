"""The appearance-model registry (fit/models/registry.py): nothing outside fit/models/ branches on a model
kind's name, and a model defined outside the package goes through fit, eval, export and report by
registering itself, with no other file touched."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from texstream.fit.models import registry

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ("core", "render", "capture", "calib", "geometry", "fit", "pipelines")
PLUGINS = ROOT / "fit" / "models"


def _names_in(node: ast.AST, kinds: set[str]) -> list[str]:
    """Kind names a comparison operand, dict key or match pattern holds (a constant or a collection of them)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in kinds:
        return [node.value]
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [n for e in node.elts for n in _names_in(e, kinds)]
    return []


def _about_a_model(node: ast.AST) -> bool:
    """An expression that reads a model kind (``layout.kind``, ``cfg.fit.model``, ``kind``): other options share
    some of the kinds' words (``residual_space "radiance"``, a penalty on the "diffuse" columns)."""
    return bool(re.search(r"kind|model", ast.unparse(node)))


def kind_branches(source: str, kinds: set[str]) -> list[tuple[int, str]]:
    """(line, name) of every comparison of a model kind with a kind's name, table keyed by kinds' names (two or
    more), or match on a model kind."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            if any(_about_a_model(o) for o in operands if not _names_in(o, kinds)):
                found += [(node.lineno, n) for o in operands for n in _names_in(o, kinds)]
        elif isinstance(node, ast.Dict):
            names = [n for k in node.keys if k is not None for n in _names_in(k, kinds)]
            found += [(node.lineno, n) for n in names] if len(names) >= 2 else []
        elif isinstance(node, ast.Match) and _about_a_model(node.subject):
            found += [(c.pattern.lineno, n) for c in node.cases if isinstance(c.pattern, ast.MatchValue)
                      for n in _names_in(c.pattern.value, kinds)]
    return found


def branch_violations(root: Path, kinds: set[str]) -> list[str]:
    bad = []
    for folder in PACKAGE:
        for path in sorted((root / folder).rglob("*.py")):
            if (root / "fit" / "models") in path.parents:
                continue
            bad += [f"{path.relative_to(root)}:{line}: branches on {name!r}"
                    for line, name in kind_branches(path.read_text(), kinds)]
    quoted = re.compile(r"""['"](%s)['"]""" % "|".join(sorted(map(re.escape, kinds))))
    for path in sorted((root / "pipelines" / "report_assets").glob("*.js")):
        for i, line in enumerate(path.read_text().splitlines(), 1):
            bad += [f"{path.relative_to(root)}:{i}: names {m.group(1)!r}" for m in quoted.finditer(line)]
    return sorted(bad)


def test_no_module_outside_the_plugins_branches_on_a_model_kind():
    assert branch_violations(ROOT, set(registry.kinds())) == []


def test_the_check_catches_a_branch_on_a_kind(tmp_path):
    (tmp_path / "fit" / "stages").mkdir(parents=True)
    (tmp_path / "fit" / "models" / "x").mkdir(parents=True)
    (tmp_path / "fit" / "stages" / "bad.py").write_text(
        "def f(kind):\n    if kind == 'lfm':\n        return 1\n    return {'radiance': 2, 'lfm': 3}.get(kind, kind in ('diffuse',))\n"
        "def g(space):\n    return space == 'radiance'\n")
    (tmp_path / "fit" / "models" / "x" / "ok.py").write_text("def f(kind):\n    return kind == 'lfm'\n")
    assert branch_violations(tmp_path, {"lfm", "radiance", "diffuse"}) == [
        "fit/stages/bad.py:2: branches on 'lfm'", "fit/stages/bad.py:4: branches on 'diffuse'",
        "fit/stages/bad.py:4: branches on 'lfm'", "fit/stages/bad.py:4: branches on 'radiance'"]


def test_every_shipped_kind_is_a_plugin_folder():
    folders = {p.name for p in PLUGINS.iterdir() if (p / "__init__.py").is_file()}
    for kind in registry.kinds():
        plugin = registry.get(kind)
        assert plugin.kind == kind and callable(plugin.fit) and callable(plugin.load)
    assert {"lafortune", "diffuse", "radiance", "view_radiance", "lfm"} <= set(registry.kinds()) <= folders
