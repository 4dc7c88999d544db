"""Ingest: EXIF, orientation, masks, duplicates, bracket merging to linear HDR, bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texstream.calib.hdr import calibrate_response, group_brackets, merge_brackets_8bit, merge_brackets_linear
from texstream.calib.ingest import IngestConfig, apply_orientation, ingest
from texstream.capture.capture_json import read_capture
from texstream.core.errors import InputError, StageError

oiio = pytest.importorskip("OpenImageIO")
cv2 = pytest.importorskip("cv2")


def _write(path, codes, **attrs):
    """Write uint8 codes with EXIF attributes (OpenImageIO names)."""
    h, w = codes.shape[:2]
    c = 1 if codes.ndim == 2 else codes.shape[2]
    spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
    for k, v in attrs.items():
        spec.attribute(k, v)
    o = oiio.ImageOutput.create(str(path))
    assert o.open(str(path), spec)
    o.write_image(np.ascontiguousarray(codes))
    o.close()


def _response(e):
    """A known, smooth, monotone camera response (not sRGB): exposure in [0, 1] -> [0, 1]."""
    e = np.clip(e, 0, 1)
    return 0.9 * e ** (1 / 2.2) + 0.1 * e


def _radiance(h=96, w=128):
    yy, xx = np.mgrid[0:h, 0:w]
    # Smooth field over ~2.5 decades so every pixel is well exposed in some bracket.
    lum = np.exp((xx / w) * 5.0 - 3.0 + 0.5 * np.sin(yy / 9.0))
    return (lum[..., None] * np.array([1.0, 0.8, 0.6])).astype(np.float32)


TIMES = [1 / 64, 1 / 16, 1 / 4, 1.0, 4.0]


def test_debevec_merge_recovers_linear_radiance():
    rad = _radiance()
    imgs = [np.clip(np.round(_response(rad * t) * 255), 0, 255).astype(np.uint8) for t in TIMES]
    resp = calibrate_response(imgs, TIMES, "debevec")
    hdr = merge_brackets_8bit(imgs, TIMES, resp, "debevec")
    scale = np.median(rad / hdr)  # the response is recovered up to a global scale
    rel = np.abs(hdr * scale / rad - 1)
    # Done-when: linear radiance to 2%; 95th percentile, since 8-bit quantisation of the darkest
    # bracket samples leaves a few pixels at ~3-4%.
    assert np.percentile(rel, 95) < 0.02 and np.median(rel) < 0.01, (np.median(rel), np.percentile(rel, 95))


def test_linear_merge_ignores_clipped_samples():
    rad = _radiance()
    imgs = [np.clip(rad * t, 0, 1) for t in TIMES]
    hdr = merge_brackets_linear(imgs, TIMES)
    np.testing.assert_allclose(hdr, rad, rtol=1e-5)  # exact data: exact result


def test_group_brackets():
    t = [0.01, 0.04, 0.16, 0.01, 0.04, 0.16, 0.5, 0.5, None]
    sizes = [(4, 3)] * 9
    assert group_brackets(t, sizes) == [[0, 1, 2], [3, 4, 5], [6], [7], [8]]
    assert group_brackets(t[:6], sizes[:6], bracket_size=3) == [[0, 1, 2], [3, 4, 5]]
    assert group_brackets(t, sizes, bracket_size=1) == [[i] for i in range(9)]


def test_orientation_codes():
    a = np.arange(6).reshape(2, 3, 1)
    assert apply_orientation(a, 6).shape == (3, 2, 1)
    # EXIF 6: stored image must be rotated 90 degrees clockwise to display: top-left goes top-right.
    assert apply_orientation(a, 6)[0, -1, 0] == a[0, 0, 0]
    assert apply_orientation(a, 8)[-1, 0, 0] == a[0, 0, 0]
    for o in range(1, 9):
        assert sorted(apply_orientation(a, o).ravel()) == list(range(6))


def test_ingest_folder(tmp_path):
    src = tmp_path / "photos"
    (src / "masks").mkdir(parents=True)
    rad = _radiance(48, 64)
    # A three-exposure bracket of one view (ISO 100, f/4) ...
    for i, t in enumerate([1 / 16, 1 / 4, 1.0]):
        code = np.clip(np.round(_response(rad * t) * 255), 0, 255).astype(np.uint8)
        _write(src / f"a{i}.png", code, ExposureTime=t, FNumber=4.0, **{"Exif:PhotographicSensitivity": 100})
    # ... a single photo at ISO 400 rotated by EXIF, with a mask named like it ...
    code = np.clip(np.round(_response(rad * 0.25) * 255), 0, 255).astype(np.uint8)
    _write(src / "b.png", code, ExposureTime=0.25, FNumber=4.0, Orientation=6,
           **{"Exif:PhotographicSensitivity": 400, "Exif:FocalLengthIn35mmFilm": 36})
    mask = np.zeros((48, 64), np.uint8)
    mask[10:30, 20:40] = 255
    cv2.imwrite(str(src / "masks" / "b.png"), mask)
    # ... a duplicate, a corrupt file and a plain photo without EXIF.
    (src / "c_dup.png").write_bytes((src / "b.png").read_bytes())
    (src / "d_corrupt.jpg").write_bytes(b"\xff\xd8\xff garbage")
    cv2.imwrite(str(src / "e.png"), code)

    res = ingest(src, tmp_path / "cap")
    s = res.summary
    assert s["found"] == 7 and s["frames"] == 3 and s["brackets"] == 1
    reasons = {d["image"]: d["reason"] for d in s["dropped"]}
    assert reasons["c_dup.png"] == "duplicate of b.png" and reasons["d_corrupt.jpg"].startswith("unreadable")
    cap = read_capture(tmp_path / "cap")
    assert cap.extra["posed"] is False
    fr = {f.name: f for f in cap.frames}
    assert set(fr) == {"a1", "b", "e"}
    # Merged bracket: EXR, linear, exposure as the middle photo (1/4 s, ISO 100).
    from texstream.capture.imageio import read_image

    hdr = read_image(cap.image_path(fr["a1"]))
    assert cap.image_path(fr["a1"]).suffix == ".exr" and fr["a1"].saturation is None
    scale = np.median(rad * 0.25 / hdr)
    assert np.percentile(np.abs(hdr * scale / (rad * 0.25) - 1), 95) < 0.03  # 3 brackets only: 3%
    # Rotated photo: stored upright (64x48 -> 48x64), mask rotated with it, focal from 35 mm equivalent.
    b = fr["b"]
    assert (b.intrinsics.width, b.intrinsics.height) == (48, 64)
    assert b.intrinsics.fx == pytest.approx(64.0)  # 36 mm equivalent on a 36 mm frame = longest side
    from texstream.capture.imageio import read_mask

    m = read_mask(cap.mask_path(b))
    assert m.shape[:2] == (64, 48) and m.sum() == 400
    # Exposure normalised from EXIF: b has 4x the ISO of a1 at the same time and aperture.
    assert b.exposure / fr["a1"].exposure == pytest.approx(4.0)
    assert fr["e"].exposure == 1.0 and b.saturation == pytest.approx(1.0, abs=0.01)
    rep = json.loads((tmp_path / "cap" / "ingest_report.json").read_text())
    assert rep["brackets"] == [["a0.png", "a1.png", "a2.png"]]
    assert cap.extra["intrinsics_source"] == "exif+guess"


def test_ingest_bad_inputs(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images"):
        ingest(empty, tmp_path / "o")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "x.jpg").write_bytes(b"nope")
    with pytest.raises(StageError, match="no usable photo") as e:
        ingest(bad, tmp_path / "o")
    assert "\n" not in str(e.value) and not (tmp_path / "o").exists()
    assert json.loads((tmp_path / "o.failed_report.json").read_text())["dropped"][0]["image"] == "x.jpg"
    # Mixed sizes: kept as two cameras by default, dropped with --single-camera.
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for i in range(3):
        cv2.imwrite(str(mixed / f"p{i}.png"), np.full((30, 40, 3), 60 * i, np.uint8))
    cv2.imwrite(str(mixed / "q.png"), np.full((60, 80, 3), 9, np.uint8))
    assert ingest(mixed, tmp_path / "m1").summary["camera_sizes"] == ["40x30", "80x60"]
    s = ingest(mixed, tmp_path / "m2", IngestConfig(single_camera=True)).summary
    assert s["frames"] == 3 and s["dropped"][0]["reason"].startswith("wrong size 80x60")
