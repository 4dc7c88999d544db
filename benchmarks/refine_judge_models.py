"""The refinement's judgement by two models (issue 39; prints): a run's registered and refined cameras and mesh, each
fitted on a validation split of the fitted photos (``choice.validation_fit``) with the run's fit options and the
model named, the validation pooled PSNR printed. Checks that the cheap diffuse judge (pipelines/refine_judge.py) and
the Lafortune model the fit keeps rank the two geometries the same way.

    python benchmarks/refine_judge_models.py RUN_DIR [diffuse|lafortune]

RUN_DIR: a ``texstream run`` output with ``lights/``, ``atlas/`` and ``refine/`` (the flash capture's photos-only run
of benchmarks/flash_capture.py: ``OUT/run``). Fits go to ``/tmp/judge_models_<name>_<model>``.
"""

import dataclasses
import json
import sys
import time
from pathlib import Path

from texstream.fit.stages.stage import fit_stage
from texstream.pipelines.run import RunConfig

run = Path(sys.argv[1])
model = sys.argv[2] if len(sys.argv) > 2 else "diffuse"
fc = RunConfig().fit
fc = dataclasses.replace(fc, device="cpu", fit=dataclasses.replace(fc.fit, model=model, ambient="auto"),
                         choice=dataclasses.replace(fc.choice, validation_fit=True), renders=0)
for name, cap, geo in (("registered", run / "lights", run / "atlas"), ("refined", run / "refine", run / "refine")):
    t = time.perf_counter()
    out = Path(f"/tmp/judge_models_{name}_{model}")
    fit_stage(cap, geo, out, fc, progress=False)
    held = json.loads((out / "model.json").read_text()).get("heldout") or {}
    print(f"{name}: validation pooled {held.get('pooled_psnr_db'):.2f} dB, worst {held.get('worst_psnr_db'):.2f} dB "
          f"({held.get('views')} views), {time.perf_counter() - t:.1f} s")
