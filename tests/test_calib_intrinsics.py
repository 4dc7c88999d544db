"""Intrinsics calibration: the real OpenCV chessboard set and synthetic ChArUco renders."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import need_data
from texstream.calib.boards import parse_board
from texstream.calib.intrinsics import CalibrateConfig, calibrate, intrinsics_for_size, load_intrinsics
from texstream.core.config import load_config
from texstream.core.errors import ConfigError, InputError, StageError


def _plain_opencv(folder):
    """Reference: OpenCV's sample calibration (calibration.cpp / camera_calibration tutorial) on the same photos."""
    board = parse_board("chessboard:9x6")
    obj, img = [], []
    for f in sorted(folder.glob("*.jpg")):
        g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(g, (9, 6))
        assert ok, f
        c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3))
        obj.append(board.object_points())
        img.append(c)
    rms, k, dist, _, _ = cv2.calibrateCamera(obj, img, (640, 480), None, None)
    return rms, k


@pytest.mark.data
def test_chessboard_matches_opencv(data_dir, tmp_path):
    photos = need_data(data_dir, "opencv_chessboard")
    ref_rms, ref_k = _plain_opencv(photos)
    # Same views, same 5-coefficient model as plain calibrateCamera: no outlier rejection.
    cfg = CalibrateConfig(board="chessboard:9x6", reject_outliers=False)
    res = calibrate(photos, tmp_path / "cal", cfg)
    cam = res.summary["cameras"][0]
    assert res.summary["found"] == 13 and not res.summary["not_found"]
    # Done-when: RMS within 0.1 px of OpenCV's own result on the same corners.
    assert abs(cam["rms"] - ref_rms) < 0.1, (cam["rms"], ref_rms)
    # fx near 536 px (OpenCV's sample result); 1% allows corner refinement differences.
    assert abs(cam["fl_x"] - 536.0) < 5.4 and abs(cam["fl_x"] - ref_k[0, 0]) < 2.0
    # Principal point: capture convention is OpenCV's + 0.5 px.
    assert abs(cam["cx"] - (ref_k[0, 2] + 0.5)) < 2.0
    intr = load_intrinsics(tmp_path / "cal")
    assert intr[0].width == 640 and intr[0].camera_model == "OPENCV" and "k3" in intr[0].distortion
    assert load_config(CalibrateConfig, tmp_path / "cal" / "calibrate_config.json") == cfg  # what made it

    # Default: outlier rejection drops left02 (its view RMS ~1.2 px vs a ~0.2 px median) and lowers RMS.
    res2 = calibrate(photos, tmp_path / "cal2", CalibrateConfig(board="chessboard:9x6"))
    assert res2.summary["rejected"] == ["left02.jpg"]
    assert res2.summary["cameras"][0]["rms"] < cam["rms"]
    rep = json.loads((tmp_path / "cal2" / "calibration_report.json").read_text())
    assert len(rep["views"]) == 13


def _render_charuco_set(folder, k, dist, size, n_views=10, seed=0):
    from texstream.calib.board_render import camera_rays, render_board_view

    spec = parse_board("charuco:8x6:0.04:0.03:DICT_5X5_100")
    board_img = spec.charuco_board().generateImage((8 * 50, 6 * 50), marginSize=0)
    rays = camera_rays(k, dist, size, supersample=2)
    rng = np.random.default_rng(seed)
    folder.mkdir()
    for i in range(n_views):
        # Tilts up to ~35 degrees about both axes decorrelate focal length, distance and distortion.
        rv = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)])
        r = cv2.Rodrigues(rv)[0]
        tv = np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.02, 0.02), rng.uniform(0.42, 0.55)]) - r @ [0.16, 0.12, 0]
        cv2.imwrite(str(folder / f"view{i:02d}.png"), render_board_view(board_img, (0.32, 0.24), rays, rv, tv))
    return str(spec)


def _distortion_field(k, dist, size):
    """Pixel displacement of the distortion over a grid covering the image, (N, 2)."""
    w, h = size
    g = np.stack(np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 7)), -1).reshape(-1, 2)
    xn = (g - k[:2, 2]) / np.diag(k)[:2]
    p3 = np.concatenate([xn, np.ones((len(xn), 1))], 1)
    proj, _ = cv2.projectPoints(p3, np.zeros(3), np.zeros(3), k, np.asarray(dist, float))
    return proj.reshape(-1, 2) - g


def test_charuco_synthetic_recovers_intrinsics(tmp_path):
    k = np.array([[700.0, 0, 330.0], [0, 705.0, 235.0], [0, 0, 1]])
    dist = np.array([-0.12, 0.05, 0.001, -0.0005])
    size = (640, 480)
    spec = _render_charuco_set(tmp_path / "board", k, dist, size)
    res = calibrate(tmp_path / "board", tmp_path / "cal", CalibrateConfig(board=spec, model="opencv"))
    cam = res.summary["cameras"][0]
    assert res.summary["found"] == 10
    # Done-when: fx, fy, cx, cy within 0.5% (capture cx = OpenCV cx + 0.5).
    for got, want in ((cam["fl_x"], 700.0), (cam["fl_y"], 705.0), (cam["cx"], 330.5), (cam["cy"], 235.5)):
        assert abs(got - want) / want < 0.005, (got, want)
    # Distortion: k1 and k2 trade off against each other, so compare the displacement field they
    # produce; 0.3 px over the whole frame is about the corner detector's noise on 8-bit renders.
    doc = json.loads((tmp_path / "cal" / "intrinsics.json").read_text())
    k_est = np.array(doc["opencv_K"])
    d_est = np.array(doc["opencv_dist"])[:4]
    err = np.abs(_distortion_field(k, dist, size) - _distortion_field(k_est, d_est, size)).max()
    assert err < 0.3, err


def test_calibrate_bad_inputs(tmp_path, data_dir):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images"):
        calibrate(empty, tmp_path / "o1")
    with pytest.raises(ConfigError, match="board spec"):
        calibrate(empty, tmp_path / "o1", CalibrateConfig(board="chess:9"))
    # A board that is never found: one-line StageError, partial report beside the output, no output.
    blank = tmp_path / "blank"
    blank.mkdir()
    for i in range(3):
        cv2.imwrite(str(blank / f"b{i}.png"), np.full((60, 80), 128, np.uint8))
    (blank / "corrupt.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(StageError, match="found in 0 of 4") as e:
        calibrate(blank, tmp_path / "o2")
    assert "\n" not in str(e.value)
    assert not (tmp_path / "o2").exists()
    rep = json.loads((tmp_path / "o2.failed_report.json").read_text())
    assert {v["status"] for v in rep["views"]} == {"no board found", "unreadable"}
    with pytest.raises(InputError, match="no calibrated camera for 800x600"):
        from texstream.capture.capture_json import Intrinsics

        intrinsics_for_size([Intrinsics(640, 480, 500, 500, 320, 240)], 800, 600, "x.json")
