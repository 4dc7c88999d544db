"""Camera registration with pycolmap (``texstream register CAPTURE``).

Pipeline (what COLMAP's automatic reconstructor does, with capture-folder plumbing around it):

1. photos: the frames of ``CAPTURE/capture.json`` (ingest output) or the images of a plain folder;
   masks from the frames' ``mask_path`` or ``masks/NAME.png``, passed to feature extraction so no
   features land on the background;
2. SIFT extraction, one COLMAP camera per image size (two cameras mixed in one folder become two
   camera models), with calibrated intrinsics (``--intrinsics``, fixed unless
   ``--refine-intrinsics``) or COLMAP's own focal guess;
3. exhaustive matching (sequential or vocabulary tree for large or video-like sets);
4. incremental mapping; with an EXIF focal prior that looks wrong after it (photos left out, the focal
   length pulled far from the prior or to the mapper's bound), mapping again from COLMAP's default guess
   without the prior, the better model kept; the largest model is kept and unregistered photos are reported; with
   estimated intrinsics, the lens distortion (and an auto-refined principal point) is kept only
   where it lowers the reprojection error (``--min-self-calibration-gain``), else the cameras are
   made pinhole and re-adjusted: an unneeded distortion term bends the focal length and the poses; by the same
   rule an EXIF focal length the mapping kept is held (poses re-adjusted) unless refining it lowers the error
   enough: on one object at one distance the focal length trades against that distance and drifts;
   photos it leaves out are placed on a turntable's ring when the registered cameras lie on one
   (``--ring``, :mod:`.ring_placement`: the focal length by the ring's fit, the other models merged, the
   left-out photos at their ring angles, checked by their silhouettes);
5. optional Sim3 alignment to known camera centres (``--align-to capture.json``, pycolmap RANSAC) or
   into a given mesh's frame (``--align-mesh MESH``: :mod:`texstream.geometry.mesh_frame`, which the
   caller passes in as ``mesh_alignment``: the similarity of the mesh onto the SfM points, inverted, so
   cameras and points land on the mesh);
6. undistortion of registered photos and masks to pinhole, conversion to ``capture.json``.

Outputs (atomically): ``capture.json``, ``images/``, ``masks/``, ``sparse/0``, ``points3D.ply``,
``registration_report.json``, ``register_config.json``. On failure a partial report is written to
``OUT.failed_report.json`` and the error says how many photos registered.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from texstream.capture.capture_json import (CAPTURE_FILE, Capture, Frame, Intrinsics, flash_fired, read_capture,
                                             write_capture)
from texstream.capture.imageio import image_size, linear_to_srgb, read_image, read_mask, write_image
from texstream.core.checkpoint import KEY_FILE, StageCheckpoint, files_signature, inputs_key, work_dir_for
from texstream.core.errors import ConfigError, InputError, StageError, TexstreamError
from texstream.core.config import config_to_dict, option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, write_atomic_with, write_json_atomic
from texstream.core.progress import bar, phase, say

from .colmap_log import colmap_errors_held, colmap_quiet, quiet_colmap_log
from .focal_check import check_focal_prior, drop_focal_priors
from .colmap_io import intrinsics_to_colmap, opencv_distortion, reconstruction_frames
from .files import (list_images, read_stored_pixels, remap_channels, write_failure_report,
                    write_stored_pixels)
from .intrinsics import intrinsics_for_size, load_intrinsics
from .photo_groups import check_groups, match_groups
from .lights import colocated_light
from .photometric import estimate_gains, observations_from_model
from .register_selfcal import hold_focal_prior, refine_principal_point, select_distortion
from .ring_placement import RingConfig, focal_by_ring, map_at_focal, place_on_ring

REPORT_FILE = "registration_report.json"


@dataclasses.dataclass
class RegisterConfig:
    """Options of the registration stage."""

    matcher: str = option("auto", help="auto (exhaustive up to 150 photos, else sequential), exhaustive, "
                          "sequential (ordered photos / video), vocab_tree (large sets; needs --vocab-tree)",
                          choices=("auto", "exhaustive", "sequential", "vocab_tree"))
    vocab_tree: str | None = option(None, help="COLMAP vocabulary tree file for --matcher vocab_tree")
    sequential_overlap: int = option(10, help="neighbours matched per photo by the sequential matcher",
                                     min=1, max=10000)
    max_num_features: int = option(8192, help="SIFT features kept per photo", min=64, max=1000000)
    max_image_size: int = option(0, help="longest side of the photos SIFT reads (COLMAP downscales them and scales "
                                 "the keypoints back: the cameras are in full-resolution pixels); 0: auto, "
                                 "FEATURE_SIDE rule (feature_image_size)", min=16, max=100000, also=(0,))
    camera_model: str = option("SIMPLE_RADIAL", help="COLMAP camera model estimated when no intrinsics are given",
                               choices=("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"))
    intrinsics: str | None = option(None, help="intrinsics.json from 'texstream calibrate' (matched by image size)")
    refine_intrinsics: bool = option(False, help="let bundle adjustment refine given intrinsics")
    refine_principal_point: str = option("auto", help="refine the principal point in a final global bundle "
                                         "adjustment when the intrinsics are estimated (COLMAP keeps it at the image "
                                         "centre): auto (on when at least 8 photos and 500 points are registered), "
                                         "on, off; a result more than a tenth of the image size off centre is rejected",
                                         choices=("auto", "on", "off"))
    min_self_calibration_gain: float = option(
        0.01, help="when the intrinsics are estimated (no --intrinsics): keep the estimated lens distortion, an "
        "auto-refined principal point, and a focal length refined away from the EXIF prior, only when it lowers the "
        "mean reprojection error by at least this fraction, else pinhole cameras (distortion 0), the image centre "
        "and the EXIF focal length; a term the tracks do not need trades against "
        "the focal length and the poses (the synthetic sphere, a perfect pinhole, came out with k = -0.12 and the "
        "focal length 8% long at a 0.02% lower error); 0 keeps every estimate", min=0.0, max=1.0)
    use_masks: bool = option(True, help="pass masks to feature extraction (no features on the background)")
    min_model_size: int = option(3, help="smallest model (registered photos) kept by the mapper", min=2)
    disconnected: str = option("auto", help="when the photos fall into two or more groups (each at least a fifth of "
                               "the photos) that share no verified match: auto (stop before mapping, naming the groups, "
                               "when their colours say they are different objects; else register the largest group), "
                               "error (always stop), largest (register the largest group; the others are reported "
                               "unregistered)", choices=("auto", "error", "largest"))
    align_to: str | None = option(None, help="capture.json / transforms.json with known camera centres: "
                                  "Sim3-align the model to them (matched by image file name)")
    align_mesh: str | None = option(None, help="mesh file (OBJ / PLY / ...) whose frame and scale the capture is brought "
                                    "into: scaled ICP of the SfM points onto the mesh (not with --align-to)")
    align_mesh_max_rms: float = option(0.01, help="largest accepted RMS distance of the SfM points to the aligned mesh, "
                                       "as a fraction of the points' bounding-box diagonal", min=0.0, max=1.0)
    align_max_error: float = option(0.02, help="RANSAC inlier threshold of the alignment, as a fraction of the "
                                    "extent of the known centres", min=0.0, max=1.0)
    colocated_light: float | None = option(None, help="light fixed to the camera (flash) with this intensity, a point "
                                           "light at each camera centre; when SfM's scale is arbitrary (no "
                                           "alignment) it is the irradiance at the median object distance",
                                           min=1e-12)
    photometric: str = option("export", help="per-photo exposure / white-balance gains from shared SfM points: off, "
                              "export (frame 'photometric_gain'), apply (also multiply frame exposure)",
                              choices=("off", "export", "apply"))
    undistort: bool = option(True, help="undistort registered photos and masks to pinhole cameras")
    num_threads: int = option(-1, help="CPU threads for COLMAP's feature matching (-1: all); the matches are the same "
                              "at any count", min=-1, max=4096)
    mapping_threads: int = option(1, help="CPU threads for incremental mapping and bundle adjustment; 1: the same "
                                  "cameras in every run and at any core count; -1: all cores, faster bundle "
                                  "adjustment on large sets (COLMAP threads it from 50,000 residuals, about 25,000 "
                                  "observations) but cameras that change with the core count and from run to run: "
                                  "COLMAP tries initial pairs on every thread at once and starts from the one that "
                                  "succeeds first (the Middlebury temple's focal length came out 0.4% apart, "
                                  "rotations up to 0.12 degrees)", min=1, max=4096, also=(-1,))
    extraction_threads: int = option(1, help="CPU threads for SIFT extraction; more is faster on many cores "
                                             "but not reproducible (COLMAP numbers the images in the order "
                                             "they finish, and matching and mapping depend on that order)",
                                             min=1, max=4096)
    seed: int = option(0, help="random seed of COLMAP's RANSAC and mapper (reproducible runs)",
                       min=0, max=2147483647)
    ring: str = option("auto", help="photos mapping leaves out: auto (when the registered cameras lie on an evenly "
                       "stepped ring, as on a turntable: the focal length chosen by the ring's fit when it is "
                       "estimated, the left-out photos placed on the ring and checked by their silhouettes; "
                       "calib/ring_placement.py), off (reported unregistered)", choices=("auto", "off"))
    overwrite: bool = option(True, help="replace an existing output folder")


FEATURE_SIDE = 1600
"""``max_image_size`` auto: SIFT reads a photo at its longest side halved, but never below this many pixels (nor
above the photo's own size). SIFT localises a keypoint to about half a pixel of the size it finds it at, so at
most a 2x reduction keeps the registered cameras within about a pixel of the full-resolution photos, which the
refine stage's pose steps then correct at the texels' resolution; 1,600 pixels (hloc's SIFT default) still
yields the default 8,192 features of a textured photo. A 6 MP photo (3072x2048) is read at 1600x1067: a
quarter of its pixels, about a quarter of the extraction time."""


def feature_image_size(width: int, height: int, requested: int) -> tuple[int, str]:
    """(longest side SIFT reads photos of ``width`` x ``height`` at, why in one line): ``requested`` when > 0,
    else the :data:`FEATURE_SIDE` rule."""
    side = max(int(width), int(height))
    if requested > 0:
        size, why = min(requested, side), f"--register.max-image-size {requested}"
    else:
        size = min(side, max(FEATURE_SIDE, (side + 1) // 2))
        why = (f"auto: the longest side halved, at least {FEATURE_SIDE} px" if size < side else
               f"auto: photos of at most {FEATURE_SIDE} px are read as they are")
    if size == side:
        return size, f"SIFT on the photos as they are, {width}x{height} ({why})"
    scale = size / side
    return size, (f"SIFT on {round(width * scale)}x{round(height * scale)} of {width}x{height} ({why}); "
                  "keypoints scaled back, cameras in full-resolution pixels")


@dataclasses.dataclass
class _Photo:
    name: str            # name inside the COLMAP image folder (unique)
    path: Path           # source file
    width: int
    height: int
    mask: Path | None
    frame: Frame | None  # ingest frame (exposure, light, saturation...) when the input is a capture


def _image_size(path: Path) -> tuple[int, int] | None:
    try:
        w, h, _ = image_size(path)
        return int(w), int(h)
    except Exception:  # noqa: BLE001 - unreadable/corrupt: reported by the caller
        return None


def _collect_photos(capture: Path, cfg: RegisterConfig) -> tuple[list[_Photo], list[dict], Capture | None]:
    dropped: list[dict] = []
    cap = None
    if (capture / CAPTURE_FILE).is_file() or (capture / "transforms.json").is_file():
        cap = read_capture(capture)
        items = [(cap.image_path(f), cap.mask_path(f), f) for f in cap.frames]
    else:
        files = list_images(capture, what="capture folder")
        mdir = capture / "masks"
        items = []
        for f in files:
            m = next((c for c in (mdir / (f.stem + ".png"), mdir / (f.name + ".png")) if c.is_file()), None)
            items.append((f, m, None))
    photos, seen = [], set()
    for path, mask, frame in items:
        if not path.is_file():
            dropped.append({"image": str(path.name), "reason": "missing file"})
            continue
        size = _image_size(path)
        if size is None:
            dropped.append({"image": path.name, "reason": "unreadable or corrupt"})
            continue
        name = path.name
        if name in seen:
            dropped.append({"image": name, "reason": "duplicate file name"})
            continue
        seen.add(name)
        if mask is not None and not mask.is_file():
            mask = None
        photos.append(_Photo(name, path, size[0], size[1], mask if cfg.use_masks else None, frame))
    return photos, dropped, cap


def _is_8bit_colmap_readable(path: Path) -> bool:
    if path.suffix.lower() not in (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff"):
        return False
    try:
        import OpenImageIO as oiio

        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            return False
        ok = inp.spec().format == oiio.UINT8
        inp.close()
        return ok
    except Exception:  # noqa: BLE001
        return False


def _stage_images(photos: list[_Photo], work: Path) -> tuple[Path, Path | None]:
    """Image and mask folders COLMAP reads: 8-bit files linked as they are, others as 8-bit sRGB proxies."""
    img_dir = work / "images"
    img_dir.mkdir(parents=True)
    mask_dir = None
    for p in photos:
        dst = img_dir / p.name
        if _is_8bit_colmap_readable(p.path):
            try:
                os.symlink(p.path.resolve(), dst)
            except OSError:
                shutil.copy2(p.path, dst)
        else:
            # HDR / 16-bit / float: SIFT wants 8-bit; tone-map by the 99th percentile, then sRGB.
            # Keep the original name so the model and the capture agree; the proxy is a PNG inside.
            img = read_image(p.path, channels=3)
            scale = float(np.percentile(img, 99.0)) or 1.0
            code = (np.clip(linear_to_srgb(np.clip(img / scale, 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8)
            tmp_png = work / "proxy.png"
            write_image(tmp_png, code, bits=8)
            os.replace(tmp_png, dst)
        if p.mask is not None:
            if mask_dir is None:
                mask_dir = work / "masks"
                mask_dir.mkdir()
            m = read_mask(p.mask, (p.height, p.width))
            write_image(mask_dir / (p.name + ".png"), (m > 0).astype(np.uint8) * 255, bits=8)
    return img_dir, mask_dir


def _camera_groups(photos: list[_Photo], cfg: RegisterConfig,
                   source: str) -> list[tuple[list[_Photo], str, str, bool | None]]:
    """Group photos into COLMAP cameras by image size: (photos, model, params string or '', whether the focal
    length is a prior: None when COLMAP decides or the intrinsics are given).

    ``source`` is the capture's ``intrinsics_source`` (ingest), or the frame's own ``focal_prior`` when it
    has one: ``calibrated`` frames' intrinsics are used as given; ``exif`` focal lengths (ingest's
    cross-checked prior) and ``guess`` ones (1.2 x the longer side, where EXIF had none or ingest dropped a
    doubtful one: no prior) seed COLMAP's estimate of ``cfg.camera_model``, given explicitly so COLMAP does
    not read the photos' EXIF again (it would take the stale focal-plane tags).
    """
    cams = load_intrinsics(cfg.intrinsics) if cfg.intrinsics else None
    groups: dict[tuple[int, int], list[_Photo]] = {}
    for p in photos:
        groups.setdefault((p.width, p.height), []).append(p)
    out = []
    for (w, h), ps in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        kind = ps[0].frame.extra.get("focal_prior", source) if ps[0].frame is not None else None
        if cams is not None:
            model, params = intrinsics_to_colmap(intrinsics_for_size(cams, w, h, cfg.intrinsics))
            out.append((ps, model, ",".join(f"{x:.10g}" for x in params), None))
        elif source == "calibrated" and ps[0].frame is not None:
            model, params = intrinsics_to_colmap(ps[0].frame.intrinsics)
            out.append((ps, model, ",".join(f"{x:.10g}" for x in params), None))
        elif kind in ("exif", "guess"):
            i0 = ps[0].frame.intrinsics
            n_extra = {"SIMPLE_PINHOLE": 0, "PINHOLE": 0, "SIMPLE_RADIAL": 1, "RADIAL": 2, "OPENCV": 4}[cfg.camera_model]
            f = [i0.fx] if cfg.camera_model.startswith("SIMPLE") or cfg.camera_model == "RADIAL" else [i0.fx, i0.fy]
            params = f + [i0.cx, i0.cy] + [0.0] * n_extra
            out.append((ps, cfg.camera_model, ",".join(f"{x:.10g}" for x in params), kind == "exif"))
        else:
            out.append((ps, cfg.camera_model, "", None))
    return out


def _run_colmap(photos: list[_Photo], img_dir: Path, mask_dir: Path | None, work: Path, cfg: RegisterConfig,
                timings: dict, source: str, capture_root: Path, out: Path, report: dict) -> dict[int, Any]:
    import pycolmap

    db = work / "database.db"
    kept = _kept_database(work, db)
    t0 = time.perf_counter()
    eo = pycolmap.FeatureExtractionOptions()
    eo.sift.max_num_features = cfg.max_num_features
    eo.num_threads = cfg.extraction_threads  # reproducible image ids (geometry/triangulate.py says why)
    cameras = _camera_groups(photos, cfg, source)
    resolution = report.setdefault("feature_resolution", {})
    for ps, model, params, _ in cameras:
        eo.max_image_size, resolution[f"{ps[0].width}x{ps[0].height}"] = feature_image_size(
            ps[0].width, ps[0].height, cfg.max_image_size)
        if kept is not None:
            continue  # features kept from an interrupted run
        ro = pycolmap.ImageReaderOptions()
        ro.camera_model = model
        if params:
            ro.camera_params = params
        if mask_dir is not None:
            ro.mask_path = str(mask_dir)
        # One camera per size group: SINGLE within a call, a new camera per call.
        with phase("register", f"SIFT features of {len(ps)} photo(s) {ps[0].width}x{ps[0].height} read at "
                   f"{eo.max_image_size} px"), colmap_quiet():
            pycolmap.extract_features(db, img_dir, image_names=[p.name for p in ps],
                                      camera_mode=pycolmap.CameraMode.SINGLE, reader_options=ro,
                                      extraction_options=eo, device=pycolmap.Device.cpu)
    timings["extract_s"] = time.perf_counter() - t0
    guessed = [p.name for ps, _, _, prior in cameras if prior is False for p in ps]
    if guessed and kept is None:
        drop_focal_priors(db, guessed)
    if kept is None:
        _keep_database(db, work / FEATURES_DB)
    t0 = time.perf_counter()
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = cfg.num_threads
    vo = pycolmap.TwoViewGeometryOptions()
    vo.ransac.random_seed = cfg.seed
    matcher = cfg.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(photos) <= 150 else "sequential"
    if matcher == "vocab_tree" and (not cfg.vocab_tree or not Path(cfg.vocab_tree).is_file()):
        raise ConfigError("--matcher vocab_tree needs --vocab-tree FILE (a COLMAP vocabulary tree)",
                          cfg.vocab_tree, "download one from colmap.github.io or use --matcher sequential")
    if kept != MATCHED_DB:
        with phase("register", f"matching features ({matcher}, {len(photos)} photos)"), colmap_quiet():
            _match(db, matcher, mo, vo, cfg)
        _keep_database(db, work / MATCHED_DB)
    timings["match_s"] = time.perf_counter() - t0
    groups = match_groups(db, vo.min_num_inliers)
    check_groups(groups, photos, capture_root, out, cfg, report)
    fixed = bool(cfg.intrinsics or source == "calibrated") and not cfg.refine_intrinsics
    t0 = time.perf_counter()
    recs = _map(db, img_dir, work / "sparse", len(photos), cfg, fixed)
    timings["map_s"] = time.perf_counter() - t0
    if timings["map_s"] >= 1.0:
        say("register", f"incremental mapping: {timings['map_s']:.1f} s")
    if any(prior for _, _, _, prior in cameras) and not fixed:
        recs = check_focal_prior(recs, db, len(photos), report,
                                 lambda: _map(db, img_dir, work / "sparse_no_prior", len(photos), cfg, fixed=False))
    return recs


def _match(db: Path, matcher: str, mo: Any, vo: Any, cfg: RegisterConfig) -> None:
    """COLMAP's feature matching of the database's photos (exhaustive, sequential or vocabulary tree)."""
    import pycolmap

    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu)
    elif matcher == "sequential":
        po = pycolmap.SequentialPairingOptions()
        po.overlap = cfg.sequential_overlap
        pycolmap.match_sequential(db, matching_options=mo, pairing_options=po, verification_options=vo,
                                  device=pycolmap.Device.cpu)
    else:
        po = pycolmap.VocabTreePairingOptions()
        po.vocab_tree_path = cfg.vocab_tree
        pycolmap.match_vocabtree(db, matching_options=mo, pairing_options=po, verification_options=vo,
                                 device=pycolmap.Device.cpu)


FEATURES_DB, MATCHED_DB = "features.db", "matched.db"
"""the work folder's copies of COLMAP's database after feature extraction and after matching: a rerun after an
interruption starts from the later one (mapping and the checks after it change database.db, never these)"""


def _kept_database(work: Path, db: Path) -> str | None:
    """The copy of the database an interrupted run kept (its name, put in place as ``db``; said in one line), or
    None. Everything else in the work folder (staged photos, mapped models) is made again."""
    kept = next((name for name in (MATCHED_DB, FEATURES_DB) if (work / name).is_file()), None)
    db.unlink(missing_ok=True)
    if kept is not None:
        shutil.copyfile(work / kept, db)
        say("register", f"resuming from {work / kept}: " + ("features and matches kept, only the mapping runs again"
                                                             if kept == MATCHED_DB else "features kept, matching again"))
    return kept


def _keep_database(db: Path, copy: Path) -> None:
    """An atomic copy of the database as it is now (a kill during the copy leaves none)."""
    with open(db, "rb") as src:
        write_atomic_with(copy, lambda fh: shutil.copyfileobj(src, fh))


def _work_folder(photos: list, cap_root: Path, out: Path, cfg: RegisterConfig) -> StageCheckpoint:
    """The registration's work folder beside ``out`` (opened), keyed by the photos and masks (paths, sizes,
    modification times), the capture.json, and the options; staged photos and models of an earlier run removed
    (made again), its databases kept."""
    files = [p.path for p in photos] + [p.mask for p in photos if p.mask is not None] + [cap_root / CAPTURE_FILE]
    ck = StageCheckpoint(work_dir_for(out, "register"), inputs_key("register", files_signature(files),
                                                                   config_to_dict(cfg)), "register")
    if ck.open():
        for entry in ck.folder.iterdir():
            if entry.name not in (FEATURES_DB, MATCHED_DB, KEY_FILE):
                shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    return ck


def _map(db: Path, img_dir: Path, sparse: Path, n_photos: int, cfg: RegisterConfig, fixed: bool) -> dict[int, Any]:
    """COLMAP's incremental mapping of the database's photos (intrinsics held when ``fixed``)."""
    import pycolmap

    op = pycolmap.IncrementalPipelineOptions()
    op.num_threads = cfg.mapping_threads  # 1 by default: the option's help says why
    op.random_seed = cfg.seed
    op.min_model_size = cfg.min_model_size
    if fixed:
        op.ba_refine_focal_length = False
        op.ba_refine_principal_point = False
        op.ba_refine_extra_params = False
        op.mapper.abs_pose_refine_focal_length = False
        op.mapper.abs_pose_refine_extra_params = False
    say("register", f"incremental mapping of {n_photos} photos")
    with colmap_quiet() as term, bar(total=n_photos, desc="register: mapping", unit="photo", file=term) as b:
        def step(k: int) -> None:  # photos registered, counted over every model the mapper starts
            b.update(min(k, max(0, n_photos - b.n)))

        return pycolmap.incremental_mapping(db, img_dir, sparse, options=op,
                                            initial_image_pair_callback=lambda: step(2),
                                            next_image_callback=lambda: step(1))


def _known_centres(path: str) -> dict[str, np.ndarray]:
    cap = read_capture(path)
    return {Path(f.file_path).name: f.center for f in cap.frames}


def align_to_centres(rec: Any, centres: dict[str, np.ndarray], max_error_frac: float, seed: int = 0) -> dict:
    """Sim3-align a reconstruction in place to known camera centres (pycolmap, RANSAC).

    Args:
        rec: pycolmap.Reconstruction (modified in place).
        centres: image name -> known world position (3,).
        max_error_frac: inlier threshold as a fraction of the known centres' extent.

    Returns:
        dict with ``scale``, ``common`` (images used) and ``rmse`` (centre error after alignment, world units).
    """
    import pycolmap

    names = [im.name for im in rec.images.values() if im.has_pose and im.name in centres]
    if len(names) < 3:
        raise StageError(f"only {len(names)} registered photo(s) have known centres; Sim3 alignment needs 3",
                         fix="check that --align-to names the same image files")
    locs = np.stack([centres[n] for n in names])
    extent = float(np.linalg.norm(locs.max(0) - locs.min(0))) or 1.0
    ro = pycolmap.RANSACOptions()
    ro.max_error = max_error_frac * extent
    ro.random_seed = seed
    sim = pycolmap.align_reconstruction_to_locations(rec, names, locs, 3, ro)
    if sim is None:
        raise StageError("Sim3 alignment to the known camera centres failed (too few consistent centres)",
                         fix="check --align-to, or raise --align-max-error")
    rec.transform(sim)
    got = np.stack([rec.find_image_with_name(n).projection_center() for n in names])
    rmse = float(np.sqrt(np.mean(np.sum((got - locs) ** 2, 1))))
    return {"kind": "centres", "scale": float(sim.scale), "common": len(names), "rmse": rmse, "extent": extent}


def _photometric_gains(rec: Any, photos: list[_Photo], mask_dir: Path | None, report: dict) -> dict[str, np.ndarray]:
    """Per-photo RGB gains from the model's shared points (see :mod:`.photometric`); {} when too few."""
    t0 = time.perf_counter()
    images, masks, sat = {}, {}, {}
    for p in photos:
        im = rec.find_image_with_name(p.name)
        if im is None or not im.has_pose:
            continue
        # Divide by the ingest exposure so the gains are what remains after EXIF normalisation.
        images[p.name] = read_image(p.path, channels=3) / (p.frame.exposure if p.frame else 1.0)
        if p.mask is not None:
            masks[p.name] = read_mask(p.mask).reshape(p.height, p.width) > 0
        s = p.frame.saturation if p.frame and p.frame.saturation else (0.99 if _is_8bit_colmap_readable(p.path) else None)
        sat[p.name] = None if s is None else s / (p.frame.exposure if p.frame else 1.0)
    ii, pp, vals, names = observations_from_model(rec, images, masks, sat)
    if len(ii) == 0:
        return {}
    gains, used = estimate_gains(ii, pp, vals, len(names))
    report["photometric"] = {"observations": int(len(ii)), "seconds": time.perf_counter() - t0,
                             "gains": {n: [float(x) for x in g] for n, g, u in zip(names, gains, used) if u > 0}}
    return {n: g for n, g, u in zip(names, gains, used) if u >= 20}  # 20: enough points for a median


def _undistort(src: Path, dst: Path, intr: Intrinsics, nearest: bool = False) -> None:
    """Undistort one image file to the same pinhole K, keeping its format and bit depth (OpenImageIO + cv2)."""
    import cv2
    import OpenImageIO as oiio

    px, spec = read_stored_pixels(src, "image to undistort")
    k, d = opencv_distortion(intr)
    size = (intr.width, intr.height)
    if intr.camera_model == "OPENCV_FISHEYE":
        m1, m2 = cv2.fisheye.initUndistortRectifyMap(k, d, np.eye(3), k, size, cv2.CV_32FC1)
    else:
        m1, m2 = cv2.initUndistortRectifyMap(k, d, None, k, size, cv2.CV_32FC1)
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    out = remap_channels(px, m1, m2, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    write_stored_pixels(dst, out, oiio.ImageSpec(spec), "undistorted image")


def _median_object_distance(rec, posed: dict) -> float:
    """Median distance from the registered cameras to the median SfM point (scene units)."""
    pts = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    centre = np.median(pts, axis=0) if len(pts) else np.zeros(3)
    centres = [-np.asarray(r).T @ np.asarray(t) for r, t, _ in posed.values()]
    return float(np.median([np.linalg.norm(c - centre) for c in centres])) if centres else 1.0


@colmap_errors_held()
def register(capture: str | os.PathLike, out: str | os.PathLike, config: RegisterConfig | None = None,
             mesh_alignment: Callable[[str], Callable[[Any, float], dict]] | None = None) -> StageResult:
    """Register the photos of a capture folder (or plain photo folder) with pycolmap.

    Args:
        capture: ingest output (``capture.json`` + images) or a folder of photos (masks in ``masks/``).
        out: posed capture folder to write (see the module doc).
        config: options.
        mesh_alignment: for ``config.align_mesh``, the mesh path -> ``align(rec, max_rms_frac)`` that brings a
            reconstruction into the mesh's frame and returns the report's ``alignment``
            (:func:`texstream.geometry.mesh_frame.mesh_alignment`: the geometry stage's, which the callers,
            above both stages, pass in).

    Returns:
        StageResult; summary has ``registered``, ``unregistered`` (names), ``dropped``, ``models``
        (sizes of all models found), ``mean_reprojection_error`` (px), ``alignment``, timings.

    Raises:
        InputError: missing/empty folder, bad intrinsics file. StageError: fewer than two photos,
        or no model (photos with no overlap); a partial report is written to ``OUT.failed_report.json``.
    """

    quiet_colmap_log()
    cfg = config or RegisterConfig()
    capture, out = Path(capture), Path(out)
    if out.exists() and not cfg.overwrite:
        raise InputError("output folder already exists", out, "remove it or pass --overwrite")
    photos, dropped, cap = _collect_photos(capture, cfg)
    report: dict[str, Any] = {"input": str(capture), "photos": len(photos) + len(dropped), "dropped": dropped,
                              "camera_sizes": sorted({f"{p.width}x{p.height}" for p in photos})}
    if len(photos) < 2:
        report["registered"], report["unregistered"] = [], [p.name for p in photos]
        path = write_failure_report(out, report)
        raise StageError(f"registration needs at least 2 readable photos, got {len(photos)} "
                         f"({len(dropped)} dropped); partial report {path}", capture,
                         "add overlapping photos of the object (20+ from all sides is typical)")
    if cfg.align_to and cfg.align_mesh:
        raise ConfigError("give either --align-to (known camera centres) or --align-mesh (a mesh frame), not both",
                          cfg.align_mesh, "drop one of the two options")
    centres = _known_centres(cfg.align_to) if cfg.align_to else None
    align_mesh = None
    if cfg.align_mesh:
        if mesh_alignment is None:
            raise ConfigError("--align-mesh needs the mesh alignment of the geometry stage, which was not given",
                              cfg.align_mesh, "run the registration through the texstream command")
        align_mesh = mesh_alignment(cfg.align_mesh)
    timings: dict[str, float] = {}
    out.parent.mkdir(parents=True, exist_ok=True)
    ck = _work_folder(photos, capture, out, cfg)
    try:
        work = ck.folder
        img_dir, mask_dir = _stage_images(photos, work)
        source = str(cap.extra.get("intrinsics_source", "")) if cap is not None else ""
        recs = _run_colmap(photos, img_dir, mask_dir, work, cfg, timings, source, capture, out, report)
        left_out = cfg.ring == "auto" and recs and max(r.num_reg_images() for r in recs.values()) < len(photos)
        ring_focal = None
        if left_out and not (cfg.intrinsics or source == "calibrated") and len({p.width for p in photos}) == 1:
            recs, ring_focal = focal_by_ring(recs, lambda f: map_at_focal(work, img_dir, f, cfg.mapping_threads,
                                                                          cfg.seed, cfg.min_model_size),
                                             [p.name for p in photos], photos[0].width, RingConfig(), report)
        sizes = sorted((r.num_reg_images() for r in recs.values()), reverse=True)
        report["models"] = sizes
        if not recs:
            report["registered"], report["unregistered"] = [], [p.name for p in photos]
            path = write_failure_report(out, report)
            raise StageError(f"no model: none of the {len(photos)} photos could be registered "
                             f"(too little overlap or texture); partial report {path}", capture,
                             "take overlapping photos (60%+ overlap between neighbours) of a textured object")
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        fixed = bool(cfg.intrinsics or source == "calibrated") and not cfg.refine_intrinsics
        rec, report["distortion"] = select_distortion(rec, cfg, not fixed)
        rec, report["principal_point"] = refine_principal_point(rec, cfg, not fixed)
        rec = _hold_focal_prior(rec, cfg, fixed, ring_focal, report)
        report["mean_reprojection_error"] = float(rec.compute_mean_reprojection_error())
        if centres is not None:
            report["alignment"] = align_to_centres(rec, centres, cfg.align_max_error, cfg.seed)
        elif align_mesh is not None:
            report["alignment"] = align_mesh(rec, cfg.align_mesh_max_rms)
        posed = {name: (r, t, intr) for name, r, t, intr in reconstruction_frames(rec)}
        if left_out:
            largest = max(recs.values(), key=lambda r: r.num_reg_images())  # the one ``rec`` was made from
            others = [r for r in recs.values() if r is not largest]
            posed = place_on_ring([rec] + others, photos, posed, lambda p: _intrinsics_of_size(posed, p),
                                  RingConfig(), report)
        gains = _photometric_gains(rec, photos, mask_dir, report) if cfg.photometric != "off" else {}
        aligned_to = "centres" if centres is not None else ("mesh" if align_mesh is not None else None)
        coloc, offset = _colocated_light(cfg, cap, rec, posed, aligned_to is not None, report)
        report["registered"] = sorted(posed)
        report["placed"] = sorted(n for n, e in report.get("ring", {}).get("photos", {}).items()
                                  if e["method"] == "ring" and n in posed)
        report["unregistered"] = [p.name for p in photos if p.name not in posed]
        with atomic_output_dir(out) as tmp:
            t0 = time.perf_counter()
            frames = [_posed_frame(p, posed[p.name], tmp, mask_dir, cfg, coloc, offset, gains)
                      for p in photos if p.name in posed]
            timings["undistort_s"] = time.perf_counter() - t0
            extra = _capture_extra(cap, cfg, fixed, report, len(frames), aligned_to)
            write_capture(Capture(root=tmp, frames=frames, extra=extra), tmp)
            (tmp / "sparse" / "0").mkdir(parents=True)
            rec.write(str(tmp / "sparse" / "0"))
            if rec.num_points3D() > 0:
                rec.export_PLY(str(tmp / "points3D.ply"))
            report["timings"] = timings
            report["points3D"] = int(rec.num_points3D())
            write_json_atomic(tmp / REPORT_FILE, report)
            save_config(cfg, tmp / "register_config.json")
    except TexstreamError:
        ck.remove()  # a clear failure: nothing to resume
        raise
    ck.remove()  # registered; only an interrupted run (Ctrl-C, a crash, SIGKILL) leaves its databases for the rerun
    summary = {k: report[k] for k in ("registered", "placed", "unregistered", "dropped", "models",
                                      "mean_reprojection_error", "points3D", "timings")}
    summary["ring"] = report.get("ring", {}).get("decision")
    summary["alignment"] = report.get("alignment")
    summary["principal_point"] = report.get("principal_point")
    summary["distortion"] = report.get("distortion")
    summary["focal_prior"] = report.get("focal_prior")
    summary["focal_hold"] = report.get("focal_hold")
    summary["resolution"] = "; ".join(report["feature_resolution"].values())
    return StageResult(output=out, summary=summary)


def _hold_focal_prior(rec: Any, cfg: RegisterConfig, fixed: bool, ring_focal: float | None, report: dict) -> Any:
    """The model with its focal length held at the EXIF prior where the photos do not tell a better one
    (:func:`.register_selfcal.hold_focal_prior`; ``report["focal_hold"]``), else ``rec``: only for an EXIF prior
    the mapping kept (not one mapped again without, nor a focal length the turntable ring chose)."""
    prior = report.get("focal_prior") or {}
    if fixed or ring_focal is not None or prior.get("kept", "prior") != "prior" or not prior.get("prior_focal_px"):
        return rec
    priors = {int(k): float(v) for k, v in prior["prior_focal_px"].items()}
    rec, report["focal_hold"] = hold_focal_prior(rec, priors, cfg, bool(report["principal_point"].get("refined")),
                                                 report["distortion"].get("kept") == "distortion")
    return rec


def _intrinsics_of_size(posed: dict, photo: _Photo) -> Intrinsics | None:
    """The intrinsics of a registered photo of ``photo``'s size (None: none registered)."""
    return next((intr for _, _, intr in posed.values() if (intr.width, intr.height) == (photo.width, photo.height)),
                None)


def _colocated_light(cfg: RegisterConfig, cap: Capture | None, rec, posed: dict, aligned: bool,
                     report: dict) -> tuple[Any, list]:
    """The colocated light's (intensity, offset) for the posed frames (None: none): the option's, else the
    capture's; for an unaligned reconstruction scaled to mean irradiance at the object (said in ``report``)."""
    coloc = cfg.colocated_light
    offset = [0.0, 0.0, 0.0]
    if coloc is None and cap is not None and isinstance(cap.extra.get("colocated_light"), dict):
        coloc = cap.extra["colocated_light"].get("intensity")
        offset = cap.extra["colocated_light"].get("offset", offset)
    if coloc is not None and not aligned:
        # an unaligned reconstruction has an arbitrary scale; a point light's irradiance falls as 1/r^2
        # in it, so the flash intensity is taken as the irradiance at the median camera-to-object
        # distance: the fitted albedos then do not depend on the scale SfM happened to pick
        d = _median_object_distance(rec, posed)
        coloc = (np.asarray(coloc, np.float64) * d * d).tolist() if np.ndim(coloc) else float(coloc) * d * d
        report["colocated_light"] = {"median_object_distance": d, "intensity_scaled_by": d * d,
                                     "why": "unaligned SfM scale: intensity means irradiance at the object"}
    return coloc, offset


def _posed_frame(p: _Photo, pose: tuple, tmp: Path, mask_dir: Path, cfg: RegisterConfig, coloc, offset: list,
                 gains: dict) -> Frame:
    """A registered photo's frame of the output capture, its photo and mask written into ``tmp`` (undistorted
    when ``cfg.undistort`` and the camera has distortion, else copied)."""
    r, t, intr = pose
    dst_rel = Path("images") / p.name
    mask_rel = None
    distorted = bool(intr.distortion) and any(abs(v) > 0 for v in intr.distortion.values())
    if cfg.undistort and distorted:
        _undistort(p.path, tmp / dst_rel, intr)
        if p.mask is not None:
            mask_rel = Path("masks") / (Path(p.name).stem + ".png")
            _undistort(mask_dir / (p.name + ".png"), tmp / mask_rel, intr, nearest=True)
        intr = dataclasses.replace(intr, camera_model="PINHOLE", distortion={})
    else:
        (tmp / dst_rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(p.path, tmp / dst_rel)
        if p.mask is not None:
            mask_rel = Path("masks") / (Path(p.name).stem + p.mask.suffix)
            (tmp / mask_rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(p.mask, tmp / mask_rel)
    base = p.frame
    light = base.light if base else None
    if coloc is not None:
        light = colocated_light(r, t, coloc, offset, fired=base is None or flash_fired(base))
    extra = dict(base.extra) if base else {}
    exposure = base.exposure if base else 1.0
    if p.name in gains:
        g = gains[p.name]
        extra["photometric_gain"] = [float(x) for x in g]
        if cfg.photometric == "apply":
            exposure *= float(np.mean(g))
    return Frame(file_path=str(dst_rel), R=r, t=t, intrinsics=intr, light=light, exposure=exposure,
                 mask_path=None if mask_rel is None else str(mask_rel),
                 saturation=base.saturation if base else None, extra=extra)


def _capture_extra(cap: Capture | None, cfg: RegisterConfig, fixed: bool, report: dict, registered: int,
                   aligned_to: str | None) -> dict:
    """The output capture.json's extra: the input capture's, with where the intrinsics came from and what
    the registration did."""
    extra = dict(cap.extra) if cap is not None else {}
    extra.pop("posed", None)
    extra.pop("colocated_light", None)
    if (report.get("focal_prior") or {}).get("retried"):
        extra["focal_prior_registration"] = report["focal_prior"]["decision"]
    if not fixed:
        # Bundle adjustment estimated the intrinsics: say so, and keep where they started.
        extra["intrinsics_prior"] = extra.get("intrinsics_source") or ("guess" if cap is None else "unknown")
        extra["intrinsics_source"] = "sfm"
        held = (report.get("focal_hold") or {}).get("held")
        extra["intrinsics_refined"] = ([] if held else ["focal_length"]) + (
            ["distortion"] if report["distortion"].get("kept") == "distortion" else []) + (
            ["principal_point"] if report["principal_point"].get("refined") else [])
    elif cfg.intrinsics:
        extra["intrinsics_source"] = "calibrated"
    extra["registration"] = {"registered": registered, "unregistered": report["unregistered"],
                             "aligned": aligned_to is not None, "aligned_to": aligned_to}
    return extra
