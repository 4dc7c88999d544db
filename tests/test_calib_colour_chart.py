"""A ColorChecker in tone-mapped photos (calib/colour_chart.py, issue 39): found in every photo that shows it,
in its patch order whichever way up; the camera's response recovered from the patches so that linearised patch
values are within 1% of the truth; photos without the chart are told apart."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.calib.colour_chart import chart_reflectance, find_chart, fit_response
from texstream.capture.synthetic.colour_chart import filmic_codes, paste_chart
from texstream.core.errors import InputError

LIGHTS = [np.array([0.9, 0.8, 0.7]), np.array([1.6, 1.5, 1.2]), np.array([0.5, 0.55, 0.6]),
          np.array([2.4, 2.2, 2.0])]
"""each photo's light times white balance at the chart (flash distance, exposure): patches from black at the
dimmest to past the tone curve's shoulder at the brightest"""
CORNERS = [[[300, 200], [780, 240], [760, 560], [290, 520]], [[620, 420], [240, 400], [260, 150], [640, 120]]]
"""two views of the chart, the second upside down"""


def _photo(k: int, rng) -> np.ndarray:
    """An 8-bit tone-mapped photo (as codes in [0, 1]) of a grey wall with the chart on it, with the sensor's noise
    (which, as in real photos, dithers the 8-bit steps: a patch's mean over its ~2,000 pixels is finer than one)."""
    linear = paste_chart(np.full((720, 1080, 3), 0.18) * LIGHTS[k], np.array(CORNERS[k % 2], np.float64), LIGHTS[k])
    linear = linear + rng.normal(0, 0.004, linear.shape)
    return np.round(filmic_codes(linear) * 255.0) / 255.0


@pytest.fixture(scope="module")
def sightings():
    rng = np.random.default_rng(1)
    return [find_chart(_photo(k, rng)) for k in range(len(LIGHTS))]


def test_the_chart_is_found_in_every_photo_in_patch_order(sightings):
    truth = filmic_codes(chart_reflectance() * LIGHTS[0])
    assert all(s is not None for s in sightings)
    upside_down = filmic_codes(chart_reflectance() * LIGHTS[1])
    for s, t in ((sightings[0], truth), (sightings[1], upside_down)):
        # patch means of noisy 8-bit codes: typically within half a code of the tone-mapped truth; the darkest
        # patches' means sit higher by up to a few codes (noise clipped at 0, and the curve's bend there)
        err = np.abs(s.patches - t) * 255
        assert np.median(err) < 0.5 and err.max() < 4.0


def test_linearised_patches_are_within_one_percent_of_the_truth(sightings):
    response = fit_response(sightings)
    refl = chart_reflectance()
    errors = []
    for k, s in enumerate(sightings):
        ok = (s.patches > 0.03) & (s.patches < 0.97)  # the response's usable codes (black and clipped left out)
        # radiance is known up to one scale for all photos, which each photo's fitted gain carries
        errors.append(np.abs(response.linearise(s.patches) / response.gains[k] / refl - 1.0)[ok])
    errors = np.concatenate(errors)
    # the bound: 1%; 8-bit codes on the darkest usable patches quantise to ~0.6% of their value
    assert np.percentile(errors, 95) < 0.01, np.percentile(errors, [50, 95, 100])
    assert response.residual_percent < 1.0
    # the gains carry the lights' ratios (one scale common to all: g(1) = 1 fixes it)
    ratio = response.gains / np.array(LIGHTS)
    assert np.abs(ratio / ratio.mean() - 1.0).max() < 0.01


def test_a_photo_without_the_chart_is_told_apart():
    rng = np.random.default_rng(2)
    wall = np.round(filmic_codes(np.full((480, 640, 3), 0.3) + rng.normal(0, 0.01, (480, 640, 3))) * 255) / 255
    assert find_chart(wall) is None
    with pytest.raises(InputError, match="no photo shows a colour chart"):
        fit_response([])


def test_texstream_chart_writes_the_response_of_a_folder(tmp_path, capsys):
    from texstream.capture.imageio import write_image
    from texstream.pipelines.cli import main

    rng = np.random.default_rng(3)
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(2):
        write_image(photos / f"p{k}.png", np.round(_photo(k, rng) * 255).astype(np.uint8), bits=8)
    wall = np.round(filmic_codes(np.full((200, 300, 3), 0.2)) * 255).astype(np.uint8)
    write_image(photos / "wall.png", wall, bits=8)
    assert main(["chart", str(photos), "-o", str(tmp_path / "out")]) == 0
    assert "chart found in 2 of 3 photos" in capsys.readouterr().out
    import json

    report = json.loads((tmp_path / "out" / "chart_report.json").read_text())
    assert [r["found"] for r in report["per_photo"]] == [True, True, False]
    response = json.loads((tmp_path / "out" / "response.json").read_text())
    assert len(response["gains"]) == 2 and response["residual_percent"] < 1.0
