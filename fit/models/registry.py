"""The appearance-model registry: each model kind is a plugin folder under ``fit/models/``.

A plugin declares in one place what the rest of texstream needs of a model kind, and nothing outside
``fit/models/`` branches on a kind's name: the fit, eval and export stages, the report, its viewer and the
run look the model up here (by the requested kind, or by ``model.json``'s ``layout.kind``).

A plugin is a folder ``fit/models/<name>/`` whose ``__init__.py`` builds an :class:`AppearanceModel` and
calls :func:`register` with it. :func:`load_plugins` imports every such folder once (the only import by
name in the package: adding a model is adding a folder); a model defined elsewhere (a test, a user's own
package) registers itself the same way.

Two halves:
- the **fit side** (:class:`AppearanceModel`): its parameter layout and bounds (``layout``), whether it
  needs a known light per photo, its units, how it fits a capture into a model folder (``fit``), and which
  candidates it offers the automatic model choice (``candidates``);
- the **model-folder side** (:class:`FittedModel`, made by ``AppearanceModel.load``): how a written
  model renders (eval, the report's held-out views), exports (glTF / OBJ material) and is shown (the
  report's parameter maps and summary lines, the viewer's data and GLSL shading function).
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from pathlib import Path
from typing import Any, Callable

import numpy as np

from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import read_json
from texstream.render.layout import LayoutTraits, register_layout_kind


@dataclasses.dataclass
class ExportMaterial:
    """A model's material as images for glTF / OBJ (fit/stages/export.py writes it).

    Attributes:
        base: (H, W, 3) linear in [0, 1]: the albedo (lit) or the clipped radiance (unlit).
        unlit: the colour is radiance (KHR_materials_unlit; OBJ's Kd with no lighting meant).
        specular: (H, W, 3) F0 / specular_scale in [0, 1], or None (no specular layer).
        specular_scale: largest F0 over covered texels (0: no specular layer).
        roughness: (H, W) glTF roughness in [0, 1], or None.
        ns: OBJ exponent.
        clipped: covered texels whose base colour was clipped at 1.
        label: what the base map holds, for file names and notes ("basecolor", "radiance").
        name: the material's name in the files (glTF ``texstream_<name>``, export.json's ``kind``):
            "lafortune", "diffuse" or "radiance".
        extras: model-specific options the export records (export.json, the glTF material's extras),
            e.g. how an LFM's unlit colour was made.
        pbr: the glTF material when it differs from the fields above (a lit model's core metallic-roughness
            fit, fit/models/lafortune/gltf_core.py ``CoreMaterial``: base colour, metallic, roughness and
            KHR_materials_specular's F0 per texel); None: the glTF material is base (+ specular) as above.
        emissive: (H, W, 3) linear radiance the surface sends whatever the light (a reflectance model's fitted
            ambient radiance, the room's light baked in, render/layout.py ``ModelLayout.ambient``), or None.
        environment: (h, w, 3) linear latitude-longitude radiance (render/sh.py's convention) of the light the
            material was estimated under, written beside the glTF / OBJ as environment.exr and named in
            export.json's ``files.environment``; None: none (a model with known lights, or unlit).
    """

    base: np.ndarray
    unlit: bool = False
    specular: np.ndarray | None = None
    specular_scale: float = 0.0
    roughness: np.ndarray | None = None
    ns: float = 1.0
    clipped: int = 0
    label: str = "basecolor"
    name: str = ""
    extras: dict = dataclasses.field(default_factory=dict)
    pbr: Any = None
    emissive: np.ndarray | None = None
    environment: np.ndarray | None = None


@dataclasses.dataclass
class ViewerModel:
    """What the report's WebGL viewer needs of a model.

    Attributes:
        grid: (H, W, P) float32 parameters per atlas texel, uploaded as the viewer's parameter texture.
        shader: GLSL (ES 3.0) source defining ``vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng,
            vec3 eye, int part)``: the radiance toward ``eye`` at a surface point, lit by the viewer's light
            (uniforms ``u_lkind``, ``u_lpd``, ``u_lI``) where ``lit`` is true. The viewer supplies
            ``P(ivec2 texel, int column)`` to read the grid, the grid's size ``u_W``, ``u_H``,
            ``Taps texel_taps(vec2 uv)`` (the bilinear taps of render/shading.py: x, y, x0, y0, fx, fy)
            and ``mat3 surface_frame(vec3 nrm, vec3 tng)`` (columns tangent, bitangent, normal);
            pipelines/report_assets/viewer.js has the prelude. A plugin ships it as viewer.glsl.
        lit: the light controls change the render.
        data: extra values for the shader, merged into the viewer's model data: ``uniforms`` {name: int}
            (integer uniforms the shader declares) and ``textures``, a list of {name, width, height,
            layers (a 2D array texture; absent: 2D), data (base64 little-endian float32 RGBA)}: float
            textures bound to units 3, 4, ... and their sampler uniforms ``name``.
        note: one sentence for the viewer's caption (what the model shows, what the controls do).
    """

    grid: np.ndarray
    shader: str
    lit: bool
    data: dict = dataclasses.field(default_factory=dict)
    note: str = ""


class FittedModel:
    """A model folder as read back by its plugin. Subclasses implement the hooks.

    Attributes:
        kind: the plugin's kind.
        folder: the model folder.
        mesh: SurfaceMesh with normals and UVs.
        manifest: model.json.
        covered: (H, W) bool, atlas texels on the surface.
    """

    def __init__(self, kind: str, folder: Path, mesh, manifest: dict, covered: np.ndarray):
        self.kind, self.folder, self.mesh, self.manifest, self.covered = kind, Path(folder), mesh, manifest, covered

    def renderer(self, device: str = "cpu") -> Callable[[Any], tuple[np.ndarray, np.ndarray]]:
        """A function frame -> (image (H, W, 3) linear, coverage mask (H, W)) rendering the model as that
        photo was taken (its camera, light and exposure)."""
        raise NotImplementedError

    def export_material(self, cfg) -> ExportMaterial:
        """The material written to glTF / OBJ (``cfg``: fit/stages/export.py ExportConfig)."""
        raise NotImplementedError

    def map_files(self) -> list[Path]:
        """The parameter maps copied beside an OBJ export."""
        names = self.manifest.get("maps")
        files = [self.folder / str(v) for v in names.values()] if isinstance(names, dict) else []
        files = [f for f in files if f.is_file()]
        return files or sorted(self.folder.glob("*.exr"))

    def report_maps(self, save: Callable, seen: np.ndarray | None) -> None:
        """Figures of the parameter maps: ``save(name, img, caption, cmap=None, vmin=None, vmax=None,
        colorbar_label=None)`` per map."""
        raise NotImplementedError

    def report_facts(self) -> list[tuple[str, str]]:
        """Model-specific (label, value) rows of the report's summary table."""
        return []

    def report_relit_lights(self) -> list[tuple[str, Any]]:
        """(caption, light) pairs the report renders a held-out view under beside its photo (a relightable
        model's ``relit_renderer(light, device)``); none for a model that cannot be relit."""
        return []

    def viewer(self) -> ViewerModel:
        raise NotImplementedError


@dataclasses.dataclass
class FitRequest:
    """What a plugin's ``fit`` is given: the posed capture, the mesh (an atlas folder or a mesh file), the output
    model folder, the fit stage's config (fit/stages/stage.py FitStageConfig, ``fit.model`` this plugin's kind) and
    whether to show progress bars."""

    capture_dir: Path
    mesh_path: Path
    out_dir: Path
    cfg: Any
    progress: bool = True


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One fit the automatic model choice may try: a plugin's kind and the FitConfig fields it changes."""

    name: str
    kind: str
    overrides: dict = dataclasses.field(default_factory=dict)
    label: str = ""
    """how logs name it ("the two-lobe Lafortune"); the name when empty"""
    supported: Callable | None = None
    """(summaries of the candidates fitted before it, by name; FitStageConfig) -> None when the photos can support
    it, else the reason it is left out unfitted; None: always fitted"""


@dataclasses.dataclass
class AppearanceModel:
    """A model kind, as the stages see it.

    Attributes:
        kind: the name in ``--model`` and in model.json's ``layout.kind``.
        title: a few words for logs and the report ("Lafortune SBRDF").
        needs_light: fitted from photos with a known light each (reflectance); False: under one fixed,
            unknown lighting (radiance).
        units: of its parameters, written to model.json.
        fit: (FitRequest) -> StageResult: fits a capture and writes the model folder.
        load: (model folder, manifest) -> FittedModel.
        candidates: (capture, FitStageConfig) -> list[Candidate]: the fits the automatic choice tries when
            this is the capture's base model (None: it is never a base model).
        escalate: (held-out scores by candidate name, FitStageConfig) -> (list[Candidate], reason): further fits
            the choice tries once the first round is scored (None: none); called with scores None before the
            fits, it returns ([], a phrase for the plan's log line). The reason is recorded in the selection
            under ``escalation_key``.
        auto_rank: the base model for a capture with lights (needs_light) or without: lowest rank wins.
        relightable: its folder can be rendered under another light than the photos' (``FittedModel.
            report_relit_lights``); the choice's ``relightable`` option fits it beside the base model's
            candidates (fit/stages/choice.py).
        layout_traits: what the kind's name means for the per-texel parameter table and kernels
            (render/layout.py LayoutTraits), or None: the model has no per-texel table of its own (light field
            mapping).
    """

    kind: str
    title: str
    needs_light: bool
    units: str
    fit: Callable
    load: Callable
    candidates: Callable | None = None
    escalate: Callable | None = None
    auto_rank: int = 100
    escalation_key: str = "escalation"
    relightable: bool = False
    layout_traits: LayoutTraits | None = None


_REGISTRY: dict[str, AppearanceModel] = {}
_LOADED = False


def register(model: AppearanceModel) -> AppearanceModel:
    """Add a model kind (a second registration of the same kind replaces the first)."""
    _REGISTRY[model.kind] = model
    if model.layout_traits is not None:
        register_layout_kind(model.kind, model.layout_traits)
    return model


def unregister(kind: str) -> None:
    _REGISTRY.pop(kind, None)


def load_plugins() -> None:
    """Import every plugin folder of ``fit/models/`` once; each registers itself."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for info in pkgutil.iter_modules([str(Path(__file__).parent)]):
        if info.ispkg:
            importlib.import_module(f"{__package__}.{info.name}")


def kinds() -> list[str]:
    load_plugins()
    return sorted(_REGISTRY)


def get(kind: str) -> AppearanceModel:
    """The plugin of ``kind``; a ConfigError listing the known kinds otherwise."""
    load_plugins()
    if kind not in _REGISTRY:
        raise ConfigError(f"unknown model kind {kind!r}", fix=f"use one of {sorted(_REGISTRY)}")
    return _REGISTRY[kind]


def kind_of_folder(model_dir: str | Path) -> tuple[str, dict]:
    """(kind, model.json) of a model folder; an InputError naming the file otherwise."""
    d = Path(model_dir)
    fix = "pass a folder written by `texstream fit` (it holds model.json)"
    if not d.is_dir():
        raise InputError("model folder not found" if not d.exists() else "not a folder", d, fix)
    if not (d / "model.json").is_file():
        raise InputError("not a model folder (no model.json)", d / "model.json", fix)
    man = read_json(d / "model.json", what="model manifest")
    if isinstance(man, dict) and isinstance(man.get("layout"), dict) and "kind" in man["layout"]:
        return str(man["layout"]["kind"]), man
    if isinstance(man, dict) and isinstance(man.get("kind"), str):  # a folder without a layout (a map and a mesh)
        return man["kind"], man
    raise InputError("model.json has no layout (kind, n_lobes, ...)", d / "model.json",
                     "re-run `texstream fit`, which writes the layout")


def load_model_folder(model_dir: str | Path) -> FittedModel:
    """The model folder read back by its plugin (found by model.json's ``layout.kind``, or ``kind`` for a
    folder without a layout)."""
    kind, man = kind_of_folder(model_dir)
    load_plugins()
    if kind not in _REGISTRY:
        raise InputError(f"model.json names a model kind this texstream does not know ({kind!r})",
                         Path(model_dir) / "model.json", f"use a texstream with that model (known: {sorted(_REGISTRY)})")
    return _REGISTRY[kind].load(Path(model_dir), man)
