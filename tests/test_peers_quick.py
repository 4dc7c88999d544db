"""The peers of benchmarks/peers/ (issue 19) still run: ``run.py --quick`` on the toy ornament.

Asserts only that each peer works on the toy case (scale 0.01, 120 photos: 105 fitted, 15 held out,
968 texels, clean photos), not how fast it is (speed lives in the benchmark's JSON and docs/peers.md).
CPU only: the scipy peer has no GPU path, and the GPU study is one command run on the GPU machine.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# scipy, torch and mitsuba come with the test extra (pyproject.toml): no skip when they are missing, the
# test fails instead, so CI cannot pass without running the peers


def test_every_peer_fits_the_toy_ornament(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks" / "peers"))
    try:
        import run as peers_run

        peers_run.main(["--quick", "--out", str(tmp_path)])
    finally:
        sys.path.remove(str(ROOT / "benchmarks" / "peers"))
        for name in ("run", "common", "peer_texstream", "peer_scipy", "peer_torch", "peer_mitsuba"):
            sys.modules.pop(name, None)  # generic names: leave no trace for other tests
    res = json.loads((tmp_path / "peers.json").read_text())
    runs = res["datasets"]["clean"]
    assert set(runs) == set(peers_run.METHODS)
    for name, r in runs.items():
        assert "error" not in r, f"{name} failed: {r.get('error')}"
        tr = r["trace"]
        best = max(x["heldout_psnr_db"] for x in tr)
        if name == "mitsuba":
            # its own BSDF and start (no lobe): the held-out PSNR must rise above its start by 1 dB
            # (measured +2.2 dB; a broken gradient, UV or camera convention leaves it at or below the start)
            assert best >= tr[0]["heldout_psnr_db"] + 1.0, (name, best, tr[0]["heldout_psnr_db"])
            continue
        # the Lafortune peers start from texstream's percentile guess, 29.9 dB held out on this toy case
        # (every fit's later lobes lose held-out PSNR: too few photos per texel); 0.4 dB below it allows for
        # another platform's float rounding, while a broken sample or scoring path renders the wrong image
        assert best >= 29.5, (name, best)
        # the optimizer works: the fitted samples' PSNR rises at least 2 dB above the start (measured
        # +3.2 dB for L-BFGS, which stalls at the bounds, to +7.8 dB for texstream's LM)
        assert tr[-1]["train_psnr_db"] >= tr[0]["train_psnr_db"] + 2.0, (name, tr[0]["train_psnr_db"],
                                                                          tr[-1]["train_psnr_db"])


def test_mitsuba_scene_matches_texstreams_renderer():
    """The Mitsuba peer's scene (mesh, UV flip, cameras, point light) renders what texstream's renderer does:
    a diffuse BSDF with the ground-truth albedo texture against texstream's render of rho_s = 0."""
    import numpy as np

    sys.path.insert(0, str(ROOT / "benchmarks" / "peers"))
    try:
        import common
        import peer_mitsuba

        peer_mitsuba.prepare_llvm()
        import drjit as dr
        import mitsuba as mi

        from texstream.fit.stages.stage import render_model

        mi.set_variant("llvm_ad_rgb")
        dr.set_thread_count(1)
        data = common.load_data("clean", 0.01, 120)
        gt = data.scene.params.copy()
        gt[..., 3:6] = 0.0  # no lobe: a Lambertian surface both renderers agree on exactly
        ms = peer_mitsuba.MitsubaScene(data, gt[..., 0:3] * np.pi, None, None, data.held_frames, diffuse_only=True)
        for k, frame in enumerate(data.held_frames):
            ref, mask = render_model(data.scene.mesh, gt, data.scene.layout, frame, "cpu")
            img = np.array(ms.render(k))
            mse = float(np.mean((img[mask] - ref[mask]) ** 2))
            # 40 dB: the renderers differ only on a few silhouette and shadow-edge pixels (63-138 dB measured);
            # a wrong UV flip, camera axis or light falloff moves other albedos or brightness onto most pixels
            assert 10 * np.log10(1.0 / max(mse, 1e-30)) >= 40.0, (k, mse)
    finally:
        sys.path.remove(str(ROOT / "benchmarks" / "peers"))
        for name in ("run", "common", "peer_texstream", "peer_scipy", "peer_torch", "peer_mitsuba"):
            sys.modules.pop(name, None)
