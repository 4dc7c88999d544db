"""Single-view, many-light fits (photometric-stereo style): the image grid is the texel grid. This module
holds their geometry, problem and renders; the stage (the model choice, shared materials, the model folder)
is fit/stages/single_view.py.

One camera, one photo per known light, and the geometry as a per-pixel normal map instead of a
mesh: no SfM, no mesh, no atlas. Each pixel inside the object mask is a texel of the SAME
streaming fit as ``texstream fit --mesh`` (fit/kernels/stream.py, fit/optim/fitter.py):

- position: the point on the pixel-centre ray at depth z (camera z, OpenCV axes) given by a
  depth map (``depth.npy`` / ``depth.exr`` beside capture.json) or a nominal ``depth``. With
  directional lights only the view direction matters, and that is the ray's direction whatever
  z is; point lights need real depths (a depth map, or the right nominal depth).
- normal: from the normal map, in the space ``normal_space`` names (see the stage's SingleViewConfig).
- tangent: the camera's x axis made orthogonal to the normal; bitangent = normal x tangent.
  Isotropic lobes (the default) depend only on u.v and u_z v_z, which no rotation of the tangent
  frame about the normal changes; anisotropic lobes are then aligned with the image's x axis.
- visibility: no depth test (there is no geometry to test against; ``PhotoSet`` without a mesh
  sets ``ImageInfo.depth_is_mask``), only each photo's mask; cast shadows are not detected, so
  mask shadowed pixels per photo (``mask_path`` in capture.json) when the object has any.

Since a texel projects exactly onto its pixel centre, the kernels' bilinear filter returns the
pixel's value (up to float rounding, ~1e-6 of a neighbour). The image's outermost rows and
columns are not texels: the kernels' out-of-frame test rejects the last row / column, and
rounding can put the first at -1e-7.

Folder layout::

    CAPTURE/capture.json    frames share one camera (same pose and intrinsics), each with a light
    CAPTURE/images/...      the photos (linear, as in any capture folder)
    normals.(png|exr|npy)   normal map, same size as the photos (path given separately)
    CAPTURE/mask.png        optional object mask (else: pixels with a valid normal)
    CAPTURE/depth.(npy|exr) optional depth map (camera z, world units)

OpenImageIO (capture.imageio) is imported inside the functions that read files.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import warp as wp

from texstream.capture.capture_json import no_flash_frames, read_capture, split_holdout
from texstream.capture.imageio import read_image, read_mask
from texstream.core.errors import ConfigError, InputError
from texstream.fit.common.inputs import validation_period
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.kernels import stream
from texstream.fit.stream.photo_set import PhotoSet
from texstream.fit.stream.problem import PhotoFrame, StreamProblem
from texstream.fit.stream.texels import TexelSet
from texstream.render.shading import incident_light, lafortune_brdf, to_local
from texstream.render.layout import ModelLayout

NORMAL_SPACES = ("opengl", "opencv", "world")
FLOAT_NORMAL_SUFFIXES = (".exr", ".hdr", ".pfm", ".npy")


@dataclasses.dataclass
class SingleViewGeometry:
    """Per-pixel surface of a single-view capture (all arrays (H, W, ...), world frame).

    Attributes:
        covered: (H, W) bool, pixels that are texels (mask, valid normal, not on the image border).
        position, normal, tangent, bitangent: (H, W, 3) float32.
    """

    covered: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    bitangent: np.ndarray


# --------------------------------------------------------------------------- inputs


def read_normal_map(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a normal map; returns unit normals (H, W, 3) float32 and validity (H, W) bool.

    ``.npy`` (H, W, 3), ``.exr`` / ``.hdr`` / ``.pfm`` hold signed components as they are; other
    formats (PNG, 8/16-bit TIFF, JPEG) are RGB-encoded, n = 2 c - 1 with c in [0, 1] (no sRGB
    decoding). A pixel is valid when its vector is finite with length in [0.5, 1.5] (zero and
    black backgrounds are not; quantised 8-bit normals are within 1% of unit length).
    """
    p = Path(path)
    if not p.exists():
        raise InputError("normal map not found", p, "pass --normals with a .png, .exr or .npy normal map")
    if p.suffix.lower() == ".npy":
        try:
            n = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise InputError(f"normal map is not a readable .npy array ({e})", p, "save it with numpy.save") from None
        if n.ndim != 3 or n.shape[2] < 3 or n.dtype.kind not in "fiu":
            raise InputError(f"normal map has shape {n.shape} dtype {n.dtype}, expected (H, W, 3) floats", p,
                             "save an (H, W, 3) float array of unit normals")
        n = n[..., :3].astype(np.float32)
    else:
        encoded = p.suffix.lower() not in FLOAT_NORMAL_SUFFIXES
        n = read_image(p, channels=3, linear=not encoded)
        if encoded:
            n = 2.0 * n - 1.0
    with np.errstate(invalid="ignore"):
        length = np.linalg.norm(n, axis=2)
        valid = np.isfinite(length) & (length >= 0.5) & (length <= 1.5)
    out = np.zeros_like(n, dtype=np.float32)
    out[valid] = n[valid] / length[valid, None]
    if not valid.any():
        raise InputError("normal map has no valid normal (length 0.5..1.5)", p,
                         "encode normals as RGB = (n + 1) / 2, or store signed floats in .exr / .npy")
    return out, valid


def _read_plane(path: Path, shape: tuple[int, int], what: str) -> np.ndarray:
    """An (H, W) float32 plane (depth map) from .npy or an image file, checked against ``shape``."""
    if path.suffix.lower() == ".npy":
        try:
            a = np.load(path, allow_pickle=False).astype(np.float32)
        except (OSError, ValueError) as e:
            raise InputError(f"{what} is not a readable .npy array ({e})", path, "save it with numpy.save") from None
        if a.ndim == 3:
            a = a[..., 0]
    else:
        a = read_image(path, channels=1, linear=False)[..., 0]
    if a.shape != tuple(shape):
        raise InputError(f"{what} is {a.shape[1]}x{a.shape[0]} but the normal map is {shape[1]}x{shape[0]}", path,
                         f"make the {what} the same size as the normal map")
    return a


def shared_camera(frames, where: Path):
    """The one camera (R, t, Intrinsics) all frames share; InputError if they differ or have no light."""
    f0 = frames[0]
    for f in frames:
        if f.light is None:
            raise InputError(f"frame {f.file_path} has no light", where, "give every frame a directional (or point) light")
        same = (np.allclose(f.R, f0.R, atol=1e-6) and np.allclose(f.t, f0.t, atol=1e-6 * max(1.0, np.abs(f0.t).max()))
                and f.intrinsics.to_json() == f0.intrinsics.to_json())
        if not same:
            raise InputError(f"frame {f.file_path} has another camera pose or intrinsics than {f0.file_path}", where,
                             "a single-view capture has one camera; fit multi-view captures with --mesh")
    if not f0.intrinsics.is_pinhole:
        raise InputError("the camera has lens distortion", where, "undistort the photos and the normal map first")
    return f0.R, f0.t, f0.intrinsics


def single_view_geometry(normals: np.ndarray, valid: np.ndarray, R: np.ndarray, t: np.ndarray, intr,
                         normal_space: str = "opengl", depth: np.ndarray | float = 1.0,
                         mask: np.ndarray | None = None) -> SingleViewGeometry:
    """Texel positions and frames of every pixel (see the module doc).

    Args:
        normals: (H, W, 3) unit normals in ``normal_space``.
        valid: (H, W) bool, pixels with a normal.
        R, t: world-to-camera rotation (3, 3) and translation (3,), OpenCV axes.
        intr: :class:`texstream.capture.capture_json.Intrinsics` (pixel centres at +0.5).
        normal_space: "opengl", "opencv" (camera frames) or "world".
        depth: camera z per pixel (H, W) or one number (world units); pixels with z <= 0 are dropped.
        mask: optional (H, W) bool object mask.
    """
    h, w = valid.shape
    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64).reshape(3)
    n = normals.reshape(-1, 3).astype(np.float64)
    if normal_space == "opengl":
        n = n * np.array([1.0, -1.0, -1.0])  # GL camera axes -> CV camera axes
    if normal_space in ("opengl", "opencv"):
        n = n @ R  # camera -> world: R^T n, row vectors
    elif normal_space != "world":
        raise InputError(f"normal space {normal_space!r} unknown", fix=f"use one of {NORMAL_SPACES}")
    z = np.broadcast_to(np.asarray(depth, np.float64), (h, w))
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pc = np.stack([(xs + 0.5 - intr.cx) / intr.fx * z, (ys + 0.5 - intr.cy) / intr.fy * z, z], axis=-1)
    pos = (pc.reshape(-1, 3) - t) @ R  # R^T (p_c - t)
    a = np.broadcast_to(R[0], n.shape).copy()  # camera x axis in world
    near = np.abs(n @ R[0]) > 0.9
    a[near] = R[1]
    tan = a - n * np.sum(n * a, axis=1, keepdims=True)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-30)
    bit = np.cross(n, tan)
    covered = valid & np.isfinite(z) & (z > 0)
    if mask is not None:
        covered &= mask
    covered[0, :] = covered[-1, :] = False  # image border: see the module doc
    covered[:, 0] = covered[:, -1] = False

    def grid(a):
        return a.reshape(h, w, 3).astype(np.float32)

    return SingleViewGeometry(covered, grid(pos), grid(n), grid(tan), grid(bit))


def find_normal_map(capture_dir: str | Path) -> Path:
    """``normals.exr``, ``normals.npy`` or ``normals.png`` beside capture.json (first found)."""
    root = Path(capture_dir)
    root = root if root.is_dir() else root.parent
    for name in ("normals.exr", "normals.npy", "normals.png"):
        if (root / name).exists():
            return root / name
    raise InputError("no normal map (normals.exr, normals.npy or normals.png) beside capture.json", root,
                     "put the normal map there or pass its path (--normals)")


def load_single_view(capture_dir: str | Path, normals_path: str | Path | None, cfg):
    """(capture, fitted frames, held-out frames, geometry, images, masks) of a single-view capture (``cfg``: the
    stage's SingleViewConfig: normal_space, depth, holdout_every)."""
    capture = read_capture(capture_dir)
    if normals_path is None:
        normals_path = find_normal_map(capture.root)
    where = capture.root / "capture.json"
    R, t, intr = shared_camera(capture.frames, where)
    normals, valid = read_normal_map(normals_path)
    shape = normals.shape[:2]
    if shape != (intr.height, intr.width):
        raise InputError(f"normal map is {shape[1]}x{shape[0]} but the camera is {intr.width}x{intr.height}",
                         normals_path, "give a normal map of the photos' size")
    mask = None
    if (capture.root / "mask.png").exists():
        mask = read_mask(capture.root / "mask.png", shape)
    depth: np.ndarray | float = float(cfg.depth)
    dfile = next((capture.root / n for n in ("depth.npy", "depth.exr") if (capture.root / n).exists()), None)
    if dfile is not None:
        depth = _read_plane(dfile, shape, "depth map")
    elif not cfg.depth > 0:
        raise InputError(f"nominal depth {cfg.depth} is not positive", fix="pass a positive --depth")
    geo = single_view_geometry(normals, valid, R, t, intr, cfg.normal_space, depth, mask)
    if not geo.covered.any():
        raise InputError("no pixel has both a valid normal and the object mask", normals_path,
                         "check that mask.png and the normal map cover the same object")
    if no_flash_frames(capture.frames):  # its per-pixel fit has no ambient term: they would be predicted black
        raise ConfigError(f"{len(no_flash_frames(capture.frames))} photos of the single-view capture were taken with "
                          "the flash off", fix="fit the single view from its flash photos alone (leave the no-flash "
                                                "ones out of capture.json)")
    frames, held = split_holdout(capture.frames, cfg.holdout_every)
    if cfg.choice.validation_fit:  # the model choice's fit of a candidate: the validation photos are scored instead
        frames, held = split_holdout(frames, validation_period(len(frames), cfg.materials.validation_every))
    images, masks = [], []
    for f in frames:
        im = read_image(capture.image_path(f), channels=3, response=capture.response)
        if im.shape[:2] != shape:
            raise InputError(f"photo is {im.shape[1]}x{im.shape[0]} but the normal map is {shape[1]}x{shape[0]}",
                             capture.image_path(f), "give photos and normal map of one size")
        images.append(im)
        mp = capture.mask_path(f)
        masks.append(read_mask(mp, shape) if mp is not None and mp.exists() else None)
    return capture, frames, held, geo, images, masks


def build_single_view_problem(geo: SingleViewGeometry, frames, images, masks, cfg: FitConfig, device: str):
    """A :class:`StreamProblem` over the covered pixels, photos without geometry (no depth test)."""
    texels = TexelSet.from_grid(geo.covered, geo.position, geo.normal, geo.tangent, geo.bitangent)
    photo_frames = [PhotoFrame.from_capture_frame(f) for f in frames]
    photos = PhotoSet(photo_frames, images, None, None, masks=masks, config=cfg.stream, device=device)
    layout = cfg.layout(photo_frames, texels.position.mean(axis=0))
    if layout.ambient or layout.room:  # its per-pixel render (render_single_view) has no ambient term
        raise ConfigError("the single-view fit (--normals) has no ambient term", fix="use --ambient off or auto")
    return StreamProblem(texels, photos, layout, cfg.stream, device=device)


# --------------------------------------------------------------------------- rendering the fit


@wp.kernel(enable_backward=False)
def render_texels_kernel(pos: wp.array(dtype=wp.vec3), nrm: wp.array(dtype=wp.vec3), tan: wp.array(dtype=wp.vec3),
                         bit: wp.array(dtype=wp.vec3), params: wp.array2d(dtype=wp.float32), n_lobes: int, aniso: int,
                         info: stream.ImageInfo, out: wp.array(dtype=wp.vec3)):
    """Pixel value exposure * E * cos(theta_i) * f_r of each texel under one photo's light and camera
    (0 when lit or seen from behind the surface), the model the fit's residuals use."""
    i = wp.tid()
    p = pos[i]
    n = nrm[i]
    wi, e_int, dist = incident_light(info.light_kind, info.light_vec, info.light_intensity, p)
    vdir = wp.normalize(info.center - p)
    cos_i = wp.dot(wi, n)
    val = wp.vec3(0.0)
    if cos_i > 0.0 and wp.dot(vdir, n) > 0.0:
        u = to_local(wi, tan[i], bit[i], n)
        v = to_local(vdir, tan[i], bit[i], n)
        f = lafortune_brdf(params, i, n_lobes, aniso, u, v, 1.0)
        val = info.exposure * cos_i * wp.cw_mul(f, e_int)
    out[i] = val


def render_single_view(problem, params: np.ndarray, layout: ModelLayout, frame) -> np.ndarray:
    """Render fitted per-texel ``params`` (N, P) for a capture frame; returns (H, W, 3) float32."""
    fr = PhotoFrame.from_capture_frame(frame)
    info = stream.ImageInfo()
    info.center = wp.vec3(*(-np.asarray(fr.R).T @ np.asarray(fr.t)).astype(np.float32))
    info.exposure = float(fr.exposure)
    info.light_kind = 0 if fr.light_kind == "point" else 1
    info.light_vec = wp.vec3(*np.asarray(fr.light_vec, np.float32))
    info.light_intensity = wp.vec3(*np.asarray(fr.light_intensity, np.float32))
    dev = problem.device
    out = wp.zeros(problem.n, dtype=wp.vec3, device=dev)
    prm = wp.array(np.ascontiguousarray(params, np.float32), dtype=wp.float32, device=dev)
    wp.launch(render_texels_kernel, dim=problem.n, device=dev,
              inputs=[problem.pos, problem.nrm, problem.tan, problem.bit, prm, layout.n_lobes,
                      int(layout.anisotropic), info], outputs=[out])
    tx = problem.texels
    img = np.zeros((tx.height * tx.width, 3), np.float32)
    img[tx.grid_index] = out.numpy()
    return img.reshape(tx.height, tx.width, 3)
