"""SfM points from photos with known cameras: SIFT features, matching and triangulation (pycolmap).

When the capture's cameras are already known (a calibrated rig, the Middlebury sets, a synthetic
capture), the points the mesh stage needs do not require a full registration: COLMAP's point
triangulator takes the given poses as fixed and only matches and triangulates. This is COLMAP's
``point_triangulator`` (pycolmap ``triangulate_points``) with capture-folder plumbing:

1. photos staged for COLMAP (8-bit files linked; HDR/float photos as 8-bit sRGB proxies) with the
   masks (no features on the background);
2. SIFT with a low peak threshold (textureless plaster / paint needs weak features), exhaustive
   matching with guided matching (the poses are known, so epipolar guidance is reliable);
3. a ``pycolmap.Reconstruction`` holding the capture's cameras (world-to-camera R, t, OpenCV axes:
   COLMAP's own convention) and triangulation with two-view tracks kept (a sparse ring sees most
   surface points in two neighbouring photos only);
4. filtering: reprojection error, and points projecting outside the object mask of any photo that
   holds them (background and shadow matches).

Normals come from :func:`texstream.geometry.reconstruct.estimate_normals` (PCA, oriented towards
the cameras that observe each point).

pycolmap / OpenImageIO are imported inside the functions.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from texstream.calib.colmap_io import intrinsics_to_colmap
from texstream.calib.colmap_log import colmap_quiet, quiet_colmap_log
from texstream.capture.capture_json import masks_are_silhouettes
from texstream.capture.imageio import linear_to_srgb, read_image, read_mask, write_image
from texstream.core.errors import InputError
from texstream.core.config import option
from .hull import load_masks
from .reconstruct import estimate_normals

_COLMAP_8BIT = (".png", ".jpg", ".jpeg")


@dataclasses.dataclass
class TriangulateConfig:
    """Options for triangulating SfM points from known cameras."""

    max_features: int = option(8192, help="SIFT features kept per photo")
    peak_threshold: float = option(0.002, help="SIFT peak threshold (COLMAP default 0.0067; lower finds the weak "
                                               "features of plaster and paint: 3x more temple points)")
    guided_matching: bool = option(True, help="epipolar-guided matching (the poses are known)")
    two_view_tracks: bool = option(True, help="keep points seen in only two photos (sparse rings need them)")
    max_reproj_error: float = option(2.0, help="drop points whose mean reprojection error exceeds this (pixels)")
    mask_margin: int = option(2, help="a point is background when it projects this many pixels outside a mask")
    outside_is_background: bool = option(True, help="a point outside a photo is background (the object is whole "
                                                    "in every photo; as the visual hull assumes)")
    outlier_factor: float = option(4.0, help="drop points whose 4th-neighbour distance exceeds this many times "
                                             "the median (isolated false matches); 0: off")
    normal_neighbours: int = option(12, help="neighbours for the points' PCA normals")
    num_threads: int = option(-1, help="CPU threads for COLMAP matching and triangulation (-1: all)")
    extraction_threads: int = option(1, help="CPU threads for SIFT extraction; more is faster on many cores "
                                             "but not reproducible (COLMAP numbers the images in the order "
                                             "they finish, and the points depend on that order)")
    seed: int = option(0, help="random seed of COLMAP's RANSAC and triangulator (reproducible points)")


@dataclasses.dataclass
class TriangulatedPoints:
    """Triangulated points and their provenance.

    Attributes:
        points: (N, 3) world points (capture frame, its units).
        normals: (N, 3) unit normals (PCA, oriented towards the cameras that observed each point).
        track_length: (N,) photos observing each point.
        error: (N,) mean reprojection error, pixels.
        report: counts and timings.
    """

    points: np.ndarray
    normals: np.ndarray
    track_length: np.ndarray
    error: np.ndarray
    report: dict


def _stage_photos(capture, work: Path) -> tuple[Path, Path | None, list[str]]:
    """COLMAP image and mask folders for the capture's frames; returns (images, masks, names)."""
    img_dir = work / "images"
    mask_dir = work / "masks"
    names = []
    has_masks = all(f.mask_path for f in capture.frames)
    for i, f in enumerate(capture.frames):
        src = capture.root / f.file_path
        if not src.is_file():
            raise InputError(f"photo {f.file_path} not found", capture.root / "capture.json",
                             "restore the photos, or make the mesh with --from hull / --from scan.obj")
        # unique flat names keep COLMAP's image and mask paths simple
        name = f"{i:05d}_{src.stem}" + (src.suffix.lower() if src.suffix.lower() in _COLMAP_8BIT else ".png")
        dst = img_dir / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.suffix.lower() in _COLMAP_8BIT:
            try:
                os.symlink(src.resolve(), dst)
            except OSError:
                shutil.copy2(src, dst)
        else:
            # HDR / float photos: SIFT wants 8-bit; tone-map by the 99th percentile, then sRGB
            img = read_image(src, channels=3)
            scale = float(np.percentile(img, 99.0)) or 1.0
            write_image(dst, (np.clip(linear_to_srgb(np.clip(img / scale, 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8),
                        bits=8)
        if has_masks:
            m = read_mask(capture.mask_path(f), (f.intrinsics.height, f.intrinsics.width))
            mask_dir.mkdir(exist_ok=True)
            write_image(mask_dir / (name + ".png"), (m > 0).astype(np.uint8)[:, :, None] * np.uint8(255), bits=8)
        names.append(name)
    return img_dir, (mask_dir if has_masks else None), names


def _intrinsics_key(intr) -> tuple:
    return (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy, intr.camera_model,
            tuple(sorted(intr.distortion.items())))


def triangulate_capture(capture, config: TriangulateConfig | None = None,
                        work_dir: str | os.PathLike | None = None,
                        masks: Sequence[np.ndarray] | None = None) -> TriangulatedPoints:
    """Triangulate SfM points from a capture's photos and known cameras (module doc).

    Args:
        capture: a :class:`texstream.capture.capture_json.Capture` with posed frames.
        config: options.
        work_dir: folder for COLMAP's database (a temporary folder, removed afterwards, when None).
        masks: per-frame (H, W) object masks for the point filter (read from the capture when None
            and every frame has one).

    Returns:
        The filtered points with normals.

    Raises:
        InputError: fewer than 2 frames or a photo is missing.
    """
    import pycolmap

    quiet_colmap_log()

    cfg = config or TriangulateConfig()
    if len(capture.frames) < 2:
        raise InputError(f"{len(capture.frames)} photo(s): triangulation needs at least 2",
                         capture.root / "capture.json", "add photos, or use --from hull / --from scan.obj")
    t0 = time.perf_counter()
    tmp = None
    if work_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="texstream_tri_")
        work = Path(tmp.name)
    else:
        work = Path(work_dir)
        work.mkdir(parents=True, exist_ok=True)
    try:
        img_dir, mask_dir, names = _stage_photos(capture, work)
        db = work / "database.db"
        if db.exists():
            db.unlink()
        groups = _extract_features(capture, db, img_dir, mask_dir, names, cfg)
        t_extract = time.perf_counter() - t0
        mo = pycolmap.FeatureMatchingOptions()
        mo.num_threads = cfg.num_threads
        mo.guided_matching = cfg.guided_matching
        vo = pycolmap.TwoViewGeometryOptions()
        vo.ransac.random_seed = cfg.seed
        with colmap_quiet():
            pycolmap.match_exhaustive(db, matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu)
        t_match = time.perf_counter() - t0 - t_extract

        rec, db_images, index = _posed_reconstruction(capture, db, groups, names)
        op = pycolmap.IncrementalPipelineOptions()
        op.num_threads = cfg.num_threads
        op.triangulation.ignore_two_view_tracks = not cfg.two_view_tracks
        op.random_seed = cfg.seed
        op.triangulation.random_seed = cfg.seed
        (work / "tri").mkdir(exist_ok=True)
        with colmap_quiet():
            out = pycolmap.triangulate_points(rec, db, img_dir, work / "tri", options=op, refine_intrinsics=False)
        t_tri = time.perf_counter() - t0 - t_extract - t_match
        pts3d = list(out.points3D.values())
        frame_of_image = {im.image_id: index[im.name] for im in db_images}
        tracks = [[frame_of_image[e.image_id] for e in p.track.elements] for p in pts3d]
    finally:
        if tmp is not None:
            tmp.cleanup()
    if pts3d:
        xyz = np.array([p.xyz for p in pts3d], np.float64)
        err = np.array([p.error for p in pts3d], np.float64)
        tl = np.array([p.track.length() for p in pts3d], np.int32)
    else:
        xyz, err, tl = np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32)
    report = {"triangulated": int(len(xyz))}
    keep = np.isfinite(xyz).all(axis=1) & (err <= cfg.max_reproj_error)
    report["after_reprojection_filter"] = int(keep.sum())
    if masks is None and masks_are_silhouettes(capture) and all(f.mask_path for f in capture.frames):
        masks = load_masks(capture)  # silhouettes only: a point outside one is background
    if masks is not None and keep.any():
        keep &= inside_masks(xyz, capture.frames, masks, cfg.mask_margin, cfg.outside_is_background)
        report["after_mask_filter"] = int(keep.sum())
    if cfg.outlier_factor > 0 and keep.sum() > 8:
        keep[keep] = isolated_points(xyz[keep], cfg.outlier_factor) == 0
        report["after_outlier_filter"] = int(keep.sum())
    centres = np.array([f.center for f in capture.frames])
    # mean unit direction from each point to the cameras that observed it: the visible side
    owner = np.repeat(np.arange(len(tracks)), [len(tr) for tr in tracks])
    cam = np.fromiter((c for tr in tracks for c in tr), np.int64, count=len(owner))
    d = centres[cam] - xyz[owner]
    view = np.zeros_like(xyz)
    np.add.at(view, owner, d / np.linalg.norm(d, axis=1, keepdims=True))
    xyz, err, tl, view = xyz[keep], err[keep], tl[keep], view[keep]
    nrm = estimate_normals(xyz, None, cfg.normal_neighbours, view_dirs=view) if len(xyz) >= 3 else view
    report.update({"points": int(len(xyz)), "mean_track_length": float(tl.mean()) if len(tl) else 0.0,
                   "median_reprojection_error_px": float(np.median(err)) if len(err) else 0.0,
                   "seconds": {"extract": round(t_extract, 2), "match": round(t_match, 2),
                               "triangulate": round(t_tri, 2), "total": round(time.perf_counter() - t0, 2)}})
    return TriangulatedPoints(xyz, nrm, tl, err, report)


def _extract_features(capture, db: Path, img_dir: Path, mask_dir: Path | None, names: list[str],
                      cfg: TriangulateConfig) -> dict[tuple, list[int]]:
    """SIFT features of the staged photos into the database ``db``, one COLMAP camera per distinct intrinsics
    (fixed, never refined). Returns the frames of each intrinsics (key: :func:`_intrinsics_key`)."""
    import pycolmap

    eo = pycolmap.FeatureExtractionOptions()
    eo.sift.max_num_features = cfg.max_features
    eo.sift.peak_threshold = cfg.peak_threshold
    # One extraction thread by default: in parallel, COLMAP gives the images their ids in the order
    # their features finish, and the ids order the matching and triangulation: the temple gave
    # 4210 to 4215 points and a different mesh and atlas from run to run (on one thread: the
    # same 4215 points, mesh and atlas in every run). On the 2-core dev box one thread is no
    # slower: extraction 6.1-7.6 s (9 runs) against 4.3-8.4 s (10 runs) on two.
    eo.num_threads = cfg.extraction_threads
    # one COLMAP camera per distinct intrinsics, fixed (never refined)
    groups: dict[tuple, list[int]] = {}
    for i, f in enumerate(capture.frames):
        groups.setdefault(_intrinsics_key(f.intrinsics), []).append(i)
    for idx in groups.values():
        model, params = intrinsics_to_colmap(capture.frames[idx[0]].intrinsics)
        ro = pycolmap.ImageReaderOptions()
        ro.camera_model = model
        ro.camera_params = ",".join(f"{x:.12g}" for x in params)
        if mask_dir is not None:
            ro.mask_path = str(mask_dir)
        with colmap_quiet():
            pycolmap.extract_features(db, img_dir, image_names=[names[i] for i in idx],
                                      camera_mode=pycolmap.CameraMode.SINGLE, reader_options=ro,
                                      extraction_options=eo, device=pycolmap.Device.cpu)
    return groups


def _posed_reconstruction(capture, db: Path, groups: dict[tuple, list[int]], names: list[str]):
    """A reconstruction holding the capture's cameras (one per intrinsics group) and known poses, its images
    the database's (their ids). Returns (reconstruction, the database's images, staged name -> frame)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids = {}
    for cid, (key, idx) in enumerate(groups.items(), start=1):
        intr = capture.frames[idx[0]].intrinsics
        model, params = intrinsics_to_colmap(intr)
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=intr.width, height=intr.height,
                                                        params=params, camera_id=cid))
        for i in idx:
            cam_ids[i] = cid
    database = pycolmap.Database.open(str(db))
    try:
        db_images = database.read_all_images()
    finally:
        database.close()
    index = {n: i for i, n in enumerate(names)}
    for im in db_images:
        i = index[im.name]
        f = capture.frames[i]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(f.R, np.float64)),
                                np.asarray(f.t, np.float64).reshape(3))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=im.name, camera_id=cam_ids[i], image_id=im.image_id),
                                         pose)
    return rec, db_images, index


def inside_masks(points: np.ndarray, frames: Sequence, masks: Sequence[np.ndarray], margin: int = 2,
                 outside_is_background: bool = True) -> np.ndarray:
    """Which points project inside (or within ``margin`` pixels of) the mask of every photo (the visual hull).

    Args:
        points: (N, 3) world points.
        frames: frames with R, t, pinhole intrinsics.
        masks: (H, W) boolean masks, one per frame.
        margin: mask dilation in pixels (mask edges are a few pixels uncertain).
        outside_is_background: a point outside a photo (or behind its camera) is background (the
            object is whole in every photo, as the visual hull assumes); off: such photos say nothing.

    Returns:
        (N,) bool.
    """
    from scipy.ndimage import binary_dilation

    ok = np.ones(len(points), bool)
    for f, m in zip(frames, masks):
        m = np.asarray(m, bool)
        if margin > 0:
            m = binary_dilation(m, iterations=int(margin))
        pc = points @ np.asarray(f.R, np.float64).T + np.asarray(f.t, np.float64).reshape(1, 3)
        front = pc[:, 2] > 0
        z = np.where(front, pc[:, 2], 1.0)
        # pixel centres at +0.5: floor of the continuous coordinate is the pixel index
        u = np.floor(f.intrinsics.fx * pc[:, 0] / z + f.intrinsics.cx).astype(np.int64)
        v = np.floor(f.intrinsics.fy * pc[:, 1] / z + f.intrinsics.cy).astype(np.int64)
        inimg = front & (u >= 0) & (v >= 0) & (u < m.shape[1]) & (v < m.shape[0])
        ok[inimg] &= m[v[inimg], u[inimg]]
        if outside_is_background:
            ok &= inimg
    return ok


def isolated_points(points: np.ndarray, factor: float = 4.0, k: int = 4) -> np.ndarray:
    """1 for points whose k-th neighbour is farther than ``factor`` times the median such distance, else 0."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=k + 1)
    dk = d[:, -1]
    return (dk > factor * np.median(dk)).astype(np.int8)


def write_points(path: str | os.PathLike, points: np.ndarray, normals: np.ndarray | None = None) -> Path:
    """Write points (and normals) as a binary little-endian PLY that :func:`.reconstruct.read_points` reads."""
    path = Path(path)
    p = np.asarray(points, np.float32).reshape(-1, 3)
    cols = [("x", p[:, 0]), ("y", p[:, 1]), ("z", p[:, 2])]
    if normals is not None:
        n = np.asarray(normals, np.float32).reshape(-1, 3)
        cols += [("nx", n[:, 0]), ("ny", n[:, 1]), ("nz", n[:, 2])]
    rec = np.empty(len(p), dtype=[(c, "<f4") for c, _ in cols])
    for c, v in cols:
        rec[c] = v
    head = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {len(p)}\n"
    head += "".join(f"property float {c}\n" for c, _ in cols) + "end_header\n"
    with open(path, "wb") as fh:
        fh.write(head.encode("ascii"))
        fh.write(rec.tobytes())
    return path
