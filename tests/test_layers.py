"""The layer rule: which package may import which (the one place it is written down).

The packages form an ordered list of layers, low to high (:data:`LAYERS`); a module may import
modules of its own layer or of lower ones, never of a higher one:

    core               the spine (errors, config fields and their JSON, atomic outputs)
    render             the camera struct, shading, depth maps, the renderer, SurfaceMesh
    capture            the capture folder, conventions, image IO (not capture.synthetic)
    calib              intrinsics, registration, ingest, lights
    geometry           meshes, atlas, texel bake, photometric refinement
    capture.synthetic  synthetic captures with ground truth (needs geometry's atlas and bake)
    fit.kernels        the fit's Warp kernels and parameter layout (and modules directly in fit/)
    fit.stream         the streaming problem and its photos
    fit.optim          optimizers and the fit loop
    fit.multi          fits split over tiles, devices, machines
    fit.common         what every model plugin's fit uses (inputs, set-up, checkpoints, model folders)
    fit.models         the appearance models
    fit.stages         the fit / eval stages
    fit.diagnostics    fpcheck, stiffcheck, accuracy
    pipelines          the CLI and the end-to-end run

Every import counts, also one inside a function: a module that imports a higher layer at call time
inverts the layers as much as one that does so at import time. On top of the order, the module
import graph (every import of a texstream module, inside functions too) has no cycle, and
``texstream.fit`` and ``texstream.render`` (the GPU side, which runs where only numpy and warp are
installed) import no third-party package but numpy and warp at module import time.

Texstream's own modules are imported at the top of the module that uses them, never inside a function
(a dependency a reader should see at the top, and one a layer or cycle check would otherwise meet only
at call time); the few exceptions, each with its reason, are :data:`FUNCTION_IMPORTS_ALLOWED`.
Third-party packages are another matter: heavy or optional ones stay inside the functions that use them.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LAYERS: list[tuple[str, ...]] = [
    ("core",),
    ("render",),
    ("capture",),
    ("calib",),
    ("geometry",),
    ("capture.synthetic",),
    ("fit.kernels", "fit"),
    ("fit.stream",),
    ("fit.optim",),
    ("fit.multi",),
    ("fit.common",),
    ("fit.models",),
    ("fit.stages",),
    ("fit.diagnostics",),
    ("pipelines",),
]
"""module prefixes (below ``texstream``) of each layer, low to high; a module belongs to the layer of
its longest matching prefix (so ``capture.synthetic.synth`` is not in ``capture``, and only modules
directly in fit/ fall to the bare ``fit``)"""
# what a GPU machine with only numpy and warp installed cannot import
HEAVY = ("cv2", "OpenImageIO", "pycolmap", "pymeshlab", "xatlas", "matplotlib", "scipy", "tqdm", "pygltflib",
         "trimesh")
FUNCTION_IMPORTS_ALLOWED: set[tuple[str, str]] = {
    # the CLI's dispatch: the decoding pool starts only for the commands that decode photos (fit, run), so
    # `texstream --help` and the other commands load no numpy (the subcommand modules themselves are loaded
    # by name, importlib, when their command runs)
    ("pipelines.cli", "fit.stream.decode_pool"),
}
"""(module, texstream module it imports inside a function): the only imports of texstream modules that
are not at a module's top. A module whose top-level import would make ``texstream.fit`` or
``texstream.render`` load a :data:`HEAVY` package would be one (none is, today)."""


def layer_of(module: str) -> int | None:
    """Index in :data:`LAYERS` of a module (dotted, below ``texstream``); None for one in no layer."""
    best, found = -1, None
    for index, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, found = len(prefix), index
    return found


def layer_name(index: int | None) -> str:
    return "no layer" if index is None else LAYERS[index][0]


def package_modules(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the layer folders, dotted below ``texstream`` (a package by its folder's name)."""
    modules = {}
    for folder in sorted({prefixes[0].split(".")[0] for prefixes in LAYERS}):
        for path in sorted((root / folder).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


def module_imports(module: str, path: Path, known: set[str],
                   in_functions_only: bool = False) -> list[tuple[int, str]]:
    """(line, module) of every texstream module ``module``'s source imports, inside functions too
    (``in_functions_only``: only those).

    ``from texstream.x import y`` is module ``x.y`` when that is a module, else ``x``; relative
    imports resolve against the module's package. Imports under ``if TYPE_CHECKING:`` are left out: they
    name a type for the checkers, run no code and order nothing at run time."""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                   and ast.unparse(block.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")
                   for stmt in block.body for n in ast.walk(stmt)}
    in_functions = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                    for n in ast.walk(f)}
    found = []
    for node in ast.walk(tree):
        if id(node) in typing_only or (in_functions_only and id(node) not in in_functions):
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                target = ".".join(base + (node.module.split(".") if node.module else []))
            elif node.module and node.module.startswith("texstream."):
                target = node.module[len("texstream."):]
            else:
                continue
            subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in known]
            # the names that are not modules come from the package itself
            if len(subs) < len(node.names):
                found.append((node.lineno, target))
            found += [(node.lineno, s) for s in subs]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name[len("texstream."):]) for a in node.names
                      if a.name.startswith("texstream.")]
    return found


def import_graph(root: Path = ROOT) -> dict[str, list[tuple[int, str]]]:
    """module -> (line, imported module) for every texstream import of every module of the package."""
    modules = package_modules(root)
    known = set(modules)
    return {m: module_imports(m, p, known) for m, p in modules.items()}


def layer_violations(root: Path = ROOT) -> list[str]:
    """One line per import of a higher layer (or of, or from, a module in no layer)."""
    modules = package_modules(root)
    bad = []
    for module, imports in import_graph(root).items():
        mine = layer_of(module)
        where = modules[module].relative_to(root)
        for line, target in imports:
            theirs = layer_of(target)
            if mine is None or theirs is None or theirs > mine:
                bad.append(f"{where}:{line}: {module} ({layer_name(mine)}) imports {target} ({layer_name(theirs)})")
    return bad


def function_imports(root: Path = ROOT,
                     allowed: set[tuple[str, str]] = FUNCTION_IMPORTS_ALLOWED) -> tuple[list[str], list[tuple[str, str]]]:
    """(one line per import of a texstream module inside a function that ``allowed`` does not list,
    the entries of ``allowed`` that no such import uses any more)."""
    modules = package_modules(root)
    known = set(modules)
    bad, used = [], set()
    for module, path in modules.items():
        for line, target in module_imports(module, path, known, in_functions_only=True):
            if (module, target) in allowed:
                used.add((module, target))
            else:
                bad.append(f"{path.relative_to(root)}:{line}: {module} imports {target} inside a function")
    return bad, sorted(allowed - used)


def import_cycles(root: Path = ROOT) -> list[list[str]]:
    """The cycles of the module import graph: per strongly connected component, a shortest cycle
    through each of its modules (each cycle once, starting at its smallest module)."""
    graph = {m: sorted({t for _, t in imports if t != m}) for m, imports in import_graph(root).items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []

    def connect(v: str) -> None:  # Tarjan; the package is small, recursion is shallow
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                connect(w)
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
                components.append(set(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    cycles = []
    for component in components:
        for start in sorted(component):
            # breadth-first within the component, back to start
            parent, frontier, cycle = {start: None}, [start], None
            while frontier and cycle is None:
                nxt = []
                for v in frontier:
                    for w in graph[v]:
                        if w == start:
                            cycle = [v]
                            while parent[cycle[-1]] is not None:
                                cycle.append(parent[cycle[-1]])
                            cycle.reverse()
                            break
                        if w in component and w not in parent:
                            parent[w] = v
                            nxt.append(w)
                    if cycle is not None:
                        break
                frontier = nxt
            i = cycle.index(min(cycle))
            cycle = cycle[i:] + cycle[:i]
            if cycle not in cycles:
                cycles.append(cycle)
    return cycles


def test_every_module_keeps_the_layer_order():
    bad = layer_violations()
    print("\n".join(bad))
    assert bad == []


def test_the_module_import_graph_has_no_cycle():
    cycles = import_cycles()
    print("\n".join(" -> ".join(c + [c[0]]) for c in cycles))
    assert cycles == []


def _plant(root: Path, files: dict[str, str]) -> None:
    for prefixes in LAYERS:
        (root / prefixes[0].replace(".", "/")).mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (root / name).write_text(text)


def test_the_check_catches_a_lower_layer_importing_a_higher_one(tmp_path):
    _plant(tmp_path, {
        "fit/stages/stage.py": "",
        "pipelines/cli.py": "",
        "capture/synthetic/synth.py": "",
        "geometry/bake.py": "",
        # inside a function, through `from package import module`
        "fit/kernels/bad.py": "def f():\n    from texstream.pipelines import cli\n",
        "core/worse.py": "import texstream.render.mesh\n",
        # capture.synthetic is above geometry, capture below it
        "capture/io.py": "def f():\n    from texstream.capture.synthetic.synth import x\n",
        "capture/synthetic/fine.py": "from texstream.geometry.bake import bake\nfrom . import synth\n",
        "fit/__init__.py": "from texstream.fit.stream import problem\n",
    })
    assert layer_violations(tmp_path) == [
        "capture/io.py:2: capture.io (capture) imports capture.synthetic.synth (capture.synthetic)",
        "core/worse.py:1: core.worse (core) imports render.mesh (render)",
        "fit/__init__.py:1: fit (fit.kernels) imports fit.stream (fit.stream)",
        "fit/kernels/bad.py:2: fit.kernels.bad (fit.kernels) imports pipelines.cli (pipelines)",
    ]


def test_the_check_catches_a_two_module_cycle(tmp_path):
    _plant(tmp_path, {
        "geometry/a.py": "from texstream.geometry.b import g\n",
        "geometry/b.py": "def g():\n    from texstream.geometry import a\n",
        "geometry/c.py": "from . import a\n",
    })
    assert import_cycles(tmp_path) == [["geometry.a", "geometry.b"]]


def test_texstream_modules_are_imported_at_the_top():
    bad, unused = function_imports()
    print("\n".join(bad))
    assert bad == [], "move these imports to the module's top (or list them, with the reason, in FUNCTION_IMPORTS_ALLOWED)"
    assert unused == [], "these allowed function-level imports are gone: drop them from FUNCTION_IMPORTS_ALLOWED"


def test_the_check_catches_an_import_inside_a_function(tmp_path):
    _plant(tmp_path, {
        "core/errors.py": "",
        "core/outputs.py": "",
        "render/mesh.py": "",
        "geometry/fine.py": "from texstream.core.errors import E\nfrom . import mvs\n",
        "geometry/mvs.py": "",
        # a relative import in a method, an absolute one in a nested function, one allowed
        "geometry/bad.py": ("class C:\n    def f(self):\n        from .mvs import x\n"
                            "def g():\n    def h():\n        import texstream.render.mesh\n"
                            "def k():\n    from texstream.core import outputs\n"),
    })
    allowed = {("geometry.bad", "core.outputs"), ("geometry.gone", "core.errors")}
    assert function_imports(tmp_path, allowed) == (
        ["geometry/bad.py:3: geometry.bad imports geometry.mvs inside a function",
         "geometry/bad.py:6: geometry.bad imports render.mesh inside a function"],
        [("geometry.gone", "core.errors")])


def test_fit_and_renderer_import_only_numpy_and_warp():
    modules = [".".join(("texstream",) + p.relative_to(ROOT).with_suffix("").parts)
               for folder in ("fit", "render") for p in (ROOT / folder).rglob("*.py") if p.stem != "__init__"]
    code = ("import importlib, sys\n"
            f"for m in {sorted(modules)!r}: importlib.import_module(m)\n"
            f"print(sorted(h for h in {HEAVY!r} if h in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"


@pytest.mark.parametrize("package", sorted(p for prefixes in LAYERS for p in prefixes))
def test_each_layer_folder_is_an_installed_package(package):
    """The rule covers every package pyproject maps into ``texstream``."""
    folder = package.replace(".", "/")
    assert (ROOT / folder).is_dir(), f"{folder}/ is a layer of LAYERS but no folder: add it or drop it from LAYERS"
    text = (ROOT / "pyproject.toml").read_text()
    assert f'"texstream.{package}" = "{folder}"' in text
