"""The mesh stage: make the mesh from what the capture has, then clean and simplify it.

Sources (``MeshConfig.source``):
    ``scan``: a given mesh file (OBJ/PLY/STL/GLB), moved into the capture frame by ``matrix``, or
        aligned to the capture's SfM points (coarse Sim3 + ICP) when it has them.
    ``sfm``: screened Poisson of the SfM points (``points3D.ply`` beside ``capture.json``; when
        absent, triangulated from the photos and the capture's known cameras, see
        :mod:`.triangulate`), or of dense stereo points (``dense``, below), intersected with the
        visual hull when masks exist, else trimmed by Poisson density.
    ``hull``: visual hull of the masks.
    ``auto``: a given mesh if one is named; otherwise Poisson intersected with the hull when the
        capture has SfM points (or photos with known cameras to triangulate them from) and masks,
        Poisson alone with points but no masks, the hull when it only has masks. The choice and
        its reason go into the report. A capture with known cameras and nothing else (no masks,
        no points3D.ply: a Metashape or RealityCapture export) gets points triangulated with those
        cameras and dense stereo without masks (below).

Why Poisson intersected with the hull is the default when both exist: the hull cannot see
concavities (on the Middlebury temple only 67% of the SfM points lie within 1% of the bounding-box
diagonal of the hull, the rest sit in the recesses between the columns), while Poisson follows the
points there (96%) but invents surface where there are none (the temple's unseen base balloons 3 cm
down); the intersection keeps Poisson where points are and the silhouettes cut what it invents,
and it is closed. Numbers: ``tests/test_geometry_temple.py`` on the 2-core CPU dev box.

Dense points (``dense``, :mod:`.mvs`): plane-sweep stereo depth maps of every photo, filtered by
geometric consistency and fused to oriented points, replace the sparse SfM points in Poisson. ``auto``
uses them when the capture has known cameras, its (pinhole) photos and masks; the depth range comes
from the capture's bounding box (e.g. the Middlebury README's), else the coarse visual hull of the
masks, else the SfM points' robust box. On the Middlebury temple the sparse points (about 4,000)
leave the steps, columns and beams to the hull and Poisson's smoothing; the dense ones (about
560,000 before fusion) follow them. When dense stereo finds fewer than ``MIN_DENSE_POINTS`` points or
confirms depths on less than ``MIN_DENSE_FILL`` of the mask pixels on average (a textureless object)
the sparse path runs instead, and the report says so.

Dense stereo without masks (:mod:`.posed_dense`): when the capture has known cameras and pinhole
photos but no masks, the SfM points (points3D.ply, or triangulated here with the given cameras, at
``posed.features`` SIFT features a photo) give each photo its depth range (robust percentiles of the
depths of the points it sees, with a margin; a scene's range widened further, the sparse points miss
the ground a facade's photos see at grazing angles) and its matched region (an object's: the convex
hull of the points' projections, grown; a scene's: every pixel). Measured (benchmarks/posed_mesh.py,
2-core CPU dev box): a glossy textured sphere from 24 cameras-only photos of 192 pixels, and the
synthetic facade (capture/synthetic/facade.py) from 11 of 640 x 480, both within 0.1% of the true
bounding-box diagonal (median, both ways); before, the first failed ("neither SfM points nor masks").
The report's ``dense`` entry says which masks (``masks``) and which depth range source
(``depth_range_from``, and per photo ``depth_range_source``) were used. The report's ``dense``
entry holds the point counts, per-photo neighbours, depth range and fill (kept depths over mask
pixels), timings and the reason.

Scenes and objects (``scene_kind``, :mod:`.scene`): SfM points of a scene (cameras inside the points'
robust extent, or over a flat cloud's footprint) are meshed by Poisson over the points inside that
extent, cropped to it and trimmed to where points are: Poisson alone closed them into a balloon
round the cameras, facing away from them. An object's closed Poisson surface that encloses a camera
gets the same treatment. Every mesh made from a capture is then oriented per connected component
towards the cameras whose rays hit it, and the stage fails (StageError) when more than
``max_back_faces`` of the rays still hit back faces, or when an object's surface encloses a camera.
The report holds the decision and its reason (``capture_kind``), ``facing``, ``cameras_enclosed``
and ``genus`` per component (and the hull's genus before and after its closing).

Outputs (atomically) in the output folder: ``mesh.ply``, ``mesh_report.json`` (source, reason,
cleanup report, alignment, triangulation), ``mesh_config.json``, and ``points3D.ply`` (points with
normals) when the points were triangulated here, or ``dense_points.ply`` (the fused dense points with
normals) when dense stereo made them.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import masks_are_silhouettes, read_capture
from texstream.core.checkpoint import work_dir_for
from texstream.core.errors import ConfigError, InputError, StageError
from texstream.core.config import option, save_config
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic
from texstream.core.progress import phase

from texstream.render.mesh import SurfaceMesh
from .align import align_to_points, transform_mesh
from .clean import CleanConfig, clean_mesh
from .hull import HullConfig, hull_bounds, load_masks, visual_hull
from .hull_fill import poisson_points_with_hull_fill
from .mesh_io import load_mesh, save_mesh
from .mvs import MvsConfig, capture_dense_points
from .posed_dense import PosedDenseConfig, coverage_masks, depth_ranges_from_points
from .reconstruct import PoissonConfig, poisson_reconstruct, read_points, trim_by_masks
from .scene import (Facing, camera_facing, cameras_enclosed, check_facing, classify_capture, crop_to_box,
                    drop_enclosed_components, genus_by_component, orient_to_cameras, point_spacing,
                    robust_box, trim_far_from_points)
from .triangulate import TriangulateConfig, triangulate_capture, write_points

POINTS_FILE = "points3D.ply"
DENSE_POINTS_FILE = "dense_points.ply"


@dataclasses.dataclass
class MeshConfig:
    """Options of ``texstream mesh``."""

    source: str = option("auto", help="where the mesh comes from: auto, scan (needs --mesh), sfm, hull",
                         choices=("auto", "scan", "sfm", "hull"))
    mesh: str = option("", help="given mesh file (OBJ/PLY/STL/GLB); implies source scan")
    faces: int = option(20000, help="decimate to this many faces (0: keep)", min=0, max=100000000)
    matrix: str = option("", help="4x4 world matrix (JSON or whitespace text) taking the given mesh into the "
                                  "capture frame; empty: align to the SfM points when the capture has them")
    align: bool = option(True, help="align a given mesh to the capture's SfM points by Sim3 + ICP")
    remesh: bool = option(False, help="isotropic remeshing after decimation")
    max_hole_edges: int = option(30, help="close holes bounded by at most this many edges", min=0)
    poisson_depth: int = option(8, help="screened Poisson octree depth", min=1, max=16)
    hull_resolution: int = option(128, help="visual hull grid nodes along the longest side", min=8, max=2048)
    intersect_hull: bool = option(True, help="intersect the Poisson surface with the visual hull when masks exist")
    triangulate: str = option("auto", help="SfM points from the photos and known cameras when the capture has no "
                                           "points3D.ply: auto (when it has its photos: the points Poisson meshes, "
                                           "or the depth ranges of dense stereo without masks), on, off",
                              choices=("auto", "on", "off"))
    dense: str = option("auto", help="dense multi-view stereo points (geometry/mvs.py) for Poisson instead of the "
                                     "sparse SfM points: auto (when the capture has known cameras, its pinhole "
                                     "photos, and masks or SfM points given or triangulated), on, off",
                        choices=("auto", "on", "off"))
    mvs: MvsConfig = option(default_factory=MvsConfig, help="dense stereo options")
    posed: PosedDenseConfig = option(default_factory=PosedDenseConfig, help="dense stereo without masks: depth "
                                     "ranges and matched regions from the SfM points (geometry/posed_dense.py)")
    device: str = option("auto", help=DEVICE_HELP + "; for hull carving, dense stereo and depth maps")
    scene_kind: str = option("auto", help="SfM points of a scene (cameras inside the points' extent: crop Poisson to "
                                          "it) or of an object (cameras around it: closed surface); auto decides "
                                          "from where the cameras stand (geometry/scene.py)",
                             choices=("auto", "scene", "object"))
    crop_percentile: float = option(2.0, help="robust extent of the SfM points: this percentile to 100 minus it on "
                                              "each axis (outliers do not stretch it)", min=0.0, max=49.0)
    crop_margin: float = option(0.05, help="margin around the robust extent, fraction of its diagonal",
                                min=0.0, max=10.0)
    trim_spacing: float = option(4.0, help="scene: drop surface farther from every SfM point than this many times "
                                           "the points' spacing (median 8th-neighbour distance) or one Poisson cell",
                                           min=0.0)
    facing_rays: int = option(48, help="camera rays along the longer image side for the facing check",
                              min=1, max=100000)
    max_back_faces: float = option(0.05, help="fail when more than this fraction of camera rays hit back faces after "
                                              "orientation (a closed mesh seen from outside has none; open scene "
                                              "surfaces and grazing rays along thin parts give a few)",
                                              min=0.0, max=1.0)
    fill_holes: float = option(0.01, help="hull: fill mask holes smaller than this fraction of the object area",
                               min=0.0, max=1.0)
    closing: int = option(0, help="hull: morphological closing radius in grid cells (0: off). 1 closes voxel-scale "
                                  "tunnels (Middlebury temple genus 10 -> 3 after hole filling; 133 with neither) but "
                                  "there the density atlas then evens texel size less (p90/p10 1.14 -> 1.71), not "
                                  "yet understood; off by default until it is", min=0, max=64)
    hull_fill: bool = option(True, help="objects with masks: add visual-hull samples to the Poisson points where the "
                                        "SfM points leave the surface open and no two cameras see it well (an "
                                        "underside seen only at grazing angles; geometry/hull_fill.py)")
    hull_fill_distance: float = option(2.0, help="hull fill: a region is open farther than this many times the "
                                                 "points' spacing (median 8th-neighbour distance) from every SfM "
                                                 "point", min=0.0)
    hull_fill_angle: float = option(60.0, help="hull fill: a camera sees the surface well within this angle "
                                               "(degrees) of its normal", min=0.0, max=90.0)


def _capture_bounds(capture):
    """The capture's object bounding box ``{"min", "max"}`` (e.g. from the Middlebury README), or None."""
    bb = capture.extra.get("bounding_box") if capture is not None else None
    try:
        lo, hi = np.asarray(bb["min"], np.float64), np.asarray(bb["max"], np.float64)
    except (TypeError, KeyError, ValueError):
        return None
    return (lo, hi) if lo.shape == (3,) and hi.shape == (3,) and np.all(hi > lo) else None


def _has_masks(capture) -> bool:
    """Every frame has a silhouette (masks of the pixels with data, an import's undistortion, do not count)."""
    return capture is not None and masks_are_silhouettes(capture) and all(f.mask_path for f in capture.frames)


def _has_photos(capture) -> bool:
    return capture is not None and len(capture.frames) >= 2 and all(
        (capture.root / f.file_path).is_file() for f in capture.frames)


def _will_dense(config: MeshConfig, capture) -> bool:
    """Whether dense stereo points are made from the photos and known cameras (module doc)."""
    if capture is None or config.dense == "off" or config.mesh or config.source in ("scan", "hull"):
        return False
    if config.dense == "on":
        return True
    if not (_has_photos(capture) and all(f.intrinsics.is_pinhole for f in capture.frames)):
        return False
    # without masks the depth range and the matched region come from SfM points (given or triangulated here)
    return _has_masks(capture) or (capture.root / POINTS_FILE).is_file() or config.triangulate != "off"


def _dense_without_masks(config: MeshConfig, capture) -> bool:
    return _will_dense(config, capture) and not _has_masks(capture)


def _will_triangulate(config: MeshConfig, capture) -> bool:
    """Whether SfM points are triangulated from the known cameras (no points3D.ply in the capture): as the
    points Poisson meshes, or as the depth range of dense stereo without masks."""
    if capture is None or (capture.root / POINTS_FILE).is_file() or config.triangulate == "off":
        return False
    if _will_dense(config, capture) and not _dense_without_masks(config, capture):
        return False  # dense stereo with masks takes its depth range from the hull
    return config.triangulate == "on" or _has_photos(capture)


def choose_source(config: MeshConfig, capture) -> tuple[str, str]:
    """(source, reason) from the config and what the capture holds."""
    triangulate = _will_triangulate(config, capture)
    dense = _will_dense(config, capture)
    has_points = capture is not None and ((capture.root / POINTS_FILE).is_file() or triangulate or dense)
    has_masks = _has_masks(capture)
    if config.mesh:
        if config.source not in ("auto", "scan"):
            raise ConfigError(f"--mesh given with --source {config.source}", fix="use one of them")
        return "scan", f"a mesh was given ({config.mesh})"
    if config.source == "scan":
        raise ConfigError("source scan needs a mesh file", fix="pass --from path/to/scan.obj")
    if capture is None:
        raise ConfigError("without a capture only a given mesh can be cleaned",
                          fix="pass a CAPTURE folder, or --from path/to/scan.obj")
    if config.source == "sfm" or (config.source == "auto" and has_points):
        if not has_points:
            raise InputError(f"no SfM points ({POINTS_FILE}) in the capture", capture.root,
                             "run 'texstream register' first" + (", or use --from hull (the capture has masks)"
                                                                 if has_masks else ", or give --from scan.obj"))
        why = ("the capture has photos with known cameras (dense stereo points from them"
               + (", without masks: depth ranges and matched regions from the SfM points"
                  + (" triangulated with those cameras)" if triangulate else " of points3D.ply)")
                  if not has_masks else ")") if dense
               else "the capture has photos with known cameras (SfM points triangulated from them)" if triangulate
               else "the capture has SfM points")
        if has_masks and config.intersect_hull:
            why += (" and masks: Poisson intersected with the visual hull (Poisson follows the concavities the "
                    "silhouettes miss; the hull cuts what Poisson invents where there are no points)")
        return "sfm", why
    if config.source == "hull" or (config.source == "auto" and has_masks):
        if not has_masks:
            raise InputError("not every frame has a mask_path: a visual hull needs masks", capture.root,
                             "add masks, or use --from sfm (after 'texstream register') or --from scan.obj")
        why = "the capture has masks but no SfM points"
        if config.triangulate != "off" and not _has_photos(capture):
            why += " (and no photos to triangulate them from)"
        return "hull", why
    raise InputError("the capture has neither SfM points nor masks to make a mesh from", capture.root,
                     "run 'texstream register' (SfM points), add masks (visual hull), or pass --from scan.obj")


def _read_matrix(path: str) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise InputError("matrix file not found", p, "give a 4x4 matrix as JSON or text")
    try:
        txt = p.read_text()
        import json

        m = np.asarray(json.loads(txt), np.float64) if txt.lstrip().startswith("[") else np.loadtxt(p)
    except (ValueError, OSError) as e:
        raise InputError(f"cannot read a 4x4 matrix ({e})", p, "write 16 numbers, row by row") from None
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"matrix has shape {m.shape}, expected 4x4 finite", p, "write 16 numbers, row by row")
    return m


def check_in_view(mesh: SurfaceMesh, capture, path=None) -> float:
    """Fraction of cameras whose image holds the mesh's bbox centre in front of them.

    Raises:
        InputError: fewer than half the cameras see it (a mesh far from the cameras: misaligned).
    """
    lo, hi = mesh.bbox()
    c = 0.5 * (lo + hi)
    seen = 0
    for f in capture.frames:
        pc = np.asarray(f.R) @ c + np.asarray(f.t).reshape(3)
        if pc[2] <= 0:
            continue
        u = f.intrinsics.fx * pc[0] / pc[2] + f.intrinsics.cx
        v = f.intrinsics.fy * pc[1] / pc[2] + f.intrinsics.cy
        seen += int(0 <= u < f.intrinsics.width and 0 <= v < f.intrinsics.height)
    frac = seen / max(1, len(capture.frames))
    if frac < 0.5:
        raise InputError(f"the mesh is not where the cameras look (its centre is in view of {seen} of "
                         f"{len(capture.frames)} cameras): it is in another frame or misaligned", path,
                         "pass --matrix with the mesh-to-capture transform, or register the capture so the mesh "
                         "can be aligned to its SfM points; fallbacks: --from sfm or --from hull")
    return frac


def make_mesh(capture_dir: str | os.PathLike | None, out: str | os.PathLike,
              config: MeshConfig | None = None) -> StageResult:
    """Run the mesh stage (module doc). Returns a StageResult whose summary is the report."""
    cfg = config or MeshConfig()
    if cfg.faces < 0:
        raise ConfigError(f"--faces {cfg.faces} is negative", fix="give a face count, or 0 to keep all")
    cfg = dataclasses.replace(cfg, device=resolve_device(cfg.device))
    t0 = time.perf_counter()
    capture = read_capture(capture_dir) if capture_dir is not None else None
    source, reason = choose_source(cfg, capture)
    report: dict = {"source": source, "reason": reason}
    masks = None
    new_points = None
    if capture is not None and _has_masks(capture) and source in ("sfm", "hull"):
        with phase("mesh", f"reading {len(capture.frames)} masks"):
            masks = load_masks(capture)
    if source == "scan":
        mesh = load_mesh(cfg.mesh)
        mesh = SurfaceMesh(mesh.vertices, mesh.faces)
        if capture is not None:
            mesh, report["alignment"] = _place_scan(mesh, capture, cfg)
            check_in_view(mesh, capture, cfg.mesh)
    elif source == "sfm":
        mesh, new_points = _from_sfm(capture, cfg, masks, report, work_dir_for(out, "dense"))
    else:
        with phase("mesh", f"visual hull: carving {len(masks)} masks (resolution {cfg.hull_resolution})"):
            mesh = visual_hull(capture.frames, masks, _hull_config(cfg), cfg.device, bounds=_capture_bounds(capture),
                               report=report.setdefault("hull", {}))
    with phase("mesh", f"cleanup and decimation of {mesh.n_faces} faces"
                       + (f" to {cfg.faces}" if cfg.faces else "")):
        cleaned, clean_rep = clean_mesh(mesh, CleanConfig(target_faces=cfg.faces, remesh=cfg.remesh,
                                                          max_hole_edges=cfg.max_hole_edges),
                                        path=cfg.mesh or capture_dir)
    report["clean"] = clean_rep.to_json()
    if capture is not None:
        # a shell inside the body (Poisson closes pockets the points leave inside an object) is seen by no
        # camera: it only takes atlas space and splits the surface into components
        cleaned, report["enclosed_components_removed"] = drop_enclosed_components(cleaned)
        with phase("mesh", f"orienting the surface towards {len(capture.frames)} cameras"):
            cleaned = _check_against_cameras(cleaned, capture, cfg, report, cfg.mesh or capture_dir)

    report["genus"] = genus_by_component(cleaned)
    report["summary"] = clean_rep.summary() + _facing_summary(report)
    report["seconds"] = round(time.perf_counter() - t0, 3)

    with atomic_output_dir(out) as tmp:
        save_mesh(tmp / "mesh.ply", cleaned)
        for name, (p, n) in (new_points or {}).items():
            write_points(tmp / name, p, n)
        write_json_atomic(tmp / "mesh_report.json", report)
        save_config(cfg, tmp / "mesh_config.json")
    shutil.rmtree(work_dir_for(out, "dense"), ignore_errors=True)  # the depth maps kept for a rerun
    return StageResult(output=Path(out), summary=report)


def _hull_config(cfg: MeshConfig):
    return HullConfig(resolution=cfg.hull_resolution, fill_holes=cfg.fill_holes, closing=cfg.closing)


def _capture_kind(cfg: MeshConfig, pts: np.ndarray, centres: np.ndarray) -> dict:
    """The scene / object decision (geometry/scene.py) with its reason, as JSON."""
    ck = classify_capture(pts, centres, cfg.crop_percentile, cfg.crop_margin).to_json()
    if cfg.scene_kind != "auto":
        ck["detected"] = ck["kind"]
        ck["kind"] = cfg.scene_kind
        ck["reason"] = f"--scene-kind {cfg.scene_kind} (detected {ck['detected']}: {ck['reason']})"
    return ck


def _crop_scene(mesh: SurfaceMesh, pts: np.ndarray, cfg: MeshConfig, pcfg, report: dict) -> SurfaceMesh:
    """The Poisson surface of a scene cropped to the points' robust box and trimmed to where points are."""
    lo, hi = robust_box(pts, cfg.crop_percentile, cfg.crop_margin)
    inside = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    faces0 = mesh.n_faces
    mesh = crop_to_box(mesh, lo, hi)
    cropped = mesh.n_faces
    # one Poisson cell: the surface's own resolution over the bounding cube of the points
    cell = pcfg.scale * float(np.ptp(pts, axis=0).max()) / 2 ** pcfg.depth
    spacing = point_spacing(inside)
    dist = max(cfg.trim_spacing * spacing, cell)
    mesh = trim_far_from_points(mesh, inside, dist)
    report["scene_crop"] = {"box_lo": lo.tolist(), "box_hi": hi.tolist(), "poisson_faces": faces0,
                            "after_box": cropped, "after_trim": mesh.n_faces, "point_spacing": spacing,
                            "trim_distance": dist}
    if mesh.n_faces == 0:
        raise StageError("nothing of the Poisson surface lies near the SfM points inside their robust extent",
                         fix="check the points (points3D.ply), or raise --trim-spacing")
    return mesh


def _check_against_cameras(mesh: SurfaceMesh, capture, cfg: MeshConfig, report: dict, path) -> SurfaceMesh:
    """Orient components towards the cameras that see them; fix or reject a surface enclosing an object's cameras;
    fail when camera rays still hit back faces (geometry/scene.py)."""
    centres = np.array([f.center for f in capture.frames])
    # objects (SfM points with cameras around them, or a hull) must not enclose a camera; scenes and scans may
    kind = report.get("capture_kind", {}).get("kind", "object" if report["source"] == "hull" else "unknown")
    enclosed = cameras_enclosed(mesh, centres)
    report["cameras_enclosed"] = int(enclosed.sum())
    if kind == "object" and enclosed.any():
        raise StageError(f"the {report['source']} surface encloses {int(enclosed.sum())} of {len(centres)} cameras of "
                         "an object capture", path,
                         "check the poses and masks, or use --scene-kind scene (cropped to the SfM points)")
    mesh, rep = orient_to_cameras(mesh, capture.frames, cfg.device, cfg.facing_rays)
    report["facing"] = rep
    check_facing(camera_facing(mesh, capture.frames, cfg.device, cfg.facing_rays) if rep["flipped_components"]
                 else _facing_of(rep), cfg.max_back_faces, path)
    return mesh


def _facing_of(rep: dict):
    b = rep["after"]
    return Facing(np.array([b["hits"] - b["back_hits"]]), np.array([b["back_hits"]]), b["rays"])


def _facing_summary(report: dict) -> str:
    f = report.get("facing")
    if not f:
        return ""
    s = f", {100 * f['after']['back_fraction']:.2f}% of camera rays on back faces"
    if f["flipped_components"]:
        s += f" ({f['flipped_components']} component(s) flipped)"
    return s


def _place_scan(mesh: SurfaceMesh, capture, cfg: MeshConfig) -> tuple[SurfaceMesh, dict]:
    if cfg.matrix:
        m = _read_matrix(cfg.matrix)
        return transform_mesh(mesh, m), {"method": "matrix", "matrix": m.tolist()}
    pts_path = capture.root / POINTS_FILE
    if cfg.align and pts_path.is_file():
        pts, _ = read_points(pts_path)
        if len(pts) >= 20:
            al = align_to_points(mesh, pts)
            return transform_mesh(mesh, al.matrix), {"method": "sim3+icp", "matrix": al.matrix.tolist(),
                                                     "rms": al.rms, "rms_fraction": al.rms_fraction}
    return mesh, {"method": "none (mesh assumed in the capture frame)"}


MIN_SFM_POINTS = 50  # fewer cannot say whether the capture is a scene or an object, nor support Poisson
# fewer dense points than this, or a smaller mean fraction of the mask pixels with a confirmed depth: the
# photos lack texture (or the cameras are off) and the sparse path is safer. The temple fills 48% (22% in
# its worst photo), the textured sphere 70%; a plain shaded sphere at 40 pixels 18% (2,025 points, whose
# Poisson surface had genus 14)
MIN_DENSE_POINTS = 2000
MIN_DENSE_FILL = 0.25


def _dense_bounds(capture, cfg: MeshConfig, masks) -> tuple[tuple[np.ndarray, np.ndarray], str]:
    """The world box the dense depth range spans, and where it came from (module doc)."""
    box = _capture_bounds(capture)
    if box is not None:
        lo, hi = box
        pad = 0.02 * float(np.linalg.norm(hi - lo))  # a tight box: surface points lie on its faces
        return (lo - pad, hi + pad), "the capture's bounding box"
    if masks is not None:
        return hull_bounds(capture.frames, masks, _hull_config(cfg), cfg.device), "the coarse visual hull"
    pts_path = capture.root / POINTS_FILE
    if pts_path.is_file():
        pts, _ = read_points(pts_path)
        if len(pts) >= MIN_SFM_POINTS:
            return robust_box(pts, cfg.crop_percentile, cfg.crop_margin), "the SfM points' robust box"
    raise InputError("dense stereo needs to know where the object is: the capture has no bounding box, masks "
                     "or SfM points", capture.root / "capture.json",
                     "add masks, run 'texstream register' (SfM points), or use --dense off")


def _dense_points(capture, cfg: MeshConfig, masks, report: dict,
                  sparse: tuple[np.ndarray, np.ndarray | None] | None, work: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Dense stereo points and normals (geometry/mvs.py), or None (with the reason in the report) when too few.
    Without masks the depth range of each photo and the region it is matched over come from the SfM
    points ``sparse`` (geometry/posed_dense.py)."""
    ranges = regions = None
    scene = False
    if masks is None and sparse is not None and len(sparse[0]) >= MIN_SFM_POINTS:
        pts = sparse[0]
        bounds = robust_box(pts, cfg.crop_percentile, cfg.crop_margin)
        scene = _capture_kind(cfg, pts, np.array([f.center for f in capture.frames]))["kind"] == "scene"
        ranges, range_rep = depth_ranges_from_points(capture.frames, pts, cfg.posed, scene)
        regions = coverage_masks(capture.frames, pts, -1.0 if scene else cfg.posed.grow, cfg.posed.min_points)
        where = (f"the {len(pts)} SfM points "
                 + ("triangulated here with the given cameras" if "triangulation" in report else "of points3D.ply")
                 + f" (per photo: their depths' {cfg.posed.percentile:g}-{100 - cfg.posed.percentile:g} percentiles "
                 f"+ {100 * cfg.posed.margin:g}% of the span each side"
                 + (f", then / and x {cfg.posed.scene_factor:g}: a scene" if scene else "") + ")")
    elif masks is None:
        raise InputError(f"dense stereo without masks needs SfM points to know where the surface is; the capture "
                         f"has {0 if sparse is None else len(sparse[0])} (need {MIN_SFM_POINTS})",
                         capture.root / "capture.json", "add masks, run 'texstream register', or use --dense off")
    else:
        bounds, where = _dense_bounds(capture, cfg, masks)
    n_photos = len(capture.frames)
    with phase("mesh", f"dense stereo of {n_photos} photos "
                       + ("inside their masks" if masks is not None else "without masks, over every pixel (a "
                          "scene)" if scene else "without masks, over the region the SfM points cover")
                       + f", depth range from {where.split(' (')[0]}"):
        dp = capture_dense_points(capture, masks if masks is not None else regions, bounds, cfg.mvs, cfg.device,
                                  ranges, work)
    why = ("on (--dense on)" if cfg.dense == "on" else "auto: the capture has known cameras, pinhole photos and "
           + ("masks" if masks is not None else "SfM points but no masks"))
    rep = {"reason": why, "masks": "the capture's" if masks is not None else "none: matched over every pixel (a "
           "scene)" if scene else f"none: matched over the convex hull of the SfM points' projections, grown "
           f"{100 * cfg.posed.grow:g}%",
           "depth_range_from": where, "bounds": [bounds[0].tolist(), bounds[1].tolist()], **dp.report}
    if ranges is not None:
        for v, r in zip(rep["views"], range_rep):
            v["depth_range_source"] = r["source"]
    report["dense"] = rep
    if len(dp.points) < MIN_DENSE_POINTS or dp.report["mean_fill"] < MIN_DENSE_FILL:
        rep["used"] = False
        rep["fallback"] = (f"too few dense points ({len(dp.points)}, need {MIN_DENSE_POINTS}) or too little of the "
                           f"{'masks' if masks is not None else 'matched regions'} filled "
                           f"({100 * dp.report['mean_fill']:.0f}%, need {100 * MIN_DENSE_FILL:.0f}%): "
                           "too little texture or misaligned cameras; the sparse SfM points instead")
        return None
    rep["used"] = True
    return dp.points, dp.normals


def _sparse_points(capture, cfg: MeshConfig, masks, report: dict, new_points: dict
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """The capture's SfM points (points3D.ply), or points triangulated here with its known cameras (none with
    --triangulate off)."""
    pts_path = capture.root / POINTS_FILE
    if pts_path.is_file():
        return read_points(pts_path)
    if cfg.triangulate == "off":
        return np.zeros((0, 3)), None
    with phase("mesh", f"triangulating SfM points from {len(capture.frames)} photos and their given cameras"
                       + ("" if masks is not None else " (no masks)")):
        tcfg = TriangulateConfig(max_features=cfg.posed.features) if masks is None and _will_dense(cfg, capture) \
            else None
        tp = triangulate_capture(capture, tcfg, masks=masks)
    report["triangulation"] = tp.report
    new_points[POINTS_FILE] = (tp.points, tp.normals)
    return tp.points, tp.normals


def _hull_instead(capture, cfg: MeshConfig, masks, report: dict, n_points: int) -> SurfaceMesh:
    """The visual hull of the masks when the SfM points are too few (a textureless object)."""
    report["source"] = "hull"
    report["reason"] = f"too few SfM points ({n_points}) for Poisson; the capture has masks, so the visual hull"
    return visual_hull(capture.frames, masks, _hull_config(cfg), cfg.device, bounds=_capture_bounds(capture),
                       report=report.setdefault("hull", {}))


def _from_sfm(capture, cfg: MeshConfig, masks, report: dict, work: Path) -> tuple[SurfaceMesh, tuple | None]:
    """Poisson (+ hull) from the capture's SfM or dense points; returns (mesh, {file name: (points, normals)} made
    here). ``work``: dense stereo's work folder (a rerun resumes from its depth maps)."""
    pts_path = capture.root / POINTS_FILE
    new_points: dict = {}  # file name -> (points, normals) made here
    will_dense = _will_dense(cfg, capture)
    # dense stereo with masks takes its depth range from the hull; without, from the sparse points
    sparse = _sparse_points(capture, cfg, masks, report, new_points) if masks is None or not will_dense else None
    dense = _dense_points(capture, cfg, masks, report, sparse, work) if will_dense else None
    if dense is not None:
        pts, nrm = dense
        new_points[DENSE_POINTS_FILE] = dense
    else:
        pts, nrm = sparse if sparse is not None else _sparse_points(capture, cfg, masks, report, new_points)
    if new_points:
        pts_path = capture.root / "capture.json"  # messages name what the points came from
    if dense is None and len(pts) < MIN_SFM_POINTS and masks is not None and cfg.source != "sfm":
        return _hull_instead(capture, cfg, masks, report, len(pts)), new_points
    centres = np.array([f.center for f in capture.frames])
    kind = _capture_kind(cfg, pts, centres)
    report["capture_kind"] = kind
    scene = kind["kind"] == "scene"
    intersect = masks is not None and cfg.intersect_hull and not scene
    # intersected with the hull, Poisson stays closed (no density trim): the hull cuts the invented parts;
    # a scene is cropped and trimmed to its points instead
    pcfg = PoissonConfig(depth=cfg.poisson_depth)
    if intersect or scene:
        pcfg.density_quantile = 0.0
    if scene:
        # Poisson over the points inside their robust box only, in a tight cube: far outliers would stretch
        # the octree (3x the scene's extent halved the resolution of the synthetic scene's surface), and the
        # room the default scale leaves for a closed surface is what makes the balloon
        lo, hi = robust_box(pts, cfg.crop_percentile, cfg.crop_margin)
        keep = np.all((pts >= lo) & (pts <= hi), axis=1)
        report["points_outside_robust_box"] = int((~keep).sum())
        pts, nrm = pts[keep], (nrm[keep] if nrm is not None else None)
        pcfg.scale = 1.1
    if intersect and cfg.hull_fill:
        pts, nrm, report["hull_fill"] = poisson_points_with_hull_fill(
            capture.frames, masks, pts, nrm, _hull_config(cfg), cfg.hull_fill_distance, cfg.hull_fill_angle,
            pcfg.normal_neighbours, cfg.device, _capture_bounds(capture))
    try:
        with phase("mesh", f"screened Poisson of {len(pts)} points (depth {pcfg.depth})"):
            mesh = poisson_reconstruct(pts, nrm, centres, pcfg, pts_path)
    except InputError:
        if masks is None or cfg.source == "sfm":
            raise
        return _hull_instead(capture, cfg, masks, report, len(pts)), new_points
    report["points"] = len(pts) - report.get("hull_fill", {}).get("kept", 0)  # SfM points only
    if scene:
        return _crop_scene(mesh, pts, cfg, pcfg, report), new_points
    if not intersect:
        enclosed = int(cameras_enclosed(mesh, centres).sum())
        if enclosed:
            # the closed Poisson surface balloons round the cameras: the fix is the scene treatment
            report["capture_kind"]["fix"] = (f"the closed Poisson surface enclosed {enclosed} of {len(centres)} "
                                             "cameras: cropped to the points' robust box and trimmed to the points")
            mesh = _crop_scene(mesh, pts, cfg, pcfg, report)
    if masks is not None:
        if intersect:
            lo, hi = mesh.bbox()
            box = _capture_bounds(capture)
            if box is not None:
                # Poisson balloons where there are no points; the grid need not reach far past the object
                grow = 0.1 * float(np.linalg.norm(box[1] - box[0]))
                lo, hi = np.maximum(lo, box[0] - grow), np.minimum(hi, box[1] + grow)
            with phase("mesh", f"visual hull: carving {len(masks)} masks, intersected with the Poisson surface"):
                return visual_hull(capture.frames, masks, _hull_config(cfg), cfg.device, bounds=(lo, hi),
                                   intersect=mesh, report=report.setdefault("hull", {})), new_points
        with phase("mesh", f"trimming the Poisson surface by {len(masks)} masks"):
            mesh = trim_by_masks(mesh, capture.frames, masks, cfg.device)
    return mesh, new_points
