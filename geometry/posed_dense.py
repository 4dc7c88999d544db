"""Dense stereo of a capture that has cameras and nothing else: the depth range and the matched region from
the points triangulated with those cameras.

Dense stereo (:mod:`.mvs`) sweeps each photo over a depth range and matches inside a region. With masks
both come from the silhouettes (the visual hull's box, the mask). A capture that gives only cameras
(a Metashape or RealityCapture export, a calibrated rig without masks) has neither, but the sparse
points triangulated with its fixed poses (:mod:`.triangulate`) say where the surface is:

- **depth range per photo** (:func:`depth_ranges_from_points`): the ``percentile`` and
  ``100 - percentile`` percentiles of the depths of the points in front of the camera and inside its
  photo, widened by ``margin`` times their span on each side (a facade's photo sees the wall and the
  ground in front of it at depths a box round all points would stretch several times; robust
  percentiles keep a stray false match from stretching the sweep, the margin covers surface the
  sparse points missed). Photos that see fewer than ``min_points`` points get the depth range of
  the points' robust box instead.
  A *scene* (:func:`texstream.geometry.scene.classify_capture`: a facade from the street) widens
  the range further, to ``near / scene_factor`` .. ``far * scene_factor``: sparse SIFT points miss
  what the photos see at grazing angles (on the synthetic facade not one of 9,689 points lay on the
  ground before it, the lower quarter of every photo), and the sweep in inverse depth pays for the
  wider range only with coarser planes (on the facade still under a pixel of parallax per plane
  between neighbouring photos, which the parabola refines).
- **matched region per photo** (:func:`coverage_masks`): for an object the convex hull of the points'
  projections, grown by ``grow`` times its size. Outside it no point was triangulated and the sweep
  would only add background (a dark room) to the depth maps and time to the run. The region is not a
  silhouette (a convex hull holds the background between an object's arms), so it never carves a
  visual hull. A scene is matched over every pixel (the ground again).

numpy at module level; cv2 inside functions.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from texstream.core.config import option
from .scene import robust_box


@dataclasses.dataclass
class PosedDenseConfig:
    """Depth range and matched region of dense stereo from triangulated points (module doc)."""

    percentile: float = option(1.0, help="depth range: this percentile to 100 minus it of the depths of the "
                                         "points a photo sees", min=0.0, max=25.0)
    margin: float = option(0.15, help="depth range: widened by this fraction of its span on each side",
                           min=0.0, max=2.0)
    min_points: int = option(20, help="a photo seeing fewer points gets the depth range of the points' robust box",
                             min=3)
    scene_factor: float = option(2.0, help="scenes: the depth range reaches from the near end over this to the "
                                           "far end times this", min=1.0)
    features: int = option(4096, help="SIFT features per photo when the triangulated points give dense stereo its "
                                      "depth ranges (exhaustive matching of 11 photos of 640x480 took 98 s with "
                                      "8,192 on the 2-core dev box)", min=256)
    grow: float = option(0.1, help="matched region: the convex hull of the points' projections, grown by this "
                                   "fraction of its larger side (0: the hull; negative: every pixel)", min=-1.0)


def _project(frame, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, z) of world points in a frame (continuous pixel coordinates, OpenCV axes)."""
    pc = points @ np.asarray(frame.R, np.float64).T + np.asarray(frame.t, np.float64).reshape(1, 3)
    z = pc[:, 2]
    zs = np.where(z > 0, z, 1.0)
    i = frame.intrinsics
    return i.fx * pc[:, 0] / zs + i.cx, i.fy * pc[:, 1] / zs + i.cy, z


def _in_view(frame, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u, v, z = _project(frame, points)
    i = frame.intrinsics
    ok = (z > 0) & (u >= 0) & (v >= 0) & (u < i.width) & (v < i.height)
    return u[ok], v[ok], z[ok]


def depth_ranges_from_points(frames: Sequence, points: np.ndarray, config: PosedDenseConfig | None = None,
                             scene: bool = False) -> tuple[list[tuple[float, float] | None], list[dict]]:
    """Per photo the (near, far) depth range of dense stereo from the points it sees (module doc).

    Returns:
        (ranges, per-photo report): a range is None where the camera sees nothing of the points' box.
    """
    cfg = config or PosedDenseConfig()
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    lo, hi = robust_box(pts, 2.0, 0.05)
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    ranges, report = [], []
    for f in frames:
        _, _, z = _in_view(f, pts)
        if len(z) >= cfg.min_points:
            near, far = np.percentile(z, [cfg.percentile, 100.0 - cfg.percentile])
            source = f"{len(z)} points in view"
        else:
            _, _, zc = _project(f, corners)
            near, far = float(zc.min()), float(zc.max())
            source = f"only {len(z)} points in view: the points' robust box"
        if far <= 0:
            ranges.append(None)
            report.append({"photo": f.name, "source": source, "skipped": "the points are behind the camera"})
            continue
        pad = cfg.margin * (far - near)
        near, far = max(near - pad, 0.05 * far), far + pad  # a camera among the points sees from just in front
        if scene:
            near, far = near / cfg.scene_factor, far * cfg.scene_factor
        ranges.append((float(near), float(far)))
        report.append({"photo": f.name, "source": source, "depth_range": [round(float(near), 6), round(float(far), 6)]})
    return ranges, report


def coverage_masks(frames: Sequence, points: np.ndarray, grow: float = 0.1, min_points: int = 20
                   ) -> list[np.ndarray]:
    """Per photo the region the points cover: the convex hull of their projections grown by ``grow`` times its
    larger side (every pixel where fewer than ``min_points`` points are in view, or ``grow`` < 0)."""
    import cv2

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out = []
    for f in frames:
        h, w = f.intrinsics.height, f.intrinsics.width
        u, v, _ = _in_view(f, pts)
        if grow < 0 or len(u) < min_points:
            out.append(np.ones((h, w), bool))
            continue
        m = np.zeros((h, w), np.uint8)
        hull = cv2.convexHull(np.stack([u, v], 1).astype(np.float32))
        cv2.fillConvexPoly(m, np.round(hull).astype(np.int32), 1)
        r = int(round(grow * max(np.ptp(u), np.ptp(v))))
        if r > 0:
            m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        out.append(m.astype(bool))
    return out
