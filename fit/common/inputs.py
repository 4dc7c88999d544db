"""What every fit reads before it sets up: the capture's frames and photos, the held-out split, the mesh and
its texel bake, and the checks that fail before any work (lights, seen texels, bad photos, the output path)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import read_capture, split_holdout  # noqa: F401  (split_holdout: the fit stage's)
from texstream.capture.imageio import photo_reader, read_image, read_mask
from texstream.core.config import config_to_dict
from texstream.core.errors import InputError, StageError
from texstream.core.progress import say
from texstream.render.layout import layout_traits


from texstream.fit.common.photo_levels import LevelImageReader, LevelMaskReader, frame_at_level
from texstream.fit.common.setup import build_problem
from texstream.fit.optim.fitter import fit_start
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.photo_stream import PhotoFiles
from texstream.geometry.atlas import AtlasConfig, build_atlas
from texstream.geometry.bake import TexelBake, bake_texels
from texstream.geometry.density import photo_level_for, texture_side_for
from texstream.geometry.mesh_io import load_mesh
from texstream.geometry.seams import Seams


def load_geometry(mesh_path: str | Path, texture_size: int, device: str, frames=None, texel_pixels: float = 3.0):
    """(mesh with UVs, TexelBake) from an atlas folder, or a mesh file baked at ``texture_size`` (0: the side
    :func:`texstream.geometry.density.texture_side_for` picks from ``frames`` and ``texel_pixels``; 256 without
    frames)."""
    p = Path(mesh_path)
    if p.is_dir():
        mfile = next((p / n for n in ("mesh.obj", "mesh.ply") if (p / n).exists()), None)
        if mfile is None:
            raise InputError("folder has no mesh.obj", p, "pass an atlas folder (texstream atlas) or a mesh file")
        if (p / "bake.npz").exists():
            return _atlas_folder(mfile, p / "bake.npz")
        mesh = load_mesh(mfile)
    else:
        mesh = load_mesh(p)
    if mesh.uvs is None:
        mesh, _ = build_atlas(mesh, AtlasConfig(resolution=texture_size or 1024))
    mesh = mesh.with_normals()
    side = texture_size
    if side == 0:
        side = 256
        if frames:
            side = texture_side_for(mesh, frames, texel_pixels)[0]
    return mesh, bake_texels(mesh, side, side, device=device)


_ATLAS_READ: dict = {}
"""the atlas folder read last: its files' identity (path, size, modification time) -> (mesh, bake). The model
choice's candidates and the fit after them read one atlas four times (0.5 s of OBJ and bake a read on the
temple's 830x834 atlas); its arrays are read-only, so no caller can change another's copy"""


def _atlas_folder(mesh_file: Path, bake_file: Path):
    """(mesh with normals, TexelBake) of an atlas folder, read once while its files stay the same."""
    key = tuple((str(f.resolve()), st.st_size, st.st_mtime_ns) for f in (mesh_file, bake_file) for st in [f.stat()])
    if key not in _ATLAS_READ:
        mesh, bake = load_mesh(mesh_file).with_normals(), TexelBake.load(bake_file)
        for array in [*vars(mesh).values(), *vars(bake).values()]:
            if isinstance(array, np.ndarray):
                array.flags.writeable = False
        _ATLAS_READ.clear()
        _ATLAS_READ[key] = mesh, bake
    return _ATLAS_READ[key]


def load_photos(capture, frames, device: str | None = None):
    """Images (linear, H x W x 3, through the capture's photo response when it has one) and masks of the given
    frames."""
    images, masks = [], []
    response = capture.response
    for f in frames:
        images.append(read_image(capture.image_path(f), channels=3, response=response))
        mp = capture.mask_path(f)
        masks.append(read_mask(mp, images[-1].shape[:2]) if mp is not None and mp.exists() else None)
    return images, masks


PHOTO_CACHE_FOLDER = ".texstream-cache"
"""the capture's folder for photos decoded once and streamed from there
(:class:`~texstream.fit.stream.photo_stream.PhotoCache`)"""


def photo_files(capture, frames, level: int = 0):
    """The frames' photos and masks as files (:class:`texstream.fit.stream.photo_stream.PhotoFiles`), decoded
    by the fit's PhotoSet on a pool of threads or processes: all at set-up when they stay in memory, or a window
    per pass when streamed from disk (``StreamConfig.photo_residency``); at pyramid level ``level``
    (fit/common/photo_levels.py; 0: as they are)."""
    masks = []
    for f in frames:
        mp = capture.mask_path(f)
        masks.append(mp if mp is not None and mp.exists() else None)
    # module functions or module classes, not closures: worker processes receive them (fit/stream/decode_pool.py)
    reader = photo_reader(capture.response)
    image_reader, mask_reader = ((reader, read_mask) if level == 0 else
                                 (LevelImageReader(reader, level), LevelMaskReader(read_mask, level)))
    return PhotoFiles([capture.image_path(f) for f in frames], masks, image_reader, mask_reader,
                      cache_dir=Path(capture.root) / PHOTO_CACHE_FOLDER)


PHOTO_LEVEL_MIN_TEXEL_PIXELS = 2.0
"""``photo_level`` auto: the coarsest level whose texels stay at least this many of its pixels wide in the tenth
of the photos that see them smallest. At 2 the default atlas (texels about 3 photo pixels wide, texel_pixels)
keeps the photos as they are; an atlas 4x coarser than its photos streams them at a quarter of the pixels"""


def choose_photo_level(mesh, bake, frames, requested: int) -> tuple[int, dict]:
    """(level, why) for the fitted photos: ``requested`` when >= 0, else
    :func:`texstream.geometry.density.photo_level_for` at the bake's size."""
    side = float(np.sqrt(bake.width * bake.height))
    level, info = photo_level_for(mesh, frames, side, PHOTO_LEVEL_MIN_TEXEL_PIXELS)
    if requested >= 0:
        level, info = requested, dict(info, level_texel_pixels=None if info["texel_pixels"] is None
                                      else info["texel_pixels"] / 2 ** requested)
    first = frames[0].intrinsics
    return level, dict(info, level=level, requested=requested,
                       size=[int(first.width) >> level, int(first.height) >> level])


def read_photos(photos, masks, indices):
    """Images and masks (all-true where none) of ``indices`` of ``photos`` (a list of arrays with a
    list of masks or None, or a PhotoFiles, which names its masks)."""
    out_images, out_masks = [], []
    for i in indices:
        if isinstance(photos, PhotoFiles):
            im = photos.read_image(photos.paths[i])
            mp = photos.mask_paths[i]
            mk = None if mp is None else photos.read_mask(mp, im.shape[:2])
        else:
            im, mk = photos[i], None if masks is None else masks[i]
        out_images.append(im)
        out_masks.append(np.ones(im.shape[:2], bool) if mk is None else mk)
    return out_images, out_masks


def validation_period(n_fitted: int, every: int) -> int:
    """The period of the validation split of ``n_fitted`` fitted photos (every period-th held back for the choices
    of materials, ambient term and model): ``every`` (``materials.validation_every``) where that leaves at least
    two validation photos, else the shortest period that does, n // 2, as long as it keeps two thirds of the
    photos fitted (n >= 6). With fewer photos than 2 x ``every`` and no split, every choice fell back to its most
    flexible model unjudged: per-texel lobes of 10 flash photos predicted an unseen view at 16 dB where a
    diffuse fit gave 41 dB (docs/scale.md, the 6-megapixel run)."""
    if every <= 0 or n_fitted // every >= 2:
        return every
    shorter = n_fitted // 2
    return shorter if shorter >= 3 else every


def check_capture_lights(capture, model: str, capture_dir: str | Path) -> None:
    """Reflectance models (layout traits ``lit``) need a light per photo; radiance models need none."""
    if layout_traits(model).lit and not capture.has_lights:
        raise InputError(f"the {model} model needs a light per photo and some frames have none",
                         Path(capture_dir) / "capture.json",
                         "fit the radiance model (--model radiance), or add per-frame lights (texstream ingest "
                         "--lights, texstream lights, or a co-located flash)")


def check_seen_texels(problem, cfg, capture_dir: str | Path) -> tuple:
    """Count the texels some photo sees and fail before fitting when almost none are: a mesh facing away
    from the cameras or in another frame than the capture's. The count comes from the fit's starting
    pass (:func:`fit_start`), returned for the fit to reuse."""
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
    full_frames: list | None = None
    """the fitted frames at full resolution (``frames`` are at ``photo_level``); None: the same as ``frames``"""
    photo_level: dict | None = None
    """the pyramid level the fitted photos stream at, and why (:func:`choose_photo_level`)"""

    def frames_as_photographed(self) -> list:
        """The fitted frames at the photos' own resolution (what renders beside the photos use)."""
        return self.frames if self.full_frames is None else self.full_frames


def load_fit_inputs(capture_dir: str | Path, mesh_path: str | Path, cfg) -> FitInputs:
    """Read and check everything a fit needs, before any long work starts."""
    capture = read_capture(capture_dir)
    check_capture_lights(capture, cfg.fit.model, capture_dir)
    frames, held = split_holdout(capture.frames, cfg.holdout_every)
    if cfg.choice.validation_fit:  # the model choice's fit of a candidate: the validation photos are scored instead
        frames, held = split_holdout(frames, validation_period(len(frames), cfg.materials.validation_every))
    if not frames:
        raise InputError("no photo is left to fit after the hold-out split", Path(capture_dir) / "capture.json",
                         "lower --holdout-every or add photos")
    mesh, bake = load_geometry(mesh_path, cfg.texture_size, cfg.device, frames, cfg.texel_pixels)
    seams = load_seams(mesh_path, bake)
    level, why = choose_photo_level(mesh, bake, frames, cfg.photo_level)
    if level:
        say("fit", f"photos streamed at level {level} ({why['size'][0]}x{why['size'][1]} pixels, 1/{2 ** level} "
                   f"of their side): the texels are {why['texel_pixels']:.1f} photo pixels wide "
                   f"(--photo-level 0 keeps full resolution)")
    return FitInputs(capture, [frame_at_level(f, level) for f in frames], held, mesh, bake, seams,
                     photo_files(capture, frames, level), None, full_frames=list(frames), photo_level=why)


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


class SharedPhotoSet:
    """The photo set (photos on the device with their depth and shadow maps) of the last fit in this process,
    handed to the next fit of the same photos (or some of them: :meth:`PhotoSet.subset`, nothing read or
    rendered again), frames, mesh, stream options and device: the candidates of the model choice (``texstream
    run``: Lafortune, diffuse, two lobes, and their fits of the validation split) differ only in their parameters
    and photos, and the photo set was most of each one's set-up (issue 40: 7 s of the demo's 48 s Lafortune
    fit, each candidate again). The set is built the same way every time, so a fit on a shared one gives the
    parameters of a fit on its own (tests/test_fit_photo_levels.py). Sets streamed from disk (their loaders
    close with the stage) and photos split over devices are not kept. One set at most: the next fit's replaces
    it unless its photos are a subset of the kept ones; :meth:`release` drops it."""

    key: str | None = None
    photo_keys: list | None = None
    photos = None

    @classmethod
    def key_for(cls, inputs: FitInputs, cfg) -> tuple[str, list[str]] | None:
        """(the key of what every photo shares: device, stream options, reader, mesh; one key per photo: its
        files, pose, intrinsics, exposure and light), or None for photos given as arrays."""
        paths = getattr(inputs.images, "paths", None)
        if paths is None:  # photos given as arrays: not a capture's files
            return None
        h = hashlib.sha256(json.dumps({"device": str(cfg.device), "stream": config_to_dict(cfg.fit.stream),
                                       "reader": getattr(inputs.images.read_image, "cache_key", None)},
                                      sort_keys=True, default=str).encode())
        for a in (inputs.mesh.vertices, inputs.mesh.faces):
            h.update(np.ascontiguousarray(a).tobytes())
        photo_keys = []
        for f, path, mask in zip(inputs.frames, paths, inputs.images.mask_paths):
            i = f.intrinsics
            k = hashlib.sha256(json.dumps([str(path), None if mask is None else str(mask)]).encode())
            k.update(np.asarray([*np.ravel(f.R), *np.ravel(f.t), i.fx, i.fy, i.cx, i.cy, i.width, i.height,
                                 f.exposure], np.float64).tobytes())
            k.update(repr(None if f.light is None else f.light.to_json()).encode())
            photo_keys.append(k.hexdigest())
        return h.hexdigest(), photo_keys

    @classmethod
    def _rows(cls, key) -> list[int] | None:
        """The kept set's rows of ``key``'s photos, or None where some photo or the shared key differs."""
        if key is None or cls.photos is None or key[0] != cls.key:
            return None
        row = {k: j for j, k in enumerate(cls.photo_keys)}
        return [row[k] for k in key[1]] if all(k in row for k in key[1]) else None

    @classmethod
    def take(cls, key):
        rows = cls._rows(key)
        if rows is None:
            return None
        return cls.photos if rows == list(range(cls.photos.n)) else cls.photos.subset(rows)

    @classmethod
    def keep(cls, key, photos) -> None:
        if cls._rows(key) is not None:
            return  # the kept set holds these photos and maybe more: kept for the next fit
        if key is None or not isinstance(photos, PhotoSet) or photos.residency == "disk":
            cls.release()
            return
        (cls.key, cls.photo_keys), cls.photos = key, photos

    @classmethod
    def release(cls) -> None:
        cls.key, cls.photo_keys, cls.photos = None, None, None


def set_up_skipping_bad_photos(inputs: FitInputs, cfg, capture_dir: str | Path):
    """The fit's problem and its starting pass (:func:`check_seen_texels`); every photo is decoded there, so
    an unreadable one fails here, before the fit and before anything is written, with one line naming it.
    With ``skip_bad_photos`` the photo is left out of ``inputs`` instead, said, and the set-up run again.
    Returns (problem, texels seen, start, skipped photos as {"file", "error"})."""
    skipped = []
    while True:
        try:
            key = SharedPhotoSet.key_for(inputs, cfg)
            shared = SharedPhotoSet.take(key)
            if shared is None and cfg.choice.validation_fit and not cfg.skip_bad_photos:
                shared = _validation_photos_from_every_fitted(inputs, cfg, key)
            if shared is not None:
                say("fit", "photos and their maps shared with the previous fit of this capture")
            problem = build_problem(inputs.mesh, inputs.bake, inputs.frames, inputs.images, inputs.masks, cfg.fit,
                                    cfg.device, photos=shared)
            SharedPhotoSet.keep(key, problem.photos)
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
            if inputs.full_frames is not None:
                inputs.full_frames = [inputs.full_frames[j] for j in keep]
            inputs.images = inputs.images.subset(keep)


def _validation_photos_from_every_fitted(inputs: FitInputs, cfg, key):
    """For the model choice's validation fit of a candidate judged first: the photo set of every fitted photo built
    and kept (:class:`SharedPhotoSet`), its validation split's subset returned, so the candidate fitted to every
    photo after it reads nothing again (the README demo's diffuse validation fit, judged first since Lafortune waits
    on its highlights, and then Lafortune's fit each read the photos: 5.2 + 5.9 s). None where the full set would
    stream at another pyramid level than the split (its photos would differ) or is not a capture's files."""
    capture = inputs.capture
    fitted, _ = split_holdout(capture.frames, cfg.holdout_every)
    level = (inputs.photo_level or {}).get("level", 0)
    if key is None or not fitted or choose_photo_level(inputs.mesh, inputs.bake, fitted, cfg.photo_level)[0] != level:
        return None
    every = dataclasses.replace(inputs, frames=[frame_at_level(f, level) for f in fitted], held=[],
                                images=photo_files(capture, fitted, level), full_frames=list(fitted))
    every_key = SharedPhotoSet.key_for(every, cfg)
    try:
        problem = build_problem(every.mesh, every.bake, every.frames, every.images, every.masks, cfg.fit, cfg.device)
    except InputError:  # a bad photo: the split's own set-up says which, as it did
        return None
    SharedPhotoSet.keep(every_key, problem.photos)
    return SharedPhotoSet.take(key)


def check_output_path(out_dir: str | Path) -> None:
    """Fail before any work when the output path cannot become a folder."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another -o path")



def load_seams(mesh_path: str | Path, bake):
    """The atlas folder's ``seams.npz`` (None without one), checked against the bake's atlas size."""
    p = Path(mesh_path)
    if not p.is_dir() or not (p / "seams.npz").is_file():
        return None

    seams = Seams.load(p / "seams.npz")
    n = bake.height * bake.width
    idx = np.concatenate([seams.idx_a.ravel(), seams.idx_b.ravel()])
    if (seams.width, seams.height) != (bake.width, bake.height) or seams.fill_source.shape != (n,) \
            or (idx.size and (idx.min() < 0 or idx.max() >= n)):
        raise InputError(f"seams are for a {seams.width}x{seams.height} atlas, "
                         f"the bake is {bake.width}x{bake.height}",
                         p / "seams.npz", "re-run `texstream atlas` to rebuild the atlas folder")
    return seams
