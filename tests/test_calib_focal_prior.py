"""The EXIF focal prior cross-checked (calib/sensors.py) and registration recovering from a wrong one
(calib/register.py), on JPEGs written as a raw converter exports them (capture/synthetic/exif.py)."""

from __future__ import annotations

import json

import pytest

from texstream.calib.sensors import focal_prior, sensor_width_mm
from texstream.capture.synthetic.exif import CameraBody, exif_for

BODY = CameraBody()  # Canon EOS 5D Mark III: 36 mm, 5760 x 3840 px


def _exif(size, *, stale=True, focal_mm=24.0, drop=(), focal_35mm=None, body=BODY):
    """ingest's EXIF fields for a photo of ``size`` with ``body``'s tags (``drop``: tags left out)."""
    tags = exif_for(body, focal_mm, size, stale=stale, focal_35mm=focal_35mm)
    names = {"Make": "make", "Model": "model", "Exif:FocalLength": "focal_mm", "Exif:FocalLengthIn35mmFilm": "focal_35mm",
             "Exif:FocalPlaneXResolution": "focal_plane_xres", "Exif:FocalPlaneResolutionUnit": "focal_plane_unit",
             "Exif:PixelXDimension": "pixel_x", "Exif:PixelYDimension": "pixel_y"}
    return {names[k]: v for k, v in tags.items() if k in names and k not in drop}


def test_sensor_table_finds_bodies_as_exif_names_them():
    assert sensor_width_mm("Canon", "Canon EOS 5D Mark III") == 36.0
    assert sensor_width_mm("NIKON CORPORATION", "NIKON D850") == 35.9
    assert sensor_width_mm("SONY", "ILCE-7RM4") == 35.7
    assert sensor_width_mm("FUJIFILM", "X-T3") == 23.5
    assert sensor_width_mm("DJI", "FC6310") == 13.2
    assert sensor_width_mm("texstream", "synthetic pinhole camera") is None
    assert sensor_width_mm(None, "X-T3") is None


def test_stale_focal_plane_tags_are_scaled_to_the_exported_size():
    # the case: 24 mm on a full-frame body, exported 1086 px wide: true 724 px, naive 3840 px (5.3x)
    p = focal_prior(_exif((1086, 724)), 1086, 724)
    truth = BODY.focal_px(24.0, 1086)
    assert p["checked"] and set(p["used"]) == {"focal_plane", "sensor_table"}
    assert p["focal_px"] == pytest.approx(truth, rel=1e-6)
    # portrait: the longer side is the sensor's width
    assert focal_prior(_exif((1086, 724)), 724, 1086)["focal_px"] == pytest.approx(truth, rel=1e-6)


def test_disagreeing_sources_outvoted_or_prior_dropped():
    truth = BODY.focal_px(24.0, 1086)
    # PixelXDimension rewritten to the export's size but the focal-plane resolution left stale: 5.3x too long;
    # the sensor table and the 35 mm tag outvote it
    e = _exif((1086, 724), focal_35mm=24)
    e.update(pixel_x=1086, pixel_y=724)
    p = focal_prior(e, 1086, 724)
    assert p["used"] == ["sensor_table", "35mm"] and p["focal_px"] == pytest.approx(truth, rel=0.01)
    assert "focal_plane disagrees" in p["decision"]
    # two sources that disagree and nothing to tell which is right: no prior
    e.pop("focal_35mm")
    p = focal_prior(e, 1086, 724)
    assert p["focal_px"] is None and "disagree" in p["decision"]
    # a cropped export (another aspect than PixelXDimension): the focal-plane tags are not scaled blindly
    p = focal_prior(_exif((1086, 724), drop=("Make",)), 1000, 724)
    assert p["focal_px"] is None and "cropped" in p["notes"]["focal_plane"]


def test_35mm_equivalent_on_the_diagonal_or_the_width():
    # 4:3 photo (a phone): CIPA's diagonal convention; 24 mm equivalent on a 4032 x 3024 photo
    p = focal_prior({"focal_35mm": 24.0}, 4032, 3024)
    assert p["focal_px"] == pytest.approx(24.0 / 43.2666 * 5040.0, rel=1e-3)
    # a square synthetic photo whose writer used the width: the convention agreeing with the focal plane wins
    e = {"focal_mm": 36.0, "focal_plane_xres": 256 / 36.0, "focal_plane_unit": 4, "focal_35mm": 36.0}
    p = focal_prior(e, 256, 256)
    assert p["checked"] and p["focal_px"] == pytest.approx(256.0, rel=1e-6)


def test_ingest_reports_the_focal_decision(tmp_path):
    import numpy as np

    from texstream.calib.ingest import ingest
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.exif import write_jpeg

    rng = np.random.default_rng(0)
    for i in range(2):
        write_jpeg(tmp_path / "photos" / f"p{i}.jpg", rng.random((64, 96, 3)), exif_for(BODY, 24.0, (96, 64), stale=True))
    res = ingest(tmp_path / "photos", tmp_path / "cap")
    cap = read_capture(tmp_path / "cap")
    assert cap.frames[0].intrinsics.fx == pytest.approx(BODY.focal_px(24.0, 96), rel=1e-6)
    report = json.loads((tmp_path / "cap" / "ingest_report.json").read_text())
    (d,) = report["focal_prior"]
    assert d["images"] == ["p0.jpg", "p1.jpg"] and "scaled" in d["decision"]
    assert res.summary["focal_prior"] == [d["decision"]]


@pytest.mark.slow  # 26-44 s on the shared 2-core dev box: render, ingest and two mappings of 24 photos
def test_registration_recovers_from_a_prior_six_times_too_long(tmp_path):
    """24 JPEGs (480 x 320) of the textured sphere whose EXIF says the full sensor's focal-plane resolution
    (6x the exported pixels per mm) with the tags that would expose it (PixelXDimension, Make, Model) left
    out: ingest cannot catch it, the mapping with it registers 3 of 24 photos, the one without a prior all."""
    from texstream.calib.ingest import ingest
    from texstream.calib.register import RegisterConfig, register
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.exif_capture import write_exif_capture

    body = CameraBody(sensor_px=(2880, 1920))
    made = write_exif_capture(tmp_path / "photos", size=(480, 320), photos=24, body=body, cameras={"distance": 4.0},
                              drop_tags=("Exif:PixelXDimension", "Exif:PixelYDimension", "Make", "Model"))
    assert made["naive_focal_px"] / made["focal_px"] == pytest.approx(6.0)
    ingest(made["photos"], tmp_path / "cap")
    assert read_capture(tmp_path / "cap").frames[0].intrinsics.fx == pytest.approx(made["naive_focal_px"])
    cfg = RegisterConfig(num_threads=2, photometric="off", max_num_features=2000)
    res = register(tmp_path / "cap", tmp_path / "reg", cfg)
    assert len(res.summary["registered"]) == 24
    fx = read_capture(tmp_path / "reg").frames[0].intrinsics.fx
    # 2%: the bar; the renderer's exact pinhole comes back within 0.3% (SfM's scale-free focal
    # length on 0.23 px reprojection error)
    assert fx == pytest.approx(made["focal_px"], rel=0.02)
    report = json.loads((tmp_path / "reg" / "registration_report.json").read_text())
    assert report["focal_prior"]["retried"] and report["focal_prior"]["kept"] == "no_prior"
    assert "without the EXIF prior" in read_capture(tmp_path / "reg").extra["focal_prior_registration"]


def test_a_mapping_without_a_model_is_reported_not_crashed_on(tmp_path):
    """A mapping that registered nothing has no reprojection error (calib/focal_check.py): the report says None
    and "no model" and is written (JSON has no infinity: a failed registration's report once crashed on it,
    hiding the real error)."""
    import numpy as np

    from texstream.calib.focal_check import _error_or_none, _model_quality, _quality_text
    from texstream.core.outputs import read_json, write_json_atomic

    none = _model_quality({})
    assert none[0] == 0 and not np.isfinite(none[1])
    assert _error_or_none(none) is None and _quality_text(none) == "no model"
    assert _error_or_none((12, -0.75)) == 0.75 and _quality_text((12, -0.75)) == "12 photos, 0.750 px"
    write_json_atomic(tmp_path / "r.json", {"with_prior": {"registered": 0, "reprojection_error": _error_or_none(none)}})
    assert read_json(tmp_path / "r.json")["with_prior"]["reprojection_error"] is None
