"""benchmarks/relight_env.py: its scores, and its fit side run end to end with a stand-in for the model's CLI
(a perfect relightable model whose albedo is off by a known per-channel scale: the ambiguity the scores align)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import SCENE_DEVICE
from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import write_image
from texstream.capture.synthetic.env_capture import load_env_ground_truth
from texstream.geometry.bake import TexelBake

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("relight_env", ROOT / "benchmarks" / "relight_env.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_scores_align_a_per_channel_scale(bench):
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.1, 0.9, size=(8, 8, 3))
    mask = np.ones((8, 8), bool)
    s = bench.ViewScores()
    s.add("a", photo * [2.0, 1.0, 0.5], photo, mask)
    out = s.summary()
    np.testing.assert_allclose(out["channel_scale"], [0.5, 1.0, 2.0], rtol=1e-12)
    assert out["aligned_psnr_db"] > 100  # aligned: exact up to round-off
    assert out["psnr_db"] < 10
    mse = np.mean((photo * [2.0, 1.0, 0.5] - photo) ** 2)
    assert out["psnr_db"] == pytest.approx(10 * math.log10(1 / mse), abs=1e-9)


def _template_values(template: list[str], args: list[str]) -> dict:
    return {t[1:-1]: a for t, a in zip(template, args) if t.startswith("{")}


def test_fit_side_runs_with_a_stand_in_model(bench, tmp_path, monkeypatch):
    """The stand-in fit writes the true albedo x (2, 1, 0.5); its relight renders the true radiance of the target
    capture (the ground truth's texture): the relit scores are exact, the albedo error 0 after the scale."""
    args = type("A", (), {"device": SCENE_DEVICE, "env_grid": 8})
    caps = bench.captures(tmp_path, "sphere", 0.02, ["sky", "studio"], args)
    calls = []

    def stand_in(argv, log):
        calls.append(argv)
        if argv[0] == "fit":
            v = _template_values(bench.FIT_ARGS, argv)
            Path(v["model"]).mkdir()
            albedo = load_env_ground_truth(v["capture"])["albedo"] * np.array([2.0, 1.0, 0.5], np.float32)
            write_image(Path(v["model"]) / bench.MODEL_ALBEDO_FILES[0], albedo, bits=32)
        else:
            v = _template_values(bench.RELIGHT_ARGS, argv)
            render = bench.texture_renderer(v["capture"], load_env_ground_truth(v["capture"])["radiance"],
                                            SCENE_DEVICE)
            for f in read_capture(v["capture"]).frames:
                write_image(Path(v["out"]) / bench.RELIT_FILE.format(frame=f.name), render(f), bits=32)
        return 1.0

    monkeypatch.setattr(bench, "texstream", stand_in)
    fits = bench.fit_and_relight(caps, "sky", tmp_path, "sphere", SCENE_DEVICE)
    assert len(calls) == 2 + 2 * 2  # two fits, each relit under both environments
    fit_calls = [c for c in calls if c[0] == "fit"]
    true_env = str(tmp_path / "sphere_sky" / "ground_truth" / "environment.exr")
    assert fit_calls[1][len(bench.FIT_ARGS):] == bench.fill(bench.TRUE_LIGHT_ARGS, env_file=true_env)
    assert len(fit_calls[0]) == len(bench.FIT_ARGS)
    for kind in ("estimated_light", "true_light"):
        for env in ("sky", "studio"):
            r = fits[kind]["relit"][env]
            assert r["views"] == caps[env]["photos"] and "missing_renders" not in r
            assert r["aligned_psnr_db"] > 100  # the photos are these renders, to float32
        alb = fits[kind]["albedo"]
        np.testing.assert_allclose(alb["channel_scale"], [0.5, 1.0, 2.0], rtol=1e-5)
        assert all(m["relative_rms"] < 1e-5 and m["interior_relative_rms"] < 1e-5 and m["texels_off_2x"] == 0
                   for m in alb["materials"].values())
    assert bench.targets(fits, "sky")["met"]
    assert "| sphere | estimated_light |" in bench.table({"scenes": {"sphere": {"fits": fits}}})
    bake = TexelBake.load(tmp_path / "sphere_sky" / "ground_truth" / "bake.npz")
    assert fits["true_light"]["albedo"]["materials"]["plastic"]["texels"] == bake.n_covered
