"""Visual hull from object masks and cameras: voxel carving in Warp, surface by marching cubes.

Each mask becomes a signed distance image in pixels (positive inside the object). A module-level
Warp kernel projects every grid node into every mask (pinhole, world-to-camera R, t in OpenCV axes,
pixel centres at +0.5; see :mod:`texstream.capture.conventions`), samples that image bilinearly and
scales it by depth / focal length to world units; the node's value is the minimum over the views
that see it. Its zero level set is the boundary of the visual hull (the intersection of the
silhouette cones) located to sub-voxel precision, which ``wp.MarchingCubes`` extracts. Nodes seen by
fewer than ``min_views`` cameras are carved (the hull is only defined where cameras constrain it).

Bounds come from the caller or from a coarse pass: the grid starts as a cube around the point
nearest to all optical axes and is refitted to the coarse hull. An optional second surface (e.g.
the Poisson mesh) is intersected as a signed distance field (min of the two fields).

Imports numpy and warp at module level; scipy / OpenImageIO inside functions.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
from typing import Sequence

import numpy as np
import warp as wp

from texstream.capture.capture_json import Frame, Intrinsics
from texstream.capture.conventions import look_at_w2c
from texstream.capture.imageio import read_mask
from texstream.core.errors import InputError, StageError
from texstream.core.config import option

from texstream.render.mesh import SurfaceMesh
from .clean import CleanConfig, clean_mesh
from .scene import genus_by_component


@dataclasses.dataclass
class HullConfig:
    """Visual-hull options."""

    resolution: int = option(128, help="grid nodes along the longest side of the bounding box")
    min_views: int = option(2, help="carve grid nodes seen (inside the image) by fewer cameras than this")
    carve_outside_image: bool = option(True, help="carve points that project outside an image (the object is "
                                                  "assumed whole in every photo); off: such views say nothing")
    margin: float = option(0.05, help="bounding box padding, fraction of its diagonal")
    clean: bool = option(True, help="clean the marching-cubes surface (weld, orient outwards)")
    fill_holes: float = option(0.01, help="fill holes in each mask smaller than this fraction of its object area "
                                          "before carving (0: off); a hole in one mask carves a tunnel through the "
                                          "hull along that view (the Middlebury temple's threshold masks have holes "
                                          "of up to 205 px in 70,000 px silhouettes; its real gaps between the "
                                          "columns are 8,000 px, 11%)")
    closing: int = option(0, help="morphological closing of the carved field with a ball of this radius in grid "
                                  "cells before marching cubes (0: off): closes tunnels and gaps narrower than "
                                  "about two cells that voxel carving and mask noise leave")


@wp.kernel(enable_backward=False)
def _carve_kernel(lo: wp.vec3, step: wp.vec3, rots: wp.array(dtype=wp.mat33), trans: wp.array(dtype=wp.vec3),
                  ks: wp.array(dtype=wp.vec4), sizes: wp.array(dtype=wp.vec2i), sdf: wp.array3d(dtype=wp.float32),
                  min_views: int, carve_outside: int, field: wp.array3d(dtype=wp.float32)):
    x, y, z = wp.tid()
    p = lo + wp.cw_mul(step, wp.vec3(float(x), float(y), float(z)))
    value = float(1.0e30)
    seen = int(0)
    for c in range(rots.shape[0]):
        pc = rots[c] * p + trans[c]
        if pc[2] <= 0.0:
            if carve_outside != 0:
                value = -1.0e30
            continue
        k = ks[c]
        # continuous pixel coords; pixel (i, j) centre at (i + 0.5, j + 0.5) -> array index coords
        u = k[0] * pc[0] / pc[2] + k[2] - 0.5
        v = k[1] * pc[1] / pc[2] + k[3] - 0.5
        w = sizes[c][0]
        h = sizes[c][1]
        if u < 0.0 or v < 0.0 or u > float(w - 1) or v > float(h - 1):
            if carve_outside != 0:
                value = -1.0e30
            continue
        seen += 1
        i0 = wp.min(int(u), w - 2)
        j0 = wp.min(int(v), h - 2)
        fu = u - float(i0)
        fv = v - float(j0)
        s = (1.0 - fv) * ((1.0 - fu) * sdf[c, j0, i0] + fu * sdf[c, j0, i0 + 1]) + \
            fv * ((1.0 - fu) * sdf[c, j0 + 1, i0] + fu * sdf[c, j0 + 1, i0 + 1])
        # pixels -> world units at this depth
        value = wp.min(value, s * pc[2] / wp.min(k[0], k[1]))
    if seen < min_views:
        value = -1.0e30
    field[x, y, z] = value


@wp.kernel(enable_backward=False)
def _mesh_sdf_kernel(mesh: wp.uint64, lo: wp.vec3, step: wp.vec3, max_dist: float,
                     field: wp.array3d(dtype=wp.float32)):
    x, y, z = wp.tid()
    p = lo + wp.cw_mul(step, wp.vec3(float(x), float(y), float(z)))
    q = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist)
    d = max_dist
    if q.result:
        d = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - p)
        # winding-number sign: -1 inside; the field is positive inside
        field[x, y, z] = wp.min(field[x, y, z], -q.sign * d)
    else:
        field[x, y, z] = wp.min(field[x, y, z], -d)


def fill_small_holes(mask: np.ndarray, max_fraction: float) -> np.ndarray:
    """The mask with its holes (background regions not touching the image border) smaller than
    ``max_fraction`` of its object area filled."""
    from scipy.ndimage import label

    m = np.asarray(mask).astype(bool)
    if max_fraction <= 0 or not m.any():
        return m
    lab, n = label(~m)
    if n == 0:
        return m
    sizes = np.bincount(lab.reshape(-1), minlength=n + 1)
    small = sizes < max_fraction * float(m.sum())
    small[0] = False
    small[np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))] = False
    return m | small[lab]


def close_field(field: np.ndarray, radius: int) -> np.ndarray:
    """Grey-scale morphological closing (max then min filter over a ball of ``radius`` cells) of a field
    that is positive inside: the inside set gets closed, so tunnels and gaps narrower than about
    ``2 * radius`` cells fill while the surface elsewhere stays where it was."""
    from scipy.ndimage import grey_closing

    if radius <= 0:
        return field
    r = int(radius)
    g = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
    ball = (g ** 2).sum(axis=0) <= r * r + r  # r = 1: the 3x3x3 cube minus its corners
    return grey_closing(field, footprint=ball, mode="nearest")


def mask_sdf(mask: np.ndarray) -> np.ndarray:
    """Signed distance in pixels to the mask boundary (positive inside), float32 (H, W)."""
    from scipy.ndimage import distance_transform_edt

    m = np.asarray(mask).astype(bool)
    if m.all():
        return np.full(m.shape, 1e6, np.float32)
    if not m.any():
        return np.full(m.shape, -1e6, np.float32)
    # the boundary lies half a pixel from the centres on either side
    return (np.where(m, distance_transform_edt(m) - 0.5, -(distance_transform_edt(~m) - 0.5))).astype(np.float32)


_FIELDS_CACHE: collections.OrderedDict = collections.OrderedDict()
_FIELDS_CACHE_BYTES = 1024 * 2 ** 20
"""the most bytes of filled masks and signed distances :func:`mask_fields` keeps: the mesh stage carves the same
masks three times (the coarse bounds, the hull, the hull of the Poisson intersection), and each mask's hole filling
and two distance transforms cost more than the carving (11 masks of 3072x2048: 340 MB, 11-13 s a pass on the
2-core CPU)"""


def mask_fields(masks: Sequence[np.ndarray], fill_holes: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(each mask with its small holes filled (:func:`fill_small_holes`), its signed distance
    (:func:`mask_sdf`)), remembered by the mask's bytes for the next call with the same masks. Masks of other calls
    are forgotten first; masks past the budget are computed each time and not kept, so that a set larger than the
    budget still finds its first masks on the next pass (forgetting the oldest, as before, made every pass of the
    6 MP run's 11 masks miss: a pass reads them in the order the last one stored them)."""
    keys = [(hashlib.blake2b(np.ascontiguousarray(m).tobytes(), digest_size=16).hexdigest(), np.shape(m),
             np.asarray(m).dtype.str, float(fill_holes)) for m in masks]
    wanted = set(keys)
    filled, sdfs = [], []
    for m, key in zip(masks, keys):
        if key in _FIELDS_CACHE:
            fm, sdf = _FIELDS_CACHE[key]
        else:
            fm = fill_small_holes(m, fill_holes)
            sdf = mask_sdf(fm)
            fm.setflags(write=False)  # shared by every caller of this mask: read only
            sdf.setflags(write=False)
            size = fm.nbytes + sdf.nbytes
            for old in [k for k in _FIELDS_CACHE if k not in wanted]:  # another capture's
                if sum(a.nbytes + b.nbytes for a, b in _FIELDS_CACHE.values()) + size <= _FIELDS_CACHE_BYTES:
                    break
                del _FIELDS_CACHE[old]
            if sum(a.nbytes + b.nbytes for a, b in _FIELDS_CACHE.values()) + size <= _FIELDS_CACHE_BYTES:
                _FIELDS_CACHE[key] = (fm, sdf)
        filled.append(fm)
        sdfs.append(sdf)
    return filled, sdfs


def _camera_arrays(frames: Sequence, sdfs: list[np.ndarray], device: str):
    n = len(frames)
    hmax = max(s.shape[0] for s in sdfs)
    wmax = max(s.shape[1] for s in sdfs)
    stack = np.full((n, hmax, wmax), -1e6, np.float32)
    for i, s in enumerate(sdfs):
        stack[i, : s.shape[0], : s.shape[1]] = s
    rots = np.stack([np.asarray(f.R, np.float32) for f in frames])
    trans = np.stack([np.asarray(f.t, np.float32).reshape(3) for f in frames])
    ks = np.array([[f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy] for f in frames], np.float32)
    sizes = np.array([[s.shape[1], s.shape[0]] for s in sdfs], np.int32)
    return (wp.array(rots, dtype=wp.mat33, device=device), wp.array(trans, dtype=wp.vec3, device=device),
            wp.array(ks, dtype=wp.vec4, device=device), wp.array(sizes, dtype=wp.vec2i, device=device),
            wp.array(stack, dtype=wp.float32, device=device))


def _grid(lo: np.ndarray, hi: np.ndarray, resolution: int) -> tuple[tuple[int, int, int], np.ndarray]:
    ext = hi - lo
    h = float(ext.max()) / (resolution - 1)
    dims = tuple(int(max(3, np.ceil(e / h) + 1)) for e in ext)
    return dims, np.full(3, h)


def axes_convergence(frames: Sequence) -> tuple[np.ndarray, float]:
    """The point nearest (least squares) to all optical axes, and the mean camera distance to it."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    centers = []
    for f in frames:
        r = np.asarray(f.R, np.float64)
        c = -r.T @ np.asarray(f.t, np.float64).reshape(3)
        d = r[2]  # optical axis (camera +z) in world coordinates
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c
        centers.append(c)
    centers = np.array(centers)
    try:
        x = np.linalg.solve(a + 1e-9 * np.eye(3), b)
    except np.linalg.LinAlgError:
        x = centers.mean(axis=0)
    return x, float(np.linalg.norm(centers - x, axis=1).mean())


def carve_field(frames: Sequence, sdfs: list[np.ndarray], lo: np.ndarray, hi: np.ndarray, resolution: int,
                min_views: int, device: str, carve_outside: bool = True) -> tuple[wp.array, np.ndarray, np.ndarray]:
    """Carved field on a grid over [lo, hi]: (field (nx, ny, nz) Warp array, grid lower corner, step)."""
    dims, step = _grid(lo, hi, resolution)
    rots, trans, ks, sizes, stack = _camera_arrays(frames, sdfs, device)
    field = wp.empty(dims, dtype=wp.float32, device=device)
    wp.launch(_carve_kernel, dim=dims,
              inputs=[wp.vec3(*lo.astype(np.float32)), wp.vec3(*step.astype(np.float32)), rots, trans, ks, sizes,
                      stack, int(min_views), int(carve_outside)],
              outputs=[field], device=device)
    return field, lo, step


def _occupied_bounds(field: np.ndarray, lo: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    idx = np.argwhere(field > 0)
    if len(idx) == 0:
        return None
    return lo + step * (idx.min(axis=0) - 1), lo + step * (idx.max(axis=0) + 1)


def _coarse_bounds(frames: Sequence, sdfs: list[np.ndarray], cfg: HullConfig, device: str
                   ) -> tuple[np.ndarray, np.ndarray]:
    centre, dist = axes_convergence(frames)
    half = 0.75 * dist  # the object lies between the cameras; a cube reaching 3/4 of the way out
    coarse, clo, cstep = carve_field(frames, sdfs, centre - half, centre + half, 48, cfg.min_views, device,
                                     cfg.carve_outside_image)
    ob = _occupied_bounds(coarse.numpy(), clo, cstep)
    if ob is None:
        raise StageError("the masks carve away everything: no point is inside the silhouettes of all cameras "
                         "(cameras misaligned with the masks?)",
                         fix="check the poses and masks, or use --from sfm or --from scan.obj")
    return ob


def hull_bounds(frames: Sequence, masks: Sequence[np.ndarray], config: HullConfig | None = None,
                device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """The bounding box (lo, hi) of a coarse visual hull (48 grid nodes along the cube the cameras look
    into), one grid step larger on each side: where the object is, for a depth range.

    Raises:
        StageError: the masks carve away everything.
    """
    cfg = config or HullConfig()
    return _coarse_bounds(frames, mask_fields(masks, cfg.fill_holes)[1], cfg, device)


def visual_hull(frames: Sequence, masks: Sequence[np.ndarray], config: HullConfig | None = None,
                device: str = "cpu", bounds: tuple[np.ndarray, np.ndarray] | None = None,
                intersect: SurfaceMesh | None = None, report: dict | None = None) -> SurfaceMesh:
    """Visual hull of object masks seen by posed pinhole cameras.

    Args:
        frames: frames with R, t, intrinsics (world-to-camera, OpenCV axes).
        masks: one (H, W) mask per frame, nonzero = object; its size must match the frame's.
        config: options.
        device: Warp device.
        bounds: (lo, hi) world box holding the object; estimated from the cameras when None.
        intersect: a closed mesh to intersect the hull with (e.g. the Poisson surface).
        report: when given, receives the mask holes filled and the genus of the marching-cubes surface
            without and with the closing (one more marching-cubes pass).

    Returns:
        The hull surface (outward faces when ``config.clean``).

    Raises:
        InputError: mask sizes do not match the cameras, or fewer than 2 frames.
        StageError: the masks and cameras carve everything away (cameras misaligned with the masks).
    """
    cfg = config or HullConfig()
    if len(frames) != len(masks):
        raise InputError(f"{len(masks)} masks for {len(frames)} frames", fix="give one mask per frame")
    if len(frames) < 2:
        raise InputError("a visual hull needs masks from at least 2 cameras", fix="add masked views, or use --from sfm")
    for f, m in zip(frames, masks):
        if np.asarray(m).shape[:2] != (f.intrinsics.height, f.intrinsics.width):
            raise InputError(f"mask of {f.file_path} is {np.asarray(m).shape[:2]} but the image is "
                             f"{(f.intrinsics.height, f.intrinsics.width)}", f.mask_path,
                             "write masks at the image resolution")
    filled, sdfs = mask_fields(masks, cfg.fill_holes)
    if report is not None:
        report["mask_pixels_filled"] = int(sum(int(fm.sum() - np.count_nonzero(m)) for fm, m in zip(filled, masks)))
    if bounds is None:
        lo, hi = _coarse_bounds(frames, sdfs, cfg, device)
    else:
        lo, hi = (np.asarray(b, np.float64) for b in bounds)
    pad = cfg.margin * float(np.linalg.norm(hi - lo))
    lo, hi = lo - pad, hi + pad
    field, lo, step = carve_field(frames, sdfs, lo, hi, cfg.resolution, cfg.min_views, device,
                                     cfg.carve_outside_image)
    if intersect is not None:
        wm = wp.Mesh(points=wp.array(np.asarray(intersect.vertices, np.float32), dtype=wp.vec3, device=device),
                     indices=wp.array(np.asarray(intersect.faces, np.int32).reshape(-1), dtype=wp.int32, device=device),
                     support_winding_number=True)
        wp.launch(_mesh_sdf_kernel, dim=field.shape,
                  inputs=[wm.id, wp.vec3(*lo.astype(np.float32)), wp.vec3(*step.astype(np.float32)),
                          float(np.linalg.norm(hi - lo))], outputs=[field], device=device)
    f = field.numpy()
    # close the surface at the grid border
    f[0, :, :] = f[-1, :, :] = f[:, 0, :] = f[:, -1, :] = f[:, :, 0] = f[:, :, -1] = -1.0
    if not (f > 0).any():
        raise StageError("the visual hull is empty (the masks and cameras disagree everywhere)",
                         fix="check the poses and masks, or use --from sfm or --from scan.obj")
    f = np.clip(f, -10 * step[0], 10 * step[0])  # clamp the 1e30 sentinels before interpolation
    if report is not None and cfg.closing > 0:
        report["genus_before_closing"] = genus_by_component(_extract(f, lo, step, device))["total"]
    f = close_field(f, cfg.closing)
    f[0, :, :] = f[-1, :, :] = f[:, 0, :] = f[:, -1, :] = f[:, :, 0] = f[:, :, -1] = -10 * step[0]
    mesh = _extract(f, lo, step, device)
    if report is not None:
        report["closing_cells"] = int(cfg.closing)
        report["genus"] = genus_by_component(mesh)["total"]
    if cfg.clean:
        mesh, _ = clean_mesh(mesh, CleanConfig(hausdorff=False, max_hole_edges=0))
    return mesh


def _extract(f: np.ndarray, lo: np.ndarray, step: np.ndarray, device: str) -> SurfaceMesh:
    """Marching cubes of the zero level set of a field that is positive inside."""
    upper = lo + step * (np.array(f.shape) - 1)
    verts, idx = wp.MarchingCubes.extract(wp.array(-f, dtype=wp.float32, device=device), 0.0,
                                          lower=tuple(lo.astype(np.float32)), upper=tuple(upper.astype(np.float32)))
    return SurfaceMesh(verts.numpy().astype(np.float64), idx.numpy().reshape(-1, 3).astype(np.int32))


def load_masks(capture) -> list[np.ndarray]:
    """Read every frame's mask (True = object) with :func:`texstream.capture.imageio.read_mask`.

    Raises:
        InputError: a frame has no mask_path, or its mask is unreadable or not the photo's size.
    """
    masks = []
    for f in capture.frames:
        p = capture.mask_path(f)
        if p is None:
            raise InputError(f"frame {f.file_path} has no mask_path", capture.root / "capture.json",
                             "give every frame a mask, or use --from sfm")
        masks.append(read_mask(p, (f.intrinsics.height, f.intrinsics.width)))
    return masks


def orbit_frames(center, radius: float, n_azimuth: int = 8, elevations_deg: Sequence[float] = (-30.0, 0.0, 30.0),
                 width: int = 256, height: int = 256, fov_deg: float = 40.0, up=(0.0, 0.0, 1.0),
                 poles: bool = True) -> list:
    """Frames on rings around ``center`` looking at it (pinhole, for synthetic tests and previews).

    Args:
        center: (3,) point the cameras look at.
        radius: camera distance to ``center``.
        n_azimuth: cameras per ring; rings at ``elevations_deg`` (degrees above the plane normal to ``up``).
        width, height, fov_deg: image size and horizontal field of view.
        up: world up axis.
        poles: add one camera above and one below.

    Returns:
        list of :class:`texstream.capture.capture_json.Frame`.
    """
    center = np.asarray(center, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    fx = 0.5 * width / np.tan(0.5 * np.radians(fov_deg))
    intr = Intrinsics(width=width, height=height, fx=fx, fy=fx, cx=width / 2, cy=height / 2)
    dirs = []
    for k, el in enumerate(elevations_deg):
        e = np.radians(el)
        for i in range(n_azimuth):
            az = 2 * np.pi * (i + 0.5 * (k % 2)) / n_azimuth  # stagger rings
            dirs.append(np.cos(e) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(e) * up)
    if poles:
        dirs += [up * 1.0, -up * 1.0]
    frames = []
    for i, d in enumerate(dirs):
        eye = center + radius * d
        r, t = look_at_w2c(eye, center, up=tuple(e1) if abs(np.dot(d, up)) > 0.99 else tuple(up))
        frames.append(Frame(file_path=f"images/{i:04d}.png", R=r, t=t, intrinsics=intr))
    return frames
