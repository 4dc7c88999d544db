"""Damaged and odd inputs for the fuzz harness (tests/fuzz_harness.py): photos, capture.json /
transforms.json, COLMAP models, meshes and TOML run configs, each made small in a few milliseconds.

Each builder writes into a given folder and returns what it made; the expectations (which are only odd
and must be read correctly, which are damaged and must fail with one line naming the file) live beside
them, so the tests and scripts/fuzz.py judge the same way.
"""

from __future__ import annotations

import base64
import copy
import json
import math
import random
import struct
from pathlib import Path
from typing import Any, Callable

import numpy as np

CMYK_JPEG = base64.b64decode(
    "/9j/7gAOQWRvYmUAZAAAAAAA/9sAQwADAgIDAgIDAwMDBAMDBAUIBQUEBAUKBwcGCAwKDAwLCgsLDQ4SEA0OEQ4LCxAWEBETFBUVFQwPFxgW"
    "FBgSFBUU/8AAFAgABgAGBEMRAE0RAFkRAEsRAP/EAB8AAAEFAQEBAQEBAAAAAAAAAAABAgMEBQYHCAkKC//EALUQAAIBAwMCBAMFBQQEAAAB"
    "fQECAwAEEQUSITFBBhNRYQcicRQygZGhCCNCscEVUtHwJDNicoIJChYXGBkaJSYnKCkqNDU2Nzg5OkNERUZHSElKU1RVVldYWVpjZGVmZ2hp"
    "anN0dXZ3eHl6g4SFhoeIiYqSk5SVlpeYmZqio6Slpqeoqaqys7S1tre4ubrCw8TFxsfIycrS09TV1tfY2drh4uPk5ebn6Onq8fLz9PX29/j5"
    "+v/aAA4EQwBNAFkASwAAPwD48r9U6/VOv0Dr/9k=")
"""a 6x6 CMYK JPEG (Adobe marker; C=200, M=0, Y=0, K=30 stored inverted), made once with Pillow
(``Image.fromarray(a, "CMYK").save(buf, "JPEG", quality=90)``) so the suite needs no Pillow for it"""
CMYK_JPEG_RGB8 = (49, 225, 225)
"""its first pixel as OpenImageIO converts it (R = (255 - C) (255 - K) / 255)"""


def textured(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth random linear RGB image in [0.05, 0.95] (photos that registration could match)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    img = np.stack([0.5 + 0.4 * np.sin(6.28 * (x * rng.uniform(1, 3) + y * rng.uniform(1, 3)) + c)
                    for c in range(3)], -1)
    return img.astype(np.float32)


def _write(path: Path, img: np.ndarray, **kw) -> Path:
    from texstream.capture.imageio import write_image

    return write_image(path, img, **kw)


def _float_exr(path: Path, img: np.ndarray) -> Path:
    """A float EXR written by OpenImageIO itself: texstream's write_image refuses NaN and Inf, a camera or another
    tool may not."""
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create("openexr")
    out.open(str(path), oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], "float"))
    out.write_image(np.ascontiguousarray(img, np.float32))
    out.close()
    return path


def _truncated(src: Path, dst: Path, fraction: float) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: max(1, int(len(data) * fraction))])
    src.unlink()
    return dst


def _cmyk_tiff(path: Path) -> Path:
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(6, 6, 4, "uint8")
    spec.attribute("tiff:ColorSpace", "CMYK")
    out = oiio.ImageOutput.create("tiff")
    out.open(str(path), spec)
    px = np.zeros((6, 6, 4), np.uint8)
    px[..., 0], px[..., 3] = 200, 30
    out.write_image(px)
    out.close()
    return path


def _bomb_png(path: Path) -> Path:
    """A PNG whose header claims 60000 x 60000 RGB (10.8 GB decoded) and holds no pixel data."""
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)))
    return path


# name -> (builder(folder) -> path, expectation): "read" = an odd but valid photo, read as (H, W, 3) finite
# linear values; "fail" = damaged, an InputError naming the file; "unusable" = read, but no photo to fit or
# register (ingest must drop it with its reason or refuse it: issue 41 saw a 1x1 photo accepted)
PHOTO_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "truncated_jpeg": (lambda d: _truncated(_write(d / "t.jpg", textured(32, 32)), d / "truncated.jpg", 0.5), "fail"),
    "truncated_png": (lambda d: _truncated(_write(d / "t.png", textured(32, 32)), d / "truncated.png", 0.5), "fail"),
    "truncated_exr": (lambda d: _truncated(_write(d / "t.exr", textured(32, 32)), d / "truncated.exr", 0.6), "fail"),
    "header_only_png": (lambda d: _truncated(_write(d / "t.png", textured(32, 32)), d / "header.png", 0.1), "fail"),
    "random_bytes_jpeg": (lambda d: _bytes(d / "random.jpg", 2000), "fail"),
    "empty_png": (lambda d: _bytes(d / "empty.png", 0), "fail"),
    "text_as_png": (lambda d: _text(d / "notes.png", "not an image\n"), "fail"),
    "bomb_png": (lambda d: _bomb_png(d / "bomb.png"), "fail"),
    "nan_exr": (lambda d: _float_exr(d / "nan.exr", _with(textured(8, 8), (2, 3), np.nan)), "fail"),
    "inf_exr": (lambda d: _float_exr(d / "inf.exr", _with(textured(8, 8), (5, 1), np.inf)), "fail"),
    "one_by_one_png": (lambda d: _write(d / "one.png", textured(1, 1)), "unusable"),
    "png16": (lambda d: _write(d / "deep.png", textured(12, 10), bits=16), "read"),
    "grey_alpha_png": (lambda d: _write(d / "ga.png", _with_alpha(textured(8, 8)[..., :1])), "read"),
    "rgba_exr_half": (lambda d: _write(d / "rgba.exr", _with_alpha(textured(8, 8))), "read"),
    "cmyk_jpeg": (lambda d: _raw(d / "cmyk.jpg", CMYK_JPEG), "read"),
    "cmyk_tiff": (lambda d: _cmyk_tiff(d / "cmyk.tif"), "read"),
    "exif_rotated_jpeg": (lambda d: _write(d / "rot6.jpg", textured(12, 20), metadata={"Orientation": 6}), "read"),
    "exif_bad_orientation_jpeg": (lambda d: _write(d / "rot99.jpg", textured(12, 20), metadata={"Orientation": 99}),
                                  "read"),
    "png_named_jpg": (lambda d: _renamed(_write(d / "p.png", textured(8, 8)), d / "really_png.jpg"), "read"),
    "float_tiff": (lambda d: _write(d / "float.tif", textured(8, 8) * 3.0, bits=32), "read"),
}


def _with_alpha(img: np.ndarray) -> np.ndarray:
    return np.concatenate([img, np.ones(img.shape[:2] + (1,), np.float32)], -1)


def _bytes(path: Path, n: int, seed: int = 0) -> Path:
    path.write_bytes(random.Random(seed).randbytes(n))
    return path


def _text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _raw(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _renamed(src: Path, dst: Path) -> Path:
    src.rename(dst)
    return dst


def _with(img: np.ndarray, yx: tuple[int, int], value: float) -> np.ndarray:
    img = img.copy()
    img[yx] = value
    return img


def good_photos(folder: Path, n: int = 4, size: tuple[int, int] = (24, 32), ext: str = ".png") -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    return [_write(folder / f"photo_{i:02d}{ext}", textured(*size, seed=i)) for i in range(n)]


# --------------------------------------------------------------------------- capture.json


def valid_capture_doc(n: int = 3, size: tuple[int, int] = (24, 32)) -> dict:
    """A posed capture document (cameras on a ring looking at the origin, a point light each)."""
    h, w = size
    frames = []
    for i in range(n):
        a = 2 * math.pi * i / n
        c = np.array([3 * math.cos(a), 0.5, 3 * math.sin(a)])
        back = c / np.linalg.norm(c)  # OpenGL camera looks along -z: z points from the object to the camera
        right = np.cross([0.0, 1.0, 0.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, c
        frames.append({"file_path": f"images/photo_{i:02d}.png", "transform_matrix": m.tolist(),
                       "light": {"type": "point", "position": c.tolist(), "intensity": [1.0, 1.0, 1.0]}})
    return {"camera_model": "PINHOLE", "fl_x": 30.0, "fl_y": 30.0, "cx": w / 2, "cy": h / 2, "w": w, "h": h,
            "frames": frames}


def write_capture_folder(folder: Path, doc: Any, name: str = "capture.json", photos: bool = True) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    if photos:
        good_photos(folder / "images", n=3)
    (folder / name).write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return folder


BAD_VALUES: tuple = (None, True, "abc", "", [], {}, [1, 2], -1, 0, 1e308, float("nan"), float("inf"), -float("inf"),
                     2 ** 70, [[float("nan")] * 4] * 4, [[0.0] * 4] * 4, "images/../../../etc/passwd", 3.5)
"""values put where a capture field goes (JSON allows NaN and Infinity as Python writes them)"""


def capture_paths(doc: dict) -> list[tuple]:
    """Every key path of a capture document (("frames", 0, "light", "position"), ...)."""
    out: list[tuple] = []

    def walk(node: Any, path: tuple) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                out.append(path + (k,))
                walk(v, path + (k,))
        elif isinstance(node, list) and node and isinstance(node[0], dict):
            for i, v in enumerate(node):
                out.append(path + (i,))
                walk(v, path + (i,))
    walk(doc, ())
    return out


def mutate(doc: dict, path: tuple, action: str, value: Any = None) -> dict:
    """A copy of ``doc`` with the node at ``path`` deleted ("delete") or set to ``value`` ("set")."""
    doc = copy.deepcopy(doc)
    node = doc
    for k in path[:-1]:
        node = node[k]
    if action == "delete":
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return doc


def damaged_json_texts(doc: dict) -> dict[str, str]:
    """Capture texts that are not JSON or not a capture at all."""
    text = json.dumps(doc)
    return {"truncated": text[: len(text) // 2], "empty": "", "binary": "\x00\xff\xfe garbage", "list": "[1, 2, 3]",
            "number": "42", "frames_not_list": json.dumps({**doc, "frames": {"a": 1}}),
            "no_frames": json.dumps({k: v for k, v in doc.items() if k != "frames"}),
            "empty_frames": json.dumps({**doc, "frames": []}), "nested_deep": "[" * 100000 + "]" * 100000,
            "bom": "\ufeff" + text, "latin1": text.replace("images", "imag\u00e9s").encode("latin-1").decode("latin-1")}


# --------------------------------------------------------------------------- COLMAP models


def colmap_model(folder: Path, n_images: int = 3, text: bool = False) -> Path:
    """A small valid COLMAP sparse model: one PINHOLE camera and ``n_images`` posed images written as COLMAP
    documents the text format (identity rotations stepped along x), converted to binary unless ``text``."""
    import pycolmap

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text("1 PINHOLE 32 24 30 30 16 12\n")
    (folder / "images.txt").write_text("".join(f"{i + 1} 1 0 0 0 {0.2 * i} 0 3 1 photo_{i:02d}.png\n\n"
                                               for i in range(n_images)))
    (folder / "points3D.txt").write_text("")
    if not text:
        pycolmap.Reconstruction(str(folder)).write(str(folder))
        for name in ("cameras.txt", "images.txt", "points3D.txt"):
            (folder / name).unlink()
    return folder


def colmap_damages(model: Path) -> dict[str, Callable[[], None]]:
    """name -> damage done in place to a model folder written by :func:`colmap_model`."""
    def cut(name: str, fraction: float) -> Callable[[], None]:
        def f() -> None:
            p = model / name
            data = p.read_bytes()
            p.write_bytes(data[: int(len(data) * fraction)])
        return f

    def junk(name: str) -> Callable[[], None]:
        return lambda: (model / name).write_bytes(random.Random(1).randbytes(300))

    def remove(name: str) -> Callable[[], None]:
        return lambda: (model / name).unlink()
    out: dict[str, Callable[[], None]] = {}
    for name in ("cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt"):
        if (model / name).exists():
            out[f"{name}_half"] = cut(name, 0.5)
            out[f"{name}_one_byte"] = cut(name, 0.01)
            out[f"{name}_junk"] = junk(name)
            out[f"{name}_missing"] = remove(name)
    if (model / "cameras.txt").exists():
        out["cameras.txt_nan_params"] = lambda: (model / "cameras.txt").write_text("1 PINHOLE 32 24 nan 30 16 12\n")
        out["cameras.txt_zero_size"] = lambda: (model / "cameras.txt").write_text("1 PINHOLE 0 0 30 30 16 12\n")
        out["cameras.txt_unknown_model"] = lambda: (model / "cameras.txt").write_text("1 WEIRD 32 24 30 30 16 12\n")
        out["cameras.txt_few_params"] = lambda: (model / "cameras.txt").write_text("1 PINHOLE 32 24 30\n")
        out["images.txt_bad_quaternion"] = lambda: (model / "images.txt").write_text(
            "1 0 0 0 0 0 0 0 1 photo_00.png\n\n")
    return out


# --------------------------------------------------------------------------- meshes


def tetra_obj() -> str:
    return "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


MESH_CASES: dict[str, Callable[[Path], Path]] = {
    "random_bytes_ply": lambda d: _bytes(d / "random.ply", 4000, seed=2),
    "random_bytes_obj": lambda d: _bytes(d / "random.obj", 4000, seed=3),
    "empty_obj": lambda d: _text(d / "empty.obj", ""),
    "empty_ply": lambda d: _bytes(d / "empty.ply", 0),
    "no_faces_obj": lambda d: _text(d / "points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
    "nan_vertex_obj": lambda d: _text(d / "nan.obj", tetra_obj().replace("v 1 0 0", "v nan 0 0")),
    "inf_vertex_obj": lambda d: _text(d / "inf.obj", tetra_obj().replace("v 1 0 0", "v inf 0 0")),
    "degenerate_faces_obj": lambda d: _text(d / "degenerate.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nf 1 1 2\n"),
    "index_out_of_range_obj": lambda d: _text(d / "range.obj", tetra_obj() + "f 1 2 99\n"),
    "text_in_indices_obj": lambda d: _text(d / "words.obj", tetra_obj() + "f a b c\n"),
    "truncated_ply": lambda d: _truncated_mesh_ply(d),
    "ply_header_only": lambda d: _text(d / "header.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                                        "property float y\nproperty float z\nend_header\n"),
    "wrong_extension": lambda d: _text(d / "mesh.xyz", tetra_obj()),
    "folder_as_mesh": lambda d: _folder(d / "meshdir.obj"),
}


def _folder(path: Path) -> Path:
    path.mkdir()
    return path


def _truncated_mesh_ply(d: Path) -> Path:
    from texstream.geometry.mesh_io import load_mesh, save_mesh

    (d / "t.obj").write_text(tetra_obj())
    save_mesh(d / "t.ply", load_mesh(d / "t.obj"))
    return _truncated(d / "t.ply", d / "truncated.ply", 0.7)


# --------------------------------------------------------------------------- TOML run configs


TOML_CASES: dict[str, str] = {
    "not_toml": "this is = = not toml\n[[[",
    "binary": "\x00\x01\x02",
    "unknown_top": "colour = 3\n",
    "unknown_table_key": "[fit]\nwobble = 1\n",
    "table_not_table": "fit = 3\n",
    "wrong_type_iterations": "[fit.fit]\nmax_iterations = \"many\"\n",
    "negative_iterations": "[fit.fit]\nmax_iterations = -5\n",
    "nan_float": "[fit]\nmin_seen_fraction = nan\n",
    "inf_float": "lfm_min_gain_db = inf\n",
    "bad_choice": "[fit.fit]\noptimizer = \"newton\"\n",
    "bad_model": "model = \"phong\"\n",
    "bool_as_string": "progress = \"yes\"\n",
    "list_for_scalar": "[atlas]\ntexels_per_unit = [1, 2]\n",
    "huge_int": "[fit]\nholdout_every = 99999999999999999\n",
    "device_number": "device = 3\n",
    "nested_unknown_table": "[fit.fit.nowhere]\nx = 1\n",
}
TOML_MAY_PASS = ("inf_float", "huge_int")
"""values a run may take as they are (an infinite gain threshold: never; holding out every 10^17th photo: none)"""
