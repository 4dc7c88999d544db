"""Photometric gains from repeated observations, and the co-located light."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texstream.calib.lights import colocated_light, load_lights_file
from texstream.calib.photometric import estimate_gains
from texstream.capture.conventions import look_at_w2c
from texstream.core.errors import InputError


def test_gains_recovered_despite_outliers():
    rng = np.random.default_rng(1)
    n_img, n_pts = 12, 400
    true = np.exp(rng.normal(0, 0.3, (n_img, 3)))
    true /= np.median(true, axis=0)
    rad = np.exp(rng.normal(-1, 1, (n_pts, 3)))
    ii, pp = [], []
    for p in range(n_pts):
        seen = rng.choice(n_img, size=rng.integers(2, 6), replace=False)
        ii += list(seen)
        pp += [p] * len(seen)
    ii, pp = np.array(ii), np.array(pp)
    vals = true[ii] * rad[pp] * np.exp(rng.normal(0, 0.02, (len(ii), 3)))  # 2% noise
    spec = rng.random(len(ii)) < 0.1  # 10% speculars / mismatches, 2-10x too bright
    vals[spec] *= rng.uniform(2, 10, (spec.sum(), 1))
    gains, used = estimate_gains(ii, pp, vals, n_img)
    # Median-normalised like the truth; 1.5%: noise/sqrt(obs per photo) plus the median's bias under outliers.
    np.testing.assert_allclose(gains, true, rtol=0.015)
    assert used.min() > 0


def test_colocated_light_and_lights_file(tmp_path):
    r, t = look_at_w2c([0, -2, 1], [0, 0, 0])
    light = colocated_light(r, t, 5.0)
    np.testing.assert_allclose(light.position, [0, -2, 1], atol=1e-12)
    flash = colocated_light(r, t, [1, 2, 3], offset=[0.1, 0, 0])  # 10 cm to the camera's right
    np.testing.assert_allclose(flash.position - [0, -2, 1], r[0] * 0.1, atol=1e-12)
    (tmp_path / "l.json").write_text(json.dumps({"default": {"type": "directional", "direction": [0, 0, -1],
                                                             "intensity": [1, 1, 1]},
                                                 "frames": {"a": {"type": "point", "position": [0, 0, 1],
                                                                  "intensity": [2, 2, 2]}}}))
    default, frames = load_lights_file(tmp_path / "l.json")
    assert default.type == "directional" and frames["a"].type == "point"
    (tmp_path / "bad.json").write_text(json.dumps({"lights": []}))
    with pytest.raises(InputError, match="'default' light"):
        load_lights_file(tmp_path / "bad.json")
