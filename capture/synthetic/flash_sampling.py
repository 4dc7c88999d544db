"""How finely a flash capture's photos sample its object (issue 39): the figures that chose the resolved flash scene
(capture/synthetic/flash_capture.py's module doc), computed from the scene alone (its cameras, mesh and maps; no
rendering), so that a test holds the scene to them and a benchmark records them beside its results.

- **pixels a texel**: a texel's footprint in a photo, the area of its two atlas edges projected (pinhole, exact for
  a texel small against its distance), in the photos facing it (view cosine above 0.1, the fit's grazing limit); the
  issue's "4x the pixels the atlas needs" is 4 in the median facing photo; given for the truth's atlas and for the
  fit's (``FIT_ATLAS``, the same UVs: the truth's figure times the ratio of the texel counts);
- **texels a noise cell**: the width in texels of the fit's atlas of the finest octave's cells of the value-noise
  albedo (its lattice spacing along u); band-limited to the atlas (its Nyquist period 2 texels) when a cell spans 3
  texels or more;
- **texel contrast**: the true albedo's largest relative step to a 4-neighbour in the atlas (frequency and
  amplitude together: the noise's amount and sharpening raise it too);
- **highlights**: the training photos (every 8th held out, the benchmarks' split) in which a texel's true lobe is
  at 10% of its peak or more, the flash at the camera (as ``texstream.fit.diagnostics.accuracy.highlight_counts``,
  which this layer may not import): a lobe is pinned down where two photos show it.
"""

from __future__ import annotations

import numpy as np

from texstream.capture.capture_json import split_holdout

from .flash_capture import FIT_ATLAS
from .synth import SynthConfig, _frames, prepare_scene

HOLDOUT_EVERY = 8
"""the benchmarks' hold-out (every 8th photo)"""
FACING_COSINE = 0.1
"""a photo faces a texel above this view cosine (the fit's grazing limit)"""
HIGHLIGHT_FRACTION = 0.1
"""a photo shows a texel's highlight where its lobe is at this fraction of its peak or more"""


def scene_sampling(scene: str, photos: int, image_size: int) -> dict:
    """The sampling figures (module doc) of a flash scene photographed by ``photos`` cameras of ``image_size`` px."""
    sc, _, bake, layout, params, *_ = prepare_scene(scene, SynthConfig(photos=photos, image_size=image_size, bits=32,
                                                                       progress=False, preview=False))
    train = split_holdout(_frames(sc, ".exr"), HOLDOUT_EVERY)[0]
    cov = bake.covered
    # texels whose right and upper atlas neighbours lie on the surface: their edges are the texel's sides
    inner = cov & np.roll(cov, -1, 1) & np.roll(cov, -1, 0)
    pos = bake.position.astype(np.float64)
    p, nrm = pos[inner], bake.normal[inner].astype(np.float64)
    edge_u, edge_v = (np.roll(pos, -1, 1) - pos)[inner], (np.roll(pos, -1, 0) - pos)[inner]
    footprints, shown = [], np.zeros(len(p), np.int64)
    n_exp = params[inner][:, layout.lobe_offset(0) + layout.lobe_stride - 1].astype(np.float64)
    for f in train:
        r, t, fx = np.asarray(f.R), np.asarray(f.t), f.intrinsics.fx

        def image(x: np.ndarray) -> np.ndarray:
            cam = x @ r.T + t
            return cam[:, :2] / cam[:, 2:3] * fx

        view = np.asarray(f.center)[None] - p
        cos = np.sum(view * nrm, axis=1) / np.linalg.norm(view, axis=1)
        a, du, dv = image(p), image(p + edge_u), image(p + edge_v)
        du, dv = du - a, dv - a
        area = np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0])
        footprints.append(np.where(cos > FACING_COSINE, area, np.nan))
        # the flash at the camera: the mirrored light meets the view at twice the normal-view angle
        mirror_cos = np.clip(2.0 * cos * cos - 1.0, 0.0, 1.0)
        shown += (cos > FACING_COSINE) & (mirror_cos ** n_exp >= HIGHLIGHT_FRACTION)
    fp = np.array(footprints)
    faced = np.sum(np.isfinite(fp), axis=0)
    median_px = np.nanmedian(np.where(faced[None] > 0, fp, 0.0), axis=0)[faced > 0]
    lum = np.where(cov, params[..., 0:3].max(axis=2), np.nan)
    contrast = np.zeros(lum.shape)
    for shift in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        contrast = np.fmax(contrast, np.abs(np.roll(lum, shift, (0, 1)) / lum - 1.0))
    seen = shown >= 1
    noise = [m["noise"] for m in sc["materials"].values() if m.get("noise")]
    cells = [(n["cells"] if isinstance(n["cells"], (int, float)) else n["cells"][0]) * 2 ** (int(n["octaves"]) - 1)
             for n in noise]
    fit_w, fit_h = FIT_ATLAS.get(scene) or (bake.width, bake.height)
    px = float(np.median(median_px))
    return {"scene": scene, "photos": photos, "image_size": image_size, "atlas": [bake.width, bake.height],
            "fit_atlas": [fit_w, fit_h], "training_photos": len(train), "texels": int(inner.sum()),
            "pixels_a_texel_median_facing_photo": px,
            "pixels_a_fit_texel_median_facing_photo": px * bake.width * bake.height / (fit_w * fit_h),
            "fit_texels_a_noise_cell": fit_w / max(cells) if cells else None,
            "texel_contrast_median": float(np.nanmedian(contrast[inner])),
            "texels_faced_by_4": float(np.mean(faced >= 4)),
            "texels_highlight_shown": float(np.mean(seen)),
            "highlight_shown_twice_of_shown": float(np.mean(shown[seen] >= 2)) if seen.any() else 0.0}
