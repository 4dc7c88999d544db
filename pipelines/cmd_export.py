"""``texstream export MODEL -o OUT``: glTF binary (model.glb) and OBJ + MTL + PNG textures of a model
folder, with the EXR maps alongside. The stage is :func:`texstream.fit.stages.export.export_stage`."""

from __future__ import annotations

import argparse

from pathlib import Path

from texstream.core.outputs import OutputTarget
from texstream.fit.stages.export import ExportConfig, export_stage
from texstream.pipelines.cli import add_config_arguments, config_from_args
from texstream.pipelines.estimates import export_bytes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="model folder written by texstream fit or texstream run")
    parser.add_argument("-o", "--out", required=True, help="export folder to write (replaced if it exists)")
    add_config_arguments(parser, ExportConfig)


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out), estimated_bytes=export_bytes(args.model), what="the export")


def run(args: argparse.Namespace) -> int:
    res = export_stage(args.model, args.out, config_from_args(ExportConfig, args))
    files = res.summary.get("files", res.summary)
    print(f"wrote {res.output}: {files}")
    return 0
