"""The model choice's LFM candidate on a finished run: its validation fit's objective and validation PSNR against
iterations and time (JSON), to see where the fit settles and what a stopping rule costs.

    python benchmarks/lfm_choice_profile.py RUN_DIR --iterations 50 --out out/lfm_choice_temple.json

RUN_DIR is a ``texstream run`` output folder (its refine/ or atlas/ geometry and posed/ capture). The fit is the
one ``fit_choice`` makes of the LFM candidate (the run's fit stage options, ``choice.validation_fit``: the fitted
photos less every ``materials.validation_every``-th, those validation photos scored; the held-out photos are not
read), with the run's options except ``--iterations`` and ``--rel-tol``. At every objective read
(``lfm.sync_every``) the validation photos are rendered and scored (pooled PSNR over their foreground, as the
choice scores them); that scoring is kept out of the fit's time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir")
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--rel-tol", type=float, default=None, help="lfm.rel_tol (default: the run's)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)

    from texstream.fit.common.inputs import load_fit_inputs, load_photos
    from texstream.fit.common.model_folder import image_metrics, pooled_psnr
    from texstream.fit.models.lfm.fit import _radiance_problem, filled_params, lfm_threads
    from texstream.fit.models.lfm.model_folder import LFMRenderer, lfm_geometry
    from texstream.fit.models.lfm.problem import LFMProblem, PhotoSamples, fit_lfm
    from texstream.pipelines.run import RunConfig

    run = Path(a.run_dir)
    geometry = run / "refine" if (run / "refine" / "mesh.obj").is_file() else run / "atlas"
    capture_dir = geometry if (geometry / "capture.json").is_file() else run / "posed"  # the run's refined cameras
    base = RunConfig().fit
    lcfg = dataclasses.replace(base.fit.lfm, iterations=a.iterations,
                               **({} if a.rel_tol is None else {"rel_tol": a.rel_tol}))
    cfg = dataclasses.replace(base, device=a.device, renders=0,
                              fit=dataclasses.replace(base.fit, model="radiance", lfm=lcfg),
                              choice=dataclasses.replace(base.choice, validation_fit=True))
    t0 = time.perf_counter()
    inputs = load_fit_inputs(capture_dir, geometry, cfg)
    sp = _radiance_problem(inputs, cfg)
    geom = lfm_geometry(inputs.mesh, inputs.bake, sp.texels)
    problem = LFMProblem(geom, PhotoSamples(sp, inputs.frames), lcfg, a.device, lfm_threads(cfg.fit, sp.n))
    setup_s = time.perf_counter() - t0
    held = inputs.held
    images, masks = load_photos(inputs.capture, held)
    grid_index = sp.texels.grid_index
    points, scoring = [], [0.0]

    def snapshot(iteration, G, H):
        ts = time.perf_counter()
        params = filled_params(problem.params(G, H), geom, problem.seen)
        renderer = LFMRenderer(inputs.mesh, inputs.bake, geom, params, lcfg, grid_index, a.device)
        rows = []
        for f, photo, mask in zip(held, images, masks):
            image, cover = renderer.render_frame(f)
            rows.append(image_metrics(image, photo, inputs.capture.within_mask(f, cover)))
        points.append({"iteration": iteration, "validation_pooled_db": pooled_psnr(rows)["pooled_psnr_db"]})
        scoring[0] += time.perf_counter() - ts

    def callback(iteration, objective):
        points.append({"iteration": iteration, "objective": objective,
                       "time_s": time.perf_counter() - t_fit - scoring[0]})

    t_fit = time.perf_counter()
    res = fit_lfm(problem, time_budget_s=0.0, callback=callback, snapshot=snapshot)
    merged = {}
    for p in points:
        merged.setdefault(p["iteration"], {}).update(p)
    rows = [merged[k] for k in sorted(merged)]
    for r in rows:
        print(f"it {r['iteration']:4d}  t {r['time_s']:7.1f} s  objective {r['objective']:.6e}  "
              f"validation {r['validation_pooled_db']:.3f} dB")
    out = {"run_dir": str(run), "iterations_cap": a.iterations, "rel_tol": lcfg.rel_tol, "setup_s": setup_s,
           "fit_s": res.fit_s, "iterations": res.iterations, "passes": res.passes, "trace": rows,
           "validation_photos": [str(f.file_path) for f in held], "machine": platform.node()}
    print(f"setup {setup_s:.1f} s, fit {res.fit_s:.1f} s (scoring excluded), {res.iterations} iterations, "
          f"{res.passes} passes")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
