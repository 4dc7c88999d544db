"""The EXIF focal prior's value taken from the finer of the agreeing tags (calib/sensors.py); registration then
holds it where the photos cannot tell a better one (tests/test_calib_register_synth.py, issue 39)."""

from __future__ import annotations

import pytest

from texstream.calib.sensors import focal_prior


def test_the_value_comes_from_the_focal_plane_tags_the_35mm_tag_only_checks_them():
    # the flash capture's camera: 428.9 px from FocalLength x FocalPlaneXResolution; the 35 mm tag, whole
    # millimetres (39), says 433.3 px: it agrees (within 5%) and so cross-checks the focal plane's value, whose
    # rational tags are far finer; the median of the two was 0.5% long
    e = {"focal_mm": 38.60112, "focal_plane_xres": 400 / 36.0, "focal_plane_unit": 4, "focal_35mm": 39.0}
    p = focal_prior(e, 400, 400)
    assert p["checked"] and p["used"] == ["focal_plane", "35mm"]
    assert p["focal_px"] == pytest.approx(428.9, abs=0.01)
    assert "from focal_plane, checked by 35mm" in p["decision"]
    # the 35 mm tag alone still gives the prior, unchecked (on the diagonal: a square photo's is 1.41 x its side)
    p = focal_prior({"focal_35mm": 39.0}, 400, 400)
    assert not p["checked"] and p["focal_px"] == pytest.approx(39.0 / 43.2666 * 400 * 2 ** 0.5, rel=1e-3)
