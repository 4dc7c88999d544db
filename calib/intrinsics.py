"""Camera intrinsics from chessboard / ChArUco photos (``texstream calibrate``).

Detects the board in every photo (sub-pixel corners), calibrates with OpenCV's
``calibrateCamera`` under a chosen distortion model, rejects outlier views by per-view RMS
reprojection error and recalibrates, and writes ``intrinsics.json`` in the capture.json
intrinsics vocabulary (``fl_x fl_y cx cy w h camera_model k1 k2 k3 p1 p2``, pixel centres at +0.5),
which ``texstream register --intrinsics`` and ``texstream ingest --intrinsics`` accept.

Photos of different sizes (two cameras) are calibrated separately, one camera entry per size.
Photos without a board are listed in the report, not fatal; a board never found is a StageError
with a partial report written beside the output.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from texstream.capture.capture_json import Intrinsics
from texstream.capture.conventions import opencv_principal_point_to_capture
from texstream.core.errors import ConfigError, InputError, StageError
from texstream.core.config import option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, read_json, write_json_atomic

from .boards import detect_board, load_gray8, parse_board
from .files import list_images, write_failure_report

INTRINSICS_FILE = "intrinsics.json"
REPORT_FILE = "calibration_report.json"

# model -> (distortion keys estimated, capture camera_model)
DISTORTION_MODELS: dict[str, tuple[tuple[str, ...], str]] = {
    "pinhole": ((), "PINHOLE"),
    "radial1": (("k1",), "OPENCV"),
    "radial2": (("k1", "k2"), "OPENCV"),
    "opencv": (("k1", "k2", "p1", "p2"), "OPENCV"),
    "opencv_k3": (("k1", "k2", "p1", "p2", "k3"), "OPENCV"),
}


@dataclasses.dataclass
class CalibrateConfig:
    """Options of the intrinsics calibration stage."""

    board: str = option("chessboard:9x6:1", help="board spec: chessboard:COLSxROWS[:SQUARE] (inner corners) or "
                        "charuco:COLSxROWS:SQUARE:MARKER[:DICT] (squares)")
    model: str = option("opencv_k3", help="distortion model: pinhole (none), radial1 (k1), radial2 (k1 k2), "
                        "opencv (k1 k2 p1 p2, COLMAP OPENCV), opencv_k3 (+k3, OpenCV's default)",
                        choices=tuple(DISTORTION_MODELS))
    fix_aspect_ratio: bool = option(False, help="estimate one focal length (fx = fy)")
    fix_principal_point: bool = option(False, help="keep the principal point at the image centre")
    reject_factor: float = option(3.0, help="reject views whose RMS exceeds this times the median view RMS",
                                  min=1.0)
    reject_min_px: float = option(1.0, help="never reject a view whose RMS is below this many pixels",
                                  min=0.0)
    reject_outliers: bool = option(True, help="drop views with outlying RMS and recalibrate (off: use every detection)")
    min_views: int = option(3, help="fewest views with a detected board needed to calibrate a camera", min=1)
    min_corners: int = option(6, help="fewest ChArUco corners for a view to count", min=4)


def _flags(cfg: CalibrateConfig) -> int:
    import cv2

    keys = DISTORTION_MODELS[cfg.model][0]
    flags = 0
    if "k1" not in keys:
        flags |= cv2.CALIB_FIX_K1
    if "k2" not in keys:
        flags |= cv2.CALIB_FIX_K2
    if "k3" not in keys:
        flags |= cv2.CALIB_FIX_K3
    if "p1" not in keys:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if cfg.fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    if cfg.fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    return flags


def calibrate_views(obj_pts: list[np.ndarray], img_pts: list[np.ndarray], size: tuple[int, int],
                    cfg: CalibrateConfig) -> dict[str, Any]:
    """OpenCV calibration of one camera with outlier-view rejection.

    Args:
        obj_pts: per view (N_i, 3) float32 board points.
        img_pts: per view (N_i, 2) float32 OpenCV pixel coordinates.
        size: (width, height) in pixels.
        cfg: options.

    Returns:
        dict with ``K`` (3x3, OpenCV pixels), ``dist`` (5,), ``rms`` (px), ``view_rms`` (per input view,
        px, after the final fit), ``used`` (bool per view), ``rvecs``/``tvecs`` of the used views.
    """
    import cv2

    flags = _flags(cfg)
    w, h = size
    k0 = np.array([[max(w, h), 0, w / 2 - 0.5], [0, max(w, h), h / 2 - 0.5], [0, 0, 1]], dtype=np.float64)
    if cfg.fix_aspect_ratio or cfg.fix_principal_point:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if len(obj_pts) < max(cfg.min_views, 1):
        raise StageError(f"only {len(obj_pts)} board view(s) of size {w}x{h}; need {cfg.min_views}",
                         fix="photograph the board in more poses")
    used = np.ones(len(obj_pts), dtype=bool)
    for _ in range(5):  # rejection converges in 1-2 rounds; 5 bounds pathological cycling
        idx = np.flatnonzero(used)
        rms, k, dist, rvecs, tvecs, *_rest = cv2.calibrateCameraExtended(
            [obj_pts[i] for i in idx], [img_pts[i] for i in idx], (w, h), k0.copy(), np.zeros(5),
            flags=flags, criteria=crit)
        # Per-view RMS for every view (also rejected ones, from a PnP pose under the fitted K).
        view_rms = np.zeros(len(obj_pts))
        for j, i in enumerate(idx):
            proj, _ = cv2.projectPoints(obj_pts[i], rvecs[j], tvecs[j], k, dist)
            view_rms[i] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_pts[i]) ** 2, 1))))
        for i in np.flatnonzero(~used):
            ok, rv, tv = cv2.solvePnP(obj_pts[i], img_pts[i], k, dist)
            proj, _ = cv2.projectPoints(obj_pts[i], rv, tv, k, dist)
            view_rms[i] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_pts[i]) ** 2, 1)))) if ok else np.inf
        if not cfg.reject_outliers:
            limit = np.inf
            break
        limit = max(cfg.reject_factor * float(np.median(view_rms[used])), cfg.reject_min_px)
        new_used = view_rms <= limit
        if np.array_equal(new_used, used) or new_used.sum() < cfg.min_views:
            break
        used = new_used
    return {"K": k, "dist": np.asarray(dist).reshape(-1)[:5], "rms": float(rms), "view_rms": view_rms,
            "used": used, "limit": limit, "rvecs": rvecs, "tvecs": tvecs}


def intrinsics_from_opencv(k: np.ndarray, dist: np.ndarray, size: tuple[int, int], model: str) -> Intrinsics:
    """OpenCV K (pixel centres at integers) + distortion -> capture Intrinsics (centres at +0.5)."""
    keys, cam_model = DISTORTION_MODELS[model]
    cx, cy = opencv_principal_point_to_capture(float(k[0, 2]), float(k[1, 2]))
    d = dict(zip(("k1", "k2", "p1", "p2", "k3"), (float(x) for x in np.asarray(dist).reshape(-1)[:5])))
    return Intrinsics(width=int(size[0]), height=int(size[1]), fx=float(k[0, 0]), fy=float(k[1, 1]), cx=cx, cy=cy,
                      camera_model=cam_model, distortion={key: d[key] for key in keys})


def calibrate(photos: str | os.PathLike, out: str | os.PathLike, config: CalibrateConfig | None = None) -> StageResult:
    """Calibrate intrinsics from board photos; write ``out/intrinsics.json`` and a report.

    Args:
        photos: folder of board photos.
        out: output folder (written atomically): ``intrinsics.json``, ``calibration_report.json``,
            ``calibrate_config.json``.
        config: options (defaults: 9x6 chessboard, OpenCV's 5-coefficient model).

    Returns:
        StageResult whose summary has per-camera ``fx, fy, cx, cy, rms`` and the photo counts.

    Raises:
        InputError: missing/empty folder. ConfigError: bad board spec. StageError: board found in too
        few photos (a partial report is written to ``<out>.failed_report.json``).
    """
    cfg = config or CalibrateConfig()
    if cfg.model not in DISTORTION_MODELS:
        raise ConfigError(f"unknown distortion model {cfg.model!r}", fix=f"use one of {list(DISTORTION_MODELS)}")
    board = parse_board(cfg.board)
    files = list_images(photos, what="board photo folder")
    views: list[dict[str, Any]] = []
    for f in files:
        gray = load_gray8(f)
        if gray is None:
            views.append({"image": f.name, "status": "unreadable"})
            continue
        det = detect_board(gray, board, cfg.min_corners)
        v: dict[str, Any] = {"image": f.name, "size": [int(gray.shape[1]), int(gray.shape[0])]}
        if det is None:
            v["status"] = "no board found"
        else:
            v.update(status="found", corners=int(len(det[0])), _img=det[0], _obj=det[1])
        views.append(v)
    report: dict[str, Any] = {"board": str(board), "model": cfg.model, "photos": len(files), "cameras": []}
    by_size: dict[tuple[int, int], list[dict]] = {}
    for v in views:
        if v["status"] == "found":
            by_size.setdefault(tuple(v["size"]), []).append(v)
    cameras = []
    problems = []
    for size, vs in sorted(by_size.items(), key=lambda kv: -len(kv[1])):
        if len(vs) < cfg.min_views:
            problems.append(f"{len(vs)} view(s) at {size[0]}x{size[1]}")
            for v in vs:
                v["used"] = False
                v["rejected"] = f"too few views of this size ({size[0]}x{size[1]})"
            continue
        res = calibrate_views([v["_obj"] for v in vs], [v["_img"] for v in vs], size, cfg)
        for v, r, u in zip(vs, res["view_rms"], res["used"]):
            v["rms"] = float(r)
            v["used"] = bool(u)
            if not u:
                v["rejected"] = f"view RMS {r:.3f} px > {res['limit']:.3f} px"
        intr = intrinsics_from_opencv(res["K"], res["dist"], size, cfg.model)
        cameras.append({**intr.to_json(), "rms": res["rms"], "images": [v["image"] for v, u in zip(vs, res["used"]) if u],
                        "opencv_K": res["K"].tolist(), "opencv_dist": res["dist"].tolist()})
    for v in views:
        v.pop("_img", None)
        v.pop("_obj", None)
    report["views"] = views
    report["cameras"] = [{k: c[k] for k in ("w", "h", "fl_x", "fl_y", "cx", "cy", "rms")} for c in cameras]
    counts = {s: sum(1 for v in views if v["status"] == s) for s in ("found", "no board found", "unreadable")}
    report["counts"] = counts
    if not cameras:
        path = write_failure_report(out, report)
        missing = [v["image"] for v in views if v["status"] != "found"]
        raise StageError(f"board {board} found in {counts['found']} of {len(files)} photos "
                         f"({'; '.join(problems) or 'none usable'}; not found: {', '.join(missing[:5])}"
                         f"{' ...' if len(missing) > 5 else ''}); partial report {path}", photos,
                         "check the --board spec (inner corners for chessboards, squares for ChArUco) and the photos")
    doc = {k: v for k, v in cameras[0].items()}
    doc["cameras"] = cameras
    doc["board"] = str(board)
    with atomic_output_dir(out) as tmp:
        write_json_atomic(tmp / INTRINSICS_FILE, doc)
        write_json_atomic(tmp / REPORT_FILE, report)
        save_config(cfg, tmp / "calibrate_config.json")
    summary = {"cameras": report["cameras"], **counts,
               "rejected": [v["image"] for v in views if "rejected" in v],
               "not_found": [v["image"] for v in views if v["status"] == "no board found"],
               "unreadable": [v["image"] for v in views if v["status"] == "unreadable"]}
    return StageResult(output=Path(out), summary=summary)


def load_intrinsics(path: str | os.PathLike) -> list[Intrinsics]:
    """Read ``intrinsics.json`` (a file, or a calibrate output folder): one Intrinsics per camera."""
    p = Path(path)
    if p.is_dir():
        p = p / INTRINSICS_FILE
    data = read_json(p, what="intrinsics file")
    entries = data.get("cameras") if isinstance(data, dict) and data.get("cameras") else [data]
    out = []
    for i, e in enumerate(entries):
        try:
            out.append(Intrinsics(width=int(e["w"]), height=int(e["h"]), fx=float(e["fl_x"]), fy=float(e["fl_y"]),
                                  cx=float(e["cx"]), cy=float(e["cy"]),
                                  camera_model=str(e.get("camera_model", "PINHOLE")),
                                  distortion={k: float(e[k]) for k in ("k1", "k2", "k3", "k4", "p1", "p2") if k in e}))
        except (KeyError, TypeError, ValueError) as ex:
            raise InputError(f"camera {i} lacks or has a bad intrinsics field ({ex!r})", p,
                             "write fl_x, fl_y, cx, cy, w, h (texstream calibrate makes this file)") from None
    return out


def intrinsics_for_size(cams: list[Intrinsics], width: int, height: int, source: str | os.PathLike) -> Intrinsics:
    """The calibrated camera matching an image size; InputError naming both sizes otherwise."""
    for c in cams:
        if (c.width, c.height) == (width, height):
            return c
    have = ", ".join(f"{c.width}x{c.height}" for c in cams)
    raise InputError(f"no calibrated camera for {width}x{height} images (calibrated: {have})", source,
                     "calibrate with photos of the same size as the capture, or omit --intrinsics")
