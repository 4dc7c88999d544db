"""A capture's photo response applied end to end (issue 39): ``texstream ingest --response auto`` finds the colour
checker in tone-mapped 8-bit photos and records the curve in capture.json; the fit's photo readers (threads and
the decoding pool's worker processes alike) then return linear radiance where sRGB decoding is bent by the tone
curve; a bad response field fails with one line naming capture.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

from texstream.calib.ingest import IngestConfig, ingest
from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import read_image, write_image
from texstream.capture.synthetic.colour_chart import filmic_codes, paste_chart
from texstream.core.errors import InputError
from texstream.core.progress import reporting

WHITE = 4.0
"""the tone curve's white (filmic_codes' default): radiance 4 is code 1"""
H, W = 360, 480
CHART_CORNERS = [[[40, 40], [300, 60], [290, 230], [30, 210]], [[440, 320], [180, 300], [200, 130], [450, 110]],
                 [[60, 300], [60, 120], [330, 110], [340, 310]]]
"""the chart in the first three photos, seen from three sides (the fourth photo shows the wall only)"""
LIGHTS = [1.0, 2.2, 0.6, 1.4]
"""each photo's light: the chart's patches span the codes of the dimmest to past the curve's shoulder"""


PINNED_CODES = (55, 224)
"""the 8-bit codes the chart's patches pin: from radiance 10x the noise (darker patches' means are biased by the
noise through the curve's bend; below code ~40 the curve is off by up to ~10%) to the brightest patch (above it
the curve is extrapolated: 2.5-7% off at codes 235-250)"""


def _codes(k: int, rng, chart: bool) -> np.ndarray:
    """Photo ``k``'s 8-bit codes: a wall whose radiance ramps left to right over the range the tone curve bends
    most (0.03..1.5 x the light), the chart pasted in when ``chart``, the sensor's noise dithering the 8-bit steps,
    through the filmic tone curve."""
    xx = np.mgrid[0:H, 0:W][1]
    light = LIGHTS[k] * np.array([1.0, 0.95, 0.85])
    linear = (0.03 + 1.5 * xx / W)[..., None] * np.array([1.0, 0.9, 0.8]) * light
    if chart:
        linear = paste_chart(linear, np.array(CHART_CORNERS[k], np.float64), light)
    linear = linear + rng.normal(0, 0.004, linear.shape)
    return np.clip(np.round(filmic_codes(linear) * 255), 0, 255).astype(np.uint8)


def true_radiance(codes8: np.ndarray) -> np.ndarray:
    """The radiance each 8-bit code stands for: filmic_codes inverted (sRGB decode, then the Reinhard shoulder
    x (1 + x / w^2) / (1 + x) = t solved for x)."""
    v = codes8.astype(np.float64) / 255.0
    t = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    a = 1.0 / WHITE ** 2
    return (-(1.0 - t) + np.sqrt((1.0 - t) ** 2 + 4.0 * a * t)) / (2.0 * a)


def _write_photos(folder, charts: int) -> list:
    rng = np.random.default_rng(7)
    folder.mkdir()
    codes = []
    for k in range(len(LIGHTS)):
        codes.append(_codes(k, rng, chart=k < charts))
        write_image(folder / f"photo_{k}.png", codes[-1], bits=8)
    return codes


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """(capture folder ingested with --response auto, the photos' codes, what ingest said)."""
    root = tmp_path_factory.mktemp("response")
    codes = _write_photos(root / "photos", charts=3)
    said = []
    with reporting(said.append):
        res = ingest(root / "photos", root / "capture", IngestConfig(response="auto", auto_masks="none"))
    return root / "capture", codes, said, res.summary


def test_ingest_auto_records_the_charts_response(captured):
    cap_dir, _, said, summary = captured
    capture = read_capture(cap_dir)
    assert capture.response is not None and capture.response.kind == "colour_chart"
    report = json.loads((cap_dir / "ingest_report.json").read_text())["response"]
    assert report["used"] == "colour_chart" and report["charts_found"] == [f"photo_{k}.png" for k in range(3)]
    assert summary["response"]["used"] == "colour_chart"
    assert any("photo response: colour chart found in 3 of 4 photos" in line for line in said)
    # the clipped level is where the curve puts the top code, not sRGB's (0.996)
    assert capture.frames[0].saturation == pytest.approx(capture.response.linearise(254.5 / 255))


def test_the_fits_reader_returns_linear_radiance(captured):
    from texstream.fit.common.inputs import load_photos, photo_files

    cap_dir, codes, _, _ = captured
    capture = read_capture(cap_dir)
    files = photo_files(capture, capture.frames)
    errors = {}
    for name, reader in (("response", files.read_image), ("srgb", read_image)):
        ratios = []
        for k, path in enumerate(files.paths):
            pinned = (codes[k] >= PINNED_CODES[0]) & (codes[k] <= PINNED_CODES[1])
            ratios.append(reader(path).astype(np.float64)[pinned] / true_radiance(codes[k][pinned]))
        ratios = np.concatenate(ratios)
        # radiance is known up to one scale (the curve fixes code 1 at 1, the photos' light is unknown)
        errors[name] = np.abs(ratios / np.median(ratios) - 1.0)
    # 2%: the chart's curve is fitted within ~1% at its patches (test_calib_colour_chart.py) and interpolates a
    # smooth curve between them (measured: 1.2% at most over PINNED_CODES)
    assert np.percentile(errors["response"], 99) < 0.02, np.percentile(errors["response"], [50, 99, 100])
    # sRGB decoding ignores the shoulder: radiance 1.5 x the light comes out compressed by a third and more
    assert np.percentile(errors["srgb"], 99) > 0.10, np.percentile(errors["srgb"], [50, 99])
    # the held-out renders' photos (load_photos) go through the same curve
    np.testing.assert_array_equal(load_photos(capture, capture.frames[:1])[0][0], files.read_image(files.paths[0]))


def test_processes_decode_through_the_response_as_threads_do(captured):
    from texstream.fit.common.inputs import photo_files
    from texstream.fit.stream import decode_pool
    from texstream.fit.stream.photo_stream import PhotoLoader

    cap_dir = captured[0]
    capture = read_capture(cap_dir)
    files = photo_files(capture, capture.frames)
    sizes = np.array([[H, W]] * len(files.paths))
    got = []
    try:
        for decoder in ("threads", "processes"):
            loader = PhotoLoader(files, None, None, sizes, 2, decoder=decoder)
            images = np.full((len(files.paths), H, W, 3), 7, np.float32)  # 7: no decoded value, shows a gap
            loader.fill(range(len(files.paths)), images, None)
            assert loader.processes == (2 if decoder == "processes" else 0)  # no fall back to threads
            loader.close()
            got.append(images)
    finally:
        decode_pool.shutdown()
    np.testing.assert_array_equal(got[0], got[1])
    np.testing.assert_array_equal(got[0][1], files.read_image(files.paths[1]))


def test_the_photo_cache_key_names_the_response(captured):
    from texstream.fit.common.inputs import photo_files

    capture = read_capture(captured[0])
    with_response = photo_files(capture, capture.frames, level=1).read_image.cache_key
    capture.extra.pop("response")
    without = photo_files(capture, capture.frames, level=1).read_image.cache_key
    assert without == "level1" and with_response.startswith("response-") and with_response.endswith("level1")


@pytest.mark.parametrize("bad, says", [({"knots": [0.5, 0.2], "log_radiance": [-1, 0]}, "not increasing"),
                                      ({"knots": [0.5, 1.0], "log_radiance": [-1, float("nan")]}, "non-finite"),
                                      ({"knots": [0.0, 1.0], "log_radiance": [-1, 0]}, r"not within \(0, 1\]"),
                                      ({"knots": [0.5, 1.0]}, "lacks 'log_radiance'")])
def test_a_bad_response_field_fails_in_one_line_naming_capture_json(captured, tmp_path, bad, says):
    doc = json.loads((captured[0] / "capture.json").read_text())
    doc["response"] = bad
    (tmp_path / "capture.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=says) as e:
        read_capture(tmp_path)
    line = e.value.one_line()
    assert "capture.json" in line and "\n" not in line and "sRGB" in line


def test_one_chart_falls_back_to_srgb_and_a_file_response_is_used(captured, tmp_path):
    codes = _write_photos(tmp_path / "photos", charts=1)
    said = []
    with reporting(said.append):
        ingest(tmp_path / "photos", tmp_path / "auto", IngestConfig(response="auto", auto_masks="none"))
    assert read_capture(tmp_path / "auto").response is None
    assert any("found in 1 of 4 photos, fewer than 2: photos decoded as sRGB" in line for line in said)
    np.testing.assert_array_equal(read_image(tmp_path / "auto/images/photo_3.png"),
                                  read_image(tmp_path / "photos/photo_3.png"))
    # the response of the first capture, given as a file (texstream chart writes the same fields)
    response = read_capture(captured[0]).response
    (tmp_path / "response.json").write_text(json.dumps(response.to_json()))
    ingest(tmp_path / "photos", tmp_path / "file",
           IngestConfig(response=str(tmp_path / "response.json"), auto_masks="none"))
    capture = read_capture(tmp_path / "file")
    assert capture.response.knots == response.knots and "response.json" in capture.response.source
    np.testing.assert_allclose(read_image(capture.image_path(capture.frames[3]), response=capture.response),
                               response.linearise(codes[3] / 255.0), rtol=1e-6)


def test_run_passes_the_response_to_ingest_and_says_which_was_used(captured):
    import argparse
    import types

    from texstream.pipelines.cmd_run import _config, add_arguments
    from texstream.pipelines.run import _response_input

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert _config(parser.parse_args(["photos", "--response", "auto"])).ingest.response == "auto"
    assert _config(parser.parse_args(["photos"])).ingest.response == "srgb"
    cap_dir, _, _, summary = captured
    ingested = types.SimpleNamespace(records=[types.SimpleNamespace(name="ingest", summary=summary)])
    said = _response_input(ingested, read_capture(cap_dir))
    assert said["source"] == "colour chart" and "found in 3 of 4 photos" in said["why"]
