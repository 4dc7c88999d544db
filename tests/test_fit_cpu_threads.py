"""A fit on the CPU on worker threads (``stream.cpu_threads``, fit/multi/cpu_threads.py): when the threads are
used, and that a fit on two threads writes the one-thread fit's model to the bit."""

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
    (2, 9580, {}, {"resuming": True}, 1),  # an untiled fit's checkpoint
])
def test_threads_chosen(monkeypatch, cores, texels, stream, other, expected):
    monkeypatch.setattr(cpu_threads_module, "usable_cpus", lambda: cores)
    prob = fake_problem(texels, other.get("device", "cpu"), other.get("residency", "device"))
    n, why = cpu_threads(prob, FitConfig(stream=StreamConfig(**stream)), resuming=other.get("resuming", False))
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


def test_texstream_fit_on_two_cpu_threads_writes_the_one_thread_model(capture_dir, tmp_path, capsys):
    """``texstream fit`` with ``--stream.cpu-threads`` 2 and 1: the same maps to the bit, the same iterations and
    the same trace, the threads recorded in model.json."""
    import OpenImageIO as oiio

    from texstream.pipelines.cli import main

    def fit(threads: int):
        out = tmp_path / f"model_t{threads}"
        code = main(["fit", str(capture_dir), "--mesh", str(capture_dir / "ground_truth"), "-o", str(out),
                     "--texture-size", "64", "--renders", "0", "--max-iterations", "12", "--materials.mode", "off",
                     "--stream.shadow-map-size", "48", "--stream.cpu-threads", str(threads)])
        assert code == 0, capsys.readouterr().err
        maps = {p.name: oiio.ImageBuf(str(p)).get_pixels() for p in sorted(out.glob("*.exr"))}
        return maps, json.loads((out / "trace.json").read_text()), json.loads((out / "model.json").read_text())

    maps1, trace1, model1 = fit(1)
    maps2, trace2, model2 = fit(2)
    assert model1["tiles"] is None
    assert model2["tiles"]["devices"] == ["cpu", "cpu"] and model2["tiles"]["backend"] == "threads"
    assert maps1.keys() == maps2.keys() and "rho_d.exr" in maps1
    for name in maps1:
        np.testing.assert_array_equal(maps2[name], maps1[name], err_msg=name)
    assert [r["iteration"] for r in trace2] == [r["iteration"] for r in trace1]
    assert [r["samples"] for r in trace2] == [r["samples"] for r in trace1]
    # the trace's sums over texels are added per tile, then across the two: another order of float64 additions
    np.testing.assert_allclose([r["objective"] for r in trace2], [r["objective"] for r in trace1], rtol=1e-12)


def test_threaded_config_keeps_everything_else():
    cfg = FitConfig(max_iterations=7, stream=StreamConfig(shadow_map_size=48))
    assert dataclasses.replace(threaded_config(cfg, 2), stream=cfg.stream) == cfg
