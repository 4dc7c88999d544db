"""Fitting a capture with light field mapping: its own problem (vertex light fields over triangle rings) and
model folder (fit/stages/lfm_stage.py)."""

from __future__ import annotations

from texstream.core.errors import ConfigError
from texstream.core.outputs import StageResult
from texstream.fit.multi.tiles import split_photos, tiled


def fit(request) -> StageResult:
    from texstream.fit.stages.lfm_stage import lfm_fit_stage

    cfg = request.cfg
    if tiled(cfg.fit) or split_photos(cfg.fit):
        raise ConfigError("stream.tiles, stream.devices and stream.tile_backend ray split per-texel models; "
                          "light field mapping couples the texels of a triangle ring",
                          fix="drop those options with --model lfm")
    return lfm_fit_stage(request.capture_dir, request.mesh_path, request.out_dir, cfg, request.progress)
