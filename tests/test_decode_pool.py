"""Photo files decoded in worker processes (fit/decode_pool.py): the same bytes as threads, the same one-line
error for a bad photo, threads when the pool fails, and the texstream command's pool started with it and
stopped at its end."""

from __future__ import annotations

import numpy as np
import pytest

from texstream.core.errors import InputError
from texstream.core.progress import reporting
from texstream.fit.stream import decode_pool
from texstream.fit.stream.photo_stream import PhotoLoader
from texstream.render.camera import PhotoFrame

SMALL = dict(scale=0.02, photos=10, image_size=40, progress=False)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    """The small ornament as a capture folder (float EXR photos with masks)."""
    from conftest import SCENE_DEVICE
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("ornament") / "capture"
    synthesize("ornament", out, SynthConfig(device=SCENE_DEVICE, preview=False, **SMALL))
    return out


@pytest.fixture(scope="module", autouse=True)
def stop_the_pool():
    yield
    decode_pool.shutdown()


def files_and_sizes(capture_dir):
    from texstream.capture.capture_json import read_capture
    from texstream.fit.stages.stage import photo_files

    capture = read_capture(capture_dir)
    sizes = np.array([[p.height, p.width] for p in map(PhotoFrame.from_capture_frame, capture.frames)])
    return photo_files(capture, capture.frames), sizes


def fill(loader: PhotoLoader, n: int, shape, dtype):
    # a value no photo or padding has, so a slot left unwritten shows
    images, masks = np.full((n, *shape, 3), 7, dtype), np.full((n, *shape), 7, np.uint8)
    loader.fill(range(n), images, masks if loader.has_masks else None)
    return images, masks


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
@pytest.mark.parametrize("cropped", [True, False])
def test_processes_decode_the_same_bytes_as_threads(capture_dir, dtype, cropped):
    files, sizes = files_and_sizes(capture_dir)
    n, (h, w) = len(files), sizes.max(axis=0)
    crops = np.array([[2 + k % 3, 3 + k % 4, w - 9, h - 11] for k in range(n)]) if cropped else None
    threads = PhotoLoader(files, None, crops, sizes, 2, decoder="threads")
    processes = PhotoLoader(files, None, crops, sizes, 2, decoder="processes")
    assert (threads.processes, processes.processes) == (0, 2) and processes.has_masks
    by_threads, by_processes = fill(threads, n, (h, w), dtype), fill(processes, n, (h, w), dtype)
    assert processes.processes == 2  # the workers decoded (no fall back to threads)
    np.testing.assert_array_equal(by_processes[0], by_threads[0])
    np.testing.assert_array_equal(by_processes[1], by_threads[1])
    assert (by_processes[1] == 1).any() and (by_processes[1] == 0).any()
    threads.close()
    processes.close()


def test_a_bad_photo_fails_with_the_threads_one_line(capture_dir, tmp_path):
    files, sizes = files_and_sizes(capture_dir)
    bad = tmp_path / "broken.exr"
    bad.write_bytes(b"not an exr at all")
    files.paths = list(files.paths)
    files.paths[6] = bad
    errors = []
    for decoder in ("threads", "processes"):
        loader = PhotoLoader(files, None, None, sizes, 2, decoder=decoder)
        with pytest.raises(InputError, match="broken.exr") as e:
            fill(loader, len(files), tuple(sizes.max(axis=0)), np.float32)
        errors.append((e.value.one_line(), e.value.path, e.value.fix))
        assert loader.processes == (2 if decoder == "processes" else 0)  # a user error is not the pool's failure
        loader.close()
    assert errors[0] == errors[1]


def test_a_failed_pool_falls_back_to_threads(capture_dir, monkeypatch):
    files, sizes = files_and_sizes(capture_dir)
    shape = tuple(sizes.max(axis=0))
    expected = fill(PhotoLoader(files, None, None, sizes, 2, decoder="threads"), len(files), shape, np.float32)

    class Broken:
        def call(self, *args):
            raise decode_pool.WorkerFailed("EOFError: a worker was killed")

    monkeypatch.setattr(decode_pool, "start", lambda processes: Broken())
    loader = PhotoLoader(files, None, None, sizes, 2, decoder="processes")
    said = []
    with reporting(said.append):
        got = fill(loader, len(files), shape, np.float32)
    assert loader.processes == 0
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    assert any("a worker was killed" in line and "decoding in threads" in line for line in said)


def test_the_automatic_choice_is_processes_only_under_the_command(monkeypatch):
    monkeypatch.setattr(decode_pool, "_command_processes", 0)
    assert decode_pool.processes_for("auto") == 0  # called from Python: threads
    assert decode_pool.processes_for("processes", 3) == 3
    assert decode_pool.processes_for("threads", 3) == 0
    monkeypatch.setattr(decode_pool, "_command_processes", 12)
    assert decode_pool.processes_for("auto") == 12 and decode_pool.processes_for("auto", 5) == 5
    monkeypatch.setattr("os.cpu_count", lambda: decode_pool.MIN_CPUS - 1)
    assert decode_pool.default_processes() == 0
    monkeypatch.setattr("os.cpu_count", lambda: 64)
    assert decode_pool.default_processes() == decode_pool.MAX_PROCESSES


def test_the_fit_command_starts_its_decoders_and_stops_them(capture_dir, tmp_path, monkeypatch, capsys):
    """`texstream fit` on a machine with enough CPUs (pretended here) decodes in processes it started before
    its imports, fits the same model as threads, and leaves no pool running when it returns."""
    import json

    from texstream.pipelines.cli import main

    decode_pool.shutdown()  # the other tests' pool
    monkeypatch.setattr(decode_pool, "MIN_CPUS", 1)
    monkeypatch.setattr(decode_pool, "MAX_PROCESSES", 2)
    started = []  # the pools created
    real_init = decode_pool.WorkerPool.__init__
    monkeypatch.setattr(decode_pool.WorkerPool, "__init__", lambda self, n, r: started.append(n) or real_init(self, n, r))
    from conftest import SCENE_DEVICE

    common = ["fit", str(capture_dir), "--mesh", str(capture_dir / "ground_truth"), "--device", SCENE_DEVICE,
              "--max-iterations", "2", "--materials.mode", "off", "--traced-polish", "0",
              "--stream.photo-cache", "off"]
    assert main(common + ["-o", str(tmp_path / "auto")]) == 0
    assert started == [2] and decode_pool._pool is None and decode_pool._command_processes == 0
    assert main(common + ["-o", str(tmp_path / "threads"), "--stream.photo-decoder", "threads"]) == 0
    assert started == [2]  # no processes started for a fit told to decode in threads
    auto, threads = (json.loads((tmp_path / d / "model.json").read_text()) for d in ("auto", "threads"))
    assert auto["final"]["objective"] == threads["final"]["objective"]
    said = capsys.readouterr()
    assert "photo decoding processes failed" not in said.out + said.err
    from texstream.capture.imageio import read_image

    np.testing.assert_array_equal(read_image(tmp_path / "auto" / "rho_d.exr", linear=False),
                                  read_image(tmp_path / "threads" / "rho_d.exr", linear=False))


def test_a_killed_worker_leaves_the_pool_and_threads_decode(capture_dir):
    files, sizes = files_and_sizes(capture_dir)
    shape = tuple(sizes.max(axis=0))
    expected = fill(PhotoLoader(files, None, None, sizes, 2, decoder="threads"), len(files), shape, np.float32)
    pool = decode_pool.start(2)
    pool.workers[0].proc.kill()
    pool.workers[0].proc.wait()
    loader = PhotoLoader(files, None, None, sizes, 2, decoder="processes")
    got = fill(loader, len(files), shape, np.float32)
    assert loader.processes == 0 and pool.broken
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    assert decode_pool.start(2) is not pool  # a broken pool is replaced
    decode_pool.shutdown()


def test_workers_do_not_run_the_main_script(tmp_path):
    """A script without a main guard, run from a file or from stdin, decodes in processes without running
    itself again in the workers (they are not multiprocessing's spawned children)."""
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text(
        "import os, numpy as np\n"
        "from texstream.fit.stream import decode_pool\n"
        f"open({str(tmp_path / 'runs.txt')!r}, 'a').write(str(os.getpid()) + '\\n')\n"
        "pool = decode_pool.start(2)\n"
        "assert [w.call(os.getpid, ()) for w in pool.workers] != [os.getpid()] * 2\n"
        "decode_pool.shutdown()\n")
    subprocess.run([sys.executable, str(script)], check=True, timeout=120)
    subprocess.run([sys.executable, "-"], input=script.read_bytes(), check=True, timeout=120)
    assert len((tmp_path / "runs.txt").read_text().split()) == 2


@pytest.mark.parametrize("ext,bits", [(".png", 8), (".png", 16), (".jpg", 8), (".exr", 32)])
def test_processes_decode_every_photo_format_as_threads(tmp_path, ext, bits):
    """8-bit sRGB PNG and JPEG, 16-bit linear PNG, float EXR, with PNG masks: the workers' slots are the
    threads' bytes (the sRGB decode and the checks run in the worker)."""
    from texstream.capture.imageio import read_image, read_mask, write_image
    from texstream.fit.stream.photo_stream import PhotoFiles

    rng = np.random.default_rng(7)
    paths, masks = [], []
    for k in range(6):
        photo = rng.random((30 + k, 40, 3), dtype=np.float32)
        paths.append(write_image(tmp_path / f"photo_{k}{ext}", photo, bits=bits))
        mask = (rng.random((30 + k, 40, 1)) > 0.3).astype(np.float32).repeat(3, axis=2)
        masks.append(write_image(tmp_path / f"mask_{k}.png", mask, bits=8) if k % 2 == 0 else None)
    files = PhotoFiles(paths, masks, read_image, read_mask)
    sizes = np.array([[30 + k, 40] for k in range(6)])
    crops = np.array([[3, 2, 30, 25]] * 6)
    loaders = [PhotoLoader(files, None, crops, sizes, 2, decoder=d) for d in ("threads", "processes")]
    slots = [fill(loader, 6, (35, 40), np.float32) for loader in loaders]
    assert loaders[1].processes == 2  # the workers decoded (no fall back to threads)
    np.testing.assert_array_equal(slots[1][0], slots[0][0])
    np.testing.assert_array_equal(slots[1][1], slots[0][1])
    assert slots[0][0][:, :25, :30].any() and (slots[0][1][0] == 0).any()  # photos and masks really decoded
