"""The fit and eval stages over folders (``texstream fit`` / ``texstream eval``).

fit: a posed capture with lights + a mesh with UVs (or an atlas folder with ``mesh.obj`` and
``bake.npz``, e.g. ``texstream atlas`` output or a synthetic set's ``ground_truth/``) -> a model
folder: mesh.obj, bake.npz, parameter maps (EXR), seen.png (texels no photo saw keep their
default values and are flagged here), model.json, trace.json, error_vs_time.png, renders/ (fitted
render beside each of a few photos) and fit_config.json.

Unlike the rest of fit/, this module imports OpenImageIO (through capture.imageio) and
matplotlib inside its functions: it is a stage, not the GPU-side core.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np

from texstream.core.errors import InputError, StageError
from texstream.core.config import check_config, option
from texstream.core.outputs import StageResult, atomic_output_dir, read_json, write_json_atomic
from texstream.core.progress import say

from texstream.fit.optim.fitter import FitConfig, FitResult, light_view_angles, resumable, run_fit
from texstream.fit.models.materials import MaterialConfig
from texstream.fit.stages.model_folder import image_metrics, plot_trace  # noqa: F401  (re-exported: tests and benchmarks use them here)
from texstream.fit.kernels.layout import ModelLayout


UNITS = {"lafortune": "BRDF values in 1/sr (capture/conventions.py)",
         "diffuse": "BRDF values in 1/sr (capture/conventions.py)",
         "radiance": "exitant radiance in photo values per unit exposure",
         "view_radiance": "exitant radiance in photo values per unit exposure (along the normal; view terms alike)"}


@dataclasses.dataclass
class FitStageConfig:
    """Options of ``texstream fit`` around the numerical FitConfig."""

    device: str = option("cpu", "Warp device: cpu or cuda:N")
    texture_size: int = option(256, "atlas side in texels when the mesh has UVs but no bake; 0: automatic, the "
                                    "power of two whose texels are about texel_pixels of the photos' pixels wide",
                               min=0, max=16384)
    texel_pixels: float = option(3.0, "texture_size 0: the texel width to aim at, in photo pixels (texels narrower "
                                      "than a pixel or two share their pixels with their neighbours and fit the "
                                      "photos' filtered highlights as broad, weak lobes that new views contradict; "
                                      "wider ones lose detail: docs/accuracy.md)", min=0.25)
    holdout_every: int = option(0, "hold out every k-th photo from the fit for evaluation (0 = none)", min=0)
    renders: int = option(4, "photos rendered beside the fitted model in renders/", min=0)
    unseen: str = option("nearest", "texels no photo saw: nearest (the value of the nearest seen texel on the "
                                    "surface, as texture bakers fill; flagged in seen.png) or default (the "
                                    "model's default values)", choices=("nearest", "default"))
    lobe_support: float = option(0.02, "per texel, drop the specular lobes (rho_s = 0; flagged in lobes.png and "
                                       "model.json) that lower the texel's error on the fitted photos by less than "
                                       "this fraction: no photo saw their highlight, so in new views they only guess "
                                       "it; with two lobes the second is also tested on its own; 0 keeps every lobe",
                                 min=0.0, max=1.0)
    traced_polish: int = option(5, "Levenberg-Marquardt iterations that end a fit with specular lobes with each "
                                    "filtered tap's pixel ray traced to the mesh (stream.tap_geometry mesh, the "
                                    "renderer's surface at every tap) when the fit ran with plane taps: a highlight "
                                    "narrower than a pixel is then fitted as the photos filtered it, not as a "
                                    "broad, weak lobe new views contradict (docs/accuracy.md); a traced pass costs "
                                    "~7-20x a plane one; 0: off", min=0)
    traced_materials: bool = option(False, "with the traced polish and shared materials chosen: polish the "
                                            "per-texel fit on traced taps first, and find the materials' evidence, "
                                            "contradictions and fit on traced taps too. It helps texels narrower "
                                            "than a pixel that saw narrow highlights; the constrained test on traced "
                                            "taps is confirmed at the materials' lobes, yet a few texels that never "
                                            "saw their highlight still pass it and keep wrong lobes "
                                            "(docs/accuracy.md): off by default")
    checkpoint: bool = option(True, "Levenberg-Marquardt fits keep a checkpoint beside the output (every sync_every "
                                    "iterations); a rerun after Ctrl-C or a killed process resumes from it to the "
                                    "same result as an uninterrupted fit")
    skip_bad_photos: bool = option(False, "leave out photos that cannot be read (corrupt, truncated, wrong size, "
                                          "NaN values) instead of failing: each is printed and listed in "
                                          "model.json's photos.skipped (every photo is decoded once at set-up, "
                                          "before the fit; each bad one costs the set-up again)")
    min_seen_fraction: float = option(0.01, "fail before fitting when fewer than this fraction of the atlas's texels "
                                            "is seen by any photo (the mesh faces away or is in another frame)",
                                      min=0.0)
    materials: MaterialConfig = option(default_factory=MaterialConfig,
                                       help="shared materials: texels whose lobe no photo constrained borrow their "
                                            "material's (fit/materials.py)")
    fit: FitConfig = option(default_factory=FitConfig, help="the fit", flat=True)


def load_geometry(mesh_path: str | Path, texture_size: int, device: str, frames=None, texel_pixels: float = 3.0):
    """(mesh with UVs, TexelBake) from an atlas folder, or a mesh file baked at ``texture_size`` (0: the side
    :func:`texstream.geometry.density.texture_side_for` picks from ``frames`` and ``texel_pixels``; 256 without
    frames)."""
    from texstream.geometry.bake import TexelBake, bake_texels
    from texstream.geometry.mesh_io import load_mesh

    p = Path(mesh_path)
    if p.is_dir():
        mfile = next((p / n for n in ("mesh.obj", "mesh.ply") if (p / n).exists()), None)
        if mfile is None:
            raise InputError("folder has no mesh.obj", p, "pass an atlas folder (texstream atlas) or a mesh file")
        mesh = load_mesh(mfile)
        if (p / "bake.npz").exists():
            return mesh.with_normals(), TexelBake.load(p / "bake.npz")
    else:
        mesh = load_mesh(p)
    if mesh.uvs is None:
        from texstream.geometry.atlas import AtlasConfig, build_atlas

        mesh, _ = build_atlas(mesh, AtlasConfig(resolution=texture_size or 1024))
    mesh = mesh.with_normals()
    side = texture_size
    if side == 0:
        side = 256
        if frames:
            from texstream.geometry.density import texture_side_for

            side = texture_side_for(mesh, frames, texel_pixels)[0]
    return mesh, bake_texels(mesh, side, side, device=device)


def load_photos(capture, frames, device: str | None = None):
    """Images (linear, H x W x 3) and masks of the given frames."""
    from texstream.capture.imageio import read_image, read_mask

    images, masks = [], []
    for f in frames:
        images.append(read_image(capture.image_path(f), channels=3))
        mp = capture.mask_path(f)
        masks.append(read_mask(mp, images[-1].shape[:2]) if mp is not None and mp.exists() else None)
    return images, masks


PHOTO_CACHE_FOLDER = ".texstream-cache"
"""the capture's folder for photos decoded once and streamed from there
(:class:`~texstream.fit.stream.photo_stream.PhotoCache`)"""


def photo_files(capture, frames):
    """The frames' photos and masks as files (:class:`texstream.fit.stream.photo_stream.PhotoFiles`), decoded
    by the fit's PhotoSet on a pool of threads or processes: all at set-up when they stay in memory, or a window
    per pass when streamed from disk (``StreamConfig.photo_residency``)."""
    from texstream.capture.imageio import read_image, read_mask

    from texstream.fit.stream.photo_stream import PhotoFiles

    masks = []
    for f in frames:
        mp = capture.mask_path(f)
        masks.append(mp if mp is not None and mp.exists() else None)
    # module functions, not closures: worker processes receive them (fit/decode_pool.py)
    return PhotoFiles([capture.image_path(f) for f in frames], masks, read_image, read_mask,
                      cache_dir=Path(capture.root) / PHOTO_CACHE_FOLDER)


def read_photos(photos, masks, indices):
    """Images and masks (all-true where none) of ``indices`` of ``photos`` (a list of arrays with a
    list of masks or None, or a PhotoFiles, which names its masks)."""
    from texstream.fit.stream.photo_stream import PhotoFiles

    images, masks = [], []
    for i in indices:
        if isinstance(photos, PhotoFiles):
            im = photos.read_image(photos.paths[i])
            mp = photos.mask_paths[i]
            mk = None if mp is None else photos.read_mask(mp, im.shape[:2])
        else:
            im, mk = photos[i], None if masks is None else masks[i]
        images.append(im)
        masks.append(np.ones(im.shape[:2], bool) if mk is None else mk)
    return images, masks


def build_problem(mesh, bake, frames, images, masks, cfg: FitConfig, device: str, photos=None):
    """The StreamProblem of a fit: texels from the bake, photos on the device with their depth and
    shadow maps (``photos``: a PhotoSet of these frames built before, e.g. by another problem's
    call, reused as it is; building one is most of the set-up time). The photos are set up on a
    thread of their own while this one computes the texels (host work, beside the photos' uploads
    and map launches); split over devices (``StreamConfig.device_split`` photos), each device's on
    a thread of its own."""
    import concurrent.futures
    import contextvars

    from texstream.fit.stream.photo_set import PhotoSet

    from texstream.fit.stream.problem import PhotoFrame, StreamProblem

    from texstream.fit.stream.texels import TexelSet, surface_derivatives, texel_coordinate_gradients
    from texstream.fit.multi.tiles import parse_devices, split_photos

    photo_frames = [PhotoFrame.from_capture_frame(f) for f in frames]
    normals = mesh.vertex_normals()  # computed anew on each call for a mesh without stored normals

    split = split_photos(cfg)  # before any work: refuses tiles with it

    def make_photos():
        if split:
            from texstream.fit.multi.photo_split import build_device_photos, check_split_devices

            devices = parse_devices(cfg.stream.devices, device)
            check_split_devices(devices, device)
            return build_device_photos(photo_frames, images, mesh.vertices, mesh.faces, masks, cfg.stream, devices,
                                       mesh_normals=normals, mesh_uvs=mesh.uvs)
        return PhotoSet(photo_frames, images, mesh.vertices, mesh.faces, masks=masks, config=cfg.stream,
                        device=device, mesh_normals=normals, mesh_uvs=mesh.uvs)

    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="texstream-photos") as pool:
        # in a copy of this context: the stage's log and its registry of loaders to close
        pending = pool.submit(contextvars.copy_context().run, make_photos) if photos is None else None
        face_normal, normal_jacobian = surface_derivatives(mesh.vertices, mesh.faces, normals, bake.face, bake.bary)
        coordinate_gradients = None
        if mesh.uvs is not None:
            coordinate_gradients = texel_coordinate_gradients(mesh.vertices, mesh.faces, mesh.uvs, bake.face,
                                                              bake.width, bake.height)
        texels = TexelSet.from_grid(bake.covered, bake.position, bake.normal, bake.tangent, bake.bitangent,
                                    face_normal, normal_jacobian, coordinate_gradients, bake.fill_source)
        if pending is not None:
            photos = pending.result()  # a photo's error is raised here, after the texels
    if texels.n == 0:
        raise InputError("the atlas has no covered texels", fix="rebuild the atlas with a larger resolution")
    layout = cfg.layout(photo_frames, texels.position.mean(axis=0))
    return StreamProblem(texels, photos, layout, cfg.stream, device=device)


def lobe_shape_report(cfg: FitConfig, layout, frames, positions: np.ndarray) -> dict:
    """What model.json records of the lobe-shape choice (fit/models.py "Lobe shape")."""
    from texstream.fit.stream.problem import PhotoFrame

    if layout.n_lobes == 0:
        return {"requested": cfg.lobe_shape, "fitted": None, "light_view_angle_deg": None}  # no lobe to shape
    angles = light_view_angles([PhotoFrame.from_capture_frame(f) for f in frames], positions.mean(axis=0))
    return {"requested": cfg.lobe_shape, "fitted": layout.lobe_shape,
            "light_view_angle_deg": [float(angles.min()), float(angles.max())] if angles.size else None}


def load_seams(mesh_path: str | Path, bake):
    """The atlas folder's ``seams.npz`` (None without one), checked against the bake's atlas size."""
    p = Path(mesh_path)
    if not p.is_dir() or not (p / "seams.npz").is_file():
        return None
    from texstream.geometry.seams import Seams

    seams = Seams.load(p / "seams.npz")
    n = bake.height * bake.width
    idx = np.concatenate([seams.idx_a.ravel(), seams.idx_b.ravel()])
    if (seams.width, seams.height) != (bake.width, bake.height) or seams.fill_source.shape != (n,) \
            or (idx.size and (idx.min() < 0 or idx.max() >= n)):
        raise InputError(f"seams are for a {seams.width}x{seams.height} atlas, "
                         f"the bake is {bake.width}x{bake.height}",
                         p / "seams.npz", "re-run `texstream atlas` to rebuild the atlas folder")
    return seams


def params_to_grid(result: FitResult, problem, bake) -> np.ndarray:
    """Compact per-texel parameters -> (H, W, P) grid with padding filled (no bilinear bleeding)."""
    lay = result.layout
    grid = np.tile(lay.defaults().astype(np.float32), (bake.height * bake.width, 1))
    grid[problem.texels.grid_index] = result.params
    return bake.fill_padding(grid.reshape(bake.height, bake.width, -1))


def render_model(mesh, grid: np.ndarray, layout: ModelLayout, frame, device: str):
    from texstream.fit.stages.render import Renderer

    rend = Renderer(mesh, grid, layout, device=device)
    res = rend.render_frame(frame)
    return res.radiance * np.float32(frame.exposure), res.mask


def heldout_psnr(mesh, grid: np.ndarray, layout: ModelLayout, frames, photos, masks, device: str) -> tuple[list, float]:
    """Per-view PSNR of the model's renders against ``photos`` (foreground: photo mask and render
    coverage) and the PSNR of the views' pooled mean squared error."""
    views = []
    for fr, photo, mask in zip(frames, photos, masks):
        render, rmask = render_model(mesh, grid, layout, fr, device)
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
    from texstream.core.progress import bar, bars_enabled

    if not (progress and bars_enabled()):
        return run_fit(problem, fit, **kw)
    start = int(kw["resume"]["iteration"]) if kw.get("resume") else 0
    with bar(total=fit.max_iterations, desc=f"fit {fit.optimizer}", unit="it") as b:
        b.update(start)
        return run_fit(problem, fit, progress=lambda it: b.update(1), **kw)


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
        if not self.path.is_file():
            return None
        try:
            with np.load(self.path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError):
            return None  # a damaged checkpoint is only a lost head start
        if str(data.pop("key", "")) != self.key:
            return None
        return {k: (v.item() if v.ndim == 0 else v) for k, v in data.items()}

    def save(self, state: dict) -> None:
        from texstream.geometry.mesh_io import write_npz_atomic

        # uncompressed: written every sync_every iterations and removed at the end
        write_npz_atomic(self.path, compress=False, key=np.array(self.key),
                         **{k: np.asarray(v) for k, v in state.items()})

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def split_holdout(frames: list, every: int) -> tuple[list, list]:
    """(fitted, held out): every ``every``-th frame (the 8th, 16th, ... for 8) is held out; 0 = none."""
    if every <= 0:
        return list(frames), []
    held = [f for i, f in enumerate(frames) if i % every == every - 1]
    return [f for i, f in enumerate(frames) if i % every != every - 1], held


def check_capture_lights(capture, model: str, capture_dir: str | Path) -> None:
    """Reflectance models need a light per photo; the radiance model needs none."""
    if model not in ("radiance", "view_radiance") and not capture.has_lights:
        raise InputError(f"the {model} model needs a light per photo and some frames have none",
                         Path(capture_dir) / "capture.json",
                         "fit the radiance model (--model radiance), or add per-frame lights (texstream ingest "
                         "--lights, texstream lights, or a co-located flash)")


def check_seen_texels(problem, cfg: FitStageConfig, capture_dir: str | Path) -> tuple:
    """Count the texels some photo sees and fail before fitting when almost none are: a mesh facing away
    from the cameras or in another frame than the capture's. The count comes from the fit's starting
    pass (:func:`fit_start`), returned for the fit to reuse."""
    from texstream.fit.optim.fitter import fit_start

    start = fit_start(problem, cfg.fit)
    seen = int((start.counts.numpy() > 0).sum())
    if seen < cfg.min_seen_fraction * problem.n:
        raise StageError(f"only {seen:,} of {problem.n:,} texels ({100.0 * seen / max(problem.n, 1):.2f}%) are seen by "
                         f"any photo (need {100 * cfg.min_seen_fraction:g}%)", Path(capture_dir) / "capture.json",
                         "check that the mesh is in the capture's frame and faces the cameras (texstream mesh "
                         "orients it), or lower --min-seen-fraction")
    return seen, start


@dataclasses.dataclass
class FitInputs:
    """What a mesh fit reads: the capture split into fitted and held-out frames, the geometry and photos."""

    capture: object
    frames: list
    held: list
    mesh: object
    bake: object
    seams: object
    images: object
    """the fitted frames' photos: a :class:`texstream.fit.stream.photo_stream.PhotoFiles` (decoded by the fit's
    PhotoSet) or a list of arrays"""
    masks: list | None


def load_fit_inputs(capture_dir: str | Path, mesh_path: str | Path, cfg: FitStageConfig) -> FitInputs:
    """Read and check everything a fit needs, before any long work starts."""
    from texstream.capture.capture_json import read_capture

    capture = read_capture(capture_dir)
    check_capture_lights(capture, cfg.fit.model, capture_dir)
    frames, held = split_holdout(capture.frames, cfg.holdout_every)
    if not frames:
        raise InputError("no photo is left to fit after the hold-out split", Path(capture_dir) / "capture.json",
                         "lower --holdout-every or add photos")
    mesh, bake = load_geometry(mesh_path, cfg.texture_size, cfg.device, frames, cfg.texel_pixels)
    seams = load_seams(mesh_path, bake)
    return FitInputs(capture, frames, held, mesh, bake, seams, photo_files(capture, frames), None)


def bad_photo(error: InputError, images) -> int | None:
    """The index of the photo (or its mask) ``error`` names, among ``images`` (a PhotoFiles); None for
    another error."""
    paths = getattr(images, "paths", None)
    if error.path is None or paths is None:
        return None
    named = Path(error.path).resolve()
    for k, (image, mask) in enumerate(zip(paths, images.mask_paths)):
        if Path(image).resolve() == named or (mask is not None and Path(mask).resolve() == named):
            return k
    return None


def set_up_skipping_bad_photos(inputs: FitInputs, cfg: FitStageConfig, capture_dir: str | Path):
    """The fit's problem and its starting pass (:func:`check_seen_texels`); every photo is decoded there, so
    an unreadable one fails here, before the fit and before anything is written, with one line naming it.
    With ``skip_bad_photos`` the photo is left out of ``inputs`` instead, said, and the set-up run again.
    Returns (problem, texels seen, start, skipped photos as {"file", "error"})."""
    skipped = []
    while True:
        try:
            problem = build_problem(inputs.mesh, inputs.bake, inputs.frames, inputs.images, inputs.masks, cfg.fit,
                                    cfg.device)
            seen, start = check_seen_texels(problem, cfg, capture_dir)
            return problem, seen, start, skipped
        except InputError as e:
            k = bad_photo(e, inputs.images)
            if k is None or not cfg.skip_bad_photos:
                if k is not None:
                    e.fix = (e.fix.rstrip(".") + "; or " if e.fix else "") + "leave it out with --skip-bad-photos"
                    e.args = (e.one_line(),)
                raise
            skipped.append({"file": str(inputs.images.paths[k]), "error": e.message})
            say("fit", f"skipping photo {inputs.images.paths[k]}: {e.message} (--skip-bad-photos)")
            keep = [j for j in range(len(inputs.frames)) if j != k]
            if not keep:
                raise InputError("every photo of the capture is unreadable", Path(capture_dir) / "capture.json",
                                 "check the images (model.json lists none: nothing was fitted)") from None
            inputs.frames = [inputs.frames[j] for j in keep]
            inputs.images = inputs.images.subset(keep)


def fill_unseen_texels(grid: np.ndarray, problem, bake, result: FitResult) -> tuple[np.ndarray, int]:
    """Give texels no photo saw the parameters of the nearest seen texel in 3D (their defaults would
    show as a foreign colour wherever a new view sees them, and bleed into seen neighbours through
    the renderer's bilinear lookup). Returns the maps and the number of texels filled."""
    seen = result.samples > 0
    if seen.all() or not seen.any():
        return grid, 0
    from scipy.spatial import cKDTree  # only when needed: the import is a large share of a short fit's run

    pos = problem.texels.position
    _, nearest = cKDTree(pos[seen]).query(pos[~seen])
    flat = grid.reshape(-1, grid.shape[-1]).copy()
    idx = problem.texels.grid_index
    flat[idx[~seen]] = flat[idx[seen][nearest]]
    return bake.fill_padding(flat.reshape(grid.shape)), int((~seen).sum())


def per_texel_objective(problem, params: np.ndarray) -> np.ndarray:
    """Each texel's objective on the fitted photos at ``params`` (N, P): one streaming pass."""
    import warp as wp

    f, g = problem.new_scalar(), problem.new_vec()
    stats = wp.zeros(problem.n, dtype=wp.vec4d, device=problem.device)
    problem.evaluate(problem.new_storage(params), f, g, stats)
    return f.numpy().astype(np.float64)


def drop_unsupported_lobes(problem, result: FitResult, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """(params, dropped): the fitted parameters with rho_s = 0 on every seen texel whose lobes lower its
    objective by less than ``fraction`` of the objective without them, and the (N,) mask of those texels.
    Such a lobe explains nothing the photos show; a narrow one whose peak fell between the cameras would
    still light up a new view at full height."""
    lay = result.layout
    dropped = np.zeros(problem.n, bool)
    if lay.n_lobes == 0 or fraction <= 0:
        return result.params, dropped
    bare = scale_lobes(result.params, lay, 0.0)
    with_lobes, without = per_texel_objective(problem, result.params), per_texel_objective(problem, bare)
    dropped = (result.samples > 0) & (without - with_lobes <= fraction * np.maximum(without, 1e-30))
    params = np.where(dropped[:, None], bare, result.params)
    if lay.n_lobes > 1:
        # each further lobe on its own: kept only where the texel's error without it is higher by the fraction
        for j in range(1, lay.n_lobes):
            one_less = scale_lobes(params, lay, 0.0, only=j)
            f_with, f_without = per_texel_objective(problem, params), per_texel_objective(problem, one_less)
            weak = ~dropped & (result.samples > 0) & (f_without - f_with <= fraction * np.maximum(f_without, 1e-30))
            params = np.where(weak[:, None], one_less, params)
    return params, dropped


def scale_lobes(params: np.ndarray, layout: ModelLayout, factor: float, only: int | None = None) -> np.ndarray:
    """A copy of (N, P) ``params`` with every lobe's rho_s (or lobe ``only``'s) times ``factor``: 0 takes the
    lobes away, 2 doubles them (the model is linear in rho_s)."""
    out = params.copy()
    for j in range(layout.n_lobes) if only is None else (only,):
        o = layout.lobe_offset(j)
        out[:, o:o + 3] = 0.0 if factor == 0 else out[:, o:o + 3] * factor
    return out


def lobes_in_use(params: np.ndarray, layout: ModelLayout, seen: np.ndarray) -> list[int]:
    """Per lobe, the seen texels whose lobe is on (rho_s not all 0): what model.json records."""
    return [int((seen & np.any(params[:, layout.lobe_offset(j):layout.lobe_offset(j) + 3] != 0, axis=1)).sum())
            for j in range(layout.n_lobes)]


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


@dataclasses.dataclass
class TexelEvidence:
    """What a per-texel fit's photos say about each texel's lobe (fit/materials.py steps 1-2)."""

    params: np.ndarray
    samples: np.ndarray
    jtj: np.ndarray
    sigma2: float
    uncertainty: np.ndarray
    """(N, 3) relative std of rho_s, of n, std of c_z (materials.texel_uncertainty)"""
    constrained: np.ndarray


def texel_evidence(problem, result: FitResult, mcfg: MaterialConfig) -> TexelEvidence:
    """J^T J, residual variance and uncertainty of a per-texel fit's lobes, and which are constrained."""
    from texstream.fit.models.materials import residual_variance, texel_uncertainty

    jtj, stats = data_jtj(problem, result.params)
    sigma2 = residual_variance(stats[result.samples > 0])
    unc = texel_uncertainty(jtj, result.params, result.layout, sigma2)
    constrained = (result.samples > 0) & (unc[:, 0] < mcfg.constrained_rel_std) & (unc[:, 1] < mcfg.constrained_rel_std)
    return TexelEvidence(result.params, result.samples, jtj, sigma2, unc, constrained)


def confirm_at_material_lobes(traced, evidence: TexelEvidence, plane: TexelEvidence, k: int,
                              mcfg: MaterialConfig) -> tuple[TexelEvidence, int]:
    """``evidence`` (a fit's on traced taps) with its constrained texels kept only where the photos also
    constrain the lobe of the texel's material: J^T J on ``traced`` taps linearised at the materials' lobes
    (found from the ``plane``-tap evidence, as the default path finds them), not at the texel's own lobe.
    A texel whose own wrong lobe is steep where its photos looked (the flank of a highlight no photo showed
    at its peak) passes the test at its own lobe; at the material's lobe those samples see almost no lobe
    and it fails. A texel that saw its (even sub-pixel) highlight passes both. Returns (the evidence, how
    many constrained texels the second test took away)."""
    from texstream.fit.models.materials import find_materials, material_lobes_on, texel_uncertainty

    lay = traced.layout
    seen = plane.samples > 0
    mats = find_materials(plane.params, seen, plane.constrained, lay, k, mcfg.min_lobe_share, mcfg.spread_floor)
    at = material_lobes_on(evidence.params, mats.labels, mats, lay)
    jtj, _ = data_jtj(traced, at)
    unc = texel_uncertainty(jtj, at, lay, evidence.sigma2)
    keep = (unc[:, 0] < mcfg.constrained_rel_std) & (unc[:, 1] < mcfg.constrained_rel_std)
    constrained = evidence.constrained & keep
    return dataclasses.replace(evidence, constrained=constrained), int((evidence.constrained & ~keep).sum())


def traced_polish_applies(problem, cfg: "FitStageConfig") -> bool:
    """Whether the fit ends with :func:`traced_polish`: a model with specular lobes, fitted with filtered plane
    taps on a mesh (an atlas fit, not a single view), untiled."""
    from texstream.fit.multi.tiles import tiled

    s = problem.cfg
    return (cfg.traced_polish > 0 and problem.layout.n_lobes > 0 and s.photo_sampling == "filtered"
            and s.tap_geometry == "plane" and problem.photos.mesh_normals is not None
            and problem.photos.mesh_uvs is not None and not tiled(cfg.fit))


def traced_problem(problem):
    """``problem``'s texels and photos with every filtered tap traced to the mesh (``tap_geometry`` mesh)."""
    from texstream.fit.stream.problem import StreamProblem

    return StreamProblem(problem.texels, problem.photos, problem.layout,
                         dataclasses.replace(problem.cfg, tap_geometry="mesh"), problem.device)


def traced_polish(problem, result: FitResult, cfg: "FitStageConfig", prior=None) -> FitResult:
    """``cfg.traced_polish`` Levenberg-Marquardt iterations from ``result`` on the same texels and photos with
    traced taps (``StreamConfig.tap_geometry`` mesh), the materials' ``prior`` (centre, weights) kept on; the
    trace continues ``result``'s (its first row: the start, evaluated with traced taps). Returns ``result``
    unchanged where :func:`traced_polish_applies` says no."""
    from texstream.fit.stream.problem import StreamProblem

    if not traced_polish_applies(problem, cfg):
        return result
    traced = traced_problem(problem)
    if prior is not None:
        traced.set_material_prior(*prior)
    fit = dataclasses.replace(cfg.fit, max_iterations=cfg.traced_polish, optimizer="lm")
    res = run_fit(traced, fit, start=(result.params, result.samples))
    t_end = result.trace[-1]["time_s"] if result.trace else 0.0
    extra = [{**r, "iteration": r["iteration"] + len(result.trace), "time_s": r["time_s"] + t_end,
              "stage": "traced polish"} for r in res.trace]
    return dataclasses.replace(res, trace=result.trace + extra, passes=result.passes + res.passes)


def fit_with_materials(problem, result: FitResult, evidence: TexelEvidence, k: int, variant: str,
                       cfg: "FitStageConfig", polish: bool = False) -> tuple[FitResult, dict]:
    """The materials model with ``k`` materials (fit/materials.py): cluster, prior, Levenberg-Marquardt from
    the per-texel fit ``result``, then (``polish``) :func:`traced_polish` with the prior on. Returns the fit
    and what model.json records of it."""
    from texstream.fit.models.materials import (contradiction_test, find_materials, material_lobes_on, material_prior,
                            reject_contradicted_lobes)

    mcfg = cfg.materials
    lay = result.layout
    seen = evidence.samples > 0
    mats = find_materials(evidence.params, seen, evidence.constrained, lay, k, mcfg.min_lobe_share,
                          mcfg.spread_floor)
    bare = scale_lobes(evidence.params, lay, 0.0)
    with_lobe = material_lobes_on(evidence.params, mats.labels, mats, lay)
    doubled = scale_lobes(with_lobe, lay, 2.0)
    f_mat, f_bare = per_texel_objective(problem, with_lobe), per_texel_objective(problem, bare)
    contradicted = contradiction_test(f_bare, f_mat, per_texel_objective(problem, doubled), evidence.samples,
                                      evidence.sigma2, mcfg.contradiction)
    mats.contradicted_share = reject_contradicted_lobes(mats, mats.labels, seen, evidence.constrained, contradicted,
                                                        mcfg.max_contradicted)
    prior = material_prior(evidence.params, evidence.jtj, seen, evidence.constrained, mats.labels, mats, lay,
                           evidence.sigma2, contradicted, mcfg, variant)
    problem.set_material_prior(prior.centre, prior.weights)
    try:
        fit = dataclasses.replace(cfg.fit, max_iterations=mcfg.iterations, optimizer="lm")
        res = run_fit(problem, fit, start=(prior.start, evidence.samples))
    finally:
        problem.set_material_prior(None)
    if polish:
        res = traced_polish(problem, res, cfg, prior=(prior.centre, prior.weights))
    info = {"variant": variant, "k": mats.k, "materials": mats.to_json(lay),
            "borrowed_texels": int(prior.borrow.sum()), "no_lobe_texels": int(prior.no_lobe.sum()),
            "contradicted_texels": int((contradicted & seen & ~evidence.constrained).sum()),
            "labels": mats.labels, "borrow_mask": prior.borrow, "no_lobe_mask": prior.no_lobe}
    return res, info


def model_grid(params: np.ndarray, result: FitResult, problem, bake, cfg: "FitStageConfig", seams=None) -> np.ndarray:
    """(H, W, P) maps of compact ``params`` as the stage writes them: padding, unseen texels, seams."""
    res = dataclasses.replace(result, params=params)
    grid = params_to_grid(res, problem, bake)
    if cfg.unseen == "nearest":
        grid, _ = fill_unseen_texels(grid, problem, bake, res)
    grid, _ = average_seams_in_bounds(grid, seams, result.layout)
    return grid


def choose_materials(inputs: "FitInputs", problem, cfg: "FitStageConfig", log=None) -> dict:
    """Pick the per-texel or a materials model (variant and K) on a validation split of the fitted photos:
    every ``materials.validation_every``-th fitted photo is held back, the per-texel fit and every
    candidate are fitted to the rest and scored by their renders of the validation photos (pooled
    PSNR; ties within 0.05 dB go to the simpler model). The fit's own held-out photos play no part.
    Returns the choice and every candidate's score, or {"chosen": "per-texel", "reason": ...} when the
    fitted photos are too few to split."""
    from texstream.fit.stream.problem import StreamProblem

    mcfg = cfg.materials
    every = mcfg.validation_every
    n = len(inputs.frames)
    val = [i for i in range(n) if i % every == every - 1]
    train = [i for i in range(n) if i % every != every - 1]
    if len(val) < 2 or len(train) < 2:
        return {"chosen": "per-texel", "reason": f"{n} fitted photos are too few for a validation split of every "
                                                 f"{every}th"}
    t0 = time.perf_counter()
    sub = StreamProblem(problem.texels, problem.photos.subset(train), problem.layout, problem.cfg, problem.device)
    res = run_fit(sub, cfg.fit)
    frames = [inputs.frames[i] for i in val]
    images, masks = read_photos(inputs.images, inputs.masks, val)

    def score(params) -> dict:
        grid = model_grid(params, res, sub, inputs.bake, cfg, inputs.seams)
        views, _ = heldout_psnr(inputs.mesh, grid, res.layout, frames, images, masks, cfg.device)
        pooled = float(-10 * np.log10(np.mean([10 ** (-v / 10) for v in views])))
        return {"pooled_psnr_db": pooled, "worst_psnr_db": float(min(views))}

    cands = []
    params, _ = drop_unsupported_lobes(sub, res, cfg.lobe_support)
    cands.append({"model": "per-texel", **score(params)})
    if mcfg.mode == "on":
        cands[0]["excluded"] = "materials mode on"
    evidence = texel_evidence(sub, res, mcfg)
    for variant in mcfg.variant_list():
        for k in range(1, mcfg.max_materials + 1):
            r, info = fit_with_materials(sub, res, evidence, k, variant, cfg)
            if info["k"] < k:
                break  # fewer distinct albedos than k: no new model
            cands.append({"model": variant, "k": info["k"], **score(r.params)})
            if log is not None:
                log(f"[fit] validation: {variant} K={k}: pooled {cands[-1]['pooled_psnr_db']:.2f} dB, "
                    f"worst {cands[-1]['worst_psnr_db']:.2f} dB")
    eligible = [c for c in cands if "excluded" not in c]
    best = eligible[0]
    for c in eligible[1:]:
        if c["pooled_psnr_db"] > best["pooled_psnr_db"] + 0.05:
            best = c
    name = best["model"] + (f" K={best['k']}" if "k" in best else "")
    return {"chosen": best["model"], "k": best.get("k"), "validation_photos": len(val), "fitted_on": len(train),
            "candidates": cands, "seconds": time.perf_counter() - t0,
            "reason": f"{name}: best pooled PSNR on {len(val)} validation photos (every {every}th fitted photo), "
                      f"{best['pooled_psnr_db']:.2f} dB against per-texel {cands[0]['pooled_psnr_db']:.2f} dB"}


def average_seams_in_bounds(grid: np.ndarray, seams, layout: ModelLayout) -> tuple[np.ndarray, dict | None]:
    """Tie the texels across chart seams (no cracks in bilinear lookups), keeping every value in its
    bounds; returns the maps and what model.json records of the seams."""
    if seams is None:
        return grid, None
    from texstream.geometry.seams import average_across_seams, seam_gaps

    # the view terms' coefficients live in each chart's own tangent frame, so two sides of a seam do
    # not share them: only the radiance along the normal (columns 0:3) is tied there
    cols = slice(0, 3) if layout.view_terms else slice(0, grid.shape[-1])
    part = np.ascontiguousarray(grid[..., cols])
    before = float(np.abs(seam_gaps(part, seams)).max()) if seams.n_samples else 0.0
    part = average_across_seams(part, seams, lower=layout.lower()[cols], upper=layout.upper()[cols])
    grid = grid.copy()
    grid[..., cols] = part
    grid = grid.astype(np.float32)
    after = float(np.abs(seam_gaps(part, seams)).max()) if seams.n_samples else 0.0
    return grid, {"samples": int(seams.n_samples), "max_gap_before": before, "max_gap_after": after}


def fit_stage(capture_dir: str | Path, mesh_path: str | Path, out_dir: str | Path,
              config: FitStageConfig | None = None, progress: bool = True) -> StageResult:
    """Fit the appearance model of ``config.fit`` to a capture; write the model folder atomically."""
    from texstream.fit.stages.model_folder import start_plotter, stop_plotter
    from texstream.fit.stream.photo_stream import loaders_closed_after

    cfg = config or FitStageConfig()
    check_config(cfg)
    check_output_path(out_dir)
    with loaders_closed_after():  # photos streamed from disk: their loaders' threads end with the stage
        if cfg.fit.model == "lfm":  # light field mapping: its own problem and model folder (fit/lfm_stage.py)
            from texstream.core.errors import ConfigError

            from texstream.fit.stages.lfm_stage import lfm_fit_stage
            from texstream.fit.multi.tiles import split_photos, tiled

            if tiled(cfg.fit) or split_photos(cfg.fit):
                raise ConfigError("stream.tiles, stream.devices and stream.tile_backend ray split per-texel models; "
                                  "light field mapping couples the texels of a triangle ring",
                                  fix="drop those options with --model lfm")

            return lfm_fit_stage(capture_dir, mesh_path, out_dir, cfg, progress)
        plotter = start_plotter()  # a child imports matplotlib while the photos are read and fitted
        try:
            return _fit_per_texel_model(capture_dir, mesh_path, out_dir, cfg, progress, plotter)
        finally:
            stop_plotter(plotter)


def _fit_per_texel_model(capture_dir: str | Path, mesh_path: str | Path, out_dir: str | Path, cfg: FitStageConfig,
                        progress: bool, plotter=None) -> StageResult:
    """:func:`fit_stage` for the per-texel models (Lafortune, radiance): ``plotter`` draws the
    error-against-time plot (:func:`~texstream.fit.stages.model_folder.start_plotter`; None: a child started at
    the end does)."""
    from texstream.capture.imageio import read_mask
    from texstream.core.progress import phase
    from texstream.geometry.mesh_io import save_mesh

    from texstream.fit.stages.model_folder import (bound_report, check_model, pooled_psnr, render_comparisons, trace_plot,
                               write_model_folder)
    from texstream.fit.diagnostics.stiffcheck import numerics_warnings

    t0 = time.perf_counter()
    with phase("fit", f"{cfg.fit.model}: reading the photos and setting up the texels"):
        inputs = load_fit_inputs(capture_dir, mesh_path, cfg)
        t_inputs = time.perf_counter() - t0
        capture, frames, held, mesh, bake = inputs.capture, inputs.frames, inputs.held, inputs.mesh, inputs.bake
        problem, seen_before, start, skipped = set_up_skipping_bad_photos(inputs, cfg, capture_dir)
        frames = inputs.frames
    t_setup = time.perf_counter() - t0
    from texstream.fit.multi.tiles import run_tiled_fit, tiled

    ckpt, resume, tiles_report = None, None, None
    if cfg.checkpoint and resumable(cfg.fit) and not tiled(cfg.fit):
        from texstream.core.config import config_to_dict

        ckpt = Checkpoint(out_dir, {"capture": str(Path(capture_dir).resolve()), "mesh": str(Path(mesh_path).resolve()),
                                    "config": config_to_dict(cfg), "texels": problem.n,
                                    "capture_mtime": (Path(capture_dir) / "capture.json").stat().st_mtime_ns
                                    if (Path(capture_dir) / "capture.json").exists() else 0})
        resume = ckpt.load()
    if tiled(cfg.fit):
        with phase("fit", f"{cfg.fit.model}: tiles of texels ({cfg.fit.stream.tile_backend})"):
            result, tiles_report = run_tiled_fit(problem, cfg.fit, start)
        say("fit", f"tiles: {tiles_report['tiles']} on {','.join(tiles_report['devices'])} "
                   f"({tiles_report['backend']}), photos per tile {min(tiles_report['photos_per_tile'])}.."
                   f"{max(tiles_report['photos_per_tile'])} of {tiles_report['photos']}")
    else:
        result = run_fit_with_progress(problem, cfg.fit, progress, start=start,
                                       **({"checkpoint": ckpt.save, "resume": resume} if ckpt else {}))
    t_loop = time.perf_counter()
    lay = result.layout
    materials_info, evidence, borrowed = None, None, None
    materials_problem = problem
    if lay.n_lobes and cfg.materials.mode != "off":
        with phase("fit", "materials: per-texel or shared lobes, judged on a validation split of the fitted photos"):
            choice = choose_materials(inputs, problem, cfg)
            traced_extra = {}
            if cfg.traced_materials and choice["chosen"] != "per-texel" and traced_polish_applies(problem, cfg):
                plane_evidence = texel_evidence(problem, result, cfg.materials)
                result = traced_polish(problem, result, cfg)
                materials_problem = traced_problem(problem)
                evidence, dropped = confirm_at_material_lobes(
                    materials_problem, texel_evidence(materials_problem, result, cfg.materials), plane_evidence,
                    choice["k"], cfg.materials)
                traced_extra = {"unconfirmed_at_material_lobe": dropped}
            else:
                evidence = texel_evidence(problem, result, cfg.materials)
        materials_info = {"mode": cfg.materials.mode, "traced": materials_problem is not problem, **traced_extra,
                          **choice}
    if materials_info is not None and materials_info["chosen"] != "per-texel":
        with phase("fit", f"materials: {materials_info['reason']}"):
            # on traced taps the materials' fit is the polish (traced_polish does nothing more there)
            res_m, info = fit_with_materials(materials_problem, result, evidence, materials_info["k"],
                                             materials_info["chosen"], cfg, polish=True)
        labels = info.pop("labels")
        materials_info.update(info)
        borrowed = (info, labels, res_m)
        t_end = result.trace[-1]["time_s"]
        extra = [{**r, "iteration": r["iteration"] + len(result.trace), "time_s": r["time_s"] + t_end,
                  "stage": r.get("stage", "materials")} for r in res_m.trace]
        lobes_dropped = np.zeros(problem.n, bool)
        result = dataclasses.replace(res_m, trace=result.trace + extra)
    else:
        if traced_polish_applies(problem, cfg):
            with phase("fit", f"traced polish: {cfg.traced_polish} iterations with taps traced to the mesh"):
                result = traced_polish(problem, result, cfg)
        params, lobes_dropped = drop_unsupported_lobes(problem, result, cfg.lobe_support)
        result = dataclasses.replace(result, params=params)
    title = f"{lay.kind} fit, {cfg.fit.optimizer}, {cfg.device}"
    polish_iterations = max(0, sum(r.get("stage") == "traced polish" for r in result.trace) - 1)  # less its start row
    grid, filled = params_to_grid(result, problem, bake), 0
    if cfg.unseen == "nearest":
        grid, filled = fill_unseen_texels(grid, problem, bake, result)
    grid, seams_info = average_seams_in_bounds(grid, inputs.seams, lay)
    check_model(grid, lay)  # before rendering it

    def render(f):
        image, coverage = render_model(mesh, grid, lay, f, cfg.device)
        m = coverage.astype(bool)
        if capture.mask_path(f) is not None and capture.mask_path(f).exists():
            m &= read_mask(capture.mask_path(f), coverage.shape)
        return image, m

    t_fitted = time.perf_counter()
    with (atomic_output_dir(out_dir) as tmp, phase("fit", f"{cfg.fit.model}: held-out renders and the model folder"),
          trace_plot(tmp, result.trace, title, plotter) as plot):  # drawn by the child while this one renders
        save_mesh(tmp / "mesh.obj", mesh)
        baked = Path(mesh_path) / "bake.npz"
        if Path(mesh_path).is_dir() and baked.is_file():  # the bake the fit read (load_geometry): copied
            shutil.copyfile(baked, tmp / "bake.npz")
        else:
            bake.save(tmp / "bake.npz")
        # every held-out view is scored (pooled and worst-view PSNR); the first `renders` are written as images
        show = held if held else frames[: max(cfg.renders, 0)]
        evals = render_comparisons(tmp / "renders", show, load_photos(capture, show)[0] if show else [], held, render,
                                   images=max(cfg.renders, 0))
        seen = np.zeros(bake.height * bake.width, bool)
        seen[problem.texels.grid_index] = result.samples > 0
        if lay.n_lobes:
            from texstream.capture.imageio import write_image

            kept = np.zeros(bake.height * bake.width, np.float32)
            kept[problem.texels.grid_index] = np.where(lobes_dropped, 0.5, (result.samples > 0).astype(np.float32))
            if borrowed is not None:
                # white: own lobe, grey: the material's lobe borrowed, dark grey: no lobe (material without one,
                # or photos that contradict it), black: unseen or padding
                prior_borrow, prior_none = borrowed[0]["borrow_mask"], borrowed[0]["no_lobe_mask"]
                kept[problem.texels.grid_index] = np.where(result.samples > 0, np.where(
                    prior_none, 0.25, np.where(prior_borrow, 0.5, 1.0)), 0.0).astype(np.float32)
            # white: lobe kept, grey: lobe dropped (no photo saw its highlight), black: unseen or padding
            write_image(tmp / "lobes.png", np.repeat(kept.reshape(bake.height, bake.width, 1), 3, axis=2), bits=8)
        if evidence is not None:
            from texstream.capture.imageio import write_image

            unc = np.zeros((bake.height * bake.width, 3), np.float32)
            unc[problem.texels.grid_index] = np.minimum(evidence.uncertainty, 1e6)
            # relative std of rho_s, relative std of n, std of c_z; 1e6: not constrained at all
            write_image(tmp / "uncertainty.exr", unc.reshape(bake.height, bake.width, 3), bits=32)
            if borrowed is not None:
                lab = np.full(bake.height * bake.width, -1, np.int64)
                lab[problem.texels.grid_index] = borrowed[1]
                palette = np.array([[0.9, 0.6, 0.1], [0.1, 0.6, 0.2], [0.8, 0.8, 0.8], [0.2, 0.3, 0.9],
                                    [0.8, 0.1, 0.1], [0.6, 0.2, 0.8], [0.1, 0.8, 0.8], [0.5, 0.4, 0.2]], np.float32)
                colours = np.where(lab[:, None] >= 0, palette[np.maximum(lab, 0) % len(palette)], 0.0)
                write_image(tmp / "materials.png", colours.reshape(bake.height, bake.width, 3), bits=8)
        last = result.trace[-1]
        at_bounds, warnings = bound_report(result.params, lay, result.samples > 0)
        warnings = numerics_warnings(cfg.fit.stream, len(frames), inputs.images, inputs.masks) + warnings
        manifest = {"mesh": "mesh.obj", "bake": "bake.npz", "warnings": warnings, "at_bounds": at_bounds,
                    "atlas": {"width": bake.width, "height": bake.height, "texels": int(problem.n),
                              "unseen_texels": int((result.samples == 0).sum()), "seen_before_fit": seen_before,
                              "unseen_filled_from_nearest": filled, "lobes_dropped": int(lobes_dropped.sum()),
                              "texels_with_lobe": lobes_in_use(result.params, lay, result.samples > 0),
                              "lobe_support": cfg.lobe_support},
                    "photos": {"fitted": len(frames), "held_out": len(held), "skipped": skipped,
                               "residency": problem.photos.residency,
                               "residency_reason": problem.photos.residency_reason,
                               "photos_per_window": problem.photos.window},
                    "tiles": tiles_report,
                    "traced_polish_iterations": polish_iterations,
                    "final": {k: last[k] for k in ("iteration", "time_s", "objective", "psnr_db", "ape_percent")},
                    "lobe_shape": lobe_shape_report(cfg.fit, lay, frames, problem.texels.position),
                    "materials": _materials_manifest(materials_info, evidence, cfg.materials),
                    "seams": seams_info, "setup_s": t_setup, "passes": result.passes, "device": cfg.device,
                    "timings_s": {"inputs": t_inputs, "setup": t_setup - t_inputs, "fit": t_loop - t0 - t_setup,
                                  "after_fit": t_fitted - t_loop, "renders": time.perf_counter() - t_fitted},
                    "render_eval": evals, "heldout": pooled_psnr([e for e in evals if e["held_out"]]),
                    "units": UNITS[lay.kind]}
        write_model_folder(tmp, grid, lay, seen.reshape(bake.height, bake.width), result.trace, title, manifest, cfg,
                           plot=plot)
    if ckpt is not None:
        ckpt.remove()
    problem.photos.wait_for_cache()  # a photo cache written in the background is complete for the next fit
    return StageResult(Path(out_dir), {"psnr_db": last["psnr_db"], "iterations": last["iteration"],
                                       "time_s": last["time_s"], "texels": problem.n, "photos": len(frames),
                                       "resumed_from": None if resume is None else int(resume["iteration"]),
                                       "skipped_photos": [p["file"] for p in skipped],
                                       "render_eval": evals, "warnings": warnings,
                                       "heldout": manifest["heldout"], "materials": manifest["materials"]})


def _materials_manifest(info: dict | None, evidence: TexelEvidence | None, mcfg: MaterialConfig) -> dict | None:
    """What model.json records of the materials choice (no masks or label arrays)."""
    if info is None:
        return None
    out = {k: v for k, v in info.items() if not k.endswith("_mask")}
    if evidence is not None:
        seen = evidence.samples > 0
        out["uncertainty"] = {"map": "uncertainty.exr", "channels": ["rho_s relative std", "n relative std", "c_z std"],
                              "residual_variance": evidence.sigma2, "constrained_rel_std": mcfg.constrained_rel_std,
                              "constrained_texels": int(evidence.constrained.sum()), "seen_texels": int(seen.sum())}
    return out


def check_output_path(out_dir: str | Path) -> None:
    """Fail before any work when the output path cannot become a folder."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another -o path")


def load_model(model_dir: str | Path):
    """(mesh, parameter grid (H, W, P), layout, model.json) of a model folder."""
    from texstream.capture.synth import read_param_maps
    from texstream.geometry.mesh_io import load_mesh

    d = Path(model_dir)
    man = read_json(d / "model.json", what="model manifest")
    lay = ModelLayout.from_json(man["layout"])
    grid = read_param_maps(d, lay)
    return load_mesh(d / "mesh.obj").with_normals(), grid, lay, man


def eval_stage(model_dir: str | Path, capture_dir: str | Path, device: str = "cpu",
               out_json: str | Path | None = None, holdout_every: int = 0) -> StageResult:
    """Render the model for the frames of a capture (all, or the held-out ones of the fit's split with
    ``holdout_every``); PSNR / APE on foreground pixels, pooled over the views and the worst view."""
    from texstream.capture.capture_json import read_capture
    from texstream.capture.imageio import read_image, read_mask

    from texstream.fit.stages.model_folder import check_render, pooled_psnr

    if read_json(Path(model_dir) / "model.json", what="model manifest").get("layout", {}).get("kind") == "lfm":
        from texstream.fit.stages.lfm_stage import load_lfm_renderer

        render = load_lfm_renderer(model_dir, device)
    else:
        mesh, grid, lay, _ = load_model(model_dir)

        def render(f):
            return render_model(mesh, grid, lay, f, device)
    capture = read_capture(capture_dir)
    frames = split_holdout(capture.frames, holdout_every)[1] if holdout_every > 0 else capture.frames
    if not frames:
        raise InputError(f"no frame is held out with --holdout-every {holdout_every}", Path(capture_dir) / "capture.json",
                         "use a smaller --holdout-every, or 0 for every frame")
    from texstream.core.progress import bar

    rows = []
    for f in bar(frames, "eval", unit="view"):
        photo = read_image(capture.image_path(f), channels=3)
        rend, rmask = render(f)
        check_render(rend, f.file_path)
        m = rmask.astype(bool)
        mp = capture.mask_path(f)
        if mp is not None and mp.exists():
            m &= read_mask(mp, rmask.shape)
        rows.append({"frame": f.file_path, **image_metrics(rend, photo, m)})
    mse_all = [10 ** (-r["psnr_db"] / 10) for r in rows if r["pixels"]]
    pooled = pooled_psnr(rows)
    summary = {"frames": len(rows), "holdout_every": holdout_every,
               "mean_psnr_db": float(np.mean([r["psnr_db"] for r in rows if r["pixels"]])),
               "psnr_of_mean_mse_db": float(-10 * np.log10(np.mean(mse_all))) if mse_all else float("nan"),
               "pooled_psnr_db": pooled["pooled_psnr_db"], "worst_psnr_db": pooled["worst_psnr_db"],
               "worst_view": pooled.get("worst_view"),
               "mean_ape_percent": float(np.mean([r["ape_percent"] for r in rows if r["pixels"]])), "per_frame": rows}
    out = Path(out_json) if out_json else Path(model_dir) / f"eval_{Path(capture_dir).resolve().name}.json"
    write_json_atomic(out, summary)
    return StageResult(out, {k: v for k, v in summary.items() if k != "per_frame"})
