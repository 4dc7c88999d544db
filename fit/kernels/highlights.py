"""The highlight diagnostic's passes (fit/common/highlights.py): per texel, its photos' samples taken as the
fit takes them (fit/kernels/stream.py ``observe``: the same projection, visibility, shadow, mask, saturation and
grazing tests, the same photo filter), sorted by how close each is to the mirror configuration, and compared with
what the fitted model's diffuse part (plus its ambient term) predicts there. An unlit photo (its light exactly 0: the
flash off, stream.py ``unlit_photo``) cannot show a highlight and is left out.

One thread per texel loops over a window of photos; windows accumulate (outputs pre-filled, added to), so the
photos stream exactly as the fit's passes stream them.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from texstream.fit.kernels.overloads import IMAGE_PIXEL, declare
from texstream.fit.kernels.stream import SampleOptions, TexelFrames, observe, unlit_photo
from texstream.render.camera import ImageInfo
from texstream.render.shading import incident_light

wp.set_module_options({"enable_backward": False})


@wp.func
def mirror_cosine(infos: wp.array(dtype=ImageInfo), k: int, tex: TexelFrames, i: int):
    """cos of the angle between photo k's view and its light mirrored about texel i's shading normal (at the
    texel centre): 1 at the mirror configuration, the base of a Phong lobe ``max(s, 0)^n``."""
    p = tex.pos[i]
    nrm = tex.nrm[i]
    wi, _e_int, _dist = incident_light(infos[k].light_kind, infos[k].light_vec, infos[k].light_intensity, p)
    vdir = wp.normalize(infos[k].center - p)
    mirrored = 2.0 * wp.dot(nrm, wi) * nrm - wi
    return wp.dot(mirrored, vdir)


@wp.func
def diffuse_residual(y: wp.vec3, w: wp.vec3, exposure: float, rho_d: wp.vec3, ambient: wp.vec3):
    """(photo minus the diffuse part's prediction, that prediction), both averaged over the channels in photo
    values: the prediction is ``w rho_d + exposure A`` (w = exposure E cos, observe's weight)."""
    pred = wp.cw_mul(w, rho_d) + exposure * ambient
    d = y - pred
    return (d[0] + d[1] + d[2]) / 3.0, (pred[0] + pred[1] + pred[2]) / 3.0


@wp.kernel
def off_mirror_residual_kernel(tex: TexelFrames, images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
                               shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo),
                               img_begin: int, img_end: int, opt: SampleOptions, rho_d: wp.array(dtype=wp.vec3),
                               ambient: wp.array(dtype=wp.vec3), s_off: float, s_cone: float,
                               sums: wp.array(dtype=wp.vec4d), cone: wp.array(dtype=wp.int32)):
    """Per texel, added to ``sums``: (samples, sum r, sum r^2, all samples) of the diffuse residual r over the
    samples off the mirror configuration (mirror cosine below ``s_off``), and the samples near it (at or above
    ``s_cone``) counted into ``cone``."""
    i = wp.tid()
    acc = sums[i]
    near = cone[i]
    for k in range(img_begin, img_end):
        if unlit_photo(infos, k):
            continue
        ok, y, w, _u, _v, _xs, _ys = observe(images, depth, shadow, infos, k, tex, i, opt)
        if ok:
            s = mirror_cosine(infos, k, tex, i)
            acc[3] = acc[3] + wp.float64(1.0)
            if s < s_off:
                r, _pred = diffuse_residual(y, w, infos[k].exposure, rho_d[i], ambient[i])
                acc[0] = acc[0] + wp.float64(1.0)
                acc[1] = acc[1] + wp.float64(r)
                acc[2] = acc[2] + wp.float64(r) * wp.float64(r)
            elif s >= s_cone:
                near = near + 1
    sums[i] = acc
    cone[i] = near


@wp.kernel
def highlight_samples_kernel(tex: TexelFrames, images: wp.array3d(dtype=Any), depth: wp.array3d(dtype=wp.float32),
                             shadow: wp.array3d(dtype=wp.float32), infos: wp.array(dtype=ImageInfo),
                             img_begin: int, img_end: int, opt: SampleOptions, rho_d: wp.array(dtype=wp.vec3),
                             ambient: wp.array(dtype=wp.vec3), s_cone: float, level: wp.array(dtype=wp.float32),
                             sigma: wp.array(dtype=wp.float32), k_sigma: float, rel_margin: float,
                             hits: wp.array(dtype=wp.int32)):
    """Per texel, added to ``hits``: the samples near the mirror configuration (mirror cosine at or above
    ``s_cone``) whose diffuse residual exceeds the texel's off-mirror ``level`` by more than both
    ``k_sigma`` times its off-mirror spread ``sigma`` and ``rel_margin`` times the diffuse prediction."""
    i = wp.tid()
    n_hits = hits[i]
    for k in range(img_begin, img_end):
        if unlit_photo(infos, k):
            continue
        ok, y, w, _u, _v, _xs, _ys = observe(images, depth, shadow, infos, k, tex, i, opt)
        if ok and mirror_cosine(infos, k, tex, i) >= s_cone:
            r, pred = diffuse_residual(y, w, infos[k].exposure, rho_d[i], ambient[i])
            threshold = wp.max(k_sigma * sigma[i], rel_margin * wp.abs(pred))
            if r - level[i] > threshold:
                n_hits = n_hits + 1
    hits[i] = n_hits


# the default run's overloads, in the module before its first launch (fit/kernels/overloads.py)
declare(off_mirror_residual_kernel, images=IMAGE_PIXEL)
declare(highlight_samples_kernel, images=IMAGE_PIXEL)
