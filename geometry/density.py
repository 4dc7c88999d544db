"""Texel density from the photos: how large each face appears, and how even an atlas's texels are.

The seed notes that a fixed texel count per triangle wastes memory: a triangle seen large in the
photos deserves more texels than one seen small. :func:`face_pixel_density` measures, per face,
the projected area in pixels per unit of surface area in the photo that sees it largest (visible,
front-facing, inside the image); :func:`density_face_weights` turns it into the ``face_weights`` of
:func:`texstream.geometry.atlas.build_atlas`, so that texels per face follow pixels per face.
:func:`texel_size_spread` reports, for an atlased mesh, the size of one texel projected into the
photos (pixels per texel side) and its spread over the surface.

numpy and warp only (depth maps from :mod:`.visibility`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from texstream.render.mesh import SurfaceMesh
from .visibility import depth_maps, visible_points


def _projected_areas(mesh: SurfaceMesh, frame) -> tuple[np.ndarray, np.ndarray]:
    """(F,) projected triangle area in pixels (0 when back-facing or behind) and (F,) centroids."""
    intr = frame.intrinsics
    r = np.asarray(frame.R, np.float64)
    t = np.asarray(frame.t, np.float64).reshape(1, 3)
    pc = mesh.vertices @ r.T + t
    z = pc[:, 2]
    zs = np.where(z > 1e-12, z, np.nan)
    uv = np.stack([intr.fx * pc[:, 0] / zs + intr.cx, intr.fy * pc[:, 1] / zs + intr.cy], axis=1)
    a, b, c = uv[mesh.faces[:, 0]], uv[mesh.faces[:, 1]], uv[mesh.faces[:, 2]]
    # a face counter-clockwise seen from outside appears clockwise in (u, v) (image y points down),
    # so the front-facing projected area is minus the usual cross product
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    area = np.nan_to_num(-0.5 * cross, nan=0.0)
    return np.maximum(area, 0.0), mesh.vertices[mesh.faces].mean(axis=1)


def face_pixel_density(mesh: SurfaceMesh, frames: Sequence, device: str = "cpu",
                       depths: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Pixels per unit surface area of each face in the photo that sees it largest.

    Args:
        mesh: the surface in the capture frame (outward faces).
        frames: frames with R, t, intrinsics.
        device: Warp device for the depth maps.
        depths: precomputed depth maps of ``mesh`` for ``frames`` (else ray-cast here).

    Returns:
        (F,) pixels per scene unit^2; 0 for faces no photo sees (centroid visibility test).
    """
    if depths is None:
        depths = depth_maps(mesh, frames, device)
    areas = mesh.face_areas()
    best = np.zeros(mesh.n_faces)
    tol = 2e-3 * mesh.bbox_diagonal()
    for fr, d in zip(frames, depths):
        pa, cen = _projected_areas(mesh, fr)
        vis = visible_points(cen, fr, d, rel_tol=1e-3, abs_tol=tol)
        best = np.maximum(best, np.where(vis, pa, 0.0))
    return np.divide(best, areas, out=np.zeros_like(best), where=areas > 0)


def density_face_weights(mesh: SurfaceMesh, frames: Sequence, device: str = "cpu",
                         depths: Sequence[np.ndarray] | None = None, max_ratio: float = 64.0) -> np.ndarray:
    """``face_weights`` for ``build_atlas``: texels per face in proportion to pixels per face.

    Faces no photo sees get the median weight (they still receive texels: the fit may see them
    through a photo not used here, and the bake needs every face); weights are clipped to
    [median / max_ratio, median * max_ratio] so a face seen at grazing angles or extremely close
    cannot starve or flood the atlas.

    Returns:
        (F,) positive weights with median 1.
    """
    dens = face_pixel_density(mesh, frames, device, depths)
    seen = dens > 0
    if not seen.any():
        return np.ones(mesh.n_faces)
    med = float(np.median(dens[seen]))
    w = np.where(seen, dens / med, 1.0)
    return np.clip(w, 1.0 / max_ratio, max_ratio)


def texel_size_spread(mesh: SurfaceMesh, width: int, height: int, frames: Sequence, device: str = "cpu",
                      depths: Sequence[np.ndarray] | None = None) -> dict:
    """How large one texel of an atlased mesh appears in the photos, and how much that varies.

    For each face seen by some photo: pixels per texel = projected pixel area (best photo) over
    texel area (UV area * width * height); the texel's projected size is its square root
    (pixels per texel side). Statistics are weighted by surface area.

    Args:
        mesh: atlased mesh (``uvs`` set; vertices split at seams are fine).
        width, height: atlas size in texels.
        frames, device, depths: as for :func:`face_pixel_density`.

    Returns:
        ``{"median", "p10", "p90"}`` texel size in pixels, ``"p90_over_p10"`` (1 = perfectly even),
        ``"log2_std"`` (area-weighted std of log2 size, in octaves), ``"faces_seen"``.
    """
    if mesh.uvs is None:
        raise ValueError("texel_size_spread needs a mesh with UVs")
    dens = face_pixel_density(mesh, frames, device, depths)
    uv = mesh.uvs[mesh.faces]
    uv_area = 0.5 * np.abs((uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1])
                           - (uv[:, 1, 1] - uv[:, 0, 1]) * (uv[:, 2, 0] - uv[:, 0, 0]))
    texels = uv_area * width * height
    area = mesh.face_areas()
    ok = (dens > 0) & (texels > 0) & (area > 0)
    size = np.sqrt(dens[ok] * area[ok] / texels[ok])
    w = area[ok]
    order = np.argsort(size)
    cw = np.cumsum(w[order]) / w.sum()

    def q(p: float) -> float:
        return float(size[order][min(np.searchsorted(cw, p), len(order) - 1)])

    lg = np.log2(size)
    mean = np.average(lg, weights=w)
    return {"median": q(0.5), "p10": q(0.1), "p90": q(0.9), "p90_over_p10": q(0.9) / q(0.1),
            "log2_std": float(np.sqrt(np.average((lg - mean) ** 2, weights=w))), "faces_seen": int(ok.sum())}


def pixel_footprints(mesh: SurfaceMesh, frames: Sequence) -> np.ndarray:
    """Per frame, the surface length one pixel spans at the mesh's median depth in that photo (scene units
    per pixel; the object's centre, seen head-on); NaN for a frame that sees no vertex in front of it."""
    sizes = np.full(len(frames), np.nan)
    for k, fr in enumerate(frames):
        pc = mesh.vertices @ np.asarray(fr.R, np.float64).T + np.asarray(fr.t, np.float64).reshape(1, 3)
        z = pc[:, 2][pc[:, 2] > 0]
        if z.size:
            sizes[k] = float(np.median(z)) / float(fr.intrinsics.fx)
    return sizes


def pixel_footprint(mesh: SurfaceMesh, frames: Sequence) -> float:
    """The median of :func:`pixel_footprints` over the frames that see the mesh."""
    sizes = pixel_footprints(mesh, frames)
    if not np.isfinite(sizes).any():
        raise ValueError("no frame sees the mesh in front of its camera")
    return float(np.median(sizes[np.isfinite(sizes)]))


def texel_unit(mesh: SurfaceMesh) -> float:
    """The side, in scene units, of a texel of an atlas one texel wide (``texel_unit / side`` for a side):
    sqrt(surface area / UV area), the UV layout's mean scale."""
    if mesh.uvs is None:
        raise ValueError("the mesh has no UVs")
    uv = np.asarray(mesh.uvs, np.float64)
    a, b, c = uv[mesh.faces[:, 0]], uv[mesh.faces[:, 1]], uv[mesh.faces[:, 2]]
    uv_area = float(0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])).sum())
    return float(np.sqrt(float(mesh.face_areas().sum()) / max(uv_area, 1e-12)))


def texture_side_for(mesh: SurfaceMesh, frames: Sequence, texel_pixels: float, smallest: int = 32,
                     largest: int = 4096) -> tuple[int, dict]:
    """The power-of-two atlas side (within [smallest, largest]) whose texels on ``mesh``'s UV layout are
    closest, in log scale, to ``texel_pixels`` of the photos' pixels wide (:func:`pixel_footprint`).

    Returns:
        (side, info) with the pixel footprint, the texel size at that side and its width in pixels.
    """
    unit = texel_unit(mesh)  # a side S gives texels of unit / S scene units
    pixel = pixel_footprint(mesh, frames)
    want = unit / (texel_pixels * pixel)
    side = int(2 ** np.clip(np.round(np.log2(max(want, 1.0))), np.log2(smallest), np.log2(largest)))
    return side, {"pixel_footprint": pixel, "texel_size": unit / side, "texel_pixels": unit / side / pixel,
                  "texel_unit": unit}


def photo_level_for(mesh: SurfaceMesh, frames: Sequence, side: int, min_texel_pixels: float = 2.0,
                    quantile: float = 0.1, smallest_photo: int = 16) -> tuple[int, dict]:
    """The pyramid level (0: the photos as they are, L: 2^L x 2^L pixel boxes averaged) at which the fit streams
    the photos of an atlas ``side`` texels wide: the coarsest whose texels stay at least ``min_texel_pixels``
    of its pixels wide in the ``quantile`` of the photos that see them smallest. A texel's samples are taken
    at its centre (seed ch. 4), so the pixels between texel centres add decoding, upload and depth-map work but
    no sample; averaging them into the coarser level's pixels keeps their light as a box filter does.

    Returns:
        (level, info): ``texel_pixels`` (that quantile, at full resolution) and ``level_texel_pixels`` (at the
        level).
    """
    per_frame = texel_unit(mesh) / side / pixel_footprints(mesh, frames)
    seen = per_frame[np.isfinite(per_frame)]
    if not seen.size:
        return 0, {"texel_pixels": None, "level_texel_pixels": None}
    texel_px = float(np.quantile(seen, quantile))
    level = int(np.floor(np.log2(max(texel_px / min_texel_pixels, 1.0))))
    short = min(min(int(f.intrinsics.width), int(f.intrinsics.height)) for f in frames)
    while level > 0 and short >> level < smallest_photo:  # a photo too small to see the object in
        level -= 1
    return level, {"texel_pixels": texel_px, "level_texel_pixels": texel_px / 2 ** level}
