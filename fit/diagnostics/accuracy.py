"""Ground-truth accuracy of a fit on a synthetic capture (numpy only; used by tests and benchmarks).

The issue's targets are stated on texels that "see the highlight in at least 5 photos":
:func:`highlight_counts` counts those photos from the true parameters. :func:`interior_texels`
marks texels whose whole 1-ring has their material: texels at a material edge are fitted to
photos that blend two BRDFs (bilinear texture lookup in the renderer, bilinear photo filtering in
the fit), which no single texel's Lafortune lobe reproduces, so their error measures the sampling,
not the optimizer.
"""

from __future__ import annotations

import numpy as np


def highlight_counts(frames: list, position: np.ndarray, normal: np.ndarray, params: np.ndarray, lobe_offset: int,
                     min_fraction: float = 0.1) -> np.ndarray:
    """(N,) per texel, the photos (capture ``Frame`` objects) in which its true lobe is at >= ``min_fraction`` of its peak.

    Counts photos where the texel is lit and seen at cos > 0.1 (occlusion is not tested: exact on
    convex scenes, an upper bound elsewhere). Isotropic lobes with c_xy = -1, c_z = 1 (the
    synthetic scenes' lobes): the lobe base is the cosine between the mirrored light and the view.
    """
    pos = position.astype(np.float64)
    nrm = normal.astype(np.float64)
    count = np.zeros(len(pos), int)
    for fr in frames:
        v = fr.center - pos
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        if fr.light.type == "directional":
            ld = np.broadcast_to(-np.asarray(fr.light.direction, np.float64), pos.shape)
        else:
            ld = fr.light.position - pos
        ld = ld / np.linalg.norm(ld, axis=1, keepdims=True)
        cv, cl = (v * nrm).sum(1), (ld * nrm).sum(1)
        mirror = 2 * cl[:, None] * nrm - ld
        lobe = np.clip((mirror * v).sum(1), 0, 1) ** params[:, lobe_offset + 5]
        count += (cv > 0.1) & (cl > 0.1) & (lobe >= min_fraction)
    return count


def interior_texels(material: np.ndarray, neighbors: np.ndarray) -> np.ndarray:
    """(N,) bool: every existing grid neighbour of the texel has its material id."""
    nb = neighbors
    same = np.where(nb >= 0, material[np.maximum(nb, 0)] == material[:, None], True)
    return same.all(axis=1)


def lobe_normal_peak(params: np.ndarray, lobe_offset: int, lobe_stride: int) -> np.ndarray:
    """(N, 3) a lobe's BRDF peak at normal incidence, rho_s * c_z^n (the lobe base at u = v = the
    normal is c_z, for isotropic and general lobes alike).

    What a capture whose light rides beside the camera measures: its highlights all sit near one
    incidence angle, so the photos fix the lobe's height there, while rho_s and c_z separately
    trade along c_z^n (fit_accuracy.py reports both)."""
    p = params.astype(np.float64)
    cz = np.clip(p[:, lobe_offset + lobe_stride - 2], 0.0, None)
    n = p[:, lobe_offset + lobe_stride - 1]
    return p[:, lobe_offset:lobe_offset + 3] * (cz ** n)[:, None]


def relative_errors(fitted: np.ndarray, truth: np.ndarray, floor: float = 1e-9) -> np.ndarray:
    """|fitted - truth| / |truth| per entry (truth below ``floor`` counts as ``floor``)."""
    return np.abs(fitted - truth) / np.maximum(np.abs(truth), floor)
