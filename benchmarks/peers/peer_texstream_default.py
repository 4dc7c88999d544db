"""``texstream fit`` with its defaults, as a user runs it on a folder of photos.

The data set is written as a capture folder (``synthesize``, the photos identical to the in-memory ones
the other peers fit: checked) and the fit reads the fitted and validation photos from it: the held-out
photos are not in the folder. ``fit_stage`` runs with the command's defaults (``--model auto``: the model
choice's candidates, shared materials, lobe support, traced polish, unseen-texel fill) and
``--holdout-every 8``, which holds back exactly the study's validation split (every 8th fitted photo,
common.VALIDATION_EVERY): the model choice judges its candidates on it, and the stopping rule
(common.early_stop) sees the model's scores on it.

The fit hands back one model at the end, after its post-processing, so each check of the rule is a fit of
its own with ``--max-iterations k`` (the Levenberg-Marquardt core is deterministic: the fit with cap k runs
the first k iterations of an uncapped one, then the same post-processing), timed whole (``fit_stage`` from
the folder: photos read, set-up, candidates, materials, model folder written); the checks run in order and
end where the rule stops. The command's own cap (``max_iterations`` 100, with its relative-decrease test) is
also run: the model a user gets with no stopping rule. Both its validation and held-out views are scored
here with texstream's renderer of the written model folder, as common.HeldOut scores the other peers.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from common import VALIDATION_EVERY, cpu_seconds, early_stop, schedule, synth_config

DEFAULT_MAX_ITERATIONS = 100
"""FitConfig.max_iterations's default: the command's own cap"""


def write_capture_folders(data, device: str, root: Path) -> tuple[Path, Path]:
    """The data set as ``texstream synthesize`` writes it (``root/all``) and a capture folder of its fitted and
    validation photos (``root/fitted``, images and masks linked, not copied); returns (fitted, mesh folder)."""
    from texstream.capture.capture_json import Capture, read_capture, write_capture
    from texstream.capture.imageio import read_image
    from texstream.capture.synthetic.synth import synthesize

    n = len(data.train_frames) + len(data.val_frames) + len(data.held_frames)
    synthesize("ornament", root / "all", synth_config(data.dataset, data.scale, n, device))
    cap = read_capture(root / "all")
    held = {f.file_path for f in data.held_frames}
    fitted = [f for f in cap.frames if f.file_path not in held]
    if len(fitted) != len(data.train_frames) + len(data.val_frames):
        raise RuntimeError("the written capture does not match the in-memory data set")
    photo = read_image(root / "all" / data.held_frames[0].file_path)
    if not np.array_equal(photo, data.held_images[0]):
        raise RuntimeError("the written photos differ from the in-memory ones the other peers fit")
    (root / "fitted").mkdir()
    for d in ("images", "masks"):
        os.symlink(root / "all" / d, root / "fitted" / d)
    write_capture(Capture(root=root / "fitted", frames=fitted, extra=cap.extra), root / "fitted")
    return root / "fitted", root / "all" / "ground_truth"


def score_model(model_dir: Path, frames: list, photos: list, masks: list, device: str) -> tuple[float, float]:
    """(pooled, worst view) PSNR in dB of a model folder's renders, texstream's heldout_psnr pooling and masks
    (photo mask and render coverage)."""
    from texstream.fit.common.model_folder import image_metrics
    from texstream.fit.models import registry

    render = registry.load_model_folder(model_dir).renderer(device)
    views = []
    for fr, photo, mask in zip(frames, photos, masks):
        img, cover = render(fr)
        views.append(image_metrics(img, photo, cover.astype(bool) & mask)["psnr_db"])
    return float(-10 * np.log10(np.mean([10 ** (-v / 10) for v in views]))), float(min(views))


def run(data, device: str, iterations: int = DEFAULT_MAX_ITERATIONS, dense: int = 6, per_doubling: int = 4,
        partial: Path | None = None) -> dict:
    """The checks ``schedule(iterations, dense, per_doubling)`` (no 0: the fit runs at least one iteration), each
    a whole ``texstream fit``, until the rule stops; then the command's own cap if not run yet. ``partial``: the
    trace so far is written there after every check (a run stopped by its time limit keeps its checks)."""
    from texstream.fit.optim.fitter import FitConfig
    from texstream.fit.stages.stage import FitStageConfig, fit_stage

    base = FitStageConfig(device=device, holdout_every=VALIDATION_EVERY, fit=FitConfig(model="auto"))
    with tempfile.TemporaryDirectory(prefix="peers_default_") as tmp:
        root = Path(tmp)
        capture, mesh = write_capture_folders(data, device, root)

        def fit(cap: int, name: str) -> dict:
            cfg = dataclasses.replace(base, fit=dataclasses.replace(base.fit, max_iterations=cap))
            t0, c0 = time.perf_counter(), cpu_seconds()
            res = fit_stage(capture, mesh, root / name, cfg, progress=False)
            wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
            s = res.summary
            if s["heldout"]["views"] != len(data.val_frames):
                raise RuntimeError(f"the fit held back {s['heldout']['views']} photos, the validation split has "
                                   f"{len(data.val_frames)}")
            val, val_worst = score_model(root / name, data.val_frames, data.val_images, data.val_masks, device)
            held, worst = score_model(root / name, data.held_frames, data.held_images, data.held_masks, device)
            sel = s.get("selection") or {}
            mat = s.get("materials") or {}
            return {"time_s": wall, "cpu_s": cpu, "iteration": cap, "heldout_psnr_db": held, "worst_psnr_db": worst,
                    "val_psnr_db": val, "val_worst_psnr_db": val_worst, "train_psnr_db": s.get("psnr_db"),
                    "fit_iterations": s.get("iterations"), "model_chosen": sel.get("chosen"),
                    "materials_chosen": mat.get("chosen"), "materials_k": mat.get("k"), "texels": s.get("texels"),
                    "setup_s": s.get("setup_s"), "fit_val_pooled_db": s["heldout"].get("pooled_psnr_db")}

        if device.startswith("cuda"):
            fit(1, "warm_up")  # Warp's kernels compiled (minutes on a fresh machine), as the other peers warm up
        trace = []
        for cap in sorted(schedule(iterations, dense, per_doubling) - {0}):
            trace.append(fit(cap, f"check_{cap}"))
            if partial is not None:  # renamed into place: a kill mid-write leaves the previous checks readable
                tmp_json = Path(str(partial) + ".tmp")
                tmp_json.write_text(json.dumps({"trace": trace, "texels": trace[-1]["texels"], "partial": True}))
                os.replace(tmp_json, partial)
            print(f"  texstream fit --max-iterations {cap}: {trace[-1]['time_s']:.1f} s, validation "
                  f"{trace[-1]['val_psnr_db']:.2f} dB, held out {trace[-1]['heldout_psnr_db']:.2f} dB", flush=True)
            if early_stop(trace)["by"] == "patience":
                break
        as_is = trace[-1] if trace[-1]["iteration"] == DEFAULT_MAX_ITERATIONS else fit(DEFAULT_MAX_ITERATIONS, "as_is")
    return {"trace": trace, "as_is": as_is, "texels": trace[-1]["texels"],
            "settings": f"texstream fit defaults (--model auto, shared materials auto, traced polish 5, lobe support "
                        f"0.02, unseen nearest) with --holdout-every {VALIDATION_EVERY} (the validation split); "
                        f"a whole fit per check of --max-iterations ({dense} dense, {per_doubling} per doubling)"}
