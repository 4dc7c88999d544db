"""Depth maps for visibility, computed once per photo at load time and kept beside the image.

Why depth maps rather than BVH ray casts in the fit's inner loop: the fit visits every
(texel, photo) pair every pass, so a per-sample ray cast (two traversals: camera and light)
would cost far more than the sample's arithmetic. A depth map costs one ray per pixel once,
and the per-sample test becomes a few texture reads, as in the seed's GPU implementation.
Camera depth maps hold z in the camera frame (0 where masked or no surface); shadow maps are
the same thing rendered from the light (a perspective camera at a point light aimed at the
object, or an orthographic one along a directional light). :func:`depth_consistent` is the depth
test the fit's bilinear samples and the photometric refinement both make against a depth map.
"""

from __future__ import annotations

import warp as wp

from texstream.render.camera import ImageInfo

# no kernel here is differentiated (the fit writes its own derivatives): skipping Warp's adjoint
# code generation roughly halves compile time
wp.set_module_options({"enable_backward": False})


@wp.func
def depth_consistent(depth: wp.array3d(dtype=wp.float32), k: int, x0: int, y0: int, z: float, tol: float,
                     slack: float):
    """All four bilinear taps see this surface (masked or empty pixels hold 0 and fail).

    A tap may differ from the texel's depth by ``tol * z`` plus ``slack``, the depth change a tilted
    surface shows across the bilinear footprint (see the fit's ``observe``, fit/kernels/stream.py)."""
    ok = True
    for dy in range(2):
        for dx in range(2):
            dz = depth[k, y0 + dy, x0 + dx]
            if wp.abs(dz - z) > tol * z + slack:
                ok = False
    return ok


@wp.func
def first_hit_depth(mesh: wp.uint64, rot: wp.mat33, trans: wp.vec3, fx: float, fy: float, cx: float, cy: float,
                    ortho: int, x: int, y: int, no_hit: float):
    """z (camera frame, along the optical axis) of the first surface seen through pixel (x, y)'s
    centre, ``no_hit`` where the ray misses. For ``ortho`` cameras fx, fy are pixels per world unit."""
    px = float(x) + 0.5
    py = float(y) + 0.5
    rt = wp.transpose(rot)
    center = -(rt @ trans)
    d_cam = wp.vec3((px - cx) / fx, (py - cy) / fy, 1.0)
    origin = center
    direction = wp.normalize(rt @ d_cam)
    if ortho != 0:
        origin = center + rt @ wp.vec3(d_cam[0], d_cam[1], 0.0)
        direction = rt @ wp.vec3(0.0, 0.0, 1.0)
    q = wp.mesh_query_ray(mesh, origin, direction, 1.0e20)
    z = no_hit
    if q.result:
        hit = origin + q.t * direction
        z = (rot @ hit + trans)[2]
    return z


@wp.kernel
def depth_map_kernel(mesh: wp.uint64, rot: wp.mat33, trans: wp.vec3, fx: float, fy: float, cx: float,
                     cy: float, ortho: int, width: int, height: int, no_hit: float,
                     depth: wp.array2d(dtype=wp.float32)):
    """One camera's depth map (:func:`first_hit_depth` per pixel)."""
    y, x = wp.tid()
    depth[y, x] = first_hit_depth(mesh, rot, trans, fx, fy, cx, cy, ortho, x, y, no_hit)


@wp.kernel
def depth_maps_kernel(mesh: wp.uint64, infos: wp.array(dtype=ImageInfo), first: int,
                      masks: wp.array3d(dtype=wp.uint8), use_masks: int, depth: wp.array3d(dtype=wp.float32)):
    """Depth maps of photos ``first + i`` into ``depth[i]`` (one launch over photos x pixels):
    0 outside the photo's own size (photos are padded to the largest), where the ray misses, and
    where ``masks[i]`` is 0 (``use_masks``), so the fit's visibility test rejects those pixels."""
    i, y, x = wp.tid()
    info = infos[first + i]
    z = float(0.0)
    if x < info.width and y < info.height:
        if use_masks == 0 or masks[i, y, x] != wp.uint8(0):
            z = first_hit_depth(mesh, info.rot, info.trans, info.fx, info.fy, info.cx, info.cy, 0, x, y, 0.0)
    depth[i, y, x] = z


@wp.kernel
def masked_depth_kernel(depth: wp.array3d(dtype=wp.float32), first: int, masks: wp.array3d(dtype=wp.uint8),
                        out: wp.array3d(dtype=wp.float32)):
    """out[i] = depth[first + i] where masks[i] is nonzero, else 0: a depth map made without its mask,
    masked (the values :func:`depth_maps_kernel` writes with the mask)."""
    i, y, x = wp.tid()
    z = float(0.0)
    if masks[i, y, x] != wp.uint8(0):
        z = depth[first + i, y, x]
    out[i, y, x] = z


@wp.kernel
def shadow_maps_kernel(mesh: wp.uint64, infos: wp.array(dtype=ImageInfo), first: int,
                       shadow: wp.array3d(dtype=wp.float32)):
    """Shadow maps of photos ``first + i`` into ``shadow[i]`` (one launch over photos x texels of
    the map): depth from the photo's shadow camera (``ImageInfo.sh_*``), +inf where the ray misses
    and everywhere for photos without a shadow camera (``has_shadow`` 0: nothing casts a shadow)."""
    i, y, x = wp.tid()
    info = infos[first + i]
    z = float(wp.inf)
    if info.has_shadow != 0:
        z = first_hit_depth(mesh, info.sh_rot, info.sh_trans, info.sh_fx, info.sh_fy, info.sh_cx, info.sh_cy,
                            info.sh_ortho, x, y, float(wp.inf))
    shadow[i, y, x] = z


@wp.kernel
def apply_mask_kernel(mask: wp.array2d(dtype=wp.uint8), depth: wp.array2d(dtype=wp.float32)):
    """Masked-out pixels get depth 0 so the fit's visibility test rejects them."""
    y, x = wp.tid()
    if mask[y, x] == wp.uint8(0):
        depth[y, x] = 0.0
