"""The streaming problem of a per-texel fit set up from its inputs, run with progress and a checkpoint, and its
parameters turned into atlas maps and renders (shared by the model plugins, the accuracy tests and the benchmarks)."""

from __future__ import annotations

import dataclasses
import time
import zipfile
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import read_capture
from texstream.capture.synthetic.param_maps import read_param_maps
from texstream.core.checkpoint import files_signature
from texstream.core.errors import InputError
from texstream.core.outputs import read_json
from texstream.core.progress import bar, bars_enabled, say

from texstream.fit.optim.fitter import FitConfig, FitResult, run_fit
from texstream.fit.common.model_folder import image_metrics
from texstream.fit.multi.photo_split import build_device_photos, check_split_devices
from texstream.fit.multi.tiles import parse_devices, split_photos
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.problem import StreamProblem
from texstream.fit.stream.texels import TexelSet, surface_derivatives, texel_coordinate_gradients
from texstream.geometry.mesh_io import load_mesh, write_npz_atomic
from texstream.render.camera import PhotoFrame
from texstream.render.layout import ModelLayout
from texstream.render.renderer import Renderer


def build_problem(mesh, bake, frames, images, masks, cfg: FitConfig, device: str, photos=None):
    """The StreamProblem of a fit: texels from the bake, photos on the device with their depth and
    shadow maps (``photos``: a PhotoSet of these frames built before, e.g. by another problem's
    call, reused as it is; building one is most of the set-up time). The photos are set up on a
    thread of their own while this one computes the texels (host work, beside the photos' uploads
    and map launches); split over devices (``StreamConfig.device_split`` photos), each device's on
    a thread of its own."""
    import concurrent.futures
    import contextvars

    # a light of intensity 0 (a photo taken with the flash off, capture_json.py ``no_flash``) stays where the capture
    # puts it: the kernels take such a photo's samples with the camera's tests alone (fit/kernels/stream.py
    # ``observe_with_unlit_func``) and their ambient alone (fit/kernels/accumulate.py)
    photo_frames = [PhotoFrame.from_capture_frame(f) for f in frames]
    normals = mesh.vertex_normals()  # computed anew on each call for a mesh without stored normals

    split = split_photos(cfg)  # before any work: refuses tiles with it

    def make_photos():
        if split:
            devices = parse_devices(cfg.stream.devices, device)
            check_split_devices(devices, device)
            return build_device_photos(photo_frames, images, mesh.vertices, mesh.faces, masks, cfg.stream, devices,
                                       mesh_normals=normals, mesh_uvs=mesh.uvs)
        return PhotoSet(photo_frames, images, mesh.vertices, mesh.faces, masks=masks, config=cfg.stream,
                        device=device, mesh_normals=normals, mesh_uvs=mesh.uvs)

    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="texstream-photos") as pool:
        # in a copy of this context: the stage's log and its registry of loaders to close
        pending = pool.submit(contextvars.copy_context().run, make_photos) if photos is None else None
        texels = texels_of(mesh, bake, normals)
        if pending is not None:
            photos = pending.result()  # a photo's error is raised here, after the texels
    if texels.n == 0:
        raise InputError("the atlas has no covered texels", fix="rebuild the atlas with a larger resolution")
    layout = cfg.layout(photo_frames, texels.position.mean(axis=0))
    return StreamProblem(texels, photos, layout, cfg.stream, device=device)


_TEXELS_BUILT: list = []
"""[(mesh, bake, TexelSet)] of the last read-only atlas set up (fit/common/inputs.py ``_atlas_folder``): the
model choice's candidates and the fit after them set up the same texels"""


def texels_of(mesh, bake, normals: np.ndarray) -> TexelSet:
    """The TexelSet of ``bake`` on ``mesh``: built once for an atlas read from disk (its arrays read-only, so it
    cannot have changed since), every time for any other."""
    for built_mesh, built_bake, texels in _TEXELS_BUILT:
        if built_mesh is mesh and built_bake is bake:
            return texels
    face_normal, normal_jacobian = surface_derivatives(mesh.vertices, mesh.faces, normals, bake.face, bake.bary)
    coordinate_gradients = None
    if mesh.uvs is not None:
        coordinate_gradients = texel_coordinate_gradients(mesh.vertices, mesh.faces, mesh.uvs, bake.face,
                                                          bake.width, bake.height)
    texels = TexelSet.from_grid(bake.covered, bake.position, bake.normal, bake.tangent, bake.bitangent,
                                face_normal, normal_jacobian, coordinate_gradients, bake.fill_source)
    if not (mesh.vertices.flags.writeable or bake.face.flags.writeable):
        for array in vars(texels).values():
            if isinstance(array, np.ndarray):
                array.flags.writeable = False
        _TEXELS_BUILT[:] = [(mesh, bake, texels)]
    return texels


def params_to_grid(result: FitResult, problem, bake) -> np.ndarray:
    """Compact per-texel parameters -> (H, W, P) grid with padding filled (no bilinear bleeding)."""
    lay = result.layout
    grid = np.tile(lay.defaults().astype(np.float32), (bake.height * bake.width, 1))
    grid[problem.texels.grid_index] = result.params
    return bake.fill_padding(grid.reshape(bake.height, bake.width, -1))


def render_model(mesh, grid: np.ndarray, layout: ModelLayout, frame, device: str):
    rend = Renderer(mesh, grid, layout, device=device)
    res = rend.render_frame(frame)
    return res.radiance * np.float32(frame.exposure), res.mask


class ModelRenders:
    """Renders of per-texel maps on one mesh, frame after frame and maps after maps: the renderer (the mesh's
    BVH, normals and output buffers) built once and each new grid copied into its maps, the renders
    :func:`render_model` gives (which builds one per frame: for the materials choice's 4 candidates x 220
    validation views of the full ornament, 880 BVH builds)."""

    def __init__(self, mesh, layout: ModelLayout, device: str):
        self.mesh, self.layout, self.device = mesh, layout, device
        self.renderer: Renderer | None = None

    def set_grid(self, grid: np.ndarray) -> None:
        """Render ``grid`` (H, W, P) from now on."""
        r = self.renderer
        if r is None or grid.shape != (r.tex_h, r.tex_w, self.layout.n_params):
            self.renderer = Renderer(self.mesh, grid, self.layout, device=self.device)
            return
        if not np.all(np.isfinite(grid)):
            raise InputError("params grid holds NaN or Inf", fix="fill every texel (fill_padding)")
        grid = self.layout.rendered(grid)[1]  # a room light's columns as the radiance they make
        r.params.assign(np.ascontiguousarray(grid.reshape(-1, self.layout.n_params), dtype=np.float32))

    def render(self, frame) -> tuple[np.ndarray, np.ndarray]:
        """(image times the frame's exposure, coverage) of ``frame``."""
        res = self.renderer.render_frame(frame)
        return res.radiance * np.float32(frame.exposure), res.mask


def heldout_psnr(mesh, grid: np.ndarray, layout: ModelLayout, frames, photos, masks, device: str,
                 renders: ModelRenders | None = None) -> tuple[list, float]:
    """Per-view PSNR of the model's renders against ``photos`` (foreground: photo mask and render
    coverage) and the PSNR of the views' pooled mean squared error; ``renders``: a renderer of ``mesh`` to
    reuse (its maps set to ``grid`` here)."""
    renders = renders or ModelRenders(mesh, layout, device)
    renders.set_grid(grid)
    views = []
    for fr, photo, mask in zip(frames, photos, masks):
        render, rmask = renders.render(fr)
        views.append(image_metrics(render, photo, rmask.astype(bool) & mask)["psnr_db"])
    pooled = float(-10 * np.log10(np.mean([10 ** (-v / 10) for v in views])))
    return views, pooled


@dataclasses.dataclass
class SyntheticFit:
    """A fit of a rendered synthetic set scored on held-out renders (:func:`fit_synthetic`)."""

    result: FitResult
    problem: object
    grid: np.ndarray
    """(H, W, P) fitted parameter maps, padding filled"""
    fit_s: float
    """wall time of run_fit alone (no problem set-up)"""
    heldout_views_db: list
    heldout_pooled_db: float


def fit_synthetic(train, held, cfg: FitConfig, device: str, photos=None) -> SyntheticFit:
    """Fit ``train`` (a rendered scene: mesh, bake, frames, images, masks) and score the fitted model
    on ``held``'s views; shared by the accuracy tests and the held-out benchmarks. ``photos``: a
    PhotoSet of ``train`` to reuse (:func:`build_problem`)."""
    prob = build_problem(train.mesh, train.bake, train.frames, train.images, train.masks, cfg, device, photos)
    t0 = time.perf_counter()
    res = run_fit(prob, cfg)
    fit_s = time.perf_counter() - t0
    grid = params_to_grid(res, prob, train.bake)
    views, pooled = heldout_psnr(train.mesh, grid, res.layout, held.frames, held.images, held.masks, device)
    return SyntheticFit(res, prob, grid, fit_s, views, pooled)


def run_fit_with_progress(problem, fit: FitConfig, progress: bool, **kw) -> FitResult:
    """run_fit with a tqdm bar over iterations when ``progress`` (``kw``: checkpoint, resume)."""
    if not (progress and bars_enabled()):
        return run_fit(problem, fit, **kw)
    start = int(kw["resume"]["iteration"]) if kw.get("resume") else 0
    with bar(total=fit.max_iterations, desc=f"fit {fit.optimizer}", unit="it") as b:
        b.update(start)
        return run_fit(problem, fit, progress=lambda it: b.update(1), **kw)


def fit_inputs_signature(capture_dir: str | Path, mesh_path: str | Path) -> list:
    """(path, size, modification time) of what a fit reads: capture.json, the photos and masks, the mesh file or
    the atlas folder's files (hidden ones, a stage's stamp, are not inputs); part of a checkpoint's key, so a
    photo replaced in place is not fitted from a checkpoint of the old one."""
    cap = read_capture(capture_dir)
    mesh = Path(mesh_path)
    files = [cap.root / "capture.json"] + [cap.image_path(f) for f in cap.frames]
    files += [m for m in map(cap.mask_path, cap.frames) if m is not None]
    files += sorted(p for p in mesh.iterdir() if not p.name.startswith(".")) if mesh.is_dir() else [mesh]
    return files_signature(files)


class Checkpoint:
    """The fit's checkpoint beside its output folder (``.NAME.checkpoint.npz``), tied to the inputs and
    options by a key: a rerun with the same ones resumes from it, anything else starts afresh."""

    def __init__(self, out_dir: str | Path, key: dict):
        import hashlib
        import json

        out = Path(out_dir)
        self.path = out.parent / f".{out.name}.checkpoint.npz"
        self.key = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()

    def load(self) -> dict | None:
        """The state of an interrupted fit of the same key, said in one line (as is one ignored)."""
        if not self.path.is_file():
            return None
        try:
            with np.load(self.path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            say("fit", f"checkpoint {self.path} is damaged: ignored, starting afresh")  # only a lost head start
            return None
        if str(data.pop("key", "")) != self.key:
            say("fit", f"checkpoint {self.path} is of other inputs or options: ignored, starting afresh")
            return None
        say("fit", f"resuming from checkpoint {self.path}: {int(data['iteration'])} iterations done")
        return {k: (v.item() if v.ndim == 0 else v) for k, v in data.items()}

    def save(self, state: dict) -> None:
        # uncompressed: written every sync_every iterations and removed at the end
        write_npz_atomic(self.path, compress=False, key=np.array(self.key),
                         **{k: np.asarray(v) for k, v in state.items()})

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def fill_unseen_texels(grid: np.ndarray, problem, bake, result: FitResult,
                       sources: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, int]:
    """Give texels no photo saw the parameters of the nearest seen texel in 3D (their defaults would
    show as a foreign colour wherever a new view sees them, and bleed into seen neighbours through
    the renderer's bilinear lookup). Returns the maps and the number of texels filled. ``sources``:
    :func:`unseen_sources` of the same problem and samples, when the caller fills several grids."""
    targets, nearest = unseen_sources(problem, result) if sources is None else sources
    if not len(targets):
        return grid, 0
    flat = grid.reshape(-1, grid.shape[-1]).copy()
    flat[targets] = flat[nearest]
    return bake.fill_padding(flat.reshape(grid.shape)), int(len(targets))


def has_unlit_photos(frames) -> bool:
    """Whether some photo's light is exactly 0 (taken with the flash off): the kernels take only its ambient."""
    return any(f.light is not None and not np.any(np.asarray(f.light.intensity, np.float64) > 0) for f in frames)


def fill_unlit_reflectance(grid: np.ndarray, problem, bake, seen: np.ndarray, lit_seen: np.ndarray,
                           layout) -> tuple[np.ndarray, int]:
    """Texels whose only samples came from photos taken with the flash off (``seen`` but not ``lit_seen``, compact
    order) get the reflectance (every column but the ambient's) of the nearest texel a lit photo saw, keeping their
    own ambient, which those photos did observe. Their albedo and lobes had no sample to fit and kept the initial
    guess, which shows wherever a flash lights them (issue 39). Returns the maps and the number of texels filled."""
    targets = seen & ~lit_seen
    if not targets.any() or not lit_seen.any() or layout.ambient_offset < 0:
        return grid, 0
    from scipy.spatial import cKDTree  # only when needed (nearest_seen says why)

    idx, position = problem.texels.grid_index, problem.texels.position
    nearest = idx[lit_seen][cKDTree(position[lit_seen]).query(position[targets], workers=-1)[1]]
    flat = grid.reshape(-1, grid.shape[-1]).copy()
    keep = flat[idx[targets], layout.ambient_offset:layout.ambient_offset + 3].copy()
    flat[idx[targets]] = flat[nearest]
    flat[idx[targets], layout.ambient_offset:layout.ambient_offset + 3] = keep
    return bake.fill_padding(flat.reshape(grid.shape)), int(targets.sum())


def unseen_sources(problem, result: FitResult) -> tuple[np.ndarray, np.ndarray]:
    """(grid rows of the texels no photo saw, grid rows of the nearest seen texel of each); empty when every
    texel or none was seen."""
    seen = result.samples > 0
    idx = problem.texels.grid_index
    if seen.all() or not seen.any():
        return idx[:0], idx[:0]
    return idx[~seen], idx[seen][nearest_seen(problem.texels.position, seen)]


def nearest_seen(position: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """For each texel not ``seen`` (in order), the index among the seen ones of the nearest in 3D (``position``
    (N, 3)): a k-d tree queried on every core (the same answer as one)."""
    from scipy.spatial import cKDTree  # only when needed: the import is a large share of a short fit's run

    return cKDTree(position[seen]).query(position[~seen], workers=-1)[1]


def per_texel_objective(problem, params: np.ndarray) -> np.ndarray:
    """Each texel's objective on the fitted photos at ``params`` (N, P): one streaming pass."""
    return per_texel_objective_and_samples(problem, params)[0]


def per_texel_objective_and_samples(problem, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(each texel's objective (N,), its usable samples (N,)) on the fitted photos at ``params`` (N, P): one
    streaming pass."""
    import warp as wp

    f, g = problem.new_scalar(), problem.new_vec()
    stats = wp.zeros(problem.n, dtype=wp.vec4d, device=problem.device)
    problem.evaluate(problem.new_storage(params), f, g, stats)
    return f.numpy().astype(np.float64), stats.numpy()[:, 0]


def data_jtj(problem, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J^T J (N, P, P), trace stats (N, 4)) of the data term at ``params``: one Gauss-Newton pass (the
    problem's material prior, if any, left out)."""
    import warp as wp

    held = (problem.material_centre, problem.material_weights)
    problem.material_centre = problem.material_weights = None
    try:
        f, g = problem.new_scalar(), problem.new_vec()
        jtj = wp.zeros(problem.n, dtype=problem.mat, device=problem.device)
        stats = wp.zeros(problem.n, dtype=wp.vec4d, device=problem.device)
        problem.evaluate_lm(problem.new_storage(params), f, g, jtj, stats)
        return jtj.numpy().astype(np.float64), stats.numpy()
    finally:
        problem.material_centre, problem.material_weights = held


def load_model(model_dir: str | Path):
    """(mesh, parameter grid (H, W, P), layout, model.json) of a model folder."""
    d = Path(model_dir)
    man = read_json(d / "model.json", what="model manifest")
    lay = ModelLayout.from_json(man["layout"])
    grid = read_param_maps(d, lay)
    return load_mesh(d / "mesh.obj").with_normals(), grid, lay, man
