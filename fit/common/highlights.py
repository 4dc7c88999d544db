"""Did the photos show highlights the fitted model has no lobe for? (issue 39 item 1)

A fit whose lobes came out empty (specular albedo 0, exponent where it started) may mean a matte object or a model
that missed what the photos show. This diagnostic tells them apart per texel, from the fitted model and its photos,
sampled exactly as the fit samples them (fit/kernels/highlights.py, two streaming passes over the fit's photo
windows), the lit photos' samples alone (a photo taken with the flash off, its light 0, shows no highlight):

highlight (the photos show one)
    Some sample near the mirror configuration exceeds the model's diffuse prediction by a clear margin.

    * Near the mirror: the view within the half-maximum of a lobe of exponent :data:`CONE_EXPONENT` (10, the
      fit's starting exponent, render/layout.py; a sharper lobe is narrower, so its peak lies inside too) about
      the light mirrored by the shading normal: mirror cosine ``s >= 0.5^(1/10)`` (21 degrees; the half vector
      within about 10.5 degrees of the normal).
    * The diffuse prediction: ``exposure (E cos rho_d + A)`` of the fitted rho_d (and ambient term A), averaged
      over the channels; the residual r = photo minus that.
    * The margin: r minus the texel's own off-mirror level (the mean r over its samples with ``s < 0.05^(1/10)``,
      where a lobe of exponent 10 is below 5% of its peak: a diffuse albedo fitted a little high or low shifts
      every sample alike and is no highlight) must exceed both :data:`K_SIGMA` (4) standard deviations of those
      off-mirror residuals (photo noise plus what the diffuse model misses elsewhere: a one-sided 4-sigma excess
      happens by chance in 3e-5 of Gaussian samples, a few texels in 100,000 over some tens of mirror samples
      each) and :data:`REL_MARGIN` (10%) of the diffuse prediction (noise-free or 8-bit photos have a tiny spread;
      a lobe whose peak is a tenth of the diffuse is also where :data:`LOBE_FRACTION` starts to count a lobe).
      Texels with fewer than :data:`MIN_OFF_SAMPLES` off-mirror samples take the median spread of the others and
      level 0.

lobe (the model has one)
    Some lobe's rho_s (channel mean) is at least :data:`LOBE_FRACTION` of rho_d's and its exponent is off its
    lower bound (1, render/layout.py): its peak is then at least a tenth of the diffuse BRDF, the height
    :data:`REL_MARGIN` detects. (An empty lobe, rho_s 0, keeps the exponent it started at, 10: the "floor" issue 39
    saw; the rho_s test rules it out.)

The counts (model.json ``highlights``): texels seen (by a lit photo), with a highlight, with a lobe, highlight but no lobe (the
failure issue 39 describes: polished bronze fitted with empty lobes) and lobe but no highlight (a lobe no photo
showed: extrapolated from the flanks, or borrowed from its material); where the fit tested which lobes its photos
constrain (materials' ``texel_evidence``), how many lobes are constrained. highlights.png maps the classes.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import warp as wp

from texstream.fit.kernels.highlights import highlight_samples_kernel, off_mirror_residual_kernel

CONE_EXPONENT = 10.0
"""the exponent whose lobe's half maximum bounds "near the mirror" (the fit's starting exponent)"""
K_SIGMA = 4.0
"""a highlight sample's excess over the texel's off-mirror level, in off-mirror standard deviations"""
REL_MARGIN = 0.1
"""... and as a fraction of the diffuse prediction"""
OFF_LOBE_FRACTION = 0.05
"""samples where a lobe of exponent CONE_EXPONENT is below this fraction of its peak are "off the mirror\""""
MIN_OFF_SAMPLES = 4
"""off-mirror samples a texel needs for its own level and spread"""
LOBE_FRACTION = 0.1
"""a lobe counts where its rho_s is at least this fraction of rho_d"""

CLASS_COLOURS = np.array([[0.0, 0.0, 0.0], [0.3, 0.3, 0.3], [0.1, 0.8, 0.2], [0.9, 0.1, 0.1], [0.2, 0.4, 1.0]],
                         np.float32)
"""highlights.png per class: unseen, neither, highlight with lobe, highlight without lobe, lobe without highlight"""
CLASS_NAMES = ("unseen (black)", "no highlight, no lobe (grey)", "highlight and lobe (green)",
               "highlight, no lobe (red)", "lobe, no highlight (blue)")


@dataclasses.dataclass
class HighlightMasks:
    """Per compact texel: seen (some usable sample of a lit photo), highlight, lobe, highlight samples and samples
    near the mirror; the seconds the two passes took."""

    seen: np.ndarray
    highlight: np.ndarray
    lobe: np.ndarray
    hits: np.ndarray
    near_mirror: np.ndarray
    seconds: float

    def classes(self) -> np.ndarray:
        """(N,) class per texel, indices into CLASS_COLOURS."""
        h, lo = self.highlight, self.lobe
        out = np.where(h, np.where(lo, 2, 3), np.where(lo, 4, 1))
        return np.where(self.seen, out, 0).astype(np.int8)


def lobe_mask(params: np.ndarray, layout) -> np.ndarray:
    """(N,) whether some lobe of compact ``params`` counts as a lobe (module doc)."""
    rho_d = params[:, 0:3].mean(axis=1)
    out = np.zeros(len(params), bool)
    n_floor = layout.lower()
    for j in range(layout.n_lobes):
        o = layout.lobe_offset(j)
        col_n = o + layout.lobe_stride - 1
        rho_s = params[:, o:o + 3].mean(axis=1)
        out |= (rho_s > 0) & (rho_s >= LOBE_FRACTION * rho_d) & (params[:, col_n] > n_floor[col_n] * (1 + 1e-3))
    return out


def _parts(problem) -> list:
    """The problem and its peers (photos split over devices): each streams its own photos."""
    return [problem, *problem.peers]


def _stream(problem, kernel, per_texel: dict, arguments, outputs: dict) -> dict:
    """Launch ``kernel`` over every window of every part's photos, as the fit's passes stream them;
    ``per_texel`` (name -> numpy) uploaded to each part's device, ``arguments(uploaded)`` the kernel's arguments
    after the sample options, ``outputs`` (name -> warp dtype) zero-filled there and summed over the parts on the
    host."""
    total = {}
    for pr in _parts(problem):
        dev = pr.device
        ins = {k: wp.array(v, dtype=wp.vec3 if v.ndim == 2 else wp.float32, device=dev) for k, v in per_texel.items()}
        outs = {k: wp.zeros(pr.n, dtype=wt, device=dev) for k, wt in outputs.items()}
        for images, depth, shadow, infos, b, e in pr.own_photos.windows():
            wp.launch(kernel, dim=pr.n, device=dev,
                      inputs=[pr.tex, images, depth, shadow, infos, b, e, pr.opt, *arguments(ins)],
                      outputs=list(outs.values()))
        for k, a in outs.items():
            total[k] = a.numpy() + total.get(k, 0)
    return total


def highlight_masks(problem, params: np.ndarray) -> HighlightMasks:
    """Which texels' photos show a highlight and which have a lobe (module doc), for the fitted compact
    ``params`` of ``problem`` (a StreamProblem of a lit model)."""
    t0 = time.perf_counter()
    lay, p = problem.layout.rendered(np.asarray(params, np.float64))  # a room light as the ambient radiance it makes
    rho_d = np.ascontiguousarray(p[:, 0:3], np.float32)
    amb = (np.ascontiguousarray(p[:, lay.ambient_offset:lay.ambient_offset + 3], np.float32) if lay.ambient
           else np.zeros_like(rho_d))
    s_cone = 0.5 ** (1.0 / CONE_EXPONENT)
    s_off = OFF_LOBE_FRACTION ** (1.0 / CONE_EXPONENT)
    first = _stream(problem, off_mirror_residual_kernel, {"rho_d": rho_d, "ambient": amb},
                    lambda a: [a["rho_d"], a["ambient"], float(s_off), float(s_cone)],
                    {"sums": wp.vec4d, "cone": wp.int32})
    sums, near = first["sums"], first["cone"]
    count = sums[:, 0]
    own = count >= MIN_OFF_SAMPLES
    mean = np.where(own, sums[:, 1] / np.maximum(count, 1), 0.0)
    spread = np.sqrt(np.maximum(sums[:, 2] / np.maximum(count, 1) - mean ** 2, 0.0))
    fallback = float(np.median(spread[own])) if own.any() else 0.0
    sigma = np.where(own, spread, fallback).astype(np.float32)
    level = mean.astype(np.float32)
    second = _stream(problem, highlight_samples_kernel,
                     {"rho_d": rho_d, "ambient": amb, "level": level, "sigma": sigma},
                     lambda a: [a["rho_d"], a["ambient"], float(s_cone), a["level"], a["sigma"], float(K_SIGMA),
                                float(REL_MARGIN)],
                     {"hits": wp.int32})
    seen = sums[:, 3] > 0
    hits = second["hits"]
    return HighlightMasks(seen=seen, highlight=seen & (hits > 0), lobe=seen & lobe_mask(p, lay), hits=hits,
                          near_mirror=near, seconds=time.perf_counter() - t0)


def highlight_report(masks: HighlightMasks, constrained: np.ndarray | None = None) -> dict:
    """What model.json records (module doc); ``constrained``: (N,) the fit's constrained-lobe test where it ran."""
    h, lo = masks.highlight, masks.lobe
    out = {"seen_texels": int(masks.seen.sum()), "highlight_texels": int(h.sum()), "lobe_texels": int(lo.sum()),
           "highlight_without_lobe": int((h & ~lo).sum()), "lobe_without_highlight": int((lo & ~h).sum()),
           "texels_near_mirror": int((masks.seen & (masks.near_mirror > 0)).sum()),
           "lobe_constrained": None if constrained is None else int((lo & constrained).sum()),
           "map": "highlights.png", "classes": list(CLASS_NAMES), "seconds": masks.seconds,
           "rule": {"cone_exponent": CONE_EXPONENT, "k_sigma": K_SIGMA, "rel_margin": REL_MARGIN,
                    "off_lobe_fraction": OFF_LOBE_FRACTION, "min_off_samples": MIN_OFF_SAMPLES,
                    "lobe_fraction": LOBE_FRACTION}}
    out["line"] = highlight_line(out)
    return out


def highlight_line(report: dict) -> str:
    """The one line the run's report shows."""
    return (f"{report['highlight_texels']} of {report['seen_texels']} seen texels showed a highlight, "
            f"{report['lobe_texels']} have a lobe; {report['highlight_without_lobe']} highlight without a lobe, "
            f"{report['lobe_without_highlight']} lobe without a highlight")


def highlight_image(masks: HighlightMasks, grid_index: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float32 map of the classes (CLASS_COLOURS), black off the texels."""
    img = np.zeros((height * width, 3), np.float32)
    img[grid_index] = CLASS_COLOURS[masks.classes()]
    return img.reshape(height, width, 3)
