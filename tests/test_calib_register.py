"""Registration with pycolmap: the Middlebury temple ring against its published cameras, bad inputs."""

from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pytest

from conftest import need_data, pose_errors
from texstream.calib.register import RegisterConfig, register
from texstream.capture.capture_json import read_capture
from texstream.core.errors import StageError

pytest.importorskip("pycolmap")
cv2 = pytest.importorskip("cv2")

# The temple's published K (templeSR_par.txt), in the capture convention (cx, cy + 0.5).
TEMPLE_K = {"w": 640, "h": 480, "fl_x": 1520.4, "fl_y": 1525.9, "cx": 302.82, "cy": 247.37}


def _temple_capture(data_dir, tmp_path):
    from texstream.capture.middlebury import import_middlebury

    src = need_data(data_dir, "middlebury_temple_sparse")
    import_middlebury(src, tmp_path / "temple")
    return tmp_path / "temple"


def _check_temple(res, out, cap):
    s = res.summary
    # Done-when: at least 12 of the 16 ring photos register (the 22.5-degree ring is sparse).
    assert len(s["registered"]) >= 12, s
    assert len(s["registered"]) + len(s["unregistered"]) == 16
    got, truth = read_capture(out), read_capture(cap)
    cen, rot = pose_errors(got, truth)
    # Done-when: after Sim3 alignment centres within 2% of the ring diameter, rotations within 2 degrees.
    assert cen.max() < 0.02, cen
    assert rot.max() < 2.0, rot
    assert (out / "sparse" / "0").is_dir() and (out / "points3D.ply").is_file()
    assert all(f.mask_path for f in got.frames)  # the importer's masks travel with the frames
    rep = json.loads((out / "registration_report.json").read_text())
    assert rep["unregistered"] == s["unregistered"]
    return cen, rot


@pytest.mark.data
def test_temple_registration_with_calibrated_intrinsics(data_dir, tmp_path):
    cap = _temple_capture(data_dir, tmp_path)
    (tmp_path / "K.json").write_text(json.dumps(TEMPLE_K))
    t0 = time.time()
    cfg = RegisterConfig(max_num_features=4000, intrinsics=str(tmp_path / "K.json"),
                         align_to=str(cap / "capture.json"), num_threads=2, colocated_light=2.0)
    res = register(cap, tmp_path / "posed", cfg)
    cen, rot = _check_temple(res, tmp_path / "posed", cap)
    got = read_capture(tmp_path / "posed")
    assert got.frames[0].intrinsics.fx == pytest.approx(1520.4)  # fixed intrinsics stay fixed
    for f in got.frames:  # co-located light at each camera centre; photometric gains exported
        np.testing.assert_allclose(f.light.position, f.center, atol=1e-9)
        assert len(f.extra["photometric_gain"]) == 3 and f.exposure == 1.0
    print(f"temple (K fixed): {len(res.summary['registered'])}/16, centre max {cen.max():.4f} of diameter, "
          f"rotation max {rot.max():.3f} deg, {time.time() - t0:.1f} s")


@pytest.mark.slow
@pytest.mark.data
def test_temple_registration_self_calibrating(data_dir, tmp_path):
    """No intrinsics given: COLMAP estimates a SIMPLE_RADIAL camera; photos are undistorted."""
    cap = _temple_capture(data_dir, tmp_path)
    t0 = time.time()
    cfg = RegisterConfig(max_num_features=4000, align_to=str(cap / "capture.json"), num_threads=2)
    res = register(cap, tmp_path / "posed", cfg)
    cen, rot = _check_temple(res, tmp_path / "posed", cap)
    got = read_capture(tmp_path / "posed")
    # Self-calibrated focal length within 2% of the published one (ring geometry constrains it weakly).
    assert abs(got.frames[0].intrinsics.fx - 1520.4) / 1520.4 < 0.02
    assert got.frames[0].intrinsics.camera_model == "PINHOLE"  # undistorted
    print(f"temple (self-calibrated): {len(res.summary['registered'])}/16, centre max {cen.max():.4f}, "
          f"rotation max {rot.max():.3f} deg, {time.time() - t0:.1f} s")


@pytest.mark.data
def test_mixed_sizes_become_two_cameras_and_bad_files_are_dropped(data_dir, tmp_path):
    src = need_data(data_dir, "middlebury_temple_sparse")
    photos = tmp_path / "photos"
    photos.mkdir()
    files = sorted(src.glob("*.png"))
    for i, f in enumerate(files):
        if i % 2:  # every second photo from a "second camera" with 1.25x the resolution
            img = cv2.imread(str(f))
            cv2.imwrite(str(photos / f.name), cv2.resize(img, (800, 600), interpolation=cv2.INTER_CUBIC))
        else:
            shutil.copy(f, photos / f.name)
    (photos / "zz_corrupt.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    k2 = {**TEMPLE_K, "w": 800, "h": 600, "fl_x": 1520.4 * 1.25, "fl_y": 1525.9 * 1.25,
          "cx": 302.82 * 1.25, "cy": 247.37 * 1.25}
    (tmp_path / "K.json").write_text(json.dumps({**TEMPLE_K, "cameras": [TEMPLE_K, k2]}))
    cap = _temple_capture(data_dir, tmp_path)
    res = register(photos, tmp_path / "posed", RegisterConfig(max_num_features=4000, intrinsics=str(tmp_path / "K.json"),
                                                              align_to=str(cap / "capture.json"), num_threads=2))
    s = res.summary
    assert s["dropped"] == [{"image": "zz_corrupt.jpg", "reason": "unreadable or corrupt"}]
    assert len(s["registered"]) >= 12
    got = read_capture(tmp_path / "posed")
    assert {(f.intrinsics.width, f.intrinsics.height) for f in got.frames} == {(640, 480), (800, 600)}
    cen, rot = pose_errors(got, read_capture(cap))
    assert cen.max() < 0.02 and rot.max() < 2.0, (cen, rot)


def test_register_bad_inputs(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    from texstream.core.errors import InputError

    with pytest.raises(InputError, match="no images"):
        register(empty, tmp_path / "o")
    one = tmp_path / "one"
    one.mkdir()
    rng = np.random.default_rng(0)
    cv2.imwrite(str(one / "a.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    with pytest.raises(StageError, match="at least 2 readable photos, got 1") as e:
        register(one, tmp_path / "o")
    assert "\n" not in str(e.value) and not (tmp_path / "o").exists()
    assert json.loads((tmp_path / "o.failed_report.json").read_text())["unregistered"] == ["a.png"]
    # Photos with no overlap (independent noise): no model, a one-line error and a partial report.
    for i in range(3):
        cv2.imwrite(str(one / f"n{i}.png"), cv2.GaussianBlur(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8), (3, 3), 0))
    with pytest.raises(StageError, match="no model") as e:
        register(one, tmp_path / "o", RegisterConfig(max_num_features=500, num_threads=2))
    assert not (tmp_path / "o").exists()
    rep = json.loads((tmp_path / "o.failed_report.json").read_text())
    assert len(rep["unregistered"]) == 4
