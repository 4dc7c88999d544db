"""Dense multi-view stereo: plane-sweep depth maps per photo, geometric consistency, fused oriented points.

For each reference photo (pinhole, world-to-camera R, t in OpenCV axes, pixel centres at +0.5; see
:mod:`texstream.capture.conventions`):

1. **Neighbours**: the photos whose viewing direction towards the object centre makes an angle in
   ``[min_angle, max_angle]`` with the reference's, closest first, at most ``neighbours`` of them. Photos
   closer than ``min_angle`` add no parallax (the Middlebury rings hold pairs taken from the same point).
2. **Plane sweep**: ``depths`` fronto-parallel planes evenly spaced in inverse depth across the object's
   depth range (the corners of its bounding box seen from the reference camera). For each plane every
   neighbour photo is warped into the reference by back-projecting each reference pixel at the plane's
   depth (for a fronto-parallel plane this *is* the plane homography), and the cost of a pixel is
   ``1 - NCC`` between its ``window`` x ``window`` grey patch and the warped neighbour's. Window sums are
   separable box sums (two passes), so a plane costs O(pixels) whatever the window. The costs of the
   neighbours are aggregated by the mean of the best ``best_of`` (a neighbour that does not see the
   pixel, or sees it occluded, then does not spoil it; missing neighbours count as cost 1).
3. **Winner take all** over the planes, refined by a parabola through the best cost and its two
   neighbours (in inverse-depth index). Kept: pixels inside the object mask, with texture in the
   window, a best cost at most ``max_cost`` and not at either end of the range.
4. **Geometric consistency**: each depth is reprojected into every other photo at least ``min_angle``
   away, that photo's depth at the hit pixel is back-projected and projected back into the reference;
   the depth agrees when it lands within ``reprojection_tolerance`` pixels and its depth differs by at
   most ``depth_tolerance`` (relative). Kept: depths agreeing with at least ``min_consistent`` photos;
   the fused point is the mean of the reference's point and the agreeing photos' points.
5. **Normals** from the depth map's gradient: the inverse depth of a plane is linear in the pixel
   coordinates, so a least-squares fit of ``1/z = a u + b v + c`` over a ``normal_window`` square of kept
   depths gives the plane's normal ``K^T (a, b, c)`` (smoother than finite differences), turned
   towards the camera.
6. **Fusion**: the points of all photos, merged on a voxel grid of ``voxel`` times the bounding-box
   diagonal (mean position, mean normal per voxel): overlapping photos see the same surface.

Everything per pixel runs in module-level Warp kernels (cpu or cuda:N); only the reference window
(the mask's bounding box plus the window radius) is swept. This module imports numpy and warp at
module level; OpenImageIO (photos) and scipy inside functions. The box sums run along rows and columns
(one thread per row or column of a neighbour, a running sum): on the 2-core CPU dev box that was 1.6x
faster than summing each window, and a GPU still gets neighbours x rows threads.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import warp as wp

from texstream.capture.imageio import read_image
from texstream.core.checkpoint import StageCheckpoint, files_signature, inputs_key
from texstream.core.config import config_to_dict, option
from texstream.core.errors import ConfigError, InputError

from .cpu_threads import in_order, threads_for, threads_within_memory
from .mvs_levels import frame_at_level, matching_level, planes_at_level, stack_at_level

MAX_NEIGHBOURS = 8  # the kernels keep one pixel's neighbour costs in a fixed-size vector


@dataclasses.dataclass
class MvsConfig:
    """Dense multi-view stereo options (module doc of texstream.geometry.mvs)."""

    depths: int = option(160, help="depth hypotheses per photo, evenly spaced in inverse depth across the "
                                   "object's depth range (about one pixel of parallax per step at 20 degrees "
                                   "on the Middlebury temple's 640x480 photos); photos matched larger than 640 "
                                   "pixels get as many more as their longer side is larger (the parallax grows "
                                   "with it), those matched at level L at least depths / 2^L", min=8, max=4096)
    window: int = option(7, help="NCC window side in pixels (odd)", min=3, max=31)
    neighbours: int = option(4, help="at most this many neighbour photos per reference photo", min=1,
                             max=MAX_NEIGHBOURS)
    min_angle: float = option(5.0, help="neighbours are at least this many degrees away (seen from the object "
                                        "centre): nearer photos give no parallax", min=0.0, max=90.0)
    max_angle: float = option(50.0, help="neighbours are at most this many degrees away (wider: the patches "
                                         "differ too much; the temple's ring has photos every 22.5 degrees, so "
                                         "50 keeps the second ones)", min=1.0, max=120.0)
    best_of: int = option(2, help="aggregate cost: mean of the best this many neighbours' 1 - NCC", min=1, max=8)
    max_cost: float = option(0.4, help="drop depths whose aggregate cost (1 - NCC) exceeds this", min=0.0, max=2.0)
    min_texture: float = option(0.01, help="drop pixels whose window's grey standard deviation is below this "
                                           "(grey in [0, 1], sRGB-encoded): NCC is noise there", min=0.0)
    depth_tolerance: float = option(0.01, help="geometric consistency: relative depth difference allowed after "
                                               "reprojecting into another photo and back", min=0.0)
    reprojection_tolerance: float = option(1.0, help="geometric consistency: pixels allowed after reprojecting "
                                                     "into another photo and back", min=0.0)
    min_consistent: int = option(2, help="keep depths that agree with at least this many other photos", min=0)
    normal_window: int = option(7, help="side of the square of depths the normal plane is fitted to (odd)",
                                min=3, max=31)
    voxel: float = option(0.001, help="fuse points on a voxel grid of this fraction of the bounding-box diagonal "
                                      "(0: keep every pixel's point)", min=0.0)
    level: int = option(-1, help="match the photos at pyramid level L (2^L x 2^L pixel boxes averaged, masks kept "
                                 "where the whole box is object, the cameras scaled); 0: as they are; -1 auto: the "
                                 "coarsest level at which the median photo's mask keeps level_min_mask_pixels "
                                 "pixels (photos of the temple's size stay at level 0; 11 photos of 3072x2048 are "
                                 "matched at level 2, 768x512, with 192 planes and 114,281 points)",
                        min=-1, max=4)
    threads: int = option(0, help="on the CPU, the reference photos swept at once, one a thread (Warp runs a CPU "
                                  "kernel on one core; the depth maps are the same to the bit); 0: one per CPU "
                                  "core this process may use, at most 8", min=0, max=64)
    level_min_mask_pixels: int = option(64000, help="level auto: the pixels the median photo's mask must keep at the "
                                                    "chosen level. The temple's 640x480 photos (masks of about 72,000 "
                                                    "pixels) stay at level 0: at level 1 (18,000) its mesh stage took "
                                                    "half the CPU time (22.5 against 47.1 s) but its held-out PSNR fell "
                                                    "0.45 dB (24.65 against 25.10 dB); photos of several megapixels "
                                                    "are matched at a level that keeps about as many", min=1)


@dataclasses.dataclass
class DensePoints:
    """Fused dense points and their provenance.

    Attributes:
        points: (N, 3) world points.
        normals: (N, 3) unit normals, facing the photos that saw them.
        depth_maps: per photo, (H, W) float32 camera-space depth after the consistency filter (0: none), at the
            matching level's size (``report["level"]``, MvsConfig.level).
        report: counts, per-photo fill and timings (JSON-ready).
    """

    points: np.ndarray
    normals: np.ndarray
    depth_maps: list
    report: dict


# ----------------------------------------------------------------------------------------------- kernels

_vec_nb = wp.types.vector(length=MAX_NEIGHBOURS, dtype=wp.float32)  # one pixel's costs, one per neighbour


@wp.func
def _pixel_ray(u: float, v: float, k: wp.vec4) -> wp.vec3:
    """Camera-space direction with z = 1 through continuous pixel (u, v) (k = fx, fy, cx, cy)."""
    return wp.vec3((u - k[2]) / k[0], (v - k[3]) / k[1], 1.0)


@wp.kernel(enable_backward=False)
def _reference_stats_kernel(grey: wp.array3d(dtype=wp.float32), mask: wp.array3d(dtype=wp.uint8), ref: int,
                            x0: int, y0: int, radius: int, min_var: float,
                            sums: wp.array2d(dtype=wp.vec3), active: wp.array2d(dtype=wp.int32)):
    """Sums over the window's object pixels of the reference grey value a, of a^2 and of 1; active = the
    centre is an object pixel, at least half the window is, and those pixels have texture."""
    y, x = wp.tid()
    gy = y0 + y
    gx = x0 + x
    h = grey.shape[1]
    w = grey.shape[2]
    active[y, x] = 0
    if mask[ref, gy, gx] == wp.uint8(0) or gx < radius or gy < radius or gx >= w - radius or gy >= h - radius:
        return
    s = float(0.0)
    ss = float(0.0)
    cnt = float(0.0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if mask[ref, gy + dy, gx + dx] != wp.uint8(0):
                a = grey[ref, gy + dy, gx + dx]
                s += a
                ss += a * a
                cnt += 1.0
    sums[y, x] = wp.vec3(s, ss, cnt)
    area = float((2 * radius + 1) * (2 * radius + 1))
    if cnt >= 0.5 * area and ss / cnt - (s / cnt) * (s / cnt) >= min_var:
        active[y, x] = 1


@wp.func
def _warped_sample(depth: float, grey: wp.array3d(dtype=wp.float32), mask: wp.array3d(dtype=wp.uint8), ref: int,
                   gx: int, gy: int, ref_k: wp.vec4,
                   c: int, rot: wp.mat33, trans: wp.vec3, k: wp.vec4) -> wp.vec4:
    """Photo c's grey value b at the point reference pixel (gx, gy) shows at ``depth``, as (b, b^2, a b, 1)
    with a the reference value; zeros where the point leaves photo c or the pixel is background in the
    reference (the window's NCC is over object pixels only: at the silhouette the background's edge would
    otherwise dominate it, and it is a different edge in each photo)."""
    if mask[ref, gy, gx] == wp.uint8(0):
        return wp.vec4(0.0)
    p = rot * (_pixel_ray(float(gx) + 0.5, float(gy) + 0.5, ref_k) * depth) + trans
    if p[2] <= 0.0:
        return wp.vec4(0.0)
    # continuous pixel coordinates -> array index coordinates (pixel centres at integers)
    u = k[0] * p[0] / p[2] + k[2] - 0.5
    v = k[1] * p[1] / p[2] + k[3] - 0.5
    h = grey.shape[1]
    w = grey.shape[2]
    if u < 0.0 or v < 0.0 or u > float(w - 1) or v > float(h - 1):
        return wp.vec4(0.0)
    i0 = wp.min(int(u), w - 2)
    j0 = wp.min(int(v), h - 2)
    fu = u - float(i0)
    fv = v - float(j0)
    b = (1.0 - fv) * ((1.0 - fu) * grey[c, j0, i0] + fu * grey[c, j0, i0 + 1]) + \
        fv * ((1.0 - fu) * grey[c, j0 + 1, i0] + fu * grey[c, j0 + 1, i0 + 1])
    a = grey[ref, gy, gx]
    return wp.vec4(b, b * b, a * b, 1.0)


@wp.kernel(enable_backward=False)
def _warp_rows_kernel(depth: float, grey: wp.array3d(dtype=wp.float32), mask: wp.array3d(dtype=wp.uint8),
                      ref: int, x0: int, y0: int, ref_k: wp.vec4,
                      nb_index: wp.array(dtype=wp.int32), nb_rot: wp.array(dtype=wp.mat33),
                      nb_trans: wp.array(dtype=wp.vec3), nb_k: wp.array(dtype=wp.vec4),
                      needed: wp.array2d(dtype=wp.uint8), radius: int, warped: wp.array3d(dtype=wp.vec4),
                      rows: wp.array3d(dtype=wp.vec4)):
    """One row of neighbour n warped into the reference at ``depth`` (only where some active pixel's window
    needs it), then its horizontal box sums over 2 radius + 1 pixels by a running sum (outside the swept
    window counts as zero, i.e. not seen)."""
    n, y = wp.tid()
    w = warped.shape[2]
    c = nb_index[n]
    for x in range(w):
        if needed[y, x] != wp.uint8(0):
            warped[n, y, x] = _warped_sample(depth, grey, mask, ref, x0 + x, y0 + y, ref_k, c, nb_rot[n], nb_trans[n],
                                             nb_k[n])
        else:
            warped[n, y, x] = wp.vec4(0.0)
    s = wp.vec4(0.0)
    for x in range(wp.min(radius, w)):
        s += warped[n, y, x]
    for x in range(w):
        if x + radius < w:
            s += warped[n, y, x + radius]
        if x - radius - 1 >= 0:
            s -= warped[n, y, x - radius - 1]
        rows[n, y, x] = s


@wp.kernel(enable_backward=False)
def _column_cost_kernel(rows: wp.array3d(dtype=wp.vec4), ref_sums: wp.array2d(dtype=wp.vec3),
                        active: wp.array2d(dtype=wp.int32), radius: int, min_var: float,
                        costs: wp.array3d(dtype=wp.float32)):
    """Vertical box sums of one column of neighbour n's row sums (running sum), and 1 - NCC of each
    active pixel's window (its object pixels); cost 1 (NCC 0) where the neighbour does not see all of
    them or they are flat there."""
    n, x = wp.tid()
    h = rows.shape[1]
    s = wp.vec4(0.0)
    for y in range(wp.min(radius, h)):
        s += rows[n, y, x]
    for y in range(h):
        if y + radius < h:
            s += rows[n, y + radius, x]
        if y - radius - 1 >= 0:
            s -= rows[n, y - radius - 1, x]
        if active[y, x] == 0:
            continue
        c = float(1.0)
        ref_s = ref_sums[y, x]
        area = ref_s[2]
        if s[3] > area - 0.5:
            var_a = ref_s[1] - ref_s[0] * ref_s[0] / area
            var_b = s[1] - s[0] * s[0] / area
            if var_b >= min_var * area:
                ncc = (s[2] - ref_s[0] * s[0] / area) / wp.sqrt(var_a * var_b)
                c = 1.0 - wp.clamp(ncc, -1.0, 1.0)
        costs[y, x, n] = c


@wp.kernel(enable_backward=False)
def _aggregate_kernel(costs: wp.array3d(dtype=wp.float32), active: wp.array2d(dtype=wp.int32), best_of: int,
                      plane: int, best_cost: wp.array2d(dtype=wp.float32), best_plane: wp.array2d(dtype=wp.int32),
                      cost_before: wp.array2d(dtype=wp.float32), cost_after: wp.array2d(dtype=wp.float32),
                      last_cost: wp.array2d(dtype=wp.float32)):
    """Mean of the best ``best_of`` neighbours' costs, and the running winner over the planes (with the
    costs of the planes either side of it, for the parabola)."""
    y, x = wp.tid()
    if active[y, x] == 0:
        return
    n_nb = costs.shape[2]
    # the best_of smallest costs by repeated selection over the handful of neighbours (a ranking by
    # comparing every pair took 60% longer than the row and column passes together)
    c = _vec_nb()
    for k in range(n_nb):
        c[k] = costs[y, x, k]
    total = float(0.0)
    used = int(0)
    taken = int(0)
    for t in range(wp.min(best_of, n_nb)):
        best = int(-1)
        for k in range(n_nb):
            if (taken >> k) & 1 == 0 and (best < 0 or c[k] < c[best]):
                best = k
        taken = taken | (1 << best)
        total += c[best]
        used += 1
    agg = total / float(wp.max(used, 1))
    if plane == 0 or agg < best_cost[y, x]:
        best_cost[y, x] = agg
        best_plane[y, x] = plane
        cost_before[y, x] = wp.where(plane == 0, agg, last_cost[y, x])
        cost_after[y, x] = agg
    elif plane == best_plane[y, x] + 1:
        cost_after[y, x] = agg
    last_cost[y, x] = agg


@wp.kernel(enable_backward=False)
def _refine_kernel(active: wp.array2d(dtype=wp.int32), best_cost: wp.array2d(dtype=wp.float32),
                   best_plane: wp.array2d(dtype=wp.int32), cost_before: wp.array2d(dtype=wp.float32),
                   cost_after: wp.array2d(dtype=wp.float32), n_planes: int, inv_near: float, inv_step: float,
                   max_cost: float, x0: int, y0: int, depth: wp.array2d(dtype=wp.float32),
                   cost: wp.array2d(dtype=wp.float32)):
    """Depth of the winning plane, refined by the parabola through its cost and its neighbours' costs;
    0 where the pixel is inactive, the match is poor or the winner is an end of the range."""
    y, x = wp.tid()
    gy = y0 + y
    gx = x0 + x
    depth[gy, gx] = 0.0
    cost[gy, gx] = 2.0
    if active[y, x] == 0:
        return
    d = best_plane[y, x]
    c0 = best_cost[y, x]
    if c0 > max_cost or d <= 0 or d >= n_planes - 1:
        return
    cm = cost_before[y, x]
    cp = cost_after[y, x]
    curvature = cm - 2.0 * c0 + cp
    offset = float(0.0)
    if curvature > 1.0e-6:
        offset = wp.clamp(0.5 * (cm - cp) / curvature, -0.5, 0.5)
    inv = inv_near - (float(d) + offset) * inv_step
    if inv <= 0.0:
        return
    depth[gy, gx] = 1.0 / inv
    cost[gy, gx] = c0


@wp.kernel(enable_backward=False)
def _consistency_kernel(ref: int, views: wp.array(dtype=wp.int32), rots: wp.array(dtype=wp.mat33),
                        trans: wp.array(dtype=wp.vec3), ks: wp.array(dtype=wp.vec4), sizes: wp.array(dtype=wp.vec2i),
                        depths: wp.array3d(dtype=wp.float32), rel_tol: float, px_tol: float,
                        count: wp.array2d(dtype=wp.int32), fused: wp.array2d(dtype=wp.vec3)):
    """Per reference depth: how many other photos' depths agree with it (reprojection there and back),
    and the mean world point of the reference and the agreeing photos; count -1 where no depth."""
    j, i = wp.tid()
    z = depths[ref, j, i]
    if z <= 0.0:
        count[j, i] = -1
        return
    rot = rots[ref]
    tr = trans[ref]
    kr = ks[ref]
    u = float(i) + 0.5
    v = float(j) + 0.5
    xw = wp.transpose(rot) * (_pixel_ray(u, v, kr) * z - tr)
    acc = xw
    agree = int(0)
    for m in range(views.shape[0]):
        c = views[m]
        pc = rots[c] * xw + trans[c]
        if pc[2] <= 0.0:
            continue
        kc = ks[c]
        uc = kc[0] * pc[0] / pc[2] + kc[2]
        vc = kc[1] * pc[1] / pc[2] + kc[3]
        if uc < 0.0 or vc < 0.0:
            continue
        ic = int(uc)  # pixel centres at +0.5: the floor is the pixel index
        jc = int(vc)
        if ic >= sizes[c][0] or jc >= sizes[c][1]:
            continue
        zc = depths[c, jc, ic]
        if zc <= 0.0:
            continue
        xc = wp.transpose(rots[c]) * (_pixel_ray(float(ic) + 0.5, float(jc) + 0.5, kc) * zc - trans[c])
        back = rot * xc + tr
        if back[2] <= 0.0:
            continue
        ub = kr[0] * back[0] / back[2] + kr[2]
        vb = kr[1] * back[1] / back[2] + kr[3]
        if wp.sqrt((ub - u) * (ub - u) + (vb - v) * (vb - v)) <= px_tol and wp.abs(back[2] - z) <= rel_tol * z:
            agree += 1
            acc += xc
    count[j, i] = agree
    fused[j, i] = acc / float(agree + 1)


@wp.kernel(enable_backward=False)
def _normal_kernel(depth: wp.array2d(dtype=wp.float32), k: wp.vec4, rot: wp.mat33, radius: int, rel_tol: float,
                   normal: wp.array2d(dtype=wp.vec3)):
    """World normal per kept depth from a least-squares plane 1/z = a u + b v + c over the window's kept
    depths (within rel_tol of the centre's: no fitting across depth edges), turned towards the camera;
    the viewing direction where fewer than 6 depths support the fit."""
    j, i = wp.tid()
    z = depth[j, i]
    if z <= 0.0:
        return
    h = depth.shape[0]
    w = depth.shape[1]
    # normal equations in offsets from the centre pixel (well conditioned)
    m = wp.mat33(0.0)
    r = wp.vec3(0.0)
    cnt = int(0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            jj = j + dy
            ii = i + dx
            if jj < 0 or ii < 0 or jj >= h or ii >= w:
                continue
            zz = depth[jj, ii]
            if zz <= 0.0 or wp.abs(zz - z) > rel_tol * z:
                continue
            q = wp.vec3(float(dx), float(dy), 1.0)
            m += wp.outer(q, q)
            r += q * (1.0 / zz)
            cnt += 1
    ray = _pixel_ray(float(i) + 0.5, float(j) + 0.5, k)
    n_cam = -ray  # towards the camera
    if cnt >= 6 and wp.abs(wp.determinant(m)) > 1.0e-6:
        abc = wp.inverse(m) * r
        # 1/z = a (u - u0) + b (v - v0) + c  =  a u + b v + (c - a u0 - b v0); the plane's normal is K^T (a, b, c')
        u0 = float(i) + 0.5
        v0 = float(j) + 0.5
        c2 = abc[2] - abc[0] * u0 - abc[1] * v0
        nc = wp.vec3(k[0] * abc[0], k[1] * abc[1], k[2] * abc[0] + k[3] * abc[1] + c2)
        ln = wp.length(nc)
        if ln > 0.0:
            nc = nc / ln
            if wp.dot(nc, ray) > 0.0:
                nc = -nc
            n_cam = nc
    normal[j, i] = wp.transpose(rot) * wp.normalize(n_cam)


# ------------------------------------------------------------------------------------------------- host


def grey_for_matching(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey in [0, 1], sRGB-encoded (a photo's noise and quantisation are even there, so
    one texture threshold serves dark and bright parts), from a linear (H, W[, C]) photo."""
    img = np.asarray(image, np.float32)
    g = img.mean(axis=2) if img.ndim == 3 else img
    scale = float(np.percentile(g, 99.5)) if g.size else 1.0
    g = np.clip(g / (scale if scale > 0 else 1.0), 0.0, 1.0)
    return np.where(g <= 0.0031308, 12.92 * g, 1.055 * np.power(g, 1 / 2.4) - 0.055).astype(np.float32)


def choose_neighbours(centres: np.ndarray, target: np.ndarray, min_angle: float, max_angle: float,
                      count: int) -> list[list[int]]:
    """Per photo, the photos whose direction from ``target`` is ``min_angle``..``max_angle`` degrees
    from its own, closest first, at most ``count``."""
    d = centres - target
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1.0, 1.0)))
    out = []
    for r in range(len(centres)):
        cand = [c for c in np.argsort(ang[r], kind="stable") if c != r and min_angle <= ang[r, c] <= max_angle]
        out.append([int(c) for c in cand[:count]])
    return out


def _angles(centres: np.ndarray, target: np.ndarray) -> np.ndarray:
    d = centres - target
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip(d @ d.T, -1.0, 1.0)))


def _depth_range(frame, lo: np.ndarray, hi: np.ndarray) -> tuple[float, float] | None:
    corners = np.array(list(itertools.product(*zip(lo, hi))))
    z = (corners @ np.asarray(frame.R, np.float64).T + np.asarray(frame.t, np.float64).reshape(1, 3))[:, 2]
    far = float(z.max())
    if far <= 0:
        return None
    near = max(float(z.min()), 1e-3 * far)  # a camera inside the box sees from just in front of it
    return near, far


def _kvec(frame) -> wp.vec4:
    i = frame.intrinsics
    return wp.vec4(float(i.fx), float(i.fy), float(i.cx), float(i.cy))


def dense_points(frames: Sequence, images: Sequence[np.ndarray], masks: Sequence[np.ndarray] | None,
                 bounds: tuple[np.ndarray, np.ndarray], config: MvsConfig | None = None,
                 device: str = "cpu", depth_ranges: Sequence[tuple[float, float] | None] | None = None,
                 checkpoint: StageCheckpoint | None = None) -> DensePoints:
    """Dense points of an object seen by posed pinhole photos (module doc).

    Args:
        frames: frames with R, t, intrinsics (world-to-camera, OpenCV axes), undistorted.
        images: one photo per frame, (H, W) or (H, W, C), linear or encoded (matched by NCC).
        masks: one (H, W) object mask per frame (nonzero = object), or None (every pixel).
        bounds: (lo, hi) world box holding the object: the depth range of every photo (unless given), the
            centre the neighbours are chosen around, the size the fusion voxel is relative to.
        config: options.
        device: Warp device.
        depth_ranges: per photo (near, far), or None (no depths): overrides the box's range (e.g. from
            the points triangulated with the cameras, :mod:`.posed_dense`).
        checkpoint: a work folder (opened) that keeps each photo's finished depth map: a rerun after an
            interruption sweeps only the others (each sweep reads only the photos, so the fused points are the
            same to the bit).

    Returns:
        The fused :class:`DensePoints`.

    Raises:
        InputError: fewer than 2 photos, or an image or mask whose size is not its frame's.
        ConfigError: an even window.
    """
    cfg = config or MvsConfig()
    _check_inputs(frames, images, masks, cfg)
    n = len(frames)
    t0 = time.perf_counter()
    grey, mask = _matching_stack(frames, images, masks)
    level = cfg.level if cfg.level >= 0 else matching_level(mask, cfg.level_min_mask_pixels)
    if level:
        frames = [frame_at_level(f, level) for f in frames]
        grey, mask = stack_at_level(grey, mask, frames, level)
    cfg = dataclasses.replace(cfg, depths=planes_at_level(cfg.depths, frames, level))
    hmax, wmax = grey.shape[1:]
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    centres = np.array([f.center for f in frames])
    target = 0.5 * (lo + hi)
    neighbours = choose_neighbours(centres, target, cfg.min_angle, cfg.max_angle, cfg.neighbours)
    angles = _angles(centres, target)

    rots = np.stack([np.asarray(f.R, np.float64) for f in frames])
    transl = np.stack([np.asarray(f.t, np.float64).reshape(3) for f in frames])
    d_grey = wp.array(grey, dtype=wp.float32, device=device)
    d_mask = wp.array(mask, dtype=wp.uint8, device=device)
    # texture threshold as a variance (grey units squared)
    min_var = float(cfg.min_texture) ** 2
    t_sweep = time.perf_counter()
    kept = _kept_depth_maps(checkpoint, n)
    ranges = [_depth_range(f, lo, hi) for f in frames] if depth_ranges is None else depth_ranges
    # the photos' sweeps on threads at once (geometry/cpu_threads.py: a sweep reads only the shared photos and
    # writes its own arrays, so the depth maps are one thread's to the bit)
    wp.load_module(_warp_rows_kernel.module, device=device)  # built once, before threads launch its kernels
    for r, (depth, rep) in in_order(lambda r: _sweep_view(r, neighbours, frames, mask, ranges[r], rots, transl, d_grey,
                                                          d_mask, cfg, min_var, device),
                                    [r for r in range(n) if r not in kept], sweep_threads(cfg, device, hmax, wmax)):
        kept[r] = depth, rep
        if checkpoint is not None and "matched" in rep:
            checkpoint.write_arrays(f"depth_{r:05d}.npz", depth=depth, report=np.array(json.dumps(rep)))
    depth_maps = np.stack([kept[r][0] for r in range(n)]).astype(np.float32, copy=False)
    per_view = [kept[r][1] for r in range(n)]
    t_sweep = time.perf_counter() - t_sweep

    # geometric consistency against every photo that is not a near duplicate of the reference
    t_fuse = time.perf_counter()
    d_depths = wp.array(depth_maps, dtype=wp.float32, device=device)
    d_rots = wp.array(rots.astype(np.float32), dtype=wp.mat33, device=device)
    d_trans = wp.array(transl.astype(np.float32), dtype=wp.vec3, device=device)
    d_ks = wp.array(np.array([[f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy]
                              for f in frames], np.float32), dtype=wp.vec4, device=device)
    d_sizes = wp.array(np.array([[f.intrinsics.width, f.intrinsics.height] for f in frames], np.int32),
                       dtype=wp.vec2i, device=device)
    count = wp.empty((hmax, wmax), dtype=wp.int32, device=device)
    fused = wp.empty((hmax, wmax), dtype=wp.vec3, device=device)
    normal = wp.zeros((hmax, wmax), dtype=wp.vec3, device=device)
    kept_depths = []
    pts_all, nrm_all = [], []
    for r in range(n):
        others = [c for c in range(n) if c != r and angles[r, c] >= cfg.min_angle]
        if not others or not per_view[r].get("matched"):
            kept_depths.append(np.zeros((frames[r].intrinsics.height, frames[r].intrinsics.width), np.float32))
            per_view[r]["kept"] = 0
            per_view[r]["fill"] = 0.0
            continue
        wp.launch(_consistency_kernel, dim=(hmax, wmax),
                  inputs=[r, wp.array(np.asarray(others, np.int32), dtype=wp.int32, device=device), d_rots, d_trans,
                          d_ks, d_sizes, d_depths, float(cfg.depth_tolerance), float(cfg.reprojection_tolerance)],
                  outputs=[count, fused], device=device)
        cnt = count.numpy()
        keep = cnt >= cfg.min_consistent
        dm = np.where(keep, depth_maps[r], 0.0).astype(np.float32)
        normal.zero_()
        wp.launch(_normal_kernel, dim=(hmax, wmax),
                  inputs=[wp.array(dm, dtype=wp.float32, device=device), _kvec(frames[r]),
                          wp.mat33(rots[r].astype(np.float32)), cfg.normal_window // 2,
                          float(max(2 * cfg.depth_tolerance, 1e-4))],
                  outputs=[normal], device=device)
        pts_all.append(fused.numpy()[keep].astype(np.float64))
        nrm_all.append(normal.numpy()[keep].astype(np.float64))
        fr = frames[r].intrinsics
        kept_depths.append(dm[:fr.height, :fr.width])
        per_view[r]["kept"] = int(keep.sum())
        per_view[r]["fill"] = round(float(keep.sum()) / max(1, per_view[r].get("mask_pixels", 1)), 4)
    pts = np.concatenate(pts_all) if pts_all else np.zeros((0, 3))
    nrm = np.concatenate(nrm_all) if nrm_all else np.zeros((0, 3))
    raw = len(pts)
    if cfg.voxel > 0 and raw:
        pts, nrm = voxel_merge(pts, nrm, cfg.voxel * float(np.linalg.norm(hi - lo)))
    t_fuse = time.perf_counter() - t_fuse
    fills = [v["fill"] for v in per_view if "fill" in v]
    report = {"points": int(len(pts)), "pixel_points": int(raw), "level": level, "depths": int(cfg.depths),
              "matched_size": [int(wmax), int(hmax)],
              "mean_fill": round(float(np.mean(fills)), 4) if fills else 0.0,
              "views": per_view, "device": device,
              "seconds": {"sweep": round(t_sweep, 2), "consistency_and_fusion": round(t_fuse, 2),
                          "total": round(time.perf_counter() - t0, 2)}}
    return DensePoints(pts, nrm, kept_depths, report)


def _sweep_view(r: int, neighbours: list, frames: Sequence, mask: np.ndarray, rng: tuple[float, float] | None,
                rots: np.ndarray, transl: np.ndarray, d_grey: wp.array, d_mask: wp.array, cfg: MvsConfig,
                min_var: float, device: str) -> tuple[np.ndarray, dict]:
    """(depth map (0: none), report) of reference photo r: its plane sweep over its mask's box, or why not."""
    rep = {"photo": frames[r].name, "neighbours": [frames[c].name for c in neighbours[r]]}
    hmax, wmax = mask.shape[1:]
    ys, xs = np.nonzero(mask[r])
    if not neighbours[r] or len(ys) == 0 or rng is None:
        rep["skipped"] = ("no neighbour photo within the angle range" if not neighbours[r]
                          else "empty mask" if len(ys) == 0 else "the object box is behind the camera")
        return np.zeros((hmax, wmax), np.float32), rep
    radius = cfg.window // 2
    y0, y1 = max(0, ys.min() - radius), min(hmax, ys.max() + radius + 1)
    x0, x1 = max(0, xs.min() - radius), min(wmax, xs.max() + radius + 1)
    near, far = rng
    depth = _sweep(r, neighbours[r], frames, rots, transl, d_grey, d_mask, (int(x0), int(y0), int(x1 - x0),
                                                                           int(y1 - y0)), (near, far), cfg, min_var, device)
    rep["depth_range"] = [round(near, 6), round(far, 6)]
    rep["mask_pixels"] = int(len(ys))
    rep["matched"] = int(np.count_nonzero(depth))
    return depth, rep


def _kept_depth_maps(checkpoint: StageCheckpoint | None, n: int) -> dict[int, tuple[np.ndarray, dict]]:
    """{photo: (depth map, its report)} a checkpoint holds from an interrupted run (said in one line)."""
    if checkpoint is None or not checkpoint.open():  # opened once the inputs passed their checks
        return {}
    kept = {}
    for r in range(n):
        saved = checkpoint.read_arrays(f"depth_{r:05d}.npz")
        if saved is not None:
            kept[r] = (saved["depth"], json.loads(str(saved["report"])))
    if kept:
        checkpoint.say(f"resuming dense stereo from {checkpoint.folder}: {len(kept)} of {n} photos' depth maps "
                       "done")
    return kept


def dense_checkpoint(capture, masks: Sequence[np.ndarray] | None, bounds, config: MvsConfig, device: str,
                     depth_ranges, work_dir: str | Path) -> StageCheckpoint:
    """The dense stereo's work folder, keyed by the photos and capture.json it reads (paths, sizes,
    modification times), the masks or regions it matches in (their bytes), the bounds, the depth ranges, its
    options and the device."""
    masks_hash = hashlib.sha256()
    for m in masks or []:
        masks_hash.update(np.ascontiguousarray(np.asarray(m) != 0).tobytes())
    files = [capture.root / "capture.json"] + [capture.image_path(f) for f in capture.frames]
    key = inputs_key("dense", files_signature(files), masks_hash.hexdigest(), np.asarray(bounds).tolist(),
                     None if depth_ranges is None else [list(r) if r else None for r in depth_ranges],
                     {k: v for k, v in config_to_dict(config).items() if k != "threads"}, device,  # same bits
                     "planes per matched size")  # the plane rule (mvs_levels.py planes_at_level): not before's maps
    return StageCheckpoint(work_dir, key, "mesh")


def _check_inputs(frames: Sequence, images: Sequence, masks: Sequence | None, cfg: MvsConfig) -> None:
    """Refuse even windows, a neighbour count out of range, and fewer than 2 photos or a missing image or mask."""
    if cfg.window % 2 == 0 or cfg.normal_window % 2 == 0:
        raise ConfigError(f"--mvs.window {cfg.window} / --mvs.normal-window {cfg.normal_window}: windows "
                          "must have odd sides", fix="use an odd number such as 5 or 7")
    if not 1 <= cfg.neighbours <= MAX_NEIGHBOURS:
        raise ConfigError(f"--mvs.neighbours {cfg.neighbours} is out of range [1, {MAX_NEIGHBOURS}]",
                          fix=f"give 1 to {MAX_NEIGHBOURS}")
    n = len(frames)
    if n < 2 or len(images) != n or (masks is not None and len(masks) != n):
        raise InputError(f"dense stereo needs at least 2 photos with one image (and mask) each; got {n} frames, "
                         f"{len(images)} images, {'no' if masks is None else len(masks)} masks",
                         fix="give every frame its photo and mask")


def sweep_threads(cfg: MvsConfig, device: str, height: int, width: int) -> int:
    """The photos swept at once (``cfg.threads``), as many as their scratch fits in half the available memory: a
    sweep holds its neighbours' warped photos and rows (two vec4 per pixel each) and their costs (one float each),
    about 36 bytes a pixel per neighbour and 20 more."""
    per_sweep = height * width * (36 * int(cfg.neighbours) + 20)
    return threads_within_memory(threads_for(cfg.threads, device), per_sweep)


def _matching_stack(frames: Sequence, images: Sequence[np.ndarray],
                    masks: Sequence[np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
    """(grey (n, hmax, wmax) float32 for matching, mask (n, hmax, wmax) uint8): each photo at the top left,
    zero padded; every pixel of a photo without masks. Refuses an image or mask of another size than its
    frame's camera."""
    n = len(frames)
    hmax = max(f.intrinsics.height for f in frames)
    wmax = max(f.intrinsics.width for f in frames)
    grey = np.zeros((n, hmax, wmax), np.float32)
    mask = np.zeros((n, hmax, wmax), np.uint8)
    for c, (f, img) in enumerate(zip(frames, images)):
        hw = (f.intrinsics.height, f.intrinsics.width)
        if np.asarray(img).shape[:2] != hw:
            raise InputError(f"photo of {f.file_path} is {np.asarray(img).shape[:2]}, its camera {hw}",
                             fix="give photos at the camera's resolution (undistorted)")
        grey[c, :hw[0], :hw[1]] = grey_for_matching(img)
        if masks is None:
            mask[c, :hw[0], :hw[1]] = 1
        else:
            m = np.asarray(masks[c])
            if m.shape[:2] != hw:
                raise InputError(f"mask of {f.file_path} is {m.shape[:2]}, its photo {hw}", f.mask_path,
                                 "write masks at the image resolution")
            mask[c, :hw[0], :hw[1]] = (m.reshape(hw) != 0)
    return grey, mask


def _sweep(r: int, nbs: list[int], frames: Sequence, rots: np.ndarray, transl: np.ndarray, d_grey: wp.array,
           d_mask: wp.array, window: tuple[int, int, int, int], depth_range: tuple[float, float], cfg: MvsConfig,
           min_var: float, device: str) -> np.ndarray:
    """The plane sweep of reference photo r over the window (x0, y0, w, h): its depth map (0: none)."""
    x0, y0, w, h = window
    radius = cfg.window // 2
    k = len(nbs)
    # the neighbours' poses relative to the reference camera: x_nb = R_rel x_ref + t_rel
    rel_r = np.stack([rots[c] @ rots[r].T for c in nbs])
    rel_t = np.stack([transl[c] - rel_r[i] @ transl[r] for i, c in enumerate(nbs)])
    d_nb = wp.array(np.asarray(nbs, np.int32), dtype=wp.int32, device=device)
    d_rel_r = wp.array(rel_r.astype(np.float32), dtype=wp.mat33, device=device)
    d_rel_t = wp.array(rel_t.astype(np.float32), dtype=wp.vec3, device=device)
    d_nb_k = wp.array(np.array([[frames[c].intrinsics.fx, frames[c].intrinsics.fy, frames[c].intrinsics.cx,
                                 frames[c].intrinsics.cy] for c in nbs], np.float32), dtype=wp.vec4, device=device)
    ref_k = _kvec(frames[r])
    sums = wp.zeros((h, w), dtype=wp.vec3, device=device)
    active = wp.zeros((h, w), dtype=wp.int32, device=device)
    wp.launch(_reference_stats_kernel, dim=(h, w), inputs=[d_grey, d_mask, r, x0, y0, radius, min_var],
              outputs=[sums, active], device=device)
    warped = wp.empty((k, h, w), dtype=wp.vec4, device=device)
    rows = wp.empty((k, h, w), dtype=wp.vec4, device=device)
    costs = wp.empty((h, w, k), dtype=wp.float32, device=device)  # pixel-major: the aggregation reads them together
    best_cost = wp.empty((h, w), dtype=wp.float32, device=device)
    best_plane = wp.zeros((h, w), dtype=wp.int32, device=device)
    cost_before = wp.empty((h, w), dtype=wp.float32, device=device)
    cost_after = wp.empty((h, w), dtype=wp.float32, device=device)
    last_cost = wp.empty((h, w), dtype=wp.float32, device=device)
    near, far = depth_range
    n_planes = int(cfg.depths)
    inv_near, inv_far = 1.0 / near, 1.0 / far
    inv_step = (inv_near - inv_far) / (n_planes - 1)
    best_of = int(min(cfg.best_of, k))
    # warp only where an active pixel's window reaches
    from scipy.ndimage import binary_dilation

    act = active.numpy() != 0
    needed = binary_dilation(act, structure=np.ones((cfg.window, cfg.window), bool)) if act.any() else act
    d_needed = wp.array(needed.astype(np.uint8), dtype=wp.uint8, device=device)
    for d in range(n_planes):
        z = 1.0 / (inv_near - d * inv_step)
        wp.launch(_warp_rows_kernel, dim=(k, h),
                  inputs=[float(z), d_grey, d_mask, r, x0, y0, ref_k, d_nb, d_rel_r, d_rel_t, d_nb_k, d_needed, radius],
                  outputs=[warped, rows], device=device)
        wp.launch(_column_cost_kernel, dim=(k, w), inputs=[rows, sums, active, radius, min_var], outputs=[costs],
                  device=device)
        wp.launch(_aggregate_kernel, dim=(h, w), inputs=[costs, active, best_of, d],
                  outputs=[best_cost, best_plane, cost_before, cost_after, last_cost], device=device)
    hmax, wmax = d_grey.shape[1], d_grey.shape[2]
    depth = wp.zeros((hmax, wmax), dtype=wp.float32, device=device)
    cost = wp.zeros((hmax, wmax), dtype=wp.float32, device=device)
    wp.launch(_refine_kernel, dim=(h, w),
              inputs=[active, best_cost, best_plane, cost_before, cost_after, n_planes, float(inv_near),
                      float(inv_step), float(cfg.max_cost), x0, y0], outputs=[depth, cost], device=device)
    return depth.numpy()


def voxel_merge(points: np.ndarray, normals: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Points merged per voxel of side ``size``: the mean position and the normalised mean normal."""
    if size <= 0 or len(points) == 0:
        return points, normals
    keys = np.floor((points - points.min(axis=0)) / size).astype(np.int64)
    _, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    p = np.zeros((len(cnt), 3))
    nn = np.zeros((len(cnt), 3))
    np.add.at(p, inv, points)
    np.add.at(nn, inv, normals)
    p /= cnt[:, None]
    ln = np.linalg.norm(nn, axis=1, keepdims=True)
    nn = np.where(ln > 1e-12, nn / np.maximum(ln, 1e-12), 0.0)
    ok = ln[:, 0] > 1e-12  # opposite normals cancelling: a thin part seen from both sides; drop the voxel
    return p[ok], nn[ok]


def capture_dense_points(capture, masks: Sequence[np.ndarray] | None, bounds: tuple[np.ndarray, np.ndarray],
                         config: MvsConfig | None = None, device: str = "cpu",
                         depth_ranges: Sequence[tuple[float, float] | None] | None = None,
                         work_dir: str | Path | None = None) -> DensePoints:
    """:func:`dense_points` of a capture folder's photos (read with OpenImageIO); with ``work_dir``, each finished
    depth map is kept there (:func:`dense_checkpoint`) and a rerun after an interruption resumes from them.

    Raises:
        InputError: a photo is missing or unreadable, or has lens distortion (undistort it first).
    """
    images = []
    for f in capture.frames:
        p = capture.image_path(f)
        if not p.is_file():
            raise InputError(f"photo {f.file_path} not found", capture.root / "capture.json",
                             "restore the photos, or use --dense off")
        if not f.intrinsics.is_pinhole:
            raise InputError(f"photo {f.file_path} has lens distortion; dense stereo needs pinhole photos",
                             capture.root / "capture.json", "undistort with 'texstream register', or use --dense off")
        images.append(read_image(p, channels=3))
    cfg = config or MvsConfig()
    ck = None if work_dir is None else dense_checkpoint(capture, masks, bounds, cfg, device, depth_ranges, work_dir)
    return dense_points(capture.frames, images, masks, bounds, cfg, device, depth_ranges, ck)
