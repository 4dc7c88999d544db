"""The colour chart kept out of the object's mesh (issue 39).

A ColorChecker photographed beside the object is textured and flat: structure from motion and dense stereo find
it as readily as the object, and a mesh made from their points fuses it in (on a real bronze the chart became part
of the torso). Every photo in which :mod:`.colour_chart` found the chart gets a mask with the chart's quad cleared,
grown about its centre by :data:`CHART_MARGIN` (the detector's box sits inside the chart's black frame, and a
stand or easel under the chart is close to it): the mesh stage's dense stereo keeps only masked pixels, its SfM
points are judged by the masks, and the fit reads no chart pixel. A photo with an object mask keeps it, minus the
parts of it that lie mostly on the chart (:func:`chart_pixels`: the object in front of the chart keeps its
silhouette whole); a photo without one gets a mask of everything but the chart, and when no photo had an object mask the
capture says so (``mask_kind`` ``valid_pixels``: such masks are not silhouettes a visual hull may be carved from).
OpenCV is imported inside the functions that need it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texstream.capture.imageio import read_mask, write_image

from .colour_chart import ChartSighting

CHART_MARGIN = 0.15
"""how far the cleared quad reaches beyond the detected chart, as a fraction of the chart's size about its centre:
the Classic's black frame (~5% of its width beyond the patches' box) and a margin for a stand's clamp"""


def chart_quad_mask(corners: np.ndarray, shape: tuple[int, int], margin: float = CHART_MARGIN) -> np.ndarray:
    """(H, W) bool, True on the chart: the quad of ``corners`` (4, 2 pixels, OpenCV's integer pixel centres) grown
    about its centre by ``margin``."""
    import cv2

    c = np.asarray(corners, np.float64)
    grown = c.mean(axis=0) + (c - c.mean(axis=0)) * (1.0 + margin)
    out = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(out, np.round(grown * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def chart_pixels(mask: np.ndarray, chart: np.ndarray) -> np.ndarray:
    """The mask's pixels to clear for the chart's (grown) quad ``chart``: each connected part of the mask lying
    mostly (over half its area) on the quad is the chart, or the chart with a little of what surrounds it, and is
    cleared whole; a part mostly off it is the object, which may stand in front of the chart (the chart's quad
    behind the object's outline): it is kept whole, so a silhouette is never cut into."""
    import cv2

    if mask.all():  # a mask of every pixel (no object mask): the quad itself
        return chart.copy()
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    area = np.bincount(labels.ravel(), minlength=n)
    on_chart = np.bincount(labels[chart], minlength=n)
    return (on_chart * 2 > area)[labels] & mask


def mask_out_charts(root: Path, frames: list, sightings: dict) -> dict:
    """Clear the chart from the masks of the ``frames`` (capture Frames of the capture folder ``root``, being
    written) named in ``sightings`` ({frame name: ChartSighting}); frames without a mask get one (their
    ``mask_path`` set, and then so do the frames without the chart: masks of every pixel). Returns the summary
    {"photos": masked, "pixels": cleared, "made": masks made, "why"}."""
    masked = made = pixels = 0
    for f in frames:
        s = sightings.get(f.name)
        if s is None:
            continue
        h, w = int(f.intrinsics.height), int(f.intrinsics.width)
        chart = chart_quad_mask(s.corners, (h, w))
        if f.mask_path is not None:
            mask = read_mask(root / f.mask_path)
            if mask.shape != (h, w):
                continue  # a mask of another size (rotated photo): its chart corners are not this frame's
        else:
            mask = np.ones((h, w), bool)
            f.mask_path = str(Path("masks") / f"{f.name}.png")
            made += 1
        clear = chart_pixels(mask, chart)
        pixels += int(clear.sum())
        write_image(root / f.mask_path, np.where(mask & ~clear, np.uint8(255), np.uint8(0)), bits=8)
        masked += 1
    if made:  # the photos without the chart or a mask get one of every pixel: all alike (COLMAP wants all or none)
        for f in frames:
            if f.mask_path is None:
                f.mask_path = str(Path("masks") / f"{f.name}.png")
                write_image(root / f.mask_path, np.full((int(f.intrinsics.height), int(f.intrinsics.width)),
                                                        np.uint8(255)), bits=8)
                made += 1
    return {"photos": masked, "pixels": pixels, "made": made,
            "why": (f"the colour chart found in {masked} photo(s): its quad (grown {CHART_MARGIN:.0%}) cleared from "
                    "their masks, so neither the mesh nor the fit reads it") if masked else "no chart found"}


def charts_by_frame(per_photo: list[dict], upright: set[str]) -> dict:
    """{frame name (the photo's stem): ChartSighting} of the photos of :func:`.colour_chart.response_from_photos`'s
    report that show the chart, among ``upright`` (the photo names stored upright: a photo that ingest rotates
    has its chart's corners in the stored orientation, not the frame's)."""
    return {Path(r["photo"]).stem: ChartSighting.from_json(r["sighting"]) for r in per_photo
            if r.get("found") and r.get("sighting") and Path(r["photo"]).name in upright}
