"""The appearance-model registry (fit/models/registry.py): nothing outside fit/models/ branches on a model
kind's name, and a model defined outside the package goes through fit, eval, export and report by
registering itself, with no other file touched."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import numpy as np
import pytest

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


# --------------------------------------------------------------------------------------------------------------------
# a model defined outside the package: registering it is all it takes

TEST_KIND = "test_half_radiance"
SHADER = """// the test plugin's viewer: the nearest texel's radiance, halved and doubled back (its own GLSL)
vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng, vec3 eye, int part) {
  Taps a = texel_taps(uv);
  ivec2 t = ivec2(a.x0, a.y0);
  return 2.0 * (0.5 * vec3(P(t, 0), P(t, 1), P(t, 2)));
}
"""


def _test_plugin():
    """A view-independent radiance model with its own folder side (export, report, viewer), fitted by the
    per-texel fit and registered under a new name."""
    from texstream.fit.models.per_texel.fit import fit as per_texel_fit
    from texstream.fit.models.per_texel.folder import PerTexelModel, load_per_texel
    from texstream.render.layout import LayoutTraits

    class HalfRadianceModel(PerTexelModel):
        def export_material(self, cfg) -> registry.ExportMaterial:
            rad = self.grid[..., 0:3].astype(np.float64)
            return registry.ExportMaterial(np.clip(rad, 0.0, 1.0), unlit=True, label="radiance", name=TEST_KIND,
                                           clipped=int((rad.max(axis=-1)[self.covered] > 1).sum()))

        def report_maps(self, save, seen) -> None:
            save("test_radiance", np.clip(self.grid[..., 0:3], 0.0, 1.0), "the test plugin's radiance")

        def viewer(self) -> registry.ViewerModel:
            return registry.ViewerModel(self.grid, SHADER, lit=False, note="The test plugin's model: unlit.")

    return registry.AppearanceModel(
        kind=TEST_KIND, title="test radiance", needs_light=False, units="photo values per unit exposure",
        fit=per_texel_fit, load=lambda d, man: load_per_texel(HalfRadianceModel, TEST_KIND, d, man),
        layout_traits=LayoutTraits(lit=False, lobes=False))


@pytest.fixture
def test_plugin():
    registry.register(_test_plugin())
    yield registry.get(TEST_KIND)
    registry.unregister(TEST_KIND)


def test_a_plugin_from_outside_goes_through_fit_eval_export_and_report(test_plugin, tmp_path):
    """Fit, eval, export and the report of a kind no file of the package names, by the same stage functions the
    CLI calls; its hooks (material, maps, shader) are the ones that run."""
    from conftest import tiny_sphere_capture

    from texstream.fit.models.radiance.fit import SETTLED_REL_TOL, SETTLED_SYNC_EVERY
    from texstream.fit.stages.export import export_stage
    from texstream.fit.stages.stage import FitStageConfig, eval_stage, fit_stage
    from texstream.pipelines.report import write_report

    cap = tiny_sphere_capture(tmp_path, photos=8)
    cfg = FitStageConfig(holdout_every=4, renders=1)
    cfg.fit.model, cfg.fit.max_iterations, cfg.fit.robust_loss = TEST_KIND, 3, "none"
    # the shipped radiance model's own stopping rule (fit/models/radiance/fit.py settled_config), given explicitly
    # so both kinds stop by the same rule
    cfg.fit.rel_tol, cfg.fit.sync_every = SETTLED_REL_TOL, SETTLED_SYNC_EVERY
    fitted = fit_stage(cap, cap / "ground_truth", tmp_path / "model", cfg, progress=False)
    man = json.loads((tmp_path / "model" / "model.json").read_text())
    assert man["layout"]["kind"] == TEST_KIND and man["units"] == test_plugin.units
    # the same traits as the shipped radiance model under the same loss: the same arithmetic, the same score
    cfg.fit.model = "radiance"
    shipped = fit_stage(cap, cap / "ground_truth", tmp_path / "radiance", cfg, progress=False)
    assert fitted.summary["heldout"]["views"] == 2
    assert fitted.summary["heldout"]["pooled_psnr_db"] == shipped.summary["heldout"]["pooled_psnr_db"]
    scored = eval_stage(tmp_path / "model", cap, holdout_every=4)
    # eval renders with the plugin's renderer the views the fit held out: the same pooled score
    assert scored.summary["pooled_psnr_db"] == pytest.approx(fitted.summary["heldout"]["pooled_psnr_db"], abs=1e-6)
    export_stage(tmp_path / "model", tmp_path / "export")
    exported = json.loads((tmp_path / "export" / "export.json").read_text())
    assert TEST_KIND in json.dumps(exported) and (tmp_path / "export" / "model.glb").stat().st_size > 0
    write_report(tmp_path, [], tmp_path / "model", cap)
    page = (tmp_path / "report" / "index.html").read_text()
    assert "the test plugin&#x27;s radiance" in page or "the test plugin's radiance" in page
    assert "halved and doubled back" in page  # the viewer's shader is the plugin's


def test_an_unregistered_kind_fails_with_the_known_kinds(tmp_path):
    from texstream.core.errors import ConfigError
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    cfg = FitStageConfig()
    cfg.fit.model = "no_such_model"
    with pytest.raises(ConfigError, match="lafortune"):
        fit_stage(tmp_path, tmp_path, tmp_path / "out", cfg, progress=False)


def test_every_plugin_folder_is_an_installed_package():
    """A wheel carries only the packages pyproject lists: a plugin folder left out would vanish on install."""
    text = (ROOT / "pyproject.toml").read_text()
    for folder in sorted(p for p in PLUGINS.iterdir() if (p / "__init__.py").is_file()):
        rel = folder.relative_to(ROOT).as_posix()
        assert f'"texstream.{rel.replace("/", ".")}" = "{rel}"' in text, rel

