"""``texstream import FORMAT SRC -o OUT``: cameras from Middlebury / COLMAP / nerfstudio to a capture folder.

``middlebury`` reads ``*_par.txt`` (:func:`texstream.capture.middlebury.import_middlebury`);
``colmap`` and ``nerfstudio`` call :mod:`texstream.calib.colmap_io` (``import_colmap`` /
``import_nerfstudio``). Options of every format's config are offered; each format uses its own.
"""

from __future__ import annotations

import argparse
import importlib
from types import ModuleType

from texstream.capture.middlebury import MiddleburyImportConfig, import_middlebury
from texstream.core.errors import TexstreamError
from texstream.pipelines.cli import add_config_arguments, config_from_args

FORMATS = ("middlebury", "colmap", "nerfstudio")
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
    parser.add_argument("src", help="source folder (Middlebury set, COLMAP project or sparse model, "
                                    "nerfstudio folder)")
    parser.add_argument("-o", "--out", required=True, help="capture folder to write")
    # The formats' configs may share option names (e.g. --overwrite): one option serves all.
    parser.conflict_handler = "resolve"
    add_config_arguments(parser.add_argument_group("middlebury options"), MiddleburyImportConfig)
    mod = _colmap_io()
    if mod is not None:
        for fmt, (_, cls_name) in _COLMAP_IO.items():
            cls = getattr(mod, cls_name, None)
            if cls is not None:
                add_config_arguments(parser.add_argument_group(f"{fmt} options"), cls)


def run(args: argparse.Namespace) -> int:
    if args.format == "middlebury":
        result = import_middlebury(args.src, args.out, config_from_args(MiddleburyImportConfig, args))
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
