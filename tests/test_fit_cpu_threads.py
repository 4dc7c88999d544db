"""A fit on the CPU on worker threads (``stream.cpu_threads``, fit/multi/cpu_threads.py): when the threads are
used, that a default fit on two threads writes the one-thread fit's model to the bit, and that a fit on
threads interrupted after a checkpoint resumes to the uninterrupted model (on two threads or on one)."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest

from texstream.fit.optim.fitter import FitConfig
from texstream.fit.stream.config import StreamConfig
from texstream.fit.stream.penalties import PenaltyConfig
import texstream.fit.multi.cpu_threads as cpu_threads_module
from texstream.fit.multi.cpu_threads import cpu_threads, threaded_config


def fake_problem(n=9580, device="cpu", residency="device"):
    """What :func:`cpu_threads` reads of a StreamProblem (texel count, device, photo residency)."""
    return SimpleNamespace(n=n, device=device, photos=SimpleNamespace(residency=residency))


@pytest.mark.parametrize("cores,texels,stream,other,expected", [
    (2, 9580, {}, {}, 2),  # the demo scene on the 2-core box
    (16, 9580, {}, {}, 4),  # 2,000 texels or more per thread
    (16, 10 ** 6, {}, {}, 8),  # at most MAX_AUTO_THREADS
    (1, 9580, {}, {}, 1),  # one core
    (2, 3000, {}, {}, 1),  # too few texels for two
    (2, 3000, {"cpu_threads": 2}, {}, 2),  # asked for
    (2, 9580, {"cpu_threads": 1}, {}, 1),
    (2, 9580, {"tiles": 3}, {}, 1),  # the user's own tiles
    (2, 9580, {"model_lookup": "bilinear"}, {}, 1),  # couples the texels
    (2, 9580, {}, {"device": "cuda:0"}, 1),
    (2, 9580, {}, {"residency": "host"}, 1),  # one shared window of streamed photos
])
def test_threads_chosen(monkeypatch, cores, texels, stream, other, expected):
    monkeypatch.setattr(cpu_threads_module, "usable_cpus", lambda: cores)
    prob = fake_problem(texels, other.get("device", "cpu"), other.get("residency", "device"))
    n, why = cpu_threads(prob, FitConfig(stream=StreamConfig(**stream)))
    assert n == expected and why


def test_laplacian_keeps_one_thread(monkeypatch):
    monkeypatch.setattr(cpu_threads_module, "usable_cpus", lambda: 2)
    assert cpu_threads(fake_problem(), FitConfig(penalties=PenaltyConfig(laplacian_weight=0.1)))[0] == 1


def test_threaded_config_tiles_on_the_cpu():
    cfg = threaded_config(FitConfig(), 3)
    assert cfg.stream.tiles == 3 and cfg.stream.devices == "cpu,cpu,cpu"


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    """A small ornament written as a capture folder (float EXR photos, masks)."""
    from conftest import DEVICES, SCENE_DEVICE
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    if "cpu" not in DEVICES:
        pytest.skip("this machine's Warp has no CPU compiler")
    out = tmp_path_factory.mktemp("ornament") / "capture"
    synthesize("ornament", out, SynthConfig(device=SCENE_DEVICE, preview=False, scale=0.02, photos=10,
                                            image_size=40, progress=False))
    return out


FIT_ARGS = ["--texture-size", "64", "--renders", "0", "--max-iterations", "12", "--sync-every", "2",
            "--stream.shadow-map-size", "48", "--materials.validation-every", "4", "--materials.max-materials", "1",
            "--materials.iterations", "4"]
"""a short fit with the defaults otherwise: the materials choice before the fit, whose validation split's fit
the main fit starts from (every 4th of the 10 photos validates: the default 8th would leave one, too few to
split; one material and 4 iterations keep the choice short), a checkpoint at every stopping test (every 2
iterations)"""


def fit_cli(capture_dir, out, *extra):
    """``texstream fit`` of ``capture_dir`` into ``out``: (EXR maps by name, trace, model.json)."""
    import OpenImageIO as oiio

    assert fit_exit_code(capture_dir, out, *extra) == 0
    maps = {p.name: oiio.ImageBuf(str(p)).get_pixels() for p in sorted(out.glob("*.exr"))}
    return maps, json.loads((out / "trace.json").read_text()), json.loads((out / "model.json").read_text())


def fit_exit_code(capture_dir, out, *extra) -> int:
    from texstream.pipelines.cli import main

    return main(["fit", str(capture_dir), "--mesh", str(capture_dir / "ground_truth"), "-o", str(out), *FIT_ARGS,
                 *extra])


def cores(monkeypatch, n: int) -> None:
    """A machine of ``n`` cores for ``stream.cpu_threads`` 0, and the small ornament's ~2,000 texels worth
    two threads (below MIN_TEXELS_PER_THREAD a thread is not taken)."""
    monkeypatch.setattr(cpu_threads_module, "usable_cpus", lambda: n)
    monkeypatch.setattr(cpu_threads_module, "MIN_TEXELS_PER_THREAD", 100)


@pytest.fixture(scope="module")
def one_thread_model(capture_dir, tmp_path_factory):
    return fit_cli(capture_dir, tmp_path_factory.mktemp("one") / "model", "--stream.cpu-threads", "1")


def assert_same_model(got, ref):
    """The maps to the bit, the same iterations, the trace's objectives to 1e-12 (its sums over texels are
    added per tile, then across tiles: another order of float64 additions)."""
    (maps, trace, _), (maps_ref, trace_ref, _) = got, ref
    assert maps.keys() == maps_ref.keys() and "rho_d.exr" in maps
    for name in maps:
        np.testing.assert_array_equal(maps[name], maps_ref[name], err_msg=name)
    assert [r["iteration"] for r in trace] == [r["iteration"] for r in trace_ref]
    assert [r["samples"] for r in trace] == [r["samples"] for r in trace_ref]
    np.testing.assert_allclose([r["objective"] for r in trace], [r["objective"] for r in trace_ref], rtol=1e-12)


def test_a_default_fit_on_two_cores_takes_two_threads_and_writes_the_one_thread_model(
        capture_dir, one_thread_model, tmp_path, monkeypatch):
    """``texstream fit`` with its defaults on a 2-core CPU: two threads (the warm start from the materials
    choice's split and the checkpoint kept), the maps of ``--stream.cpu-threads 1`` to the bit."""
    from texstream.fit.multi import tiles

    cores(monkeypatch, 2)
    real, calls = tiles.run_tiled_fit, []
    monkeypatch.setattr(tiles, "run_tiled_fit", lambda *a, **kw: calls.append(kw) or real(*a, **kw))
    got = fit_cli(capture_dir, tmp_path / "model")
    assert one_thread_model[2]["tiles"] is None
    assert got[2]["tiles"]["devices"] == ["cpu", "cpu"] and got[2]["tiles"]["backend"] == "threads"
    assert len(calls) == 1 and calls[0]["p0"] is not None and calls[0]["checkpoint"] is not None
    assert_same_model(got, one_thread_model)


def test_a_fit_on_two_threads_resumes_after_a_kill(capture_dir, one_thread_model, tmp_path, monkeypatch, capsys):
    """A fit on two threads stopped right after its second checkpoint (iteration 4; what a kill before the next
    write leaves), rerun: it resumes from iteration 4 and writes the uninterrupted model, on two threads and on
    one (a machine of one core: the checkpoint is in the untiled texel order, and its key holds no thread count)."""
    import shutil

    from texstream.fit.common.setup import Checkpoint

    real_save, saves = Checkpoint.save, []

    def save_then_stop(self, state):
        real_save(self, state)
        saves.append(int(state["iteration"]))
        if len(saves) == 2:
            raise KeyboardInterrupt

    cores(monkeypatch, 2)
    monkeypatch.setattr(Checkpoint, "save", save_then_stop)
    assert fit_exit_code(capture_dir, tmp_path / "model") == 130  # the command's exit code after Ctrl-C
    monkeypatch.setattr(Checkpoint, "save", real_save)
    checkpoint = tmp_path / ".model.checkpoint.npz"
    assert saves == [2, 4] and checkpoint.is_file() and not (tmp_path / "model").exists()
    shutil.copyfile(checkpoint, tmp_path / ".on_one_core.checkpoint.npz")  # the same state for the second rerun
    for name, n in [("model", 2), ("on_one_core", 1)]:
        cores(monkeypatch, n)
        capsys.readouterr()
        got = fit_cli(capture_dir, tmp_path / name)
        said = capsys.readouterr().out
        assert f"resuming from checkpoint {tmp_path / f'.{name}.checkpoint.npz'}: 4 iterations done" in said, said
        assert not (tmp_path / f".{name}.checkpoint.npz").exists()
        assert (got[2]["tiles"] is None) == (n == 1)
        assert_same_model(got, one_thread_model)


def test_threaded_config_keeps_everything_else():
    cfg = FitConfig(max_iterations=7, stream=StreamConfig(shadow_map_size=48))
    assert dataclasses.replace(threaded_config(cfg, 2), stream=cfg.stream) == cfg
