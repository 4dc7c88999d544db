"""The highlight diagnostic (fit/common/highlights.py) of a model folder already fitted: its photos streamed as
its fit streamed them (the fit_config.json beside the model), the counts printed as JSON with the diagnostic's
seconds. Usage: ``python scripts/highlights_of_model.py MODEL_DIR CAPTURE_DIR``.

For models fitted before the diagnostic joined the fit, and to time it on its own. The model folder's mesh.obj and
bake.npz stand for the atlas the fit read."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from texstream.core.config import load_config
from texstream.fit.common.highlights import highlight_masks, highlight_report
from texstream.fit.common.inputs import load_fit_inputs, set_up_skipping_bad_photos
from texstream.fit.common.setup import load_model
from texstream.fit.stages.stage import FitStageConfig


def main(model_dir: str, capture_dir: str) -> dict:
    t0 = time.perf_counter()
    cfg = load_config(FitStageConfig, Path(model_dir) / "fit_config.json")
    _, grid, layout, _ = load_model(model_dir)
    inputs = load_fit_inputs(capture_dir, model_dir, cfg)
    problem, _, _, _ = set_up_skipping_bad_photos(inputs, cfg, capture_dir)
    if problem.layout.n_params != layout.n_params:
        sys.exit(f"{model_dir}: the model's layout ({layout.kind}) differs from its fit_config.json's; "
                 "re-run the fit")
    t_setup = time.perf_counter() - t0
    params = grid.reshape(-1, grid.shape[-1])[problem.texels.grid_index]
    report = highlight_report(highlight_masks(problem, params))
    return {**report, "setup_seconds": t_setup, "photos": len(inputs.frames), "texels": problem.n,
            "loadavg": os.getloadavg()}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2]), indent=1))
