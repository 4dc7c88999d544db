"""Ingest: EXIF, orientation, masks, duplicates, bracket merging to linear HDR, bad inputs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest

from texstream.calib.hdr import calibrate_response, group_brackets, merge_brackets_8bit, merge_brackets_linear
from texstream.calib.ingest import IngestConfig, apply_orientation, ingest
from texstream.capture.capture_json import read_capture
from texstream.core.errors import InputError, StageError


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
        _write(src / f"a{i}.png", code, ExposureTime=t, FNumber=4.0,
               **{"Exif:PhotographicSensitivity": 100, "Exif:ExposureMode": 2})
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
    # Rotated photo: stored upright (64x48 -> 48x64), mask rotated with it, focal from the 35 mm equivalent.
    b = fr["b"]
    assert (b.intrinsics.width, b.intrinsics.height) == (48, 64)
    # 36 mm equivalent: the 35 mm frame's diagonal (43.27 mm, CIPA's convention) over the photo's (80 px)
    assert b.intrinsics.fx == pytest.approx(36.0 / np.hypot(36.0, 24.0) * 80.0)
    from texstream.capture.imageio import read_mask

    m = read_mask(cap.mask_path(b))
    assert m.shape[:2] == (64, 48) and m.sum() == 400
    # Exposure normalised from EXIF: b has 4x the ISO of a1 at the same time and aperture.
    assert b.exposure / fr["a1"].exposure == pytest.approx(4.0)
    assert fr["e"].exposure == 1.0 and b.saturation == pytest.approx(1.0, abs=0.01)
    rep = json.loads((tmp_path / "cap" / "ingest_report.json").read_text())
    assert rep["brackets"] == [["a0.png", "a1.png", "a2.png"]]
    dec = rep["bracket_decisions"]
    assert len(dec) == 1 and dec[0]["merged"] and "EXIF auto bracket; photos align" in dec[0]["reason"]
    assert cap.extra["intrinsics_source"] == "exif+guess"


def _textured(h=120, w=160, seed=0):
    """A textured scene radiance (blurred noise over ~1.5 decades)."""
    rng = np.random.default_rng(seed)
    n = cv2.GaussianBlur(rng.uniform(0, 1, (h, w)).astype(np.float32), (0, 0), 2.0)
    n = (n - n.min()) / np.ptp(n)
    return (np.exp(3.5 * n - 2.5)[..., None] * np.array([1.0, 0.85, 0.7])).astype(np.float32)


def test_handheld_auto_exposure_photos_are_not_merged(tmp_path):
    """Handheld photos from different viewpoints (shifted crops) with auto exposure: never merged, each
    stands alone with its EXIF exposure; even with --brackets on, the alignment check refuses them."""
    src = tmp_path / "photos"
    src.mkdir()
    scene = _textured(160, 220)
    for i, (t, dx) in enumerate([(1 / 60, 0), (1 / 30, 14), (1 / 125, 28)]):
        code = np.clip(np.round(_response(scene[20:116, 10 + dx:138 + dx] * t * 30) * 255), 0, 255).astype(np.uint8)
        _write(src / f"h{i}.jpg", code, ExposureTime=t, FNumber=2.8,
               **{"Exif:PhotographicSensitivity": 100, "Exif:ExposureMode": 0})
    res = ingest(src, tmp_path / "cap", IngestConfig(auto_masks="none"))
    s = res.summary
    assert s["frames"] == 3 and s["brackets"] == 0
    (dec,) = s["bracket_decisions"]
    assert not dec["merged"] and "EXIF does not say exposure bracketing" in dec["reason"]
    cap = read_capture(tmp_path / "cap")
    assert [f.name for f in cap.frames] == ["h0", "h1", "h2"]
    assert all(cap.image_path(f).suffix == ".jpg" for f in cap.frames)  # originals, no EXR
    e = {f.name: f.exposure for f in cap.frames}
    assert e["h1"] / e["h0"] == pytest.approx(2.0, rel=0.01) and e["h0"] / e["h2"] == pytest.approx(125 / 60, rel=0.01)
    # The user says they are brackets: the viewpoints still differ, so no ghosted merge.
    s = ingest(src, tmp_path / "cap2", IngestConfig(brackets="on", auto_masks="none")).summary
    (dec,) = s["bracket_decisions"]
    assert s["brackets"] == 0 and s["frames"] == 3 and not dec["merged"]
    assert "do not align" in dec["reason"]


def test_true_bracket_with_exif_is_merged_and_misaligned_bracket_is_not(tmp_path):
    from texstream.calib.hdr import bracket_alignment

    scene = _textured()
    times = [1 / 200, 1 / 50, 1 / 12.5]
    src = tmp_path / "photos"
    src.mkdir()
    for i, t in enumerate(times):
        code = np.clip(np.round(_response(scene * t * 20) * 255), 0, 255).astype(np.uint8)
        _write(src / f"b{i}.jpg", code, ExposureTime=t, **{"Exif:ExposureMode": 2})
    s = ingest(src, tmp_path / "cap", IngestConfig(auto_masks="none")).summary
    assert s["brackets"] == 1 and s["frames"] == 1 and s["bracket_decisions"][0]["merged"]
    # The same bracket with its middle photo shifted by 6 px (a hand moved): refused, reason recorded.
    lin = [np.clip(scene * t * 20, 0, 1) for t in times]
    lin[1] = np.roll(lin[1], 6, axis=1)
    al = bracket_alignment(lin, times, tol_px=2.0)
    assert not al["aligned"] and "do not align" in al["reason"], al
    al = bracket_alignment([np.clip(scene * t * 20, 0, 1) for t in times], times)
    assert al["aligned"] and al["max_shift_px"] < 0.5, al


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
