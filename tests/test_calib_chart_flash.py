"""A ColorChecker beside a flash-lit object (issue 39): the flash's intensity in absolute units from the chart's
pose and patches (calib/chart_flash.py), and the chart kept out of the masks the mesh and the fit read
(calib/chart_masks.py), on photos of the synthetic flash capture's chart (capture/synthetic/flash_capture.py)
through its tone curve, with its true cameras."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.calib.chart_flash import chart_flash_applies, flash_from_chart
from texstream.calib.chart_masks import chart_pixels, chart_quad_mask
from texstream.calib.colour_chart import find_chart
from texstream.capture.capture_json import Frame, Intrinsics, Light
from texstream.capture.synthetic.colour_chart import filmic_codes
from texstream.capture.synthetic.flash_capture import (CHART_CENTRE, TONE_WHITE, _chart_light, _project,
                                                       chart_corners_world, develop_codes, true_response)
from texstream.capture.synthetic.synth import camera_poses
from texstream.capture.synthetic.colour_chart import paste_chart

FLASH, ROOM = 40.0, 0.3
SIZE = 400


def _frames(count: int = 8) -> list[Frame]:
    """The flash capture's first ring, on the chart's side (cameras that see it square enough to read)."""
    cams = {"layout": "ring", "count": 2 * count, "rings": [28.0], "distance": 5.5, "target": [0.0, -1.0, -0.55]}
    fx = (SIZE / 2) / np.tan(np.radians(25.0))
    intr = Intrinsics(width=SIZE, height=SIZE, fx=fx, fy=fx, cx=SIZE / 2, cy=SIZE / 2)
    frames = []
    for i, (r, t) in enumerate(camera_poses(cams, 2 * count)):
        c = -r.T @ t
        if c[1] < -1.0:  # the chart's side of the sphere
            frames.append(Frame(file_path=f"images/f{i:02d}.png", R=r, t=t, intrinsics=intr,
                                light=Light.point(c, [FLASH] * 3), exposure=1.0 / TONE_WHITE))
    return frames


def _chart_photo(frame: Frame, seed: int) -> np.ndarray:
    """The chart alone on black, as the flash capture draws it, as stored codes in [0, 1]."""
    uv, _ = _project(frame, chart_corners_world())
    linear = paste_chart(np.zeros((SIZE, SIZE, 3)), uv - 0.5,
                         _chart_light(frame, np.full(3, FLASH), np.full(3, ROOM), (SIZE, SIZE)))
    return develop_codes(linear, np.random.default_rng(seed), 0.002) / 255.0


@pytest.fixture(scope="module")
def sightings():
    frames = _frames()
    found = {f.name: find_chart(_chart_photo(f, k)) for k, f in enumerate(frames)}
    return frames, {n: s for n, s in found.items() if s is not None}


def test_the_true_response_inverts_the_tone_curve():
    lin = np.geomspace(0.005, 3.5, 200)
    codes = filmic_codes(lin, TONE_WHITE)
    # 128 knots: the curve linear in log code between them is within 0.1% of the exact inverse (the fit's reference
    # must not add an error of its own to the 1% the issue allows the chart's curve)
    assert np.abs(true_response().linearise(codes) * TONE_WHITE / lin - 1.0).max() < 1e-3


def test_the_flash_intensity_comes_out_absolute(sightings):
    frames, found = sightings
    assert len(found) >= 0.75 * len(frames)  # the chart read in most photos that see it square enough
    res = flash_from_chart(frames, found, true_response())
    # the world units per patch pitch: the chart's long side over its 6.43 pitches (450 / 70 in its layout)
    assert res.scale == pytest.approx(1.9 * 70 / 450, rel=0.01)
    assert np.linalg.norm(res.centre - np.asarray(CHART_CENTRE)) < 0.03
    # the bound on albedos is 2%; 8-bit codes of patches a dozen pixels wide and the PnP depth leave ~1%
    assert np.abs(res.intensity / FLASH - 1.0).max() < 0.02, res.intensity
    assert res.room_fitted and np.abs(res.room_irradiance - ROOM).max() < 0.1 * ROOM + 0.02


def test_too_few_sightings_are_a_clear_error(sightings):
    from texstream.core.errors import InputError

    frames, found = sightings
    one = dict(list(found.items())[:1])
    with pytest.raises(InputError, match="needs 2 or more"):
        flash_from_chart(frames, one, true_response())


def test_chart_masks_clear_the_chart_and_keep_the_object_whole():
    corners = np.array([[40.0, 100.0], [140.0, 100.0], [140.0, 160.0], [40.0, 160.0]])
    chart = chart_quad_mask(corners, (200, 300))
    assert chart[130, 90] and chart[97, 35] and not chart[130, 200]  # grown by 15% about its centre (y 95.5-164.5)
    yy, xx = np.mgrid[0:200, 0:300]
    sphere = (yy - 100) ** 2 + (xx - 210) ** 2 < 60 ** 2
    # the object apart from the chart: the chart's part of the mask goes, the object's stays
    mask = sphere | ((yy > 105) & (yy < 155) & (xx > 45) & (xx < 135))
    clear = chart_pixels(mask, chart)
    assert not (mask & ~clear)[130, 90] and (mask & ~clear)[sphere].all()
    # the object in front of the chart, one part with it: kept whole (a silhouette is never cut into)
    overlap = (yy - 130) ** 2 + (xx - 130) ** 2 < 50 ** 2
    clear = chart_pixels(overlap | mask, chart)
    assert not clear[overlap].any()
    # no object mask: the quad itself
    assert np.array_equal(chart_pixels(np.ones((200, 300), bool), chart), chart)


def test_ingest_keeps_the_chart_out_of_the_masks_and_records_it(tmp_path, sightings):
    from texstream.calib.ingest import IngestConfig, ingest
    from texstream.capture.capture_json import read_capture
    from texstream.capture.imageio import read_mask, write_image

    frames, found = sightings
    photos = tmp_path / "photos"
    for k, f in enumerate(frames[:3]):
        write_image(photos / f"{f.name}.png", np.round(_chart_photo(f, k) * 255).astype(np.uint8), bits=8)
    res = ingest(photos, tmp_path / "cap", IngestConfig(response="auto", colocated_light=1.0, auto_masks="none"))
    cap = read_capture(tmp_path / "cap")
    assert "3 photo(s)" in res.summary["chart_masks"] and sorted(cap.extra["colour_chart"]) == [f.name for f in frames[:3]]
    assert cap.extra["mask_kind"] == "valid_pixels"  # every mask made here: none is a silhouette
    for f in cap.frames:
        box = np.asarray(cap.extra["colour_chart"][f.name]["corners"]).mean(axis=0).round().astype(int)
        mask = read_mask(cap.mask_path(f))
        assert not mask[box[1], box[0]] and mask[5, 5]
    # the chart's response and sightings are there: a registered copy of this capture gets its flash from the chart
    assert chart_flash_applies(cap)


def test_the_lights_stage_gives_every_frame_the_flash_from_the_chart(tmp_path, sightings):
    from texstream.calib.chart_flash import flash_lit_capture
    from texstream.capture.capture_json import Capture, read_capture, write_capture

    frames, found = sightings
    posed = tmp_path / "posed"
    guess = [Frame(file_path=f.file_path, R=f.R, t=f.t, intrinsics=f.intrinsics, exposure=f.exposure,
                   light=Light.point(f.center, [1.0] * 3)) for f in frames]
    extra = {"colour_chart": {n: s.to_json() for n, s in found.items()}, "response": true_response().to_json()}
    write_capture(Capture(root=posed, frames=guess, extra=extra), posed)
    assert chart_flash_applies(read_capture(posed))  # as registration leaves it: a point light at every camera
    res = flash_lit_capture(posed, tmp_path / "lights")
    lit = read_capture(tmp_path / "lights")
    assert np.abs(np.asarray(res.summary["intensity"]) / FLASH - 1.0).max() < 0.02  # as flash_from_chart's bound
    assert all(np.allclose(f.light.intensity, res.summary["intensity"]) for f in lit.frames)
    # the photos stay where the posed capture has them (paths relative to the lights folder)
    assert lit.image_path(lit.frames[0]).resolve() == (posed / frames[0].file_path).resolve()
    assert res.summary["replaced"] == [1.0, 1.0, 1.0] and "colour chart" in lit.extra["lights_source"]
