"""The EXIF focal length held where the photos cannot tell a better one, refined where they can (issue 39;
calib/register_selfcal.py hold_focal_prior), and its value taken from the finer EXIF tags (calib/sensors.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texstream.calib.sensors import focal_prior


def test_the_value_comes_from_the_focal_plane_tags_the_35mm_tag_only_checks_them():
    # the flash capture's camera: 428.9 px from FocalLength x FocalPlaneXResolution; the 35 mm tag, whole
    # millimetres (39), says 433.3 px: it agrees (within 5%) and so cross-checks the focal plane's value, whose
    # rational tags are 100x finer; the median of the two was 0.5% long
    e = {"focal_mm": 38.60112, "focal_plane_xres": 400 / 36.0, "focal_plane_unit": 4, "focal_35mm": 39.0}
    p = focal_prior(e, 400, 400)
    assert p["checked"] and p["used"] == ["focal_plane", "35mm"]
    assert p["focal_px"] == pytest.approx(428.9, abs=0.01)
    assert "from focal_plane, checked by 35mm" in p["decision"]
    # the 35 mm tag alone still gives the prior, unchecked
    p = focal_prior({"focal_35mm": 39.0}, 400, 400)
    assert not p["checked"] and p["focal_px"] == pytest.approx(39.0 / 43.2666 * 400 * 2 ** 0.5, rel=1e-3)


@pytest.fixture(scope="module")
def ingested_sphere(tmp_path_factory):
    """The textured sphere's 24 photos (256 px, two rings) as a camera leaves them (EXIF focal tags only),
    ingested as ``texstream run PHOTOS`` does; and the true capture."""
    from texstream.calib.ingest import ingest
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.photos_only import write_photos_only
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("focal_hold")
    synthesize("textured_sphere", root / "truth", SynthConfig(progress=False, preview=False))
    src = write_photos_only(root / "truth", root / "photos")[0].parent
    ingest(src, root / "capture")
    return root, read_capture(root / "truth")


def _register_with_prior(root, scale: float, name: str):
    """Register the ingested photos with their EXIF prior multiplied by ``scale`` (a stale or wrong tag)."""
    import shutil

    from texstream.calib.register import RegisterConfig, register
    from texstream.capture.capture_json import read_capture

    cap = root / f"capture_{name}"
    shutil.copytree(root / "capture", cap)
    data = json.loads((cap / "capture.json").read_text())
    data["fl_x"] *= scale
    data["fl_y"] *= scale
    (cap / "capture.json").write_text(json.dumps(data))
    res = register(cap, root / f"posed_{name}", RegisterConfig(max_num_features=2000, num_threads=1,
                                                               photometric="off"))
    return res.summary, read_capture(root / f"posed_{name}")


def test_a_right_prior_is_held_and_a_wrong_one_refined(ingested_sphere):
    """A right EXIF focal length is held: refining it lowers the reprojection error by far less than 1% (the
    tracks of one object at one distance barely tell the focal length from the distance). One 6% off (a stale
    tag) costs more than 1% when held, so the photos free it and bundle adjustment brings it back."""
    root, truth = ingested_sphere
    fx_true = truth.frames[0].intrinsics.fx
    summary, got = _register_with_prior(root, 1.0, "right")
    hold = summary["focal_hold"]
    print(f"right prior: {hold['reason']}; free {hold['free_focal_px']} px, true {fx_true:.2f} px")
    assert hold["held"] and hold["gain"] < 0.01
    assert got.frames[0].intrinsics.fx == pytest.approx(fx_true, rel=1e-4)  # the focal plane's value, exact
    assert "focal_length" not in got.extra["intrinsics_refined"]
    assert len(got.frames) == 24

    summary, got = _register_with_prior(root, 1.06, "wrong")
    hold = summary["focal_hold"]
    fx = got.frames[0].intrinsics.fx
    print(f"prior 6% long: {hold['reason']}; focal {fx / fx_true - 1:+.4f}")
    assert not hold["held"] and hold["gain"] >= 0.01
    assert "focal_length" in got.extra["intrinsics_refined"]
    # measured below; 2%: a third of the prior's error, what an unobservable focal length would not recover
    assert abs(fx / fx_true - 1) < 0.02, (fx, fx_true)
    assert np.isfinite(summary["mean_reprojection_error"])
