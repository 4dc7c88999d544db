"""Flash/no-flash pairs (issue 39): photos taken with the flash off, their marking (EXIF Flash tag, ``--no-flash``),
the flash at intensity 0 wherever the stages place it, and the fit's ambient term observed directly from them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from texstream.capture.capture_json import NO_FLASH_KEY, Light, flash_fired, read_capture, write_capture
from texstream.core.errors import ConfigError

from conftest import SCENE_DEVICE, tiny_sphere_capture


def matte_room_scene() -> dict:
    """The built-in sphere_room (a flash at each camera, the room's light brighter from above) made matte and fitted
    as a diffuse model: the model expresses it exactly, so the albedo's error is the ambient's ambiguity alone."""
    from texstream.capture.synthetic.synth import load_scene

    room = load_scene("sphere_room")
    room["model"] = {"kind": "diffuse", "n_lobes": 0}
    room["materials"]["plastic"]["lobes"] = []
    return room


NOISE = 0.002
"""the photos' Gaussian noise (linear units; the lit sphere's pixels are about 0.1 to 0.6): noise-free photos pin the
ambient even without pairs (0.33% median albedo error measured), the ambiguity shows as noise amplification"""


def add_no_flash_pairs(folder) -> None:
    """Every frame of a synthetic capture also photographed with the flash off (the truth rendered with the light at
    intensity 0, with the flash photos' noise), appended after the flash frames as ``NAME_noflash.exr`` and marked
    ``no_flash``."""
    from texstream.capture.imageio import write_image
    from texstream.capture.synthetic.synth import load_ground_truth
    from texstream.render.renderer import Renderer

    cap = read_capture(folder)
    mesh, params, layout, _, _ = load_ground_truth(folder)
    rend = Renderer(mesh, params, layout, device=SCENE_DEVICE)
    pairs = []
    rng = np.random.default_rng(7)
    for f in cap.frames:
        off = dataclasses.replace(f, file_path=f"images/{f.name}_noflash.exr",
                                  light=Light.point(f.light.position, np.zeros(3)), extra={NO_FLASH_KEY: True})
        img = rend.render_frame(off).radiance * np.float32(f.exposure)
        write_image(folder / off.file_path, img + rng.normal(0.0, NOISE, img.shape).astype(np.float32), bits=32)
        pairs.append(off)
    cap.frames += pairs
    write_capture(cap)


def fit_config(ambient: str):
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig

    return FitStageConfig(device=SCENE_DEVICE, renders=0, holdout_every=8,
                          fit=FitConfig(model="diffuse", max_iterations=30, ambient=ambient))


@pytest.fixture(scope="module")
def pair_fits(tmp_path_factory):
    """The matte lit sphere, 16 float photos of 40x40 on a 29x14 atlas, fitted with the ambient term on; the same
    photos with their 16 no-flash pairs fitted with ``auto``."""
    import shutil

    from texstream.capture.synthetic.synth import SynthConfig, synthesize
    from texstream.fit.stages.stage import fit_stage

    root = tmp_path_factory.mktemp("pairs")
    synthesize(matte_room_scene(), root / "flash", SynthConfig(scale=0.05, photos=16, image_size=40, noise=NOISE,
                                                               progress=False, preview=False, device=SCENE_DEVICE))
    shutil.copytree(root / "flash", root / "pairs")
    add_no_flash_pairs(root / "pairs")
    fit_stage(root / "flash", root / "flash" / "ground_truth", root / "flash_on", fit_config("on"), progress=False)
    fit_stage(root / "pairs", root / "pairs" / "ground_truth", root / "pairs_auto", fit_config("auto"), progress=False)
    return root


def albedo_errors(root, fit: str, truth: str) -> np.ndarray:
    from texstream.capture.imageio import read_image
    from texstream.capture.synthetic.synth import load_ground_truth
    from texstream.fit.stages.stage import load_model

    _, grid, _, _ = load_model(root / fit)
    _, params, _, bake, _ = load_ground_truth(root / truth)
    seen = bake.covered & (read_image(root / fit / "seen.png", channels=3)[..., 0] > 0.5)
    return np.abs(grid[seen][:, 0:3] / params[seen][:, 0:3] - 1.0).max(axis=1)


def test_no_flash_pairs_pin_the_albedo(pair_fits):
    """Without pairs the free per-texel ambient trades with the albedo (the flash's E cos varies little between
    views), which amplifies the photos' noise into both; with pairs the no-flash photos show the ambient alone.
    Measured over the texels the photos saw (the largest channel's relative error; the blue channel's pixels are
    0.02 to 0.04, so noise 0.002 is 5-10% of a pixel there): with pairs median 3.7%, 90th percentile 7.2%; without
    them 8.0% and 25%. Bounds: with pairs median 5% and 90th percentile 10% (the noise's share, with margin);
    without them above 1.5x the median and 2.5x the 90th percentile with pairs (measured 2.1x and 3.5x; noise-free
    photos measured 0.14% against 0.33%). ``auto`` takes the term on without the validation comparison, saying why."""
    from texstream.fit.stages.stage import load_model

    _, _, lay, man = load_model(pair_fits / "pairs_auto")
    assert lay.ambient and man["ambient"]["chosen"] == "on" and "candidates" not in man["ambient"], man["ambient"]
    assert man["ambient"]["no_flash_photos"] == 14 and "flash off" in man["ambient"]["reason"]
    with_pairs = albedo_errors(pair_fits, "pairs_auto", "pairs")
    without = albedo_errors(pair_fits, "flash_on", "flash")
    med, p90 = np.median(with_pairs), np.percentile(with_pairs, 90)
    assert med < 0.05 and p90 < 0.10, (med, p90)
    assert np.median(without) > 1.5 * med and np.percentile(without, 90) > 2.5 * p90, (
        np.median(without), np.percentile(without, 90), med, p90)


def test_the_no_flash_photos_give_the_ambient(pair_fits):
    """The pairs fitted with the no-flash photos' light at 0, as the capture states it: every parameter finite, the
    ambient (the truth's own ambient columns, the room's radiance) recovered on the seen texels within 0.002 median
    and 0.004 90th percentile (the largest channel's absolute error: one photo's noise is 0.002 and a texel's
    ambient is pinned by several no-flash photos, so their mean's noise is below it; measured 0.00096 and 0.0017), and
    the held-out no-flash photos, rendered as the ambient alone, above 51 dB (their noise alone allows 54.0 dB;
    measured 53.4 and 53.5 dB)."""
    from texstream.capture.imageio import read_image
    from texstream.capture.synthetic.synth import load_ground_truth
    from texstream.core.outputs import read_json
    from texstream.fit.stages.stage import load_model

    _, grid, lay, _ = load_model(pair_fits / "pairs_auto")
    _, truth, truth_layout, bake, _ = load_ground_truth(pair_fits / "pairs")
    seen = bake.covered & (read_image(pair_fits / "pairs_auto" / "seen.png", channels=3)[..., 0] > 0.5)
    assert np.isfinite(grid).all() and truth_layout.ambient
    fitted = grid[seen][:, lay.ambient_offset:lay.ambient_offset + 3]
    err = np.abs(fitted - truth[seen][:, truth_layout.ambient_offset:]).max(axis=1)
    assert np.median(err) < 0.002 and np.percentile(err, 90) < 0.004, (np.median(err), np.percentile(err, 90))
    views = read_json(pair_fits / "pairs_auto" / "model.json", what="model")["render_eval"]
    dark = [v["psnr_db"] for v in views if v["held_out"] and v["frame"].endswith("_noflash.exr")]
    assert len(dark) == 2 and min(dark) > 51.0, views


def test_ambient_off_with_no_flash_photos_is_one_line(pair_fits, tmp_path):
    """``--ambient off`` would predict the no-flash photos black: refused, naming the fix."""
    from texstream.fit.stages.stage import fit_stage

    with pytest.raises(ConfigError) as e:
        fit_stage(pair_fits / "pairs", pair_fits / "pairs" / "ground_truth", tmp_path / "off", fit_config("off"),
                  progress=False)
    assert "no-flash" in str(e.value) and "\n" not in e.value.one_line() and "--ambient on" in e.value.one_line()


def test_a_zero_intensity_frame_gives_finite_gradients(pair_fits):
    """No-flash frames alone, their light at intensity 0 as the capture states it, here a lamp's above the sphere (as
    ``--lights`` leaves it): the fit keeps the light where the capture puts it; every objective and gradient entry
    finite; the ambient's gradient is what the photos say (non-zero), the albedo's exactly 0 (such a sample's only
    feature is the ambient, fit/kernels/accumulate.py). Where the zero light sits does not matter (the kernels skip
    its tests, fit/kernels/stream.py ``observe_with_unlit_func``): at the camera or at the sphere's centre (behind
    every texel) the objective, gradient, sample counts and initial guess are the lamp's to the bit."""
    import warp as wp

    from texstream.capture.synthetic.synth import load_ground_truth
    from texstream.fit.common.inputs import load_photos
    from texstream.fit.common.setup import build_problem
    from texstream.fit.optim.fitter import FitConfig, fit_start

    cap = read_capture(pair_fits / "pairs")
    mesh, params, _, bake, _ = load_ground_truth(pair_fits / "pairs")
    dark = [f for f in cap.frames if not flash_fired(f)][:2]
    cfg = FitConfig(model="diffuse", ambient="on")
    images, masks = load_photos(cap, dark)
    lamp = np.array([0.0, 0.0, 10.0])
    placements = {"lamp": [lamp] * 2, "camera": [f.center for f in dark],
                  "centre": [mesh.vertices.mean(axis=0)] * 2}
    got = {}
    for name, where in placements.items():
        frames = [dataclasses.replace(f, light=Light.point(pos, np.zeros(3))) for f, pos in zip(dark, where)]
        prob = build_problem(mesh, bake, frames, images, masks, cfg, SCENE_DEVICE)
        infos = prob.photos.infos_host
        assert not infos["light_intensity"].any() and np.allclose(infos["light_vec"], np.float32(where))
        p = np.tile(prob.layout.defaults(), (prob.n, 1))
        f, g = prob.new_scalar(), prob.new_vec()
        stats = wp.zeros(prob.n, dtype=wp.vec4d, device=prob.device)
        prob.evaluate(prob.new_storage(p), f, g, stats)
        got[name] = (f.numpy(), g.numpy()[:, :prob.layout.n_params], stats.numpy(), *fit_start(prob, cfg).numpy())
    f, g, stats, _, counts = got["lamp"]
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(g)) and stats[:, 0].sum() > 0 and counts.sum() > 0
    assert np.abs(g[:, prob.layout.ambient_offset:]).max() > 0 and not g[:, 0:3].any()
    for name in ("camera", "centre"):
        for a, b in zip(got["lamp"], got[name]):
            np.testing.assert_array_equal(a, b, err_msg=name)


BEHIND_THE_PLANE = (0.0, 0.0, -2.0)
"""a point light under test_fit_gradients' plane z = 0, whose normals face +z: every texel faces away from it"""
UNLIT_CASES = {"filtered": ({}, False), "point": ({"sampling": "point"}, False),
               "lookup": ({"lookup": "bilinear"}, False), "traced": ({"taps": "mesh"}, False),
               "room": ({"lookup": "bilinear"}, True),
               "filtered_light_behind": ({"unlit_light": BEHIND_THE_PLANE}, False),
               "traced_light_behind": ({"taps": "mesh", "unlit_light": BEHIND_THE_PLANE}, False)}
"""plane_problem options of the unlit samples' derivative checks, and whether the layout has the room light"""


@pytest.mark.parametrize("case", list(UNLIT_CASES))
def test_unlit_samples_derivatives_match_finite_differences(device, case):
    """Half the photos of test_fit_gradients' plane scene with their light at 0: each column's gradient (the room
    light's frozen S included: what its solve reduces) against central differences in float64 (bound 1e-6 of each
    texel's gradient norm, test_fit_gradients'), and the full d^T H d against second differences (an unlit sample is
    linear in its parameters: its curvature is the Gauss-Newton one). With every photo unlit, the albedo's and the
    lobes' gradient is exactly 0 and the ambient's not, also with the zero light behind the plane (its cosine and
    shadow tests would reject every sample: the kernels skip them for a light of intensity 0)."""
    from test_fit_ambient import AMBIENT_STEP, ambient_params
    from test_fit_gradients import (assert_full_dhd_matches_second_difference,
                                    assert_gradient_matches_finite_differences, evaluate, plane_problem)
    from test_fit_room_light import room_params

    from texstream.render.layout import ModelLayout

    options, room = UNLIT_CASES[case]
    layout = ModelLayout(room=room, ambient=not room)
    params = room_params if room else ambient_params
    prob, rng = plane_problem(device, layout, unlit=3, **options)
    p = params(layout, prob.n, rng)
    prob.refresh_lookup(prob.new_storage(p))
    assert_gradient_matches_finite_differences(prob, layout, p, range(layout.n_params))
    if not room:  # the room's frozen S has no step
        assert_full_dhd_matches_second_difference(prob, p, rng, AMBIENT_STEP)
    dark, _ = plane_problem(device, layout, unlit=6, **options)
    dark.refresh_lookup(dark.new_storage(p))
    f, g, _, stats = evaluate(dark, p)
    extra = layout.n_params - 3
    assert stats[:, 0].sum() > 0 and np.isfinite(f).all() and np.abs(g[:, extra:]).max() > 0
    assert not g[:, 3:extra].any() and (room or not g[:, 0:3].any())


@pytest.mark.parametrize("sampling", ["filtered", "point"])
def test_the_zero_lights_placement_does_not_matter(device, sampling):
    """test_fit_gradients' plane with every photo unlit, their zero light near each camera (where the lit photos'
    is) or behind the plane: the objective, gradient, d^T H d, sample statistics, the LM pass's J^T J, the initial
    guess and the tiles' photos are the same to the bit (an unlit sample's camera tests, its ambient feature and its
    zero weight do not read the light's position; its lobes see no light direction)."""
    import warp as wp
    from test_fit_ambient import ambient_params
    from test_fit_gradients import evaluate, plane_problem

    from texstream.fit.multi.tile_plan import tile_photo_visibility
    from texstream.fit.optim.fitter import FitConfig, fit_start
    from texstream.render.layout import ModelLayout

    layout = ModelLayout(ambient=True)
    got = []
    for where in (None, BEHIND_THE_PLANE):
        prob, rng = plane_problem(device, layout, unlit=6, unlit_light=where, sampling=sampling)
        p = ambient_params(layout, prob.n, rng)
        f_lm, g_lm = prob.new_scalar(), prob.new_vec()
        jtj = wp.zeros(prob.n, dtype=prob.mat, device=device)
        prob.evaluate_lm(prob.new_storage(p), f_lm, g_lm, jtj, wp.zeros(prob.n, dtype=wp.vec4d, device=device))
        direction = rng.normal(size=p.shape) * 0.01
        tiles = tile_photo_visibility(prob, np.array([[0, 12], [12, prob.n]]))
        got.append((*evaluate(prob, p, direction=direction, full=True), jtj.numpy(),
                    *fit_start(prob, FitConfig()).numpy(), tiles))
    assert got[0][3][:, 0].sum() > 0 and got[0][-1].any()
    for near, behind in zip(*got):
        np.testing.assert_array_equal(near, behind)


def test_the_highlight_diagnostic_leaves_unlit_photos_out(device):
    """A photo whose light is 0 shows no highlight (fit/common/highlights.py): with every photo of test_fit_gradients'
    plane unlit the diagnostic sees no texel and no sample near the mirror (each photo's samples are there, as the
    fit's passes take them); with half of them unlit its masks are the same wherever their zero light sits."""
    from test_fit_ambient import ambient_params
    from test_fit_gradients import evaluate, plane_problem

    from texstream.fit.common.highlights import highlight_masks
    from texstream.render.layout import ModelLayout

    layout = ModelLayout(ambient=True)
    prob, rng = plane_problem(device, layout, unlit=6)
    p = ambient_params(layout, prob.n, rng)
    dark = highlight_masks(prob, p)
    assert evaluate(prob, p)[3][:, 0].sum() > 0 and not dark.seen.any() and not dark.near_mirror.any()
    masks = []
    for where in (None, BEHIND_THE_PLANE):
        prob, rng = plane_problem(device, layout, unlit=3, unlit_light=where)
        masks.append(highlight_masks(prob, ambient_params(layout, prob.n, rng)))
    assert masks[0].seen.any()
    for name in ("seen", "highlight", "lobe", "hits", "near_mirror"):
        np.testing.assert_array_equal(getattr(masks[0], name), getattr(masks[1], name), err_msg=name)


def write_photos(folder, flash_tags: dict) -> None:
    """Small textured 8-bit PNGs, each with the given EXIF Flash tag (None: no tag)."""
    from texstream.capture.imageio import write_image

    rng = np.random.default_rng(0)
    for name, tag in flash_tags.items():
        write_image(folder / f"{name}.png", rng.integers(0, 255, (48, 64, 3)).astype(np.uint8), bits=8,
                    metadata=None if tag is None else {"Exif:Flash": tag})


def ingested(photos, out, **options):
    from texstream.calib.ingest import IngestConfig, ingest

    res = ingest(photos, out, IngestConfig(auto_masks="none", **options))
    cap = read_capture(out)
    return res.summary["no_flash"], sorted(f.name for f in cap.frames if not flash_fired(f)), cap


def test_ingest_marks_no_flash_photos_from_exif_and_the_glob(tmp_path):
    """The EXIF Flash tag marks the photos whose flash did not fire (0x10: suppressed; 0x9: fired) when another's
    fired; ``--no-flash`` overrides it; a capture where no flash fired marks none (another light lit it); a glob
    that matches nothing is a one-line error."""
    photos = tmp_path / "photos"
    photos.mkdir()
    write_photos(photos, {"a": 0x9, "a_noflash": 0x10, "b": 0x9, "b_noflash": 0x10})
    entry, dark, cap = ingested(photos, tmp_path / "exif")
    assert dark == ["a_noflash", "b_noflash"] and entry["source"] == "exif" and cap.extra["no_flash"]["photos"] == 2
    entry, dark, _ = ingested(photos, tmp_path / "glob", no_flash="b*")
    assert dark == ["b", "b_noflash"] and entry["source"] == "--no-flash"
    with pytest.raises(ConfigError) as e:
        ingested(photos, tmp_path / "typo", no_flash="*_nofalsh*")
    assert "matches none" in e.value.one_line() and "\n" not in e.value.one_line()
    lamp = tmp_path / "lamp"
    lamp.mkdir()
    write_photos(lamp, {"c": 0x10, "d": 0x10, "e": None})
    entry, dark, cap = ingested(lamp, tmp_path / "lamp_capture")
    assert dark == [] and entry["source"] == "none" and "no_flash" not in cap.extra


def test_a_lights_file_leaves_no_flash_photos_to_the_room(tmp_path, monkeypatch):
    """``--lights``: a no-flash photo is lit by the room alone, so the file's default light reaches it at intensity
    0 (in place), said in one line; a light the file gives that photo by name contradicts the marking (which of the
    two is wrong only the user knows): a one-line error naming the file and both fixes; an entry at intensity 0 is
    what the marking says, accepted. The mirror ball's light (the lights stage, its estimate stubbed here) is every
    photo's default: at intensity 0 on the no-flash ones too."""
    import json

    from texstream.calib import lights as lights_stage
    from texstream.core.errors import InputError
    from texstream.core.outputs import StageResult
    from texstream.core.progress import reporting
    from texstream.pipelines.light_inputs import light_and_resolution_inputs

    photos = tmp_path / "photos"
    photos.mkdir()
    write_photos(photos, {"a": 0x9, "a_noflash": 0x10})
    lamp = {"type": "point", "position": [1.0, 2.0, 3.0], "intensity": [5.0, 5.0, 5.0]}
    lights = tmp_path / "lights.json"
    lights.write_text(json.dumps({"default": lamp}))
    lines = []
    with reporting(lines.append, bars=False):
        _, dark, cap = ingested(photos, tmp_path / "default", lights=str(lights))
    light = {f.name: f.light for f in cap.frames}
    assert dark == ["a_noflash"] and light["a"].intensity.tolist() == [5.0] * 3
    assert light["a_noflash"].intensity.tolist() == [0.0] * 3 and light["a_noflash"].position.tolist() == [1, 2, 3]
    assert [line for line in lines if "intensity 0" in line] == [
        "  ingest: --lights: the default light at intensity 0 on the 1 photo(s) taken with the flash off (the room "
        "lights them alone)"]
    def ball(posed, out, cfg):
        out.mkdir()
        return StageResult(output=out, summary={"light": lamp, "kind": "point", "views": 2})

    monkeypatch.setattr(lights_stage, "estimate_lights", ball)
    lines.clear()
    with reporting(lines.append, bars=False):
        lights_stage.lit_capture(tmp_path / "default", tmp_path / "ball", lights_stage.LightsConfig())
    assert [f.light.intensity.tolist() for f in read_capture(tmp_path / "ball").frames] == [[5.0] * 3, [0.0] * 3]
    assert [line for line in lines if "intensity 0" in line] == [
        "  lights: the mirror ball's light at intensity 0 on the 1 photo(s) taken with the flash off (the room lights "
        "them alone)"]
    light = light_and_resolution_inputs(read_capture(tmp_path / "ball"), tmp_path / "no_model", tmp_path, {})["light"]
    assert light["source"].endswith(", intensity 0 on the 1 photos taken with the flash off (the room lights them "
                                    "alone)"), light
    lights.write_text(json.dumps({"default": lamp, "frames": {"a_noflash": lamp}}))
    with pytest.raises(InputError) as e:
        ingested(photos, tmp_path / "named", lights=str(lights))
    line = e.value.one_line()
    assert "a_noflash" in line and str(lights) in line and "--no-flash" in line and "\n" not in line
    lights.write_text(json.dumps({"default": lamp, "frames": {"a_noflash": {**lamp, "intensity": [0.0] * 3}}}))
    _, dark, cap = ingested(photos, tmp_path / "named_dark", lights=str(lights))
    assert dark == ["a_noflash"] and [f.light.intensity.tolist() for f in cap.frames] == [[5.0] * 3, [0.0] * 3]


def test_the_flash_of_a_no_flash_photo_has_intensity_zero():
    """The colocated light (ingest's --colocated-light, the chart's flash, the imports) of a no-flash photo sits at
    the camera with intensity 0, exactly."""
    from texstream.calib.lights import colocated_light

    r, t = np.eye(3), np.array([0.0, 0.0, 4.0])
    on, off = colocated_light(r, t, 40.0), colocated_light(r, t, 40.0, fired=False)
    assert on.intensity.tolist() == [40.0] * 3 and off.intensity.tolist() == [0.0] * 3
    assert off.position.tolist() == on.position.tolist() == [0.0, 0.0, -4.0]


def test_no_flash_sightings_of_the_chart_give_the_room_not_the_flash():
    """The chart seen in flash photos and in their no-flash pairs (the synthetic flash capture's chart through its
    tone curve, test_calib_chart_flash's cameras; the chart read in 5 pairs): the no-flash patches measure the room's
    light on the chart alone (the flash line's intercept) and leave the flash's intensity to the flash photos: within
    2% of the truth, as without pairs (the issue's albedo bound; 8-bit patches a dozen pixels wide and the PnP depth
    leave ~1%; measured 1.0-1.5%, the flash photos alone 1.6-2.4%), the room's light within 5% (measured 0.4-1.0%
    from the no-flash patches, against 3-7% from the intercept of the flash photos' line over their narrow range of
    flash irradiance, which test_calib_chart_flash bounds by 10% + 0.02). Sightings only in no-flash photos are
    refused."""
    from texstream.calib.chart_flash import flash_from_chart
    from texstream.calib.colour_chart import find_chart
    from texstream.capture.synthetic.colour_chart import paste_chart
    from texstream.capture.synthetic.flash_capture import (_chart_light, _project, chart_corners_world, develop_codes,
                                                           true_response)
    from texstream.core.errors import InputError
    from test_calib_chart_flash import FLASH, ROOM, SIZE, _frames

    def photo(frame, flash, seed):
        uv, _ = _project(frame, chart_corners_world())
        linear = paste_chart(np.zeros((SIZE, SIZE, 3)), uv - 0.5,
                             _chart_light(frame, np.full(3, flash), np.full(3, ROOM), (SIZE, SIZE)))
        return develop_codes(linear, np.random.default_rng(seed), 0.002) / 255.0

    lit = _frames(6)
    dark = [dataclasses.replace(f, file_path=f.file_path.replace(".png", "_noflash.png"),
                                light=Light.point(f.light.position, np.zeros(3)), extra={NO_FLASH_KEY: True})
            for f in lit]
    found = {f.name: find_chart(photo(f, FLASH if flash_fired(f) else 0.0, k)) for k, f in enumerate(lit + dark)}
    found = {n: s for n, s in found.items() if s is not None}
    assert sum(n.endswith("_noflash") for n in found) >= 2 and sum(not n.endswith("_noflash") for n in found) >= 2
    res = flash_from_chart(lit + dark, found, true_response())
    assert np.abs(res.intensity / FLASH - 1.0).max() < 0.02, res.intensity
    assert res.room_fitted and np.abs(res.room_irradiance / ROOM - 1.0).max() < 0.05, res.room_irradiance
    assert [p["flash"] for p in res.photos].count(False) == sum(n.endswith("_noflash") for n in found)
    with pytest.raises(InputError, match="flash off"):
        flash_from_chart(dark, {n: s for n, s in found.items() if n.endswith("_noflash")}, true_response())


def test_the_run_says_how_many_photos_had_no_flash_and_why(pair_fits):
    """The run's light provenance (pipelines/light_inputs.py) names the no-flash photos and what marked them; a
    capture without them gets no entry (most captures: their summaries stay as they were)."""
    from texstream.pipelines.light_inputs import light_and_resolution_inputs

    pairs = light_and_resolution_inputs(read_capture(pair_fits / "pairs"), pair_fits / "pairs_auto", pair_fits, {})
    assert pairs["no_flash"]["source"].startswith("16 of 32 photos taken with the flash off"), pairs["no_flash"]
    assert "flash off" in pairs["ambient"]["why"]
    flash = light_and_resolution_inputs(read_capture(pair_fits / "flash"), pair_fits / "flash_on", pair_fits, {})
    assert "no_flash" not in flash


def test_run_passes_no_flash_to_ingest():
    """``texstream run PHOTOS --no-flash GLOB`` reaches ingest's option."""
    import argparse

    from texstream.pipelines.cmd_run import _config, add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert _config(parser.parse_args(["photos", "--no-flash", "*_noflash.*"])).ingest.no_flash == "*_noflash.*"
    assert _config(parser.parse_args(["photos"])).ingest.no_flash is None


def test_a_camera_without_a_flash_says_nothing_about_pairs():
    """EXIF Flash bit 5 (0x20, "no flash function"): neither fired nor off, so a second camera without a flash in
    the capture does not mark its photos as no-flash pairs; bit 0 says fired (0x9) or not (0x10)."""
    from texstream.calib.no_flash import exif_flash_fired

    assert exif_flash_fired(0x20) is None and exif_flash_fired(None) is None
    assert exif_flash_fired(0x9) is True and exif_flash_fired(0x10) is False


def test_the_lobe_shape_choice_leaves_out_photos_without_light():
    """A no-flash photo's light (0, left at the lamp as ``--lights`` leaves it) shows no highlight, so the lobe
    shape's light-view spread (fit/optim/fitter.py ``choose_lobe_shape``) leaves it out: six photos under a fixed lamp
    22.6-27 degrees from their cameras stay "phong" with two no-flash photos beside them (at 10 and 40 degrees they
    would make the spread 30 degrees, over the 10 degree default, and "free")."""
    from types import SimpleNamespace

    from texstream.fit.optim.fitter import choose_lobe_shape, light_view_angles

    lamp = np.array([1.0, 0.0, 0.0])

    def frame(angle_deg: float, intensity: float, light=None):
        a = np.radians(angle_deg)
        centre = 4.0 * np.array([np.cos(a), np.sin(a), 0.0])  # the camera, looking at the origin
        return SimpleNamespace(R=np.eye(3), t=-centre, light_kind="point",
                               light_vec=centre if light is None else light, light_intensity=np.full(3, intensity))

    lit = [frame(a, 1.0, 4.0 * lamp) for a in (22.6, 23.5, 24.4, 25.3, 26.1, 27.0)]
    unlit = [frame(a, 0.0, 4.0 * lamp) for a in (10.0, 40.0)]  # the lamp, intensity 0
    assert light_view_angles(lit + unlit, np.zeros(3)).size == len(lit)
    assert choose_lobe_shape(lit + unlit, np.zeros(3), 10.0) == choose_lobe_shape(lit, np.zeros(3), 10.0) == "phong"


def test_a_zero_light_gets_no_shadow_map():
    """A no-flash photo's light lights nothing and its samples skip the light's tests, so it gets no shadow camera
    (render/camera.py): its shadow map is not rendered; the same light with an intensity gets one."""
    from texstream.render.camera import PhotoFrame, image_infos

    def frame(intensity: float) -> PhotoFrame:
        return PhotoFrame(np.eye(3), np.array([0.0, 0.0, 4.0]), 50.0, 50.0, 32.0, 32.0, 64, 64, "point",
                          np.array([0.0, 0.0, -4.0]), np.full(3, intensity))

    infos = image_infos([frame(40.0), frame(0.0)], None, np.zeros(3), 1.0, 64)
    assert infos["has_shadow"].tolist() == [1, 0]


def test_texels_seen_only_without_the_flash_take_the_nearest_lit_reflectance(tmp_path):
    """A texel only photos taken with the flash off saw has no sample for its albedo or lobes (they keep the initial
    guess, which shows wherever a flash lights them): it takes the reflectance columns of the nearest texel a lit
    photo saw and keeps its own ambient; lit texels and texels no photo saw are left to the other fills."""
    from types import SimpleNamespace

    from texstream.fit.common.setup import fill_unlit_reflectance
    from texstream.geometry.bake import TexelBake
    from texstream.render.layout import ModelLayout

    cap = tiny_sphere_capture(tmp_path, photos=2, image_size=32)
    bake = TexelBake.load(cap / "ground_truth" / "bake.npz")
    grid_index = np.flatnonzero(bake.covered.reshape(-1))
    position = bake.position.reshape(-1, 3)[grid_index].astype(np.float64)
    problem = SimpleNamespace(texels=SimpleNamespace(grid_index=grid_index, position=position))
    layout = ModelLayout(kind="lafortune", n_lobes=1, ambient=True)
    rng = np.random.default_rng(3)
    grid = rng.uniform(0.1, 1.0, (bake.height, bake.width, layout.n_params)).astype(np.float32)
    n = len(grid_index)
    seen = np.ones(n, bool)
    seen[:5] = False  # no photo saw these: not this fill's
    lit_seen = position[:, 2] < np.quantile(position[:, 2], 0.7)  # the top 30% only unlit photos saw
    lit_seen &= seen
    out, filled = fill_unlit_reflectance(grid, problem, bake, seen, lit_seen, layout)
    flat_in, flat_out = grid.reshape(-1, layout.n_params), out.reshape(-1, layout.n_params)
    targets = seen & ~lit_seen
    assert filled == int(targets.sum()) > 0
    a = layout.ambient_offset
    assert np.array_equal(flat_out[grid_index[targets], a:a + 3], flat_in[grid_index[targets], a:a + 3])
    lit_rows = flat_in[grid_index[lit_seen], :a]
    for row in flat_out[grid_index[targets], :a][:50]:  # every filled texel holds some lit texel's reflectance
        assert np.any(np.all(lit_rows == row, axis=1))
    untouched = ~targets
    assert np.array_equal(flat_out[grid_index[untouched]], flat_in[grid_index[untouched]])
    # its nearest lit texel, in 3D
    t = np.flatnonzero(targets)[0]
    nearest = np.flatnonzero(lit_seen)[np.argmin(np.linalg.norm(position[lit_seen] - position[t], axis=1))]
    assert np.array_equal(flat_out[grid_index[t], :a], flat_in[grid_index[nearest], :a])
    # no photo without the flash, or a layout without the ambient term: nothing to fill
    assert fill_unlit_reflectance(grid, problem, bake, seen, seen, layout)[1] == 0
    assert fill_unlit_reflectance(grid, problem, bake, seen, lit_seen, ModelLayout(kind="lafortune"))[1] == 0
