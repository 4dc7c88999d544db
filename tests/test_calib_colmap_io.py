"""COLMAP / nerfstudio import and camera-model conversion."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pycolmap
import pytest

from texstream.calib.colmap_io import (camera_to_intrinsics, import_colmap, import_nerfstudio,
                                       intrinsics_to_colmap)
from texstream.capture.capture_json import read_capture
from texstream.capture.conventions import w2c_cv_to_c2w_gl
from texstream.core.errors import InputError


def _colmap_project(root):
    """A two-image COLMAP text model (hand-written, as COLMAP documents the format)."""
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").mkdir()
    (root / "sparse" / "0" / "cameras.txt").write_text("1 OPENCV 64 48 60 61 32.5 24.5 0.01 -0.002 0.001 0.0005\n")
    # Image 2: rotation of 45 degrees about y (qw = cos 22.5, qy = sin 22.5).
    (root / "sparse" / "0" / "images.txt").write_text(
        "1 1 0 0 0 0.1 0.2 3 1 a.png\n\n2 0.92387953 0 0.38268343 0 0 0 3 1 b.png\n\n")
    (root / "sparse" / "0" / "points3D.txt").write_text("")
    for n in ("a.png", "b.png"):
        cv2.imwrite(str(root / "images" / n), np.full((48, 64, 3), 100, np.uint8))


def test_import_colmap_text_model(tmp_path):
    _colmap_project(tmp_path / "proj")
    res = import_colmap(tmp_path / "proj", tmp_path / "cap")
    assert res.summary["images"] == 2 and res.summary["missing_images"] == []
    cap = read_capture(tmp_path / "cap")
    a, b = cap.frames
    # COLMAP's cam_from_world is texstream's (R, t) as is (OpenCV axes, same pixel convention).
    np.testing.assert_allclose(a.R, np.eye(3), atol=1e-7)
    np.testing.assert_allclose(a.t, [0.1, 0.2, 3.0])
    c = np.cos(np.pi / 4)
    np.testing.assert_allclose(b.R, [[c, 0, c], [0, 1, 0], [-c, 0, c]], atol=1e-6)
    assert a.intrinsics.camera_model == "OPENCV" and a.intrinsics.cx == 32.5
    assert a.intrinsics.distortion == {"k1": 0.01, "k2": -0.002, "p1": 0.001, "p2": 0.0005}
    # the photos and the model travel with the capture: b.png's pixels, the model's two images
    assert np.array_equal(cv2.imread(str(tmp_path / "cap" / "images" / "b.png")), np.full((48, 64, 3), 100, np.uint8))
    model = pycolmap.Reconstruction(str(tmp_path / "cap" / "sparse" / "0"))
    assert sorted(im.name for im in model.images.values()) == ["a.png", "b.png"]
    # An image missing from the folder is reported, not fatal.
    (tmp_path / "proj" / "images" / "b.png").unlink()
    res = import_colmap(tmp_path / "proj", tmp_path / "cap2")
    assert res.summary["missing_images"] == ["b.png"]
    with pytest.raises(InputError, match="no COLMAP sparse model"):
        import_colmap(tmp_path / "proj" / "images", tmp_path / "cap3")


def test_import_nerfstudio(tmp_path):
    ns = tmp_path / "ns"
    (ns / "images").mkdir(parents=True)
    cv2.imwrite(str(ns / "images" / "frame_00001.png"), np.zeros((48, 64, 3), np.uint8))
    r = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])
    doc = {"camera_model": "OPENCV", "fl_x": 50, "fl_y": 50, "cx": 32, "cy": 24, "w": 64, "h": 48,
           "k1": 0.1, "k2": 0, "p1": 0, "p2": 0, "applied_scale": 1.0,
           "frames": [{"file_path": "images/frame_00001.png", "transform_matrix": w2c_cv_to_c2w_gl(r, [0, 0, 2]).tolist()},
                      {"file_path": "images/frame_00002.png", "transform_matrix": np.eye(4).tolist()}]}
    (ns / "transforms.json").write_text(json.dumps(doc))
    res = import_nerfstudio(ns, tmp_path / "cap")
    assert res.summary == {"images": 1, "missing_images": ["images/frame_00002.png"]}
    cap = read_capture(tmp_path / "cap")
    np.testing.assert_allclose(cap.frames[0].R, r, atol=1e-12)
    assert cap.frames[0].intrinsics.distortion["k1"] == 0.1 and cap.extra["applied_scale"] == 1.0
    with pytest.raises(InputError, match="no transforms.json"):
        import_nerfstudio(tmp_path, tmp_path / "cap2")


@pytest.mark.parametrize("model,params", [
    ("SIMPLE_PINHOLE", [100, 32, 24]), ("PINHOLE", [100, 101, 32, 24]), ("SIMPLE_RADIAL", [100, 32, 24, 0.1]),
    ("RADIAL", [100, 32, 24, 0.1, -0.01]), ("OPENCV", [100, 101, 32, 24, 0.1, -0.01, 0.001, 0.002]),
    ("FULL_OPENCV", [100, 101, 32, 24, 0.1, -0.01, 0.001, 0.002, 0.003, 0, 0, 0]),
    ("OPENCV_FISHEYE", [100, 101, 32, 24, 0.1, -0.01, 0.001, 0.002])])
def test_camera_model_round_trip(model, params):
    """COLMAP camera -> capture intrinsics -> COLMAP camera projects identically (same distortion)."""
    intr = camera_to_intrinsics(model, np.array(params, float), 64, 48)
    m2, p2 = intrinsics_to_colmap(intr)
    c1 = pycolmap.Camera(model=model, width=64, height=48, params=params)
    c2 = pycolmap.Camera(model=m2, width=64, height=48, params=p2)
    pts = np.array([[0.1, -0.2, 1.0], [0.3, 0.25, 1.0], [-0.3, 0.1, 1.0]])
    np.testing.assert_allclose(c1.img_from_cam(pts), c2.img_from_cam(pts), atol=1e-9)
