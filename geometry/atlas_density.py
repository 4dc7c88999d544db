"""Density-weighted charts of the UV atlas (:func:`texstream.geometry.atlas.build_atlas` with face weights):
charts split into pieces whose faces ask for about the same texel density, each scaled to its ask.

Imports only numpy (scipy inside :func:`_components`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .atlas import AtlasConfig


def _uv_areas(uvs: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = np.asarray(uvs, dtype=np.float64)[faces]
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


def _density_charts(chart: np.ndarray, idx: np.ndarray, uv: np.ndarray, vmap: np.ndarray, weights: np.ndarray,
                    area3: np.ndarray, config: AtlasConfig, merge_any: float = 0.0):
    """Charts split into density bands and scaled so that texels per face follow the weights.

    Per-face target: texels per unit area in proportion to the weight. The flattening is not
    area-preserving (xatlas' charts are near-conformal), so a face of a chart scaled by s gets
    s^2 * stretch texels per unit area at unit density; the scale a face asks for is
    sqrt(w / stretch) (slivers can come out of the flattening with almost no area: the correction
    is clipped to two octaves either way). No face is asked to hold fewer than
    ``min_face_texels``. Each piece then gets the area-weighted geometric mean of its faces' asks
    (the least-squares fit in log texel size).

    Args:
        chart, idx, uv, vmap: xatlas' charts (chart id per face, (F, 3) vertex ids, (V, 2)
            flattening in scene units, input vertex per vertex).
        weights, area3: (F,) face weights and surface areas.
        config: atlas options (density_bands, density_smoothing, min_face_texels, min_piece_texels,
            resolution, texels_per_unit).
        merge_any: pieces below this fraction of ``min_piece_texels`` merge into a neighbour of
            any weight (0: only into neighbours less than a band away).

    Returns:
        (chart, idx, uv, vmap) of the scaled pieces.
    """
    stretch = np.abs(_uv_areas(uv, idx)) / np.maximum(area3, 1e-300)
    ok = (area3 > 0) & (stretch > 0)
    want = weights / np.clip(np.where(ok, stretch, 1.0), 0.25, 4.0)
    # area of one texel at unit weight: from the density asked for, or ~60% packing efficiency
    if config.texels_per_unit > 0:
        texel_area = 1.0 / config.texels_per_unit ** 2
    else:
        texel_area = float((want * area3).sum()) / (0.6 * config.resolution ** 2)
    want = np.maximum(want, config.min_face_texels * texel_area / np.maximum(area3, 1e-300))
    if config.density_bands > 0:
        # split charts where the wanted scale changes by more than a band (atlas.py's module doc, step 2)
        chart, idx, uv, vmap = _split_by_weight(chart, idx, uv, vmap, want, area3, config.density_bands,
                                                smooth=config.density_smoothing,
                                                min_size=config.min_piece_texels * texel_area,
                                                merge_any=merge_any)
    n = int(chart.max()) + 1
    lw = np.log(np.maximum(want, 1e-300))
    ca = np.bincount(chart, weights=area3, minlength=n)
    cl = np.bincount(chart, weights=lw * area3, minlength=n)
    wc = np.exp(np.divide(cl, ca, out=np.zeros_like(cl), where=ca > 0))
    # Zero-weight charts still get a sliver of texels (1/100 of the largest linear scale) so
    # every face keeps a parameter.
    scale = np.sqrt(np.maximum(wc, 1e-4 * wc.max()))
    return chart, idx, _scale_charts(uv, idx, chart, scale), vmap


def _scale_charts(uv: np.ndarray, idx: np.ndarray, chart: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Scale each chart's UVs by ``scale[chart]`` (split vertices belong to exactly one chart)."""
    vscale = np.ones(len(uv))
    vscale[idx.reshape(-1)] = np.repeat(scale[chart], 3)
    return uv * vscale[:, None]


def _split_by_weight(chart: np.ndarray, idx: np.ndarray, uv: np.ndarray, vmap: np.ndarray, weights: np.ndarray,
                     area: np.ndarray, band: float, smooth: int = 1, min_size: float = 0.0,
                     merge_any: float = 0.0):
    """Split charts into connected pieces of faces whose weights lie in one band of ``band`` octaves.

    The log2 weights are first smoothed ``smooth`` times over faces sharing an edge of the chart
    (area-weighted Jacobi steps) so noisy weights do not shatter charts, and pieces whose area is
    below ``min_size`` (weight times area: the area of that many texels at unit weight) are merged
    into their largest neighbour in the same chart. Vertices shared by two pieces are duplicated
    (each piece gets its own scale before packing).

    Args:
        chart: (F,) chart id per face; idx: (F, 3) vertex ids; uv: (V, 2) flattened charts;
        vmap: (V,) input vertex of each vertex; weights, area: (F,); band: octaves per band;
        smooth: smoothing iterations; min_size: smallest piece (sum of weight * area, scene units^2);
        merge_any: fraction of ``min_size`` below which a piece merges at any weight difference.

    Returns:
        (chart (F,), idx (F, 3), uv (V', 2), vmap (V',)) with the new pieces.
    """
    nf = len(chart)
    fa, fb = _face_adjacency(idx)
    lw = np.log2(np.maximum(weights, 1e-12))
    lw_s = _smooth_faces(lw, area, fa, fb, smooth)
    key = chart.astype(np.int64) * 100000 + np.floor(lw_s / band).astype(np.int64)
    _, key = np.unique(key, return_inverse=True)
    piece = _components(key, fa, fb, nf)
    if min_size > 0:
        # pieces under min_size join a neighbour less than a band away; with merge_any, pieces under
        # that fraction of it join the nearest in weight at any distance (the packer's border
        # around a tiny chart costs more than it holds: noisy weights make more charts than a
        # small atlas can hold)
        piece = _merge_small_pieces(piece, area * np.exp2(lw), lw_s, fa, fb, min_size, band)
        if merge_any > 0:
            piece = _merge_small_pieces(piece, area * np.exp2(lw), lw_s, fa, fb, merge_any * min_size, np.inf)
    _, piece = np.unique(piece, return_inverse=True)
    # one vertex per (vertex, piece)
    vp = idx.reshape(-1) * (piece.max() + 1) + np.repeat(piece, 3)
    uniq, new_idx = np.unique(vp, return_inverse=True)
    old_v = uniq // (piece.max() + 1)
    return piece.astype(np.int64), new_idx.reshape(-1, 3), uv[old_v], vmap[old_v]


def _face_adjacency(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b) of faces sharing an edge (vertex ids as given: split seams separate charts)."""
    f = np.asarray(idx, np.int64)
    e = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2)
    e.sort(axis=1)
    face = np.repeat(np.arange(len(f)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, face = e[order], face[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    return face[:-1][same], face[1:][same]


def _smooth_faces(x: np.ndarray, area: np.ndarray, fa: np.ndarray, fb: np.ndarray, n: int) -> np.ndarray:
    """``n`` Jacobi steps x <- (x + area-weighted mean of the edge neighbours) / 2."""
    nf = len(x)
    wsum = np.bincount(fa, weights=area[fb], minlength=nf) + np.bincount(fb, weights=area[fa], minlength=nf)
    for _ in range(int(n)):
        acc = np.bincount(fa, weights=(area * x)[fb], minlength=nf) + np.bincount(fb, weights=(area * x)[fa],
                                                                                minlength=nf)
        x = np.where(wsum > 0, 0.5 * x + 0.5 * np.divide(acc, wsum, out=np.zeros(nf), where=wsum > 0), x)
    return x


def _components(key: np.ndarray, fa: np.ndarray, fb: np.ndarray, nf: int) -> np.ndarray:
    """Connected components of faces joined by shared edges whose two faces have the same key."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    keep = key[fa] == key[fb]
    g = coo_matrix((np.ones(int(keep.sum())), (fa[keep], fb[keep])), shape=(nf, nf))
    _, comp = connected_components(g, directed=False)
    return comp.astype(np.int64)


def _merge_small_pieces(piece: np.ndarray, size: np.ndarray, value: np.ndarray, fa: np.ndarray, fb: np.ndarray,
                        min_size: float, max_diff: float, max_rounds: int = 10) -> np.ndarray:
    """Merge pieces whose summed ``size`` is below ``min_size`` into the edge neighbour whose
    ``size``-weighted mean ``value`` is closest, if it differs by at most ``max_diff``.

    A piece only merges into a larger one (ties: the higher id), so merges never form cycles; one
    step per round (a merged piece's new mean decides the next round).
    """
    piece = piece.copy()
    for _ in range(max_rounds):
        n = int(piece.max()) + 1
        psize = np.bincount(piece, weights=size, minlength=n)
        pval = np.bincount(piece, weights=size * value, minlength=n) / np.maximum(psize, 1e-300)
        pa, pb = piece[fa], piece[fb]
        d = pa != pb
        a = np.concatenate([pa[d], pb[d]])
        b = np.concatenate([pb[d], pa[d]])
        diff = np.abs(pval[b] - pval[a])
        ok = (psize[a] < min_size) & (diff <= max_diff) & (
            (psize[b] > psize[a]) | ((psize[b] == psize[a]) & (b > a)))
        a, b, diff = a[ok], b[ok], diff[ok]
        if a.size == 0:
            break
        # per small piece, the neighbour closest in value (last after sorting by -distance)
        order = np.lexsort((b, -diff, a))
        last = np.r_[a[order][1:] != a[order][:-1], True]
        target = np.arange(n)
        target[a[order][last]] = b[order][last]
        piece = target[piece]
    return piece
