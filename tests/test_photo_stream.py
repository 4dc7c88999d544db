"""Photo set-up and streaming (fit/photo_stream.py, PhotoSet): batched depth and shadow maps equal the
per-photo ones, cropping keeps every sample, and photos streamed from disk, held in host memory or on
the device give the same fit."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import warp as wp

from texstream.core.errors import InputError
from texstream.fit.optim.fitter import FitConfig, initial_guess, run_fit
from texstream.render.visibility import depth_map_kernel
from texstream.fit.stream.photo_stream import choose_residency
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.problem import PhotoFrame
from texstream.fit.stages.stage import build_problem, photo_files

# small maps and few photos keep the CPU ray casts of each test to a fraction of a second
SHADOW = 48


SMALL = dict(scale=0.02, photos=10, image_size=40, progress=False)


@pytest.fixture(scope="module")
def scene():
    """(mesh, bake, frames, images, masks) of a small ornament rendered in memory."""
    from conftest import SCENE_DEVICE
    from texstream.capture.synthetic.synth import SynthConfig, render_scene

    sc = render_scene("ornament", SynthConfig(device=SCENE_DEVICE, **SMALL))
    return sc.mesh, sc.bake, sc.frames, sc.images, sc.masks


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    """The small ornament written as a capture folder (float EXR photos, masks)."""
    from conftest import SCENE_DEVICE
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("ornament") / "capture"
    synthesize("ornament", out, SynthConfig(device=SCENE_DEVICE, preview=False, **SMALL))
    return out


@pytest.fixture(scope="module")
def disk_scene(capture_dir):
    """(capture, mesh, bake, frames, images, masks) of the capture folder, photos also read into memory."""
    from texstream.capture.capture_json import read_capture
    from texstream.fit.stages.stage import load_geometry, load_photos

    capture = read_capture(capture_dir)
    mesh, bake = load_geometry(capture_dir / "ground_truth", 64, "cpu")
    images, masks = load_photos(capture, capture.frames)
    return capture, mesh, bake, capture.frames, images, masks


def photo_set(scene, device, **stream):
    mesh, bake, frames, images, masks = scene
    cfg = StreamConfig(shadow_map_size=SHADOW, **stream)
    return PhotoSet([PhotoFrame.from_capture_frame(f) for f in frames], images, mesh.vertices, mesh.faces,
                    masks=masks, config=cfg, device=device)


def per_photo_maps(ps: PhotoSet, masks, device):
    """The maps as the set-up made them before batching: one depth-map launch per photo and camera."""
    n, h, w, s = ps.n, ps.hmax, ps.wmax, ps.shadow_side
    depth = np.zeros((n, h, w), np.float32)
    shadow = np.full((n, s, s), np.inf, np.float32)
    for k, r in enumerate(ps.infos_host):
        buf = wp.zeros((h, w), dtype=wp.float32, device=device)
        wp.launch(depth_map_kernel, dim=(int(r["height"]), int(r["width"])), device=device,
                  inputs=[ps.mesh.id, wp.mat33(*r["rot"].reshape(-1)), wp.vec3(*r["trans"]), float(r["fx"]),
                          float(r["fy"]), float(r["cx"]), float(r["cy"]), 0, int(r["width"]), int(r["height"]),
                          0.0, buf])
        depth[k] = np.where(masks[k], buf.numpy(), 0.0) if masks[k] is not None else buf.numpy()
        if r["has_shadow"]:
            sb = wp.zeros((s, s), dtype=wp.float32, device=device)
            wp.launch(depth_map_kernel, dim=(s, s), device=device,
                      inputs=[ps.mesh.id, wp.mat33(*r["sh_rot"].reshape(-1)), wp.vec3(*r["sh_trans"]),
                              float(r["sh_fx"]), float(r["sh_fy"]), float(r["sh_cx"]), float(r["sh_cy"]),
                              int(r["sh_ortho"]), s, s, float(np.inf), sb])
            shadow[k] = sb.numpy()
    return depth, shadow


def test_batched_maps_equal_the_per_photo_maps(scene, device):
    ps = photo_set(scene, device, crop_photos=False)
    depth, shadow = per_photo_maps(ps, scene[4], device)
    assert ps.infos_host["has_shadow"].all()
    np.testing.assert_array_equal(ps.depth.numpy(), depth)
    np.testing.assert_array_equal(ps.shadow.numpy(), shadow)


def test_cropped_photos_and_depth_maps_are_crops_of_the_whole_ones(scene, device):
    whole = photo_set(scene, device, crop_photos=False)
    crop = photo_set(scene, device)
    assert crop.hmax * crop.wmax < whole.hmax * whole.wmax  # the object does not fill the frame
    imgs, dm = whole.images.numpy(), whole.depth.numpy()
    for k, (x0, y0, w, h) in enumerate(crop.crops):
        # the crop's camera casts the same rays (principal point shifted exactly in float32): same depths
        np.testing.assert_array_equal(crop.depth.numpy()[k, :h, :w], dm[k, y0:y0 + h, x0:x0 + w])
        np.testing.assert_array_equal(crop.images.numpy()[k, :h, :w], imgs[k, y0:y0 + h, x0:x0 + w])
        outside = dm[k].copy()
        outside[y0:y0 + h, x0:x0 + w] = 0
        assert not outside.any()  # no pixel outside the crop sees the object


def test_cropped_photos_keep_every_sample(scene, device):
    mesh, bake, frames, images, masks = scene
    cfg = FitConfig(optimizer="lm", max_iterations=1, stream=StreamConfig(shadow_map_size=SHADOW, crop_photos=False))
    whole = build_problem(mesh, bake, frames, images, masks, cfg, device)
    crop = build_problem(mesh, bake, frames, images, masks,
                         dataclasses.replace(cfg, stream=dataclasses.replace(cfg.stream, crop_photos=True)), device)
    p0, count_whole = initial_guess(whole, cfg)
    _, count_crop = initial_guess(crop, cfg)
    np.testing.assert_array_equal(count_crop, count_whole)
    out = []
    for prob in (whole, crop):
        params = prob.new_storage(p0)
        f, g, st = prob.new_scalar(), prob.new_vec(), wp.zeros(prob.n, dtype=wp.vec4d, device=device)
        prob.evaluate(params, f, g, st)
        out.append((f.numpy(), g.numpy()))
    # a sample's projection is fx X / Z + cx: with cx less the crop's integer offset it rounds once more
    # differently (~1e-7 relative of the pixel coordinate), moving bilinear weights by as much
    scale = np.abs(out[0][0]).max()
    np.testing.assert_allclose(out[1][0], out[0][0], rtol=1e-4, atol=1e-6 * scale)
    gscale = np.abs(out[0][1]).max()
    np.testing.assert_allclose(out[1][1], out[0][1], rtol=1e-3, atol=1e-5 * gscale)


def fit(disk_scene, files, device, **stream):
    """A 3-iteration LM fit of the capture, from its files (``files``: True, or a PhotoFiles) or from the
    photos in memory; photos are decoded, not read from a cache, unless ``photo_cache`` says otherwise."""
    capture, mesh, bake, frames, images, masks = disk_scene
    stream.setdefault("photo_cache", "off")
    cfg = FitConfig(optimizer="lm", max_iterations=3, stream=StreamConfig(shadow_map_size=SHADOW, **stream))
    source = images if files is False else photo_files(capture, frames) if files is True else files
    prob = build_problem(mesh, bake, frames, source, None if files is False else masks, cfg, device)
    return prob, run_fit(prob, cfg)


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_photos_streamed_from_disk_are_decoded_once_into_a_cache(disk_scene, device, tmp_path, precision):
    """The first pass from disk fills the cache; later passes and later fits read it (no decoding) and fit
    to the same bits as decoding every pass; a ready cache also feeds a fit with the photos on the device."""
    import os

    capture, mesh, bake, frames, images, masks = disk_scene
    files = photo_files(capture, frames)
    files.cache_dir = tmp_path / "cache"  # the module's capture folder stays uncached for the other tests
    kw = dict(photo_residency="disk", photos_per_window=4, image_precision=precision)
    decoded, r_decoded = fit(disk_scene, True, device, **kw)
    first, r_first = fit(disk_scene, files, device, photo_cache="auto", **kw)
    cache = first.photos.loader.cache
    assert cache is not None and cache.ready and first.photos.loader.cached()
    assert [p.name for p in files.cache_dir.iterdir()] == [cache.path.name]  # no temporary file left
    np.testing.assert_array_equal(r_first.params, r_decoded.params)
    assert [r["objective"] for r in r_first.trace] == [r["objective"] for r in r_decoded.trace]
    again, r_again = fit(disk_scene, files, device, photo_cache="auto", **kw)
    assert again.photos.loader.cached() and again.photos.loader.cache.path == cache.path
    np.testing.assert_array_equal(r_again.params, r_decoded.params)
    dev = dict(photo_residency="device", image_precision=precision)
    on_device, r_on_device = fit(disk_scene, True, device, **dev)
    from_cache, r_from_cache = fit(disk_scene, files, device, photo_cache="auto", **dev)
    np.testing.assert_array_equal(r_from_cache.params, r_on_device.params)
    # a photo edited since (its modification time) makes another cache; an unwritable folder none
    st = os.stat(files.paths[3])
    os.utime(files.paths[3], ns=(st.st_atime_ns, st.st_mtime_ns + 1))
    try:
        edited, _ = fit(disk_scene, files, device, photo_cache="auto", **kw)
        assert edited.photos.loader.cache.path != cache.path and edited.photos.loader.cached()
    finally:
        os.utime(files.paths[3], ns=(st.st_atime_ns, st.st_mtime_ns))
    # photo_cache on: a fit with the photos on the device writes the cache in the background
    files.cache_dir = tmp_path / "cache_on"
    dev_on, r_dev_on = fit(disk_scene, files, device, photo_cache="on", **dev)
    dev_on.photos.wait_for_cache()
    written = list(files.cache_dir.glob("photos-*.bin"))
    assert len(written) == 1 and not list(files.cache_dir.glob("*.tmp*"))
    np.testing.assert_array_equal(r_dev_on.params, r_on_device.params)

    def no_decoding(*args, **kw):
        raise AssertionError("a photo was decoded although the cache holds it")

    reread, r_reread = fit(disk_scene, dataclasses.replace(files, read_image=no_decoding, read_mask=no_decoding),
                           device, photo_cache="auto", **dev)
    np.testing.assert_array_equal(r_reread.params, r_on_device.params)
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the cache folder would go")
    files.cache_dir = blocked
    none, r_none = fit(disk_scene, files, device, photo_cache="auto", **kw)
    assert none.photos.loader.cache is None
    np.testing.assert_array_equal(r_none.params, r_decoded.params)


def test_streamed_from_disk_host_and_device_fits_agree(disk_scene, device):
    disk, r_disk = fit(disk_scene, True, device, photo_residency="disk", photos_per_window=4)
    host, r_host = fit(disk_scene, False, device, photo_residency="host", photos_per_window=4)
    assert (disk.photos.residency, host.photos.residency) == ("disk", "host")
    assert disk.photos.window == 4 and disk.photos.loader is not None and not hasattr(disk.photos, "host_images")
    # same windows, same summation order: the same parameters to the last bit
    np.testing.assert_array_equal(r_disk.params, r_host.params)
    assert [r["objective"] for r in r_disk.trace] == [r["objective"] for r in r_host.trace]
    # one window of all photos, decoded again every pass, sums as the photos resident on the device do
    dev, r_dev = fit(disk_scene, True, device, photo_residency="device")
    disk1, r_disk1 = fit(disk_scene, True, device, photo_residency="disk", photos_per_window=len(disk_scene[3]))
    assert dev.photos.residency == "device" and disk1.photos.residency == "disk"
    np.testing.assert_array_equal(r_disk1.params, r_dev.params)


@pytest.mark.parametrize("rank", [0, 1, 3])
def test_the_initial_guess_of_windows_is_the_one_pass_guess(scene, device, rank):
    """Windows carry each texel's 4 smallest samples per channel from one to the next: the starting parameters
    and sample counts of photos streamed 3 at a time are those of all photos on the device, to the bit."""
    mesh, bake, frames, images, masks = scene

    def start(**stream):
        cfg = FitConfig(optimizer="lm", init_rank=rank, stream=StreamConfig(shadow_map_size=SHADOW, **stream))
        prob = build_problem(mesh, bake, frames, images, masks, cfg, device)
        return prob.photos.window, initial_guess(prob, cfg)

    w_dev, (p_dev, n_dev) = start(photo_residency="device")
    w_win, (p_win, n_win) = start(photo_residency="host", photos_per_window=3)
    assert w_dev == len(frames) and w_win == 3
    np.testing.assert_array_equal(n_win, n_dev)
    np.testing.assert_array_equal(p_win, p_dev)


def test_a_memory_cap_below_the_photos_streams_them_from_disk(disk_scene, device):
    prob, res = fit(disk_scene, True, device, memory_limit_mb=0.05)
    ph = prob.photos
    assert ph.residency == "disk" and ph.window < ph.n
    assert "exceed" in ph.residency_reason
    assert np.isfinite(res.trace[-1]["objective"])


def test_automatic_residency_follows_the_memory_available():
    # sizes in bytes; 1 << 62 exceeds any machine's memory
    assert choose_residency("auto", "cpu", 1 << 20, 1 << 20, True)[0] == "device"
    assert choose_residency("auto", "cpu", 1 << 20, 1 << 20, True, limit_bytes=1 << 10)[0] == "disk"
    # photos given in memory are never read back from disk: windows from where they are
    assert choose_residency("auto", "cpu", 1 << 20, 1 << 20, False, limit_bytes=1 << 10)[0] == "host"
    assert choose_residency("disk", "cpu", 1, 1, True) == ("disk", "requested")
    assert choose_residency("auto", "cpu", 1 << 62, 1 << 62, True)[0] == "disk"
    # windows asked for (photos_per_window): from host memory when it holds them, else from disk
    assert choose_residency("auto", "cpu", 1 << 20, 1 << 20, True, windows=True)[0] == "host"
    assert choose_residency("auto", "cpu", 1 << 20, 1 << 62, True, windows=True)[0] == "disk"
    assert choose_residency("auto", "cpu", 1 << 20, 1 << 62, False, windows=True)[0] == "host"


def test_a_corrupt_photo_in_the_stream_fails_naming_it(disk_scene, device, tmp_path):
    capture, mesh, bake, frames, images, masks = disk_scene
    files = photo_files(capture, frames)
    bad = tmp_path / "broken.exr"
    bad.write_bytes(b"not an exr at all")
    files.paths = list(files.paths)
    files.paths[5] = bad
    cfg = FitConfig(optimizer="lm", max_iterations=1,
                    stream=StreamConfig(shadow_map_size=SHADOW, photo_residency="disk", photos_per_window=4))
    with pytest.raises(InputError, match="broken.exr"):
        prob = build_problem(mesh, bake, frames, files, None, cfg, device)
        run_fit(prob, cfg)


@pytest.mark.parametrize("keep_maps", [False, True])
def test_subsets_of_a_disk_stream_interleave_with_it(disk_scene, device, keep_maps, monkeypatch):
    """A subset shares the streamed set's window buffers (fit/materials.py fits part of the photos
    between passes over all of them): each pass still reads its own photos."""
    from texstream.fit.stream.problem import StreamProblem

    def passes(prob):
        sub = StreamProblem(prob.texels, prob.photos.subset([0, 2, 3, 7, 9]), prob.layout, prob.cfg, device)
        out = []
        for p in (prob, sub, prob, sub):
            params = p.new_storage(np.tile(p.layout.defaults(), (p.n, 1)))
            f, g, st = p.new_scalar(), p.new_vec(), wp.zeros(p.n, dtype=wp.vec4d, device=device)
            p.evaluate(params, f, g, st)
            out.append(f.numpy())
        return out

    import texstream.fit.stream.photo_set as problem

    monkeypatch.setattr(problem, "keep_maps_on_device", lambda *a: keep_maps)
    disk, _ = fit(disk_scene, True, device, photo_residency="disk", photos_per_window=3)
    assert disk.photos.maps_on_device == keep_maps
    host, _ = fit(disk_scene, False, device, photo_residency="host", photos_per_window=3)
    for a, b in zip(passes(disk), passes(host)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("precision", ["fp16", "fp32"])
@pytest.mark.parametrize("slots", [2, 3, 5])
def test_staged_upload_gives_the_cropped_photos(scene, device, precision, slots, monkeypatch):
    """The chunked upload through the ring of host buffers (the CUDA set-up, here also run on the CPU) gives
    each photo's crop, zero padded, in the image precision: half floats converted on the device round to
    nearest even as numpy does, so the bits are numpy's; the depth and shadow maps equal the set's. So
    do two sets uploaded together through the same buffers (the photo split's upload), with any number of
    buffers (more than the chunks, too)."""
    import texstream.fit.stream.photo_set as problem

    monkeypatch.setattr(problem, "UPLOAD_SLOTS", slots)

    ref = photo_set(scene, device, image_precision=precision)
    want = np.zeros((ref.n, ref.hmax, ref.wmax, 3), np.float16 if precision == "fp16" else np.float32)
    want_m = np.zeros((ref.n, ref.hmax, ref.wmax), np.uint8)
    for k, (x0, y0, w, h) in enumerate(ref.crops):
        want[k, :h, :w] = scene[3][k][y0:y0 + h, x0:x0 + w, :3]
        want_m[k, :h, :w] = scene[4][k][y0:y0 + h, x0:x0 + w]
    np.testing.assert_array_equal(ref.images.numpy(), want)
    halves = [(0, ref.n // 2), (ref.n // 2, ref.n)]
    layouts = {"one set": [(0, ref.n)], "two sets": halves}
    saved = problem.ARRAY_UPLOAD_CHUNK_BYTES  # the photos are arrays
    # chunks of 3 photos: both buffers, a short last one, and a set's first chunk in either buffer
    problem.ARRAY_UPLOAD_CHUNK_BYTES = 3 * ref.hmax * ref.wmax * 12
    try:
        for name, runs in layouts.items():
            sets = []
            for b, e in runs:
                ps = ref.subset(range(b, e))
                ps.loader = problem.PhotoLoader(scene[3][b:e], scene[4][b:e], ps.crops, ps.sizes)
                ps.timings = dict.fromkeys(ref.timings, 0.0)
                ps._init_device(defer_upload=True)
                sets.append(ps)
            interval = sys.getswitchinterval()
            try:
                problem.upload_photo_sets(sets, in_place=False)
            finally:
                for ps in sets:
                    ps.loader.close()
            assert sys.getswitchinterval() == interval, name  # the upload's shorter switch interval is undone
            for ps, (b, e) in zip(sets, runs):
                np.testing.assert_array_equal(ps.images.numpy(), want[b:e], err_msg=name)
                np.testing.assert_array_equal(ps.device_masks.numpy(), want_m[b:e], err_msg=name)
                np.testing.assert_array_equal(ps.depth.numpy(), ref.depth.numpy()[b:e], err_msg=name)
                np.testing.assert_array_equal(ps.shadow.numpy(), ref.shadow.numpy()[b:e], err_msg=name)
                assert ps.timings["upload"] > 0, name
    finally:
        problem.ARRAY_UPLOAD_CHUNK_BYTES = saved


def test_staged_upload_fails_on_a_bad_photo_with_nothing_left_running(scene, device):
    """A photo that fails in the middle of the upload raises its own error, and when it does no crop is still
    writing the host buffers (they are freed with the pipeline) and no copy is still reading them. Chunks of 3
    photos: photo 4 fails in the second chunk while the third chunk's crops (slowed to 0.2 s each) run."""
    import time

    import texstream.fit.stream.photo_set as problem

    ref = photo_set(scene, device)
    assert ref.n >= 9
    ps = ref.subset(range(ref.n))
    ps.loader = problem.PhotoLoader(scene[3], scene[4], ps.crops, ps.sizes)
    ps.timings = dict.fromkeys(ref.timings, 0.0)
    ps._init_device(defer_upload=True)
    fill, submit, submitted = ps.loader._fill_one, ps.loader.submit, []

    def failing(k, img, msk):
        if k == 4:
            raise InputError("photo 4 is bad", fix="leave it out")
        if 6 <= k <= 8:
            time.sleep(0.2)
        fill(k, img, msk)

    def recording(*args, **kwargs):
        futures = submit(*args, **kwargs)
        submitted.extend(futures)
        return futures

    ps.loader._fill_one, ps.loader.submit = failing, recording
    saved = problem.ARRAY_UPLOAD_CHUNK_BYTES
    problem.ARRAY_UPLOAD_CHUNK_BYTES = 3 * ref.hmax * ref.wmax * 12
    try:
        interval = sys.getswitchinterval()
        with pytest.raises(InputError, match="photo 4 is bad"):
            problem.upload_photo_sets([ps], in_place=False)
        assert len(submitted) >= 9 and all(f.done() for f in submitted)
        assert sys.getswitchinterval() == interval  # the upload's shorter switch interval is undone
    finally:
        problem.ARRAY_UPLOAD_CHUNK_BYTES = saved
        ps.loader.close()


def test_maps_launched_in_chunks_equal_one_launch(scene, device, monkeypatch):
    """Sets too large for one launch (MAX_LAUNCH_THREADS) make their maps a few photos at a time."""
    import texstream.fit.stream.photo_set as problem

    one = photo_set(scene, device)
    monkeypatch.setattr(problem, "MAX_LAUNCH_THREADS", 3 * one.hmax * one.wmax)
    chunked = photo_set(scene, device)
    np.testing.assert_array_equal(chunked.depth.numpy(), one.depth.numpy())
    np.testing.assert_array_equal(chunked.shadow.numpy(), one.shadow.numpy())


def test_fit_stage_streams_a_capture_from_disk_and_records_it(capture_dir, tmp_path):
    """``texstream fit`` under a memory cap: the photos stream from the capture's files, and
    model.json says so (residency, why, photos per window)."""
    import json

    from conftest import SCENE_DEVICE
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    cfg = FitStageConfig(texture_size=64, renders=1, device=SCENE_DEVICE)
    cfg.fit.max_iterations = 2
    cfg.fit.stream = StreamConfig(shadow_map_size=SHADOW, memory_limit_mb=0.05)
    fit_stage(capture_dir, capture_dir / "ground_truth", tmp_path / "model", cfg, progress=False)
    photos = json.loads((tmp_path / "model" / "model.json").read_text())["photos"]
    assert photos["residency"] == "disk" and "exceed" in photos["residency_reason"]
    assert 1 <= photos["photos_per_window"] < photos["fitted"]


def test_disk_stream_with_maps_kept_on_the_device_equals_recomputing_them(disk_scene, device, monkeypatch):
    """On CUDA, photos streamed from disk keep every depth and shadow map on the device when there is
    room (made once, masked per window); the maps are the recomputed ones, so the fit is the same."""
    import texstream.fit.stream.photo_set as problem

    monkeypatch.setattr(problem, "keep_maps_on_device", lambda *a: False)
    again, r_again = fit(disk_scene, True, device, photo_residency="disk", photos_per_window=4)
    monkeypatch.setattr(problem, "keep_maps_on_device", lambda *a: True)
    kept, r_kept = fit(disk_scene, True, device, photo_residency="disk", photos_per_window=4)
    assert kept.photos.maps_on_device and not again.photos.maps_on_device
    assert "kept on the device" in kept.photos.residency_reason
    np.testing.assert_array_equal(r_kept.params, r_again.params)
    assert [r["objective"] for r in r_kept.trace] == [r["objective"] for r in r_again.trace]


def test_uploads_at_once_share_the_short_switch_interval_and_restore_it():
    """Uploads on two threads overlap: the interval stays short until the last one ends, then is the one before
    (not the first upload's short value left behind by the second)."""
    import threading

    import texstream.fit.stream.photo_set as problem

    before = sys.getswitchinterval()
    first_in, second_done = threading.Event(), threading.Event()
    seen = []

    def first():
        with problem._short_switch_interval():
            first_in.set()
            second_done.wait(5)
            seen.append(sys.getswitchinterval())

    t = threading.Thread(target=first)
    t.start()
    first_in.wait(5)
    with problem._short_switch_interval():
        seen.append(sys.getswitchinterval())
    second_done.set()
    t.join(5)
    assert seen == [pytest.approx(problem.UPLOAD_SWITCH_INTERVAL_S)] * 2  # held in microseconds
    assert sys.getswitchinterval() == before
