"""``texstream relight MODEL --env FILE --capture CAPTURE --out DIR``: a relightable model (``--model
env_diffuse``) rendered under another light, from the capture's cameras.

FILE: a linear latitude-longitude environment map (.exr / .hdr, row 0 the zenith +z: render/sh.py's
convention) or JSON {"sh": [[r, g, b] x 9]} (a model folder's light.json). DIR gets one linear float EXR per
capture frame, named like the frame's image (``images/r_003.png`` -> ``r_003.exr``), each exposure x the
radiance (as the capture's photos are), and relight.json (the light, the frames); written atomically. Example:

    texstream relight out/ornament_env --env sky.exr --capture out/ornament_sky --out out/relit
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import write_image
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.errors import InputError
from texstream.core.outputs import OutputTarget, atomic_output_dir, write_json_atomic
from texstream.fit.models import registry
from texstream.fit.models.env_diffuse.light_file import light_json, read_light


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="relightable model folder (texstream fit --model env_diffuse)")
    parser.add_argument("--env", required=True, help="the light: a linear latitude-longitude .exr / .hdr (row 0 the "
                        "zenith +z) or a JSON file {\"sh\": [[r, g, b] x 9]}")
    parser.add_argument("--capture", required=True, help="capture folder whose cameras (poses, intrinsics, "
                        "exposures) to render from; its photos are not read")
    parser.add_argument("--out", "-o", required=True, help="folder of the renders (replaced if it exists)")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP + " (default: auto)")


def output_target(args: argparse.Namespace) -> OutputTarget:
    return OutputTarget(Path(args.out), what="the relit renders")


def relight(model_dir, env_file, capture_dir, out_dir, device: str = "auto") -> dict:
    """Render ``model_dir`` under the light of ``env_file`` from every frame of ``capture_dir`` into ``out_dir``;
    returns relight.json. Every input is checked before anything is rendered or written."""
    light = read_light(env_file)
    model = registry.load_model_folder(model_dir)
    if not getattr(model, "relightable", False):
        raise InputError(f"a {model.kind} model cannot be relit (it holds no reflectance under a light of its own)",
                         Path(model_dir) / "model.json", "fit a relightable model: texstream fit --model env_diffuse")
    capture = read_capture(capture_dir)
    names = [f.name for f in capture.frames]
    if len(set(names)) != len(names):
        raise InputError("two frames share an image name, their renders would overwrite each other",
                         Path(capture_dir) / "capture.json", "give every frame its own file name")
    render = model.relit_renderer(light, resolve_device(device))
    rows = []
    with atomic_output_dir(out_dir) as tmp:
        for f in capture.frames:
            image, mask = render(f)
            write_image(tmp / f"{f.name}.exr", np.where(mask[..., None], image, 0.0).astype(np.float32), bits=32)
            rows.append({"frame": f.file_path, "render": f"{f.name}.exr", "exposure": float(f.exposure)})
        summary = {"model": str(Path(model_dir).resolve()), "env": str(Path(env_file).resolve()),
                   "capture": str(Path(capture_dir).resolve()), "light": light_json(light), "renders": rows,
                   "units": "linear, exposure x radiance (as the capture's photos); 0 off the model"}
        write_json_atomic(tmp / "relight.json", summary)
    return summary


def run(args: argparse.Namespace) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    s = relight(args.model, args.env, args.capture, args.out, args.device)
    print(f"wrote {args.out}: {len(s['renders'])} renders under the light of {args.env}")
    return 0
