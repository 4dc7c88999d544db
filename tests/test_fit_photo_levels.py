"""Photos streamed at the resolution the texels need (fit/common/photo_levels.py, issue 40): the level's
camera sees a point where the full photo's does, the readers average boxes (masks keep only whole boxes),
the automatic level follows the texels' footprint, and a fit at the coarser level loses under 0.2 dB held out
against the same fit at full resolution."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import SCENE_DEVICE
from texstream.capture.capture_json import Frame, Intrinsics
from texstream.fit.common.photo_levels import LevelImageReader, LevelMaskReader, box_average, frame_at_level
from texstream.fit.stream.photo_stream import PhotoCache, PhotoFiles
from texstream.pipelines.cli import main


def _project(frame, point):
    pc = frame.R @ point + frame.t
    i = frame.intrinsics
    return np.array([i.fx * pc[0] / pc[2] + i.cx, i.fy * pc[1] / pc[2] + i.cy])


def test_a_levels_camera_sees_a_point_where_the_photos_box_holds_it():
    rng = np.random.default_rng(0)
    frame = Frame("images/a.png", np.eye(3), np.array([0.1, -0.2, 3.0]),
                  Intrinsics(width=203, height=150, fx=180.0, fy=181.0, cx=101.3, cy=74.9))
    level = frame_at_level(frame, 2)
    assert (level.intrinsics.width, level.intrinsics.height) == (50, 37)  # 203 // 4, 150 // 4: the rest dropped
    for p in rng.uniform(-0.5, 0.5, size=(20, 3)):
        full, coarse = _project(frame, p), _project(level, p)
        # pixel centres at +0.5 at every level: continuous coordinates scale by exactly 1/4 (float64 round-off)
        np.testing.assert_allclose(coarse, full / 4, rtol=0, atol=1e-12)
    assert frame_at_level(frame, 0) is frame


def test_the_readers_average_boxes_and_keep_only_whole_mask_boxes():
    img = np.arange(6 * 9 * 3, dtype=np.float32).reshape(6, 9, 3)
    mask = np.ones((6, 9), bool)
    mask[0, 0] = False

    def read_image(path, rows=None, size=None):
        return img if rows is None else img[rows[0]:rows[1]]

    def read_mask(path, shape=None, rows=None):
        return mask if rows is None else mask[rows[0]:rows[1]]

    coarse = LevelImageReader(read_image, 1)("a.exr", size=(3, 4))
    assert coarse.shape == (3, 4, 3)
    np.testing.assert_array_equal(coarse[1, 2], img[2:4, 4:6].mean(axis=(0, 1)))  # exact: sums of small integers
    # rows of the level read the photo's rows twice as far down
    np.testing.assert_array_equal(LevelImageReader(read_image, 1)("a.exr", rows=(1, 3), size=(3, 4)), coarse[1:3])
    m = LevelMaskReader(read_mask, 1)("a.png", (3, 4))
    assert not m[0, 0] and m.sum() == 11  # the box holding the one background pixel is background
    with pytest.raises(Exception, match="expects 10x6"):
        LevelImageReader(read_image, 1)("a.exr", size=(3, 5))
    np.testing.assert_array_equal(box_average(img, 0), img)


def test_the_photo_cache_key_names_the_level(tmp_path):
    photo = tmp_path / "a.exr"
    photo.write_bytes(b"x")

    def cache(reader):
        files = PhotoFiles([photo], [None], reader, None, cache_dir=tmp_path)
        return PhotoCache(files, None, 8, 8, np.float32, False).path

    assert cache(LevelImageReader(lambda *a, **k: None, 1)) != cache(LevelImageReader(lambda *a, **k: None, 2))


@pytest.fixture(scope="module")
def fine_capture(tmp_path_factory):
    """The small ornament photographed at 160x160 pixels: its mesh baked at 16x16 texels has texels about 10
    photo pixels wide, 4x or more finer photos than the texels need."""
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("fine") / "capture"
    synthesize("ornament", out, SynthConfig(device=SCENE_DEVICE, preview=False, scale=0.02, photos=16,
                                            image_size=160, progress=False))
    return out


def _fit(capture, out, level):
    args = ["fit", str(capture), "--mesh", str(capture / "ground_truth" / "mesh.obj"), "-o", str(out),
            "--texture-size", "16", "--model", "diffuse", "--holdout-every", "4", "--renders", "0",
            "--photo-level", str(level), "--device", SCENE_DEVICE]
    assert main(args) == 0
    return json.loads((out / "model.json").read_text())


def test_photos_finer_than_the_texels_stream_at_a_coarser_level_and_lose_under_a_fifth_of_a_db(fine_capture,
                                                                                                tmp_path):
    auto = _fit(fine_capture, tmp_path / "auto", -1)
    full = _fit(fine_capture, tmp_path / "full", 0)
    chosen = auto["photos"]["resolution"]
    assert chosen["level"] >= 2 and chosen["size"][0] <= 40  # 1/16 of the pixels or fewer
    assert 2.0 <= chosen["level_texel_pixels"] < 4.0  # the rule: the coarsest level keeping texels >= 2 px wide
    assert full["photos"]["resolution"]["level"] == 0
    # the issue's bound: the texels' centre samples see box-averaged light at the coarse level, the same light
    # point-sampled at full resolution; the held-out views are scored at full resolution in both
    assert auto["heldout"]["pooled_psnr_db"] >= full["heldout"]["pooled_psnr_db"] - 0.2


def _maps(folder):
    from texstream.capture.imageio import read_image

    return {p.name: read_image(p, channels=3) for p in sorted(folder.glob("*.exr"))}


def test_a_fit_on_the_previous_candidates_photo_set_gives_the_same_model(fine_capture, tmp_path, capsys):
    """The model choice's candidates share one photo set (fit/common/inputs.py SharedPhotoSet): the Lafortune fit
    after a diffuse fit of the same capture, on the diffuse fit's photos and maps, equals a Lafortune fit that
    built its own, to the bit (the same arithmetic on the same bytes)."""
    from texstream.fit.common.inputs import SharedPhotoSet
    from texstream.fit.stages.stage import FitStageConfig, fit_model
    from texstream.fit.models.materials import MaterialConfig
    from texstream.fit.optim.fitter import FitConfig

    def cfg(model):  # materials and polish off: they add fits, not another use of the photo set
        return FitStageConfig(device=SCENE_DEVICE, texture_size=16, holdout_every=4, renders=0, traced_polish=0,
                              materials=MaterialConfig(mode="off"), fit=FitConfig(model=model, max_iterations=4))

    mesh = fine_capture / "ground_truth" / "mesh.obj"
    SharedPhotoSet.release()
    fit_model(fine_capture, mesh, tmp_path / "alone", cfg("lafortune"), progress=False)
    SharedPhotoSet.release()
    fit_model(fine_capture, mesh, tmp_path / "diffuse", cfg("diffuse"), progress=False)
    assert SharedPhotoSet.photos is not None
    from texstream.core.progress import reporting

    said = []
    with reporting(said.append):
        fit_model(fine_capture, mesh, tmp_path / "shared", cfg("lafortune"), progress=False)
    SharedPhotoSet.release()
    assert any("shared with the previous fit" in line for line in said)
    alone, shared = _maps(tmp_path / "alone"), _maps(tmp_path / "shared")
    assert alone.keys() == shared.keys() and alone
    for name in alone:
        np.testing.assert_array_equal(shared[name], alone[name], err_msg=name)


def _split_fit_config(model: str, validation: bool):
    """A fit of the fine capture's photos (every 4th held out, a validation split of every 3rd fitted), materials and
    polish off: they add fits, not another use of the photo set."""
    from texstream.fit.models.materials import MaterialConfig
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.choice import ModelChoiceConfig
    from texstream.fit.stages.stage import FitStageConfig

    return FitStageConfig(device=SCENE_DEVICE, texture_size=16, holdout_every=4, renders=0, traced_polish=0,
                          materials=MaterialConfig(mode="off", validation_every=3),
                          choice=ModelChoiceConfig(validation_fit=validation), fit=FitConfig(model=model, max_iterations=4))


def test_a_validation_fit_takes_its_photos_from_the_previous_fits_set(fine_capture, tmp_path):
    """The model choice's fit of the validation split (choice.validation_fit) after a fit of every fitted photo
    takes its photos from that fit's set (PhotoSet.subset: nothing decoded or shadow-mapped again), leaves the
    larger set kept for the next fit, and gives the model of a validation fit that set up its own, to the bit."""
    from texstream.core.progress import reporting
    from texstream.fit.common.inputs import SharedPhotoSet
    from texstream.fit.stages.stage import fit_model

    cfg = _split_fit_config

    mesh = fine_capture / "ground_truth" / "mesh.obj"
    SharedPhotoSet.release()
    alone = fit_model(fine_capture, mesh, tmp_path / "alone", cfg("lafortune", True), progress=False)
    SharedPhotoSet.release()
    fit_model(fine_capture, mesh, tmp_path / "every", cfg("diffuse", False), progress=False)
    every = SharedPhotoSet.photos
    said = []
    with reporting(said.append):
        split = fit_model(fine_capture, mesh, tmp_path / "split", cfg("lafortune", True), progress=False)
    assert SharedPhotoSet.photos is every and every.n == 12
    SharedPhotoSet.release()
    assert any("shared with the previous fit" in line for line in said)
    # 12 fitted photos, every 3rd a validation photo: 8 fitted, 4 scored where the held-out ones are
    assert split.summary["photos"] == alone.summary["photos"] == 8 and split.summary["heldout"]["views"] == 4
    # a validation fit writes its scores only (model.json): the same fit to the bit gives the same final objective
    # and the same validation scores, view by view
    a, b = (json.loads((tmp_path / name / "model.json").read_text()) for name in ("alone", "split"))
    untimed = lambda m: {k: v for k, v in m["final"].items() if k != "time_s"}
    assert a["scores_only"] and untimed(a) == untimed(b)
    assert [e["psnr_db"] for e in a["render_eval"]] == [e["psnr_db"] for e in b["render_eval"]]


def test_a_validation_fit_judged_first_leaves_every_fitted_photo_for_the_next_fit(fine_capture, tmp_path):
    """A validation fit with nothing kept before it (the diffuse candidate, judged first) builds the set of every
    fitted photo, keeps it and fits its split's subset: the Lafortune fit of every photo after it reads nothing
    again, and the validation fit's model is the same as before (a fit on a shared set gives its own's, tested
    above)."""
    from texstream.core.progress import reporting
    from texstream.fit.common.inputs import SharedPhotoSet
    from texstream.fit.stages.stage import fit_model

    cfg = _split_fit_config

    mesh = fine_capture / "ground_truth" / "mesh.obj"
    SharedPhotoSet.release()
    split = fit_model(fine_capture, mesh, tmp_path / "split", cfg("diffuse", True), progress=False)
    every = SharedPhotoSet.photos
    assert split.summary["photos"] == 8 and every is not None and every.n == 12  # every fitted photo kept
    said = []
    with reporting(said.append):
        fit_model(fine_capture, mesh, tmp_path / "every", cfg("lafortune", False), progress=False)
    assert any("shared with the previous fit" in line for line in said), said
    SharedPhotoSet.release()
