"""Metashape and RealityCapture camera imports, round-tripped through synthetic exports with known cameras.

The synthetic sphere is rendered through two sensors with Brown distortion (capture/synthetic/camera_exports.py),
written as a Metashape project (calibration at 4x the photos' resolution, a chunk transform with scale 2.5, one
disabled and one unaligned camera, JPEGs with the full sensor's stale EXIF) and as RealityCapture XMPs; the
imports must give back the true cameras. Tolerances: the exports write numbers with repr (17 significant
digits), so what comes back differs from the truth only by double rounding through a few 4x4 products:
1e-9 (relative, or radians / pixels) is a million times that and a thousand times below anything that matters.
"""

from __future__ import annotations

import dataclasses
import math
import shutil

import numpy as np
import pytest

from texstream.calib.metashape import MetashapeImportConfig, import_metashape, read_metashape  # noqa: E402
from texstream.calib.posed_import import LensCamera, undistort_photo  # noqa: E402
from texstream.calib.realitycapture import RealityCaptureImportConfig, import_realitycapture  # noqa: E402
from texstream.capture.capture_json import read_capture  # noqa: E402
from texstream.capture.imageio import read_image, read_mask, write_image  # noqa: E402
from texstream.capture.synthetic.camera_exports import (render_export_set, write_metashape,  # noqa: E402
                                                        write_realitycapture)
from texstream.core.errors import InputError  # noqa: E402
from texstream.pipelines import cli  # noqa: E402
from texstream.pipelines.cmd_import import transform_mesh_file  # noqa: E402

PHOTOS, W, H = 8, 128, 96
QUIET = {"log": lambda *_: None}


@pytest.fixture(scope="module")
def ms_set():
    return render_export_set("sphere", PHOTOS, W, H)


@pytest.fixture(scope="module")
def rc_set():
    return render_export_set("sphere", PHOTOS, W, H, skew_free=True)


@pytest.fixture(scope="module")
def ms_export(ms_set, tmp_path_factory):
    root = tmp_path_factory.mktemp("ms")
    info = write_metashape(ms_set, root)
    return root, info


def _rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.acos(min(1.0, max(-1.0, (np.trace(a.T @ b) - 1) / 2)))


def _check_cameras(cap, es, skipped: set[int], keep_distortion: bool) -> None:
    """Every imported frame against its true camera; the skipped ones absent."""
    labels = [f.extra["label"] for f in cap.frames]
    assert labels == [lab for i, lab in enumerate(es.labels) if i not in skipped]
    for f in cap.frames:
        i = es.labels.index(f.extra["label"])
        truth, lens = es.frames[i], es.lenses[i]
        assert _rotation_angle(f.R, truth.R) < 1e-9
        assert np.linalg.norm(f.center - truth.center) < 1e-9 * np.linalg.norm(truth.center)
        k = f.intrinsics
        assert (k.width, k.height) == (lens.width, lens.height)
        for got, want in ((k.fx, lens.fx), (k.fy, lens.fy), (k.cx, lens.cx), (k.cy, lens.cy)):
            assert abs(got - want) < 1e-9 * lens.fx
        if keep_distortion:
            d = k.distortion
            for name in ("k1", "k2", "k3", "p1", "p2"):
                assert abs(d[name] - getattr(lens, name)) < 1e-12, name
        else:
            assert k.is_pinhole


@pytest.mark.parametrize("components", [False, True], ids=["chunk", "component"])
def test_metashape_round_trip(ms_set, tmp_path, components):
    """Poses (chunk or chunk + component transform, scale 2.5), per-sensor intrinsics scaled from the 4x
    calibration resolution, OpenCV distortion with Metashape's P1/P2 swapped; skipped cameras said."""
    info = write_metashape(ms_set, tmp_path / "ms", components=components)
    lines = []
    res = import_metashape(tmp_path / "ms" / "cameras.xml", tmp_path / "ms" / "photos", tmp_path / "cap",
                           MetashapeImportConfig(undistort=False), log=lines.append)
    assert res.summary["disabled"] == 1 and res.summary["unaligned"] == 1
    assert res.summary["chunk_scale"] == pytest.approx(2.5, rel=1e-12)
    assert len(res.summary["sensors"]) == 2 and all(s["scale"] == 0.25 for s in res.summary["sensors"].values())
    assert any("IMG_0002 skipped (disabled)" in ln for ln in lines)
    assert any("IMG_0003 skipped (not aligned)" in ln for ln in lines)
    cap = read_capture(tmp_path / "cap")
    _check_cameras(cap, ms_set, set(info["disabled"]) | set(info["unaligned"]), keep_distortion=True)
    # photos copied byte for byte when not resampled
    f0 = cap.frames[0]
    assert (tmp_path / "cap" / f0.file_path).read_bytes() == (tmp_path / "ms" / "photos" / "IMG_0001.JPG").read_bytes()


def test_metashape_undistorted_photos_are_the_pinhole_views(ms_set, ms_export, tmp_path):
    """The default import resamples the distorted JPEGs through Metashape's model onto the pinhole cameras:
    they must match the pinhole renders."""
    root, info = ms_export
    import_metashape(root / "cameras.xml", root / "photos", tmp_path / "cap", **QUIET)
    cap = read_capture(tmp_path / "cap")
    _check_cameras(cap, ms_set, set(info["disabled"]) | set(info["unaligned"]), keep_distortion=False)
    masked = 0
    for f in cap.frames:
        i = ms_set.labels.index(f.extra["label"])
        want = ms_set.pinhole[i]
        seen = np.ones((H, W), bool)
        if f.mask_path is not None:  # the pincushion sensor's corners see past the photo (see the mask test)
            seen = read_mask(cap.mask_path(f), (H, W))
            masked += 1
        err = np.abs(read_image(cap.image_path(f))[seen] - want[seen]).mean()
        raw = np.abs(read_image(root / "photos" / f"{f.extra['label']}.JPG")[seen] - want[seen]).mean()
        # JPEG (quality 95) and two bicubic resamplings leave about 0.3 8-bit codes on average (0.0012 measured);
        # the photo as taken, its distortion not undone (1-3 pixels at the corners), is off by half as much again
        # along the sphere's silhouette (0.0018 measured)
        assert err < 0.002 and err < 0.8 * raw, (f.file_path, err, raw)
        assert f.saturation == 1.0
    assert masked == sum(ms_set.sensor_of[ms_set.labels.index(f.extra["label"])] == 1 for f in cap.frames)
    assert cap.extra["mask_kind"] == "valid_pixels"  # these masks are no silhouettes (test below)


def test_undistort_photo_without_distortion_is_the_identity(tmp_path):
    """Pixel centres: capture pixels have them at +0.5, cv2.remap at integers; a half-pixel slip would shift a
    textured photo visibly. Through a lens without distortion every 8-bit code must come back unchanged
    (bicubic weights at whole-pixel offsets are 1 and 0), and no pixel is masked."""
    rng = np.random.default_rng(0)
    codes = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    write_image(tmp_path / "noise.png", codes, bits=8)
    lens = LensCamera(W, H, fx=110.0, fy=110.0, cx=W * 0.53, cy=H * 0.46)
    assert undistort_photo(tmp_path / "noise.png", tmp_path / "out.png", lens) is None
    assert np.array_equal(read_image(tmp_path / "out.png", channels=3), read_image(tmp_path / "noise.png"))


def test_undistort_photo_masks_the_rays_leaving_the_photo(tmp_path):
    """A pincushion lens (k1 > 0) spreads the photo's edge beyond the same-focal pinhole frame: the pinhole
    pixels whose source lies outside the photo's outermost pixel centres have no value. They are black and out
    of the mask; every other pixel is kept. A barrel lens (k1 < 0) maps the whole frame inside: no mask."""
    write_image(tmp_path / "grey.png", np.full((H, W, 3), 0.5, np.float32), bits=8)
    lens = LensCamera(W, H, fx=120.0, fy=120.0, cx=W / 2, cy=H / 2, k1=0.25)
    seen = undistort_photo(tmp_path / "grey.png", tmp_path / "out.png", lens)
    v, u = np.mgrid[0:H, 0:W] + 0.5
    xd, yd = lens.distort((u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy)
    su, sv = lens.fx * xd + lens.cx, lens.fy * yd + lens.cy
    want = (su >= 0.5) & (su <= W - 0.5) & (sv >= 0.5) & (sv <= H - 0.5)
    assert 0 < (~want).sum() < 0.2 * want.size and np.array_equal(seen, want)
    out = read_image(tmp_path / "out.png", channels=3)
    assert np.all(out[~want] == 0)
    # a flat photo stays flat up to the edge (the taps beyond the edge repeat it): no black bled in
    assert np.abs(out[want] - out[H // 2, W // 2]).max() < 1e-6
    barrel = dataclasses.replace(lens, k1=-0.3)
    assert undistort_photo(tmp_path / "grey.png", tmp_path / "out2.png", barrel) is None


def _metashape_formula(cal: dict, w: int, h: int, pts: np.ndarray) -> np.ndarray:
    """The manual's frame camera projection (Metashape manual, appendix "Camera models"), written out."""
    x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    r2 = x * x + y * y
    radial = 1 + cal["k1"] * r2 + cal["k2"] * r2 ** 2 + cal["k3"] * r2 ** 3 + cal["k4"] * r2 ** 4
    xp = x * radial + cal["p1"] * (r2 + 2 * x * x) + 2 * cal["p2"] * x * y
    yp = y * radial + cal["p2"] * (r2 + 2 * y * y) + 2 * cal["p1"] * x * y
    u = w * 0.5 + cal["cx"] + xp * cal["f"] + xp * cal["b1"] + yp * cal["b2"]
    v = h * 0.5 + cal["cy"] + yp * cal["f"]
    return np.stack([u, v], 1)


def test_metashape_distortion_convention_against_the_manual(ms_export, tmp_path):
    """Points projected by OpenCV through the imported camera land where Metashape's own formula puts them."""
    import cv2
    import xml.etree.ElementTree as ET

    root, _ = ms_export
    import_metashape(root / "cameras.xml", root / "photos", tmp_path / "cap", MetashapeImportConfig(undistort=False),
                     **QUIET)
    frame = read_capture(tmp_path / "cap").frames[0]  # IMG_0001: sensor 0 (affinity b1, both P terms)
    sensor = ET.parse(root / "cameras.xml").getroot().find("chunk/sensors/sensor[@id='0']")
    cal_el = sensor.find("calibration")
    cal = {t: float(cal_el.find(t).text) for t in ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2")}
    cw, ch = int(cal_el.find("resolution").get("width")), int(cal_el.find("resolution").get("height"))
    assert cal["b1"] != 0 and cal["p1"] != 0 and cal["p2"] != 0 and cal["p1"] != cal["p2"]
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.4, 0.4, (50, 2)), np.ones(50)])  # camera frame, within the view
    want = _metashape_formula(cal, cw, ch, pts) * (W / cw)  # calibration pixels -> photo pixels (same ratio in y)
    k = frame.intrinsics
    kmat = np.array([[k.fx, 0, k.cx - 0.5], [0, k.fy, k.cy - 0.5], [0, 0, 1.0]])  # OpenCV: centres at integers
    dist = np.array([k.distortion[n] for n in ("k1", "k2", "p1", "p2", "k3")])
    got, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), kmat, dist)
    assert np.abs(got.reshape(-1, 2) + 0.5 - want).max() < 1e-9 * k.fx
    # with P1 and P2 taken as OpenCV's p1 and p2, the same points miss by a visible amount
    swapped = dist[[0, 1, 3, 2, 4]]
    wrong, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), kmat, swapped)
    assert np.abs(wrong.reshape(-1, 2) + 0.5 - want).max() > 1e-3


def test_metashape_lens_keeps_k4_and_skew_only_when_resampling():
    """k4 (r^8) and a B2 skew have no place in capture.json's OpenCV distortion: refused there, exact in the
    resampling model."""
    lens = LensCamera(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0, k4=0.01)
    with pytest.raises(InputError, match="k4"):
        lens.opencv_intrinsics("camera X")
    assert lens.pinhole().is_pinhole
    x = np.array([0.3])
    xd, _ = lens.distort(x, np.zeros(1))
    assert xd[0] == pytest.approx(0.3 * (1 + 0.01 * 0.09 ** 4), rel=1e-15)


def test_metashape_mesh_taken_into_the_world_frame(ms_set, ms_export, tmp_path):
    """The mesh Metashape exported in chunk coordinates lands on the true mesh; capture.json names it and the
    run takes it as its mesh."""
    from texstream.geometry.mesh_io import load_mesh
    from texstream.pipelines.run import RunConfig, _capture_mesh

    root, _ = ms_export
    res = import_metashape(root / "cameras.xml", root / "photos", tmp_path / "cap",
                           MetashapeImportConfig(mesh=str(root / "mesh_chunk.obj")), mesh_writer=transform_mesh_file,
                           **QUIET)
    assert res.summary["mesh"] == "mesh.obj"
    got = load_mesh(tmp_path / "cap" / "mesh.obj")
    # OBJ reading re-welds the vertices (another order): each vertex against the nearest true one; the OBJ
    # writes about 9 significant digits, so 1e-6 of the unit sphere is far above rounding and far below error
    from scipy.spatial import cKDTree

    assert cKDTree(ms_set.mesh.vertices).query(got.vertices)[0].max() < 1e-6
    assert cKDTree(got.vertices).query(ms_set.mesh.vertices)[0].max() < 1e-6
    cap = read_capture(tmp_path / "cap")
    cfg = _capture_mesh(RunConfig(), cap, True, tmp_path / "cap", lambda *_: None)
    assert cfg.mesh_file == str(tmp_path / "cap" / "mesh.obj")
    # the run says where its cameras and mesh came from
    from texstream.pipelines.provenance import run_inputs

    used = run_inputs([], "capture", cap, cfg.mesh_file)
    assert used["cameras"]["source"] == "imported (metashape)" and "cameras.xml" in used["cameras"]["why"]
    assert used["mesh"]["source"] == "imported with the cameras" and "chunk frame" in used["mesh"]["why"]


def test_metashape_photos_by_label_case_insensitive(ms_set, tmp_path):
    write_metashape(ms_set, tmp_path / "ms")
    (tmp_path / "ms" / "photos" / "IMG_0001.JPG").rename(tmp_path / "ms" / "photos" / "img_0001.jpeg")
    res = import_metashape(tmp_path / "ms" / "cameras.xml", tmp_path / "ms" / "photos", tmp_path / "cap", **QUIET)
    assert res.summary["cameras"] == PHOTOS - 2


def test_metashape_bad_inputs_one_line_errors(ms_set, tmp_path):
    """A missing photo, a malformed XML, a photo of another aspect ratio: one line naming the file and the fix."""
    from texstream.capture.imageio import write_image

    write_metashape(ms_set, tmp_path / "ms")
    xml, photos = tmp_path / "ms" / "cameras.xml", tmp_path / "ms" / "photos"
    shutil.copytree(photos, tmp_path / "few")
    (tmp_path / "few" / "IMG_0004.JPG").unlink()
    with pytest.raises(InputError, match="no photo for camera 'IMG_0004'") as e:
        import_metashape(xml, tmp_path / "few", tmp_path / "out", **QUIET)
    assert "Fix:" in str(e.value) and "\n" not in str(e.value)
    bad = tmp_path / "bad.xml"
    bad.write_text(xml.read_text()[:500])
    with pytest.raises(InputError, match="not a readable XML"):
        import_metashape(bad, photos, tmp_path / "out", **QUIET)
    shutil.copytree(photos, tmp_path / "square")
    (tmp_path / "square" / "IMG_0004.JPG").unlink()
    write_image(tmp_path / "square" / "IMG_0004.png", np.zeros((W, W, 3), np.float32), bits=8)
    with pytest.raises(InputError, match="another aspect ratio"):
        import_metashape(xml, tmp_path / "square", tmp_path / "out", **QUIET)
    assert not (tmp_path / "out").exists()


def test_realitycapture_round_trip(rc_set, tmp_path):
    """XMP poses (world-to-camera rotation, centre), 35 mm focal and relative principal point on the larger
    side, Brown3 with tangential terms (t1 = OpenCV p2); the XMP without a pose skipped."""
    info = write_realitycapture(rc_set, tmp_path / "rc")
    res = import_realitycapture(tmp_path / "rc" / "xmp", tmp_path / "rc" / "photos", tmp_path / "cap",
                                RealityCaptureImportConfig(undistort=False), **QUIET)
    assert res.summary["without_pose"] == 1
    _check_cameras(read_capture(tmp_path / "cap"), rc_set, set(info["unposed"]), keep_distortion=True)
    res = import_realitycapture(tmp_path / "rc" / "xmp", tmp_path / "rc" / "photos", tmp_path / "cap2", **QUIET)
    cap = read_capture(tmp_path / "cap2")
    _check_cameras(cap, rc_set, set(info["unposed"]), keep_distortion=False)
    f = cap.frames[0]
    err = np.abs(read_image(cap.image_path(f))[8:-8, 8:-8] - rc_set.pinhole[0][8:-8, 8:-8]).mean()
    raw = np.abs(read_image(tmp_path / "rc" / "photos" / "IMG_0001.jpg")[8:-8, 8:-8] - rc_set.pinhole[0][8:-8, 8:-8])
    assert err < 0.002 and err < 0.8 * raw.mean()  # as for Metashape


def test_realitycapture_bad_inputs(rc_set, tmp_path):
    write_realitycapture(rc_set, tmp_path / "rc")
    csv = tmp_path / "cams.csv"
    csv.write_text("#name,x,y,alt,heading,pitch,roll,f,px,py,k1,k2,k3,k4,t1,t2\n")
    with pytest.raises(InputError, match="CSV camera export is not supported"):
        import_realitycapture(csv, tmp_path / "rc" / "photos", tmp_path / "out", **QUIET)
    xmp = tmp_path / "rc" / "xmp" / "IMG_0001.xmp"
    xmp.write_text(xmp.read_text().replace('xcr:Skew="0"', 'xcr:Skew="0.01"'))
    with pytest.raises(InputError, match="Skew"):
        import_realitycapture(tmp_path / "rc" / "xmp", tmp_path / "rc" / "photos", tmp_path / "out", **QUIET)


def test_cli_import_metashape_needs_photos(ms_export, tmp_path, capsys):
    root, _ = ms_export
    assert cli.main(["import", "metashape", str(root / "cameras.xml"), "-o", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "needs the photo folder" in err and len(err.strip().splitlines()) == 1
    assert cli.main(["import", "metashape", str(root / "cameras.xml"), str(root / "photos"), "-o",
                     str(tmp_path / "o"), "--mesh", str(root / "mesh_chunk.obj")]) == 0
    assert read_capture(tmp_path / "o").extra["mesh"] == "mesh.obj"


def test_read_metashape_reports_sensors(ms_export):
    chunk = read_metashape(ms_export[0] / "cameras.xml")
    assert len(chunk.sensors) == 2 and all(s.calibration_class == "adjusted" for s in chunk.sensors.values())
    assert sum(c.transform is None for c in chunk.cameras) == 1 and sum(not c.enabled for c in chunk.cameras) == 1


def test_masks_of_the_pixels_with_data_are_no_silhouettes(tmp_path):
    """An import's undistortion masks mark the pixels that have data, not the object: the mesh stage must not
    carve a visual hull from them, triangulation must not call a point outside one background, and the run
    must not call them the object's masks."""
    from texstream.capture.capture_json import VALID_PIXELS, Capture, Frame, Intrinsics, masks_are_silhouettes
    from texstream.geometry.make_mesh import MeshConfig, choose_source
    from texstream.pipelines.provenance import run_inputs

    intr = Intrinsics(W, H, 100.0, 100.0, W / 2, H / 2)
    frames = [Frame(file_path=f"images/{i}.png", R=np.eye(3), t=np.array([0.0, 0.0, 3.0 + i]), intrinsics=intr,
                    mask_path=f"masks/{i}.png") for i in range(3)]
    silhouettes = Capture(root=tmp_path, frames=frames, extra={})
    data_only = Capture(root=tmp_path, frames=frames, extra={"mask_kind": VALID_PIXELS})
    assert masks_are_silhouettes(silhouettes) and not masks_are_silhouettes(data_only)
    no_points = MeshConfig(triangulate="off", dense="off")
    assert choose_source(no_points, silhouettes)[0] == "hull"
    with pytest.raises(InputError, match="neither SfM points nor masks"):
        choose_source(no_points, data_only)
    assert run_inputs([], "capture", data_only)["masks"]["source"] == "pixels with data only"
