"""``texstream import FORMAT SRC [PHOTOS] -o OUT``: cameras from Middlebury / COLMAP / nerfstudio / Metashape /
RealityCapture to a capture folder.

``middlebury`` reads ``*_par.txt`` (:func:`texstream.capture.middlebury.import_middlebury`);
``colmap`` and ``nerfstudio`` call :mod:`texstream.calib.colmap_io` (``import_colmap`` /
``import_nerfstudio``); ``metashape CAMERAS.xml PHOTOS`` calls :mod:`texstream.calib.metashape` (with
``--mesh FILE``: the mesh Metashape exported, taken into the capture's frame by :func:`transform_mesh_file`);
``realitycapture XMP_FOLDER PHOTOS`` calls :mod:`texstream.calib.realitycapture`. Options of every format's
config are offered; each format uses its own.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
from pathlib import Path
from types import ModuleType

import numpy as np

from texstream.calib.metashape import MetashapeImportConfig, import_metashape
from texstream.calib.realitycapture import RealityCaptureImportConfig, import_realitycapture
from texstream.capture.middlebury import MiddleburyImportConfig, import_middlebury
from texstream.core.errors import InputError, TexstreamError
from texstream.core.outputs import OutputTarget
from texstream.geometry.mesh_io import load_mesh, save_mesh
from texstream.pipelines.cli import add_config_arguments, config_from_args

FORMATS = ("middlebury", "colmap", "nerfstudio", "metashape", "realitycapture")
WITH_PHOTOS = ("metashape", "realitycapture")
"""the formats whose cameras file and photos are given apart (SRC PHOTOS)"""
# format -> (function name, config class name) in texstream.calib.colmap_io
_COLMAP_IO = {"colmap": ("import_colmap", "ColmapImportConfig"),
              "nerfstudio": ("import_nerfstudio", "NerfstudioImportConfig")}


def _colmap_io() -> ModuleType | None:
    try:
        return importlib.import_module("texstream.calib.colmap_io")
    except ModuleNotFoundError as e:
        if e.name != "texstream.calib.colmap_io":
            raise
        return None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", choices=FORMATS, help="source format")
    parser.add_argument("src", help="source: Middlebury set, COLMAP project or sparse model, nerfstudio folder, "
                                    "Metashape cameras XML, or RealityCapture XMP folder")
    parser.add_argument("photos", nargs="?", default=None,
                        help="metashape and realitycapture: the folder holding the photos")
    parser.add_argument("-o", "--out", required=True, help="capture folder to write")
    # The formats' configs may share option names (e.g. --overwrite): one option serves all.
    parser.conflict_handler = "resolve"
    add_config_arguments(parser.add_argument_group("middlebury options"), MiddleburyImportConfig)
    add_config_arguments(parser.add_argument_group("metashape options"), MetashapeImportConfig)
    add_config_arguments(parser.add_argument_group("realitycapture options"), RealityCaptureImportConfig)
    mod = _colmap_io()
    if mod is not None:
        for fmt, (_, cls_name) in _COLMAP_IO.items():
            cls = getattr(mod, cls_name, None)
            if cls is not None:
                add_config_arguments(parser.add_argument_group(f"{fmt} options"), cls)


def transform_mesh_file(src: Path, dst: Path, m: np.ndarray) -> None:
    """Write the mesh ``src`` to ``dst`` taken through the 4x4 similarity ``m`` (x -> s R x + t; normals
    rotated); UVs and faces as they are."""
    mesh = load_mesh(src)
    a = np.asarray(m, dtype=np.float64)[:3, :3]
    rot = a / np.cbrt(np.linalg.det(a))
    normals = None if mesh.normals is None else mesh.normals @ rot.T
    save_mesh(dst, dataclasses.replace(mesh, vertices=mesh.vertices @ a.T + np.asarray(m)[:3, 3], normals=normals))


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out))


def run(args: argparse.Namespace) -> int:
    if args.format in WITH_PHOTOS and args.photos is None:
        raise InputError(f"'texstream import {args.format}' needs the photo folder after the cameras",
                         args.src, f"run 'texstream import {args.format} {args.src} PHOTOS -o {args.out}'")
    if args.format not in WITH_PHOTOS and args.photos is not None:
        raise InputError(f"'texstream import {args.format}' takes one source, not a photo folder too", args.photos,
                         "use the format's own option for the images (e.g. --images for colmap)")
    if args.format == "middlebury":
        result = import_middlebury(args.src, args.out, config_from_args(MiddleburyImportConfig, args))
    elif args.format == "metashape":
        result = import_metashape(args.src, args.photos, args.out, config_from_args(MetashapeImportConfig, args),
                                  mesh_writer=transform_mesh_file)
    elif args.format == "realitycapture":
        result = import_realitycapture(args.src, args.photos, args.out,
                                       config_from_args(RealityCaptureImportConfig, args))
    else:
        fn_name, cls_name = _COLMAP_IO[args.format]
        mod = _colmap_io()
        fn = getattr(mod, fn_name, None) if mod is not None else None
        if fn is None:
            raise TexstreamError(f"importing {args.format} cameras is not available yet "
                                 f"(texstream.calib.colmap_io.{fn_name} is missing)",
                                 fix="update texstream, or use 'texstream import middlebury'")
        cls = getattr(mod, cls_name, None)
        config = config_from_args(cls, args) if cls is not None else None
        result = fn(args.src, args.out, config)
    s = result.summary
    details = ", ".join(f"{k} {v}" for k, v in s.items() if not isinstance(v, (dict, list)))
    print(f"wrote {result.output}" + (f" ({details})" if details else ""))
    return 0
