"""The photometric refinement at the resolution it needs (geometry/refine_levels.py, issue 40): its finest level
follows the atlas's texel footprint (never finer than the texels), the blur levels run coarse to fine on the
pyramid, a level's cameras are the full photo's at 1/2^L, the finer levels run only when the coarse one moved
something (the skip and its reason recorded), and the run's resolution lines (pipelines/resolutions.py)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import SCENE_DEVICE
from texstream.geometry import refine_levels as rl


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """12 photos of 128x128 of the textured sphere (a flash at each camera) with its true mesh and atlas."""
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("levels") / "cap"
    synthesize("textured_sphere", root, SynthConfig(photos=12, image_size=128, progress=False, preview=False,
                                                    device=SCENE_DEVICE))
    return root, read_capture(root)


def test_the_finest_level_follows_the_texel_footprint(sphere):
    from texstream.geometry.mesh_io import load_mesh

    root, cap = sphere
    mesh = load_mesh(root / "ground_truth" / "mesh.obj")
    # the scene's own atlas (1024x512) has texels narrower than these 128-px photos' pixels: the photos as they are
    level, info = rl.finest_level(mesh, SimpleNamespace(width=1024, height=512), cap.frames, -1)
    assert level == 0 and info["texel_pixels"] < 1.0
    # an atlas 32x coarser: texels several pixels wide; the coarsest level whose pixels are no larger than them
    level, info = rl.finest_level(mesh, SimpleNamespace(width=32, height=16), cap.frames, -1)
    assert level >= 2 and 1.0 <= info["level_texel_pixels"] < 2.0, info
    assert info["size"] == [128 >> level, 128 >> level] and f"level {level}" in info["why"]
    assert rl.finest_level(mesh, SimpleNamespace(width=32, height=16), cap.frames, 0)[0] == 0  # as asked


def test_blur_levels_run_coarse_to_fine_on_the_pyramid():
    frames = [SimpleNamespace(intrinsics=SimpleNamespace(width=3072, height=2048))]
    assert rl.level_schedule([2.0, 1.0, 0.5], 2, frames, True) == [(4, 0.5), (3, 0.5), (2, 0.5)]
    assert rl.level_schedule([2.0, 1.0, 0.5], 2, frames, False) == [(2, 2.0), (2, 1.0), (2, 0.5)]
    assert rl.level_schedule([3.0, 0.0], 0, frames, True) == [(0, 3.0), (0, 0.0)]  # no finest blur to scale by
    # a coarse level keeps the short side at least MIN_LEVEL_SIDE pixels: 2048 >> 5 = 64, 2048 >> 6 = 32
    assert rl.level_schedule([8.0, 0.5], 2, frames, True) == [(5, 8.0 / 8), (2, 0.5)]


def test_a_levels_cameras_are_the_photos_at_half_the_scale_per_level(sphere):
    from texstream.render.camera import ImageInfo, PhotoFrame, image_infos

    _, cap = sphere
    infos = image_infos([PhotoFrame.from_capture_frame(f) for f in cap.frames], None, None, 0.0, 0)
    assert infos.dtype == ImageInfo.numpy_dtype()
    sizes = np.array([[32, 32]] * len(cap.frames))
    down = rl.rescale_infos(infos, sizes, 0.25)
    assert np.array_equal(down["fx"], infos["fx"] / 4) and np.array_equal(down["cx"], infos["cx"] / 4)  # exact
    assert (down["width"] == 32).all() and np.array_equal(down["rot"], infos["rot"])
    back = rl.rescale_infos(down, np.array([[128, 128]] * len(cap.frames)), 4.0)
    assert np.array_equal(back["fx"], infos["fx"]) and np.array_equal(back["cy"], infos["cy"])


def _refine(sphere, tmp_path, capture_dir, **options):
    from texstream.geometry.refine import RefineConfig, refine_stage

    root, _ = sphere
    cfg = RefineConfig(mesh=False, holdout_every=0, iterations=4, normal_iterations=0, intensity_iterations=0,
                       **options)
    refine_stage(capture_dir, root / "ground_truth", tmp_path / "refined", cfg, device=SCENE_DEVICE)
    return json.loads((tmp_path / "refined" / "refine.json").read_text())  # the summary with its trace


def test_a_coarse_level_that_moves_too_little_skips_the_finer_levels_and_says_why(sphere, tmp_path):
    root, _ = sphere
    # the true cameras: the coarse level moves them by about a pixel of these tiny photos (measured 1.4 px; blur 2
    # on the full photos, the old schedule, 1.0 px): its steps follow the 8-bit photos' aliasing, not a pose
    # error. A threshold above that skips the finer levels; the trace and the summary say so
    s = _refine(sphere, tmp_path, root, min_move=20.0)
    finer = s["levels"]["finer_levels"]
    assert finer["ran"] is False and "less than 20: the finer levels skipped" in finer["reason"], finer
    assert max(finer["moved_finest_px"].values()) < 20.0
    assert s["levels"]["ran"] == 1 and {r["photo_level"] for r in s["trace"]} == {1}  # 128 px: a 64 px coarse level
    assert len(s["trace"]) == 4 and [lv["photo_level"] for lv in s["levels"]["schedule"]] == [1, 1, 0]
    assert "128x128 (level 0" in s["resolution"] and "finer levels skipped" in s["resolution"]


def test_moved_cameras_run_the_finer_levels(sphere, tmp_path):
    import dataclasses

    from texstream.calib.lights import colocated_light
    from texstream.capture.capture_json import Capture, write_capture

    root, cap = sphere
    frames = []
    for f in cap.frames:  # every camera slid sideways by 1% of its distance: about 2 px of these photos
        c = f.center + 0.01 * np.linalg.norm(f.center) * np.asarray(f.R)[0]
        t = -np.asarray(f.R) @ c
        frames.append(dataclasses.replace(f, t=t, light=colocated_light(f.R, t, f.light.intensity),
                                          file_path=str(root / f.file_path),
                                          mask_path=None if f.mask_path is None else str(root / f.mask_path)))
    moved = tmp_path / "moved"
    write_capture(Capture(root=moved, frames=frames, extra=cap.extra), moved)
    s = _refine(sphere, tmp_path, moved)
    finer = s["levels"]["finer_levels"]
    assert finer["ran"] is True and max(finer["moved_finest_px"].values()) >= 0.25, finer  # the default rule
    assert s["levels"]["ran"] == 3 and len(s["trace"]) == 3 * 4
    assert s["residual_after"]["fit_rms"] < s["residual_before"]["fit_rms"]


def test_the_run_says_which_resolution_each_stage_used(tmp_path):
    from texstream.pipelines.resolutions import HELDOUT_LINE, resolutions_html, stage_resolutions

    (tmp_path / "model.json").write_text(json.dumps({"photos": {"resolution": {
        "level": 1, "size": [1536, 1024], "texel_pixels": 5.1, "requested": -1}}}))
    stages = [{"name": "ingest", "status": "ran", "summary": {}},
              {"name": "register", "status": "ran", "summary": {"resolution": "SIFT on 1600x1067 of 3072x2048"}},
              {"name": "mesh", "status": "ran", "summary": {"dense": {"level": 2, "matched_size": [768, 512],
                                                                      "depths": 192, "points": 114281}}},
              {"name": "refine", "status": "skipped", "summary": {"resolution": "768x512 (level 2)"}}]
    lines = stage_resolutions(stages, tmp_path)
    assert list(lines) == ["register", "mesh", "refine", "fit", "report"]
    assert lines["mesh"].startswith("dense stereo on 768x512 (level 2") and "192 depth planes, 114,281 points" in lines["mesh"]
    assert lines["refine"].endswith("(unchanged since the last run)")
    assert lines["fit"].startswith("1536x1024 (level 1; auto: texels 5.10 px") and lines["report"] == HELDOUT_LINE
    assert "<td>register</td><td>SIFT on 1600x1067 of 3072x2048</td>" in resolutions_html(lines)


def test_a_coarse_level_samples_a_coarser_bake_of_the_same_charts(sphere):
    from texstream.geometry.bake import TexelBake
    from texstream.geometry.mesh_io import load_mesh

    root, _ = sphere
    mesh = load_mesh(root / "ground_truth" / "mesh.obj")
    bake = TexelBake.load(root / "ground_truth" / "bake.npz")
    assert rl.coarse_bake(mesh, bake, 0, SCENE_DEVICE) is bake  # the finest level: the atlas's own
    coarse = rl.coarse_bake(mesh, bake, 2, SCENE_DEVICE)
    assert (coarse.width, coarse.height) == (bake.width // 4, bake.height // 4)
    # texels 4x wider: a sixteenth as many (chart borders and faces claiming a texel of their own add a few)
    ratio = coarse.covered.sum() / bake.covered.sum()
    assert 1 / 16 <= ratio < 1.3 / 16, ratio
    assert set(np.unique(coarse.face[coarse.covered])) == set(range(len(mesh.faces)))  # every face sampled


def test_a_level_stops_once_its_objective_settled_and_threads_change_no_bit(tmp_path):
    # rel_tol 0.5: the second iteration of a level lowers the objective by far less than half, so every level
    # stops there; two threads split the kernels' photos and texels and give the one thread's result exactly
    from conftest import tiny_sphere_capture
    from texstream.geometry.refine import RefineConfig, refine_stage

    root = tiny_sphere_capture(tmp_path, photos=6, image_size=32)
    runs = []
    for threads in (1, 2):
        cfg = RefineConfig(holdout_every=0, min_move=0.0, rel_tol=0.5, threads=threads, normal_iterations=0)
        refine_stage(root, root / "ground_truth", tmp_path / str(threads), cfg, device="cpu")
        runs.append([(tmp_path / str(threads) / name).read_text() for name in ("refine.json", "capture.json")])
    one = json.loads(runs[0][0])
    assert one["levels"]["iterations"] == [2, 2, 2] and len(one["trace"]) == 6
    assert [t["iteration"] for t in one["trace"]] == [0, 1] * 3
    two = json.loads(runs[1][0])
    for s in (one, two):
        s.pop("seconds")
    assert two == one and runs[1][1] == runs[0][1]
