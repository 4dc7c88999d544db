"""COLMAP and nerfstudio cameras <-> capture folders.

- :func:`camera_to_intrinsics` / :func:`intrinsics_to_colmap`: COLMAP camera models <-> capture
  :class:`Intrinsics` (COLMAP and the capture share the pixel convention: centres at +0.5).
- :func:`reconstruction_frames`: a ``pycolmap.Reconstruction``'s registered images as
  (name, R, t, Intrinsics), world-to-camera in OpenCV axes (COLMAP's own convention).
- :func:`import_colmap` / :func:`import_nerfstudio`: stages that turn an existing COLMAP project
  (``sparse/0``) or nerfstudio folder (``transforms.json``) into a capture folder, so users who
  already ran COLMAP or nerfstudio skip registration.

pycolmap is imported inside the functions.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np

from texstream.capture.capture_json import Capture, Frame, Intrinsics, read_capture, write_capture
from texstream.core.errors import InputError
from texstream.core.config import option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir

from .files import IMAGE_EXTS

# COLMAP model -> names of its parameters (COLMAP's src/colmap/sensor/models.h).
COLMAP_PARAMS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "SIMPLE_RADIAL_FISHEYE": ("f", "cx", "cy", "k1"),
    "RADIAL_FISHEYE": ("f", "cx", "cy", "k1", "k2"),
}


def camera_to_intrinsics(model: str, params: np.ndarray, width: int, height: int, where: str = "") -> Intrinsics:
    """A COLMAP camera (model name, params) -> capture Intrinsics.

    Perspective models become ``PINHOLE`` (no distortion) or ``OPENCV`` (k1 k2 [k3] p1 p2, as
    nerfstudio's ``ns-process-data`` writes them); fisheye models become ``OPENCV_FISHEYE``.
    """
    names = COLMAP_PARAMS.get(model)
    if names is None or len(params) != len(names):
        raise InputError(f"camera model {model} with {len(params)} parameters is not supported{where}",
                         fix=f"use one of {sorted(COLMAP_PARAMS)} (e.g. re-run COLMAP with OPENCV)")
    p = dict(zip(names, (float(x) for x in params)))
    if not (np.all(np.isfinite(list(p.values()))) and int(width) > 0 and int(height) > 0
            and p.get("fx", p.get("f", 0.0)) > 0 and p.get("fy", p.get("f", 0.0)) > 0):
        raise InputError(f"camera {model} {int(width)}x{int(height)} with parameters {[round(v, 6) for v in p.values()]} "
                         f"is not a camera (sizes and focal lengths must be positive, every parameter finite){where}",
                         fix="re-export the COLMAP model (the cameras file is damaged)")
    fx = p.get("fx", p.get("f"))
    fy = p.get("fy", p.get("f"))
    dist = {k: p[k] for k in ("k1", "k2", "k3", "k4", "p1", "p2") if k in p}
    if model == "FULL_OPENCV":
        if any(abs(p[k]) > 0 for k in ("k4", "k5", "k6")):
            raise InputError(f"FULL_OPENCV camera with rational terms k4..k6 is not supported{where}",
                             fix="re-run COLMAP with the OPENCV model, or undistort the images first")
        dist.pop("k4", None)
    if model.endswith("FISHEYE"):
        cam_model = "OPENCV_FISHEYE"
        dist = {k: dist.get(k, 0.0) for k in ("k1", "k2", "k3", "k4")}
    elif any(abs(v) > 0 for v in dist.values()):
        cam_model = "OPENCV"
        dist = {k: dist.get(k, 0.0) for k in ("k1", "k2", "p1", "p2")} | ({"k3": dist["k3"]} if "k3" in dist else {})
    else:
        cam_model, dist = "PINHOLE", {}
    return Intrinsics(width=int(width), height=int(height), fx=fx, fy=fy, cx=p["cx"], cy=p["cy"],
                      camera_model=cam_model, distortion=dist)


def intrinsics_to_colmap(intr: Intrinsics) -> tuple[str, list[float]]:
    """Capture Intrinsics -> (COLMAP model name, params) for fixed or prior intrinsics."""
    d = intr.distortion
    if intr.camera_model == "OPENCV_FISHEYE":
        return "OPENCV_FISHEYE", [intr.fx, intr.fy, intr.cx, intr.cy, *(d.get(k, 0.0) for k in ("k1", "k2", "k3", "k4"))]
    if not any(abs(v) > 0 for v in d.values()):
        return "PINHOLE", [intr.fx, intr.fy, intr.cx, intr.cy]
    base = [intr.fx, intr.fy, intr.cx, intr.cy, d.get("k1", 0.0), d.get("k2", 0.0), d.get("p1", 0.0), d.get("p2", 0.0)]
    if abs(d.get("k3", 0.0)) > 0 or abs(d.get("k4", 0.0)) > 0:
        # OpenCV's 5-coefficient model is FULL_OPENCV with the rational terms at zero.
        return "FULL_OPENCV", base + [d.get("k3", 0.0), 0.0, 0.0, 0.0]
    return "OPENCV", base


def opencv_distortion(intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(K in OpenCV pixels (centres at integers), distortion coefficients) for cv2 undistortion."""
    k = intr.matrix().copy()
    k[0, 2] -= 0.5
    k[1, 2] -= 0.5
    d = intr.distortion
    if intr.camera_model == "OPENCV_FISHEYE":
        return k, np.array([d.get(x, 0.0) for x in ("k1", "k2", "k3", "k4")])
    return k, np.array([d.get(x, 0.0) for x in ("k1", "k2", "p1", "p2", "k3")])


def reconstruction_frames(rec: Any) -> list[tuple[str, np.ndarray, np.ndarray, Intrinsics]]:
    """Registered images of a ``pycolmap.Reconstruction`` as (name, R, t, Intrinsics), sorted by name."""
    out = []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        pose = image.cam_from_world()
        intr = camera_to_intrinsics(cam.model.name, np.asarray(cam.params), cam.width, cam.height,
                                    f" (image {image.name})")
        quat, t = np.asarray(pose.rotation.quat, dtype=np.float64), np.asarray(pose.translation, dtype=np.float64)
        if not (np.all(np.isfinite(quat)) and abs(np.linalg.norm(quat) - 1.0) < 1e-3 and np.all(np.isfinite(t))):
            raise InputError(f"image {image.name} has the pose quaternion {quat.tolist()} and translation {t.tolist()} "
                             "(a rotation needs a finite unit quaternion)",
                             fix="re-export the COLMAP model (the images file is damaged)")
        out.append((image.name, np.asarray(pose.rotation.matrix(), dtype=np.float64),
                    np.asarray(pose.translation, dtype=np.float64).reshape(3), intr))
    return sorted(out, key=lambda x: x[0])


COLMAP_MODEL_IDS: dict[int, int] = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12}
"""COLMAP's camera model id -> its number of parameters (src/colmap/sensor/models.h), to walk cameras.bin"""
_MIN_RECORD = {"cameras.bin": 4 + 4 + 8 + 8 + 8, "images.bin": 4 + 32 + 24 + 4 + 1 + 8,
               "points3D.bin": 8 + 24 + 3 + 8 + 8}
"""the smallest record of each binary model file (COLMAP's src/colmap/scene/reconstruction_io.cc)"""
_MODEL_FIX = "re-export the model from COLMAP (File > Export model), or pass a folder with an intact one"


def _check_binary_model(model_dir: Path) -> None:
    """Refuse damaged binary model files before pycolmap reads them: pycolmap reads a truncated cameras.bin
    without a word (the missing bytes as zeros) and spends minutes on a points3D.bin of junk claiming
    billions of points. Each file's count must fit its size; cameras.bin and images.bin are walked to
    their exact end (seeks only: a large images.bin is not read)."""
    for name, min_record in _MIN_RECORD.items():
        p = model_dir / name
        if not p.is_file():
            continue
        size = p.stat().st_size
        with open(p, "rb") as fh:
            head = fh.read(8)
            if len(head) < 8:
                raise InputError(f"COLMAP {name} is truncated ({size} bytes)", p, _MODEL_FIX)
            (count,) = struct.unpack("<Q", head)
            if count * min_record > size - 8:
                raise InputError(f"COLMAP {name} claims {count} records but has {size} bytes (truncated or not a "
                                 "COLMAP file)", p, _MODEL_FIX)
            end = _walk_cameras(fh, count) if name == "cameras.bin" else (
                _walk_images(fh, count, size) if name == "images.bin" else None)
        if end is not None and end != size:
            raise InputError(f"COLMAP {name} ends at byte {size}, its {count} records at byte {end} (truncated, or "
                             "not a COLMAP file)", p, _MODEL_FIX)


def _walk_cameras(fh, count: int) -> int | None:
    """The byte where cameras.bin's records end (None when a camera model id is unknown here)."""
    pos = 8
    for _ in range(count):
        fh.seek(pos)
        rec = fh.read(24)
        if len(rec) < 24:
            return pos + len(rec)
        n_params = COLMAP_MODEL_IDS.get(struct.unpack("<iiQQ", rec)[1])
        if n_params is None:
            return None
        pos += 24 + 8 * n_params
    return pos


def _walk_images(fh, count: int, size: int) -> int:
    """The byte where images.bin's records end (at most ``size``)."""
    pos = 8
    for _ in range(count):
        fh.seek(pos + 64)
        name_len = 0
        while True:
            chunk = fh.read(256)
            if not chunk:
                return size + 1
            k = chunk.find(b"\0")
            if k >= 0:
                name_len += k + 1
                break
            name_len += len(chunk)
        fh.seek(pos + 64 + name_len)
        n2d = fh.read(8)
        if len(n2d) < 8:
            return size + 1
        pos += 64 + name_len + 8 + 24 * struct.unpack("<Q", n2d)[0]
        if pos > size:
            return pos
    return pos


def read_reconstruction(model_dir: str | os.PathLike):
    """A COLMAP model folder as a ``pycolmap.Reconstruction``; a damaged one is an InputError naming it."""
    import pycolmap

    model_dir = Path(model_dir)
    _check_binary_model(model_dir)
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # noqa: BLE001 - pycolmap raises plain RuntimeError/ValueError on bad files
        why = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        raise InputError(f"cannot read COLMAP model ({why})", model_dir, _MODEL_FIX) from None


def _overwrite_guard(out: Path, overwrite: bool) -> None:
    if out.exists() and not overwrite:
        raise InputError("output folder already exists", out, "remove it or pass --overwrite")


def _copy_file(src: Path, dst: Path, mode: str) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if mode == "symlink":
        os.symlink(src.resolve(), dst)
    elif mode == "hardlink":
        try:
            os.link(src, dst)
        except OSError:  # other file system: fall back to a copy
            shutil.copy2(src, dst)
    else:
        shutil.copy2(src, dst)


@dataclasses.dataclass
class ColmapImportConfig:
    """Options of ``texstream import colmap``."""

    images: str | None = option(None, help="image folder (default: SRC/images, or the folder beside the model)")
    model: str | None = option(None, help="sparse model folder inside SRC (default: the largest of sparse/*, or SRC)")
    masks: str | None = option(None, help="mask folder with masks named like the images (.png), if any")
    copy_mode: str = option("copy", help="how images reach the capture folder", choices=("copy", "hardlink", "symlink"))
    points_ply: bool = option(True, help="also write the sparse points as points3D.ply (for meshing)")
    overwrite: bool = option(True, help="replace an existing output folder")


def _find_model(src: Path, cfg: ColmapImportConfig) -> Path:
    if cfg.model:
        cand = [src / cfg.model]
    elif any((src / f).exists() for f in ("cameras.bin", "cameras.txt")):
        cand = [src]
    else:
        cand = sorted(p for p in (src / "sparse").glob("*") if p.is_dir()) if (src / "sparse").is_dir() else []
        if (src / "sparse").is_dir() and any(((src / "sparse") / f).exists() for f in ("cameras.bin", "cameras.txt")):
            cand.append(src / "sparse")
    cand = [c for c in cand if any((c / f).exists() for f in ("cameras.bin", "cameras.txt"))]
    if not cand:
        raise InputError("no COLMAP sparse model found (cameras/images/points3D .bin or .txt)", src,
                         "pass a COLMAP project with sparse/0, the model folder itself, or --model")
    if len(cand) == 1:
        return cand[0]
    sizes = []
    for c in cand:
        try:
            sizes.append(read_reconstruction(c).num_reg_images())
        except InputError:  # an unreadable model is just not chosen
            sizes.append(-1)
    return cand[int(np.argmax(sizes))]


def import_colmap(src: str | os.PathLike, out: str | os.PathLike, config: ColmapImportConfig | None = None) -> StageResult:
    """Convert an existing COLMAP model and its images into a capture folder.

    Args:
        src: a COLMAP project folder (``images/`` + ``sparse/N``) or a model folder.
        out: capture folder to create (atomically): ``capture.json``, ``images/``, optional
            ``masks/``, ``points3D.ply``, ``sparse/0`` (the model as read), ``import_config.json``.
        config: options.

    Returns:
        StageResult with counts of imported and missing images.
    """
    cfg = config or ColmapImportConfig()
    src = Path(src)
    out = Path(out)
    if not src.exists():
        raise InputError("COLMAP source not found", src, "check the path")
    _overwrite_guard(out, cfg.overwrite)
    model_dir = _find_model(src, cfg)
    rec = read_reconstruction(model_dir)
    if cfg.images:
        img_dir = Path(cfg.images)
    else:
        tries = [src / "images", model_dir.parent.parent / "images", model_dir.parent / "images"]
        img_dir = next((t for t in tries if t.is_dir()), tries[0])
    try:
        frames_in = reconstruction_frames(rec)
    except InputError as e:  # a damaged camera or pose: name the model folder it came from
        raise InputError(e.message, e.path or model_dir, e.fix) from None
    if not frames_in:
        raise InputError("COLMAP model has no registered images", model_dir, "run COLMAP mapping first")
    missing = [n for n, *_ in frames_in if not (img_dir / n).is_file()]
    present = [f for f in frames_in if (img_dir / f[0]).is_file()]
    if not present:
        raise InputError(f"none of the model's {len(frames_in)} images are in the image folder", img_dir,
                         "pass --images pointing at the photos COLMAP used")
    mask_dir = Path(cfg.masks) if cfg.masks else None
    with atomic_output_dir(out) as tmp:
        frames = []
        for name, r, t, intr in present:
            dst = Path("images") / name
            _copy_file(img_dir / name, tmp / dst, cfg.copy_mode)
            mask_rel = None
            if mask_dir is not None:
                for cand in (mask_dir / (name + ".png"), mask_dir / (Path(name).stem + ".png"), mask_dir / name):
                    if cand.is_file():
                        mask_rel = str(Path("masks") / (Path(name).with_suffix(".png")))
                        _copy_file(cand, tmp / mask_rel, "copy")
                        break
            frames.append(Frame(file_path=str(dst), R=r, t=t, intrinsics=intr, mask_path=mask_rel))
        cap = Capture(root=tmp, frames=frames, extra={"source": f"colmap:{model_dir}"})
        write_capture(cap, tmp)
        (tmp / "sparse" / "0").mkdir(parents=True)
        rec.write(str(tmp / "sparse" / "0"))
        if cfg.points_ply and rec.num_points3D() > 0:
            rec.export_PLY(str(tmp / "points3D.ply"))
        save_config(cfg, tmp / "import_config.json")
    return StageResult(output=out, summary={"images": len(present), "missing_images": missing,
                                            "points3D": int(rec.num_points3D()), "model": str(model_dir)})


@dataclasses.dataclass
class NerfstudioImportConfig:
    """Options of ``texstream import nerfstudio``."""

    copy_mode: str = option("copy", help="how images reach the capture folder", choices=("copy", "hardlink", "symlink"))
    skip_missing: bool = option(True, help="drop frames whose image file is missing (listed in the summary) "
                                "instead of failing")
    overwrite: bool = option(True, help="replace an existing output folder")


def import_nerfstudio(src: str | os.PathLike, out: str | os.PathLike,
                      config: NerfstudioImportConfig | None = None) -> StageResult:
    """Convert a nerfstudio folder (``transforms.json`` + images) into a capture folder.

    Poses, intrinsics, masks and unknown keys are kept; images (and masks) are copied under
    ``images/`` (``masks/``) keeping their relative names, and ``capture.json`` points at them.

    Args:
        src: nerfstudio data folder holding ``transforms.json``, or the JSON file itself.
        out: capture folder to create (atomically).
        config: options.
    """
    cfg = config or NerfstudioImportConfig()
    src = Path(src)
    out = Path(out)
    if src.is_dir() and not (src / "transforms.json").exists():
        raise InputError("no transforms.json in the folder", src, "pass a nerfstudio data folder (ns-process-data output)")
    _overwrite_guard(out, cfg.overwrite)
    cap = read_capture(src if src.is_file() else src / "transforms.json")
    root = cap.root
    kept, missing = [], []
    for f in cap.frames:
        p = root / f.file_path
        if not p.is_file() and p.suffix == "" :
            # nerfstudio sometimes stores paths without extension; try the usual ones.
            p = next((p.with_suffix(e) for e in IMAGE_EXTS if p.with_suffix(e).is_file()), p)
        if p.is_file():
            kept.append((f, p))
        else:
            missing.append(f.file_path)
    if missing and not cfg.skip_missing:
        raise InputError(f"{len(missing)} frame image(s) missing, e.g. {missing[0]}", root,
                         "put the images beside transforms.json or pass --skip-missing")
    if not kept:
        raise InputError("none of the frames' images exist", root, "put the images beside transforms.json")
    used: set[str] = set()
    with atomic_output_dir(out) as tmp:
        frames = []
        for f, p in kept:
            rel = Path(f.file_path)
            rel = Path(*[x for x in rel.parts if x not in ("..", ".")])
            rel = rel if rel.parts and rel.parts[0] == "images" else Path("images") / rel
            if rel.suffix == "":
                rel = rel.with_suffix(p.suffix)
            if str(rel) in used:
                raise InputError(f"two frames use the same image {rel}", root, "remove the duplicate frame")
            used.add(str(rel))
            _copy_file(p, tmp / rel, cfg.copy_mode)
            mask_rel = None
            if f.mask_path:
                mp = root / f.mask_path
                if not mp.is_file():
                    raise InputError(f"mask {f.mask_path} of frame {f.file_path} not found", root,
                                     "fix mask_path or remove it")
                mask_rel = str(Path("masks") / rel.relative_to("images").with_suffix(mp.suffix))
                _copy_file(mp, tmp / mask_rel, "copy")
            frames.append(dataclasses.replace(f, file_path=str(rel), mask_path=mask_rel))
        extra = dict(cap.extra)
        extra.setdefault("source", f"nerfstudio:{root}")
        write_capture(Capture(root=tmp, frames=frames, extra=extra), tmp)
        save_config(cfg, tmp / "import_config.json")
    return StageResult(output=out, summary={"images": len(frames), "missing_images": missing})
