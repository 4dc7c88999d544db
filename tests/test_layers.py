"""The layer rule: which top-level folder may import which (the one place it is written down).

    core       the spine (errors, config fields and their JSON, atomic outputs): imports no texstream folder
    capture    \
    calib       |  the stages: import core and each other (lazily where a stage needs another's
    geometry    |  function), never pipelines
    fit        /
    pipelines  the CLI and the end-to-end run: may import everything

Every import counts, also one inside a function: a stage that imports the CLI package at call
time inverts the layers as much as one that does so at import time. On top of the folder rule,
``texstream.fit`` (the GPU side, which runs where only numpy and warp are installed) imports no
third-party package but numpy and warp at module import time.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
STAGES = {"capture", "calib", "geometry", "fit"}
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    **{stage: {"core"} | STAGES for stage in STAGES},
    "pipelines": {"core", "pipelines"} | STAGES,
}
# what a GPU machine with only numpy and warp installed cannot import
HEAVY = ("cv2", "OpenImageIO", "pycolmap", "pymeshlab", "xatlas", "matplotlib", "scipy", "tqdm", "pygltflib",
         "trimesh")


def texstream_imports(source: str, own_folder: str) -> list[tuple[int, str]]:
    """(line, folder) of every texstream folder a module's source imports (relative imports resolve
    to ``own_folder``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: within the folder
                found.append((node.lineno, own_folder))
                continue
            names = [node.module] if node.module else []
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] == "texstream" and len(parts) > 1:
                found.append((node.lineno, parts[1]))
    return found


def layer_violations(root: Path = ROOT) -> list[str]:
    """One line per import that breaks :data:`ALLOWED`."""
    bad = []
    for folder, allowed in ALLOWED.items():
        for path in sorted((root / folder).rglob("*.py")):
            for line, target in texstream_imports(path.read_text(), folder):
                if target != folder and target not in allowed:
                    bad.append(f"{path.relative_to(root)}:{line}: {folder} imports {target}")
    return bad


def test_every_folder_keeps_the_layer_rule():
    assert layer_violations() == []


def test_the_check_catches_a_stage_importing_the_cli(tmp_path):
    for folder in ALLOWED:
        (tmp_path / folder).mkdir()
    (tmp_path / "fit" / "bad.py").write_text("def f():\n    from texstream.pipelines.cli import main\n")
    (tmp_path / "core" / "worse.py").write_text("import texstream.capture.imageio\n")
    assert layer_violations(tmp_path) == ["core/worse.py:1: core imports capture",
                                          "fit/bad.py:2: fit imports pipelines"]


def test_fit_and_renderer_import_only_numpy_and_warp():
    modules = [".".join(("texstream",) + p.relative_to(ROOT).with_suffix("").parts) for p in (ROOT / "fit").rglob("*.py")
               if p.stem != "__init__"]
    code = ("import importlib, sys\n"
            f"for m in {sorted(modules)!r}: importlib.import_module(m)\n"
            f"print(sorted(h for h in {HEAVY!r} if h in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"


@pytest.mark.parametrize("folder", sorted(ALLOWED))
def test_each_layer_folder_is_an_installed_package(folder):
    """The rule covers every top-level package folder pyproject maps into ``texstream``."""
    text = (ROOT / "pyproject.toml").read_text()
    assert f'"texstream.{folder}" = "{folder}"' in text
