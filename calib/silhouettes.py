"""Silhouette consistency of cameras with object masks: each photo's mask against the visual hull of the others.

Registration places photos SfM left out (:mod:`.turntable`) from a model of the rig; the masks say whether a
placement is right: the visual hull carved by every other camera, projected into a photo, should cover its
mask and no more. :class:`SilhouetteSet` carves a voxel grid once per camera (which voxels each mask rejects,
so the hull of "all but one" is a count) and scores a camera by the IoU of its mask with that projection.

Pure numpy (cv2 inside functions); masks are used at a reduced resolution (``downscale``) for speed.
"""

from __future__ import annotations

import numpy as np



def nearest_point_to_axes(rotations, centres) -> np.ndarray:
    """The point nearest (least squares) to every camera's optical axis."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for r, c in zip(rotations, centres):
        d = r[2]  # the viewing direction in world axes (third row of world-to-camera R)
        m = np.eye(3) - np.outer(d, d)
        a += m
        b += m @ c
    return np.linalg.lstsq(a, b, rcond=None)[0]


class SilhouetteSet:
    """Cameras (world-to-camera R, centre, shared pinhole K) with their masks, and the voxels each rejects.

    Args:
        k: (fx, fy, cx, cy) of the full-size photos (pixel centres at +0.5).
        masks: (H, W) bool per camera, full size.
        rotations, centres: the cameras.
        resolution: voxels along the grid's side (a cube around the point the cameras look at, as wide as the
            median camera's view at that distance).
        downscale: masks are compared at 1/downscale of their size.
    """

    def __init__(self, k, masks, rotations, centres, resolution: int = 96, downscale: int = 2):
        import cv2

        self.rotations = [np.asarray(r, np.float64) for r in rotations]
        self.centres = [np.asarray(c, np.float64) for c in centres]
        self.scale = 1.0 / downscale
        fx, fy, cx, cy = (float(v) for v in k)
        self.k = np.array([fx * self.scale, fy * self.scale, cx * self.scale, cy * self.scale])
        self.masks = [cv2.resize(m.astype(np.uint8), (m.shape[1] // downscale, m.shape[0] // downscale),
                                 interpolation=cv2.INTER_AREA) > 0 for m in masks]
        h, w = masks[0].shape
        middle = nearest_point_to_axes(self.rotations, self.centres)
        dist = float(np.median([np.linalg.norm(c - middle) for c in self.centres]))
        half = dist * 0.5 * max(w / fx, h / fy)
        axis = np.linspace(-half, half, resolution)
        grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        self.points = grid + middle
        self.voxel = 2.0 * half / (resolution - 1)
        self.rejects = np.stack([self._rejected(i) for i in range(len(self.masks))])

    def _project(self, r: np.ndarray, c: np.ndarray, points: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray,
                                                                                          np.ndarray]:
        """Pixel (row, column) of each point and whether it is in front of the camera and inside the image."""
        pc = (points - c) @ r.T
        z = np.maximum(pc[:, 2], 1e-12)
        u = self.k[0] * pc[:, 0] / z + self.k[2] - 0.5
        v = self.k[1] * pc[:, 1] / z + self.k[3] - 0.5
        ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
        inside = (pc[:, 2] > 0) & (ui >= 0) & (vi >= 0) & (ui < shape[1]) & (vi < shape[0])
        return vi, ui, inside

    def _rejected(self, i: int) -> np.ndarray:
        """Voxels camera ``i``'s mask carves (inside its image, outside the object); outside the image says
        nothing (the object may be cut by the frame)."""
        m = self.masks[i]
        vi, ui, inside = self._project(self.rotations[i], self.centres[i], self.points, m.shape)
        out = np.zeros(len(self.points), bool)
        out[inside] = ~m[vi[inside], ui[inside]]
        return out

    def hull_without(self, i: int, excluded=()) -> np.ndarray:
        """Voxel centres of the visual hull of every camera but ``i`` and the ``excluded`` ones."""
        return self.points[self._carved_by(list(excluded) + [i]) == 0]

    def _carved_by(self, excluded) -> np.ndarray:
        """How many of the cameras not ``excluded`` carve each voxel."""
        keep = [j for j in range(len(self.masks)) if j not in excluded]
        return self.rejects[keep].sum(0, dtype=np.int32)

    def _ious(self, excluded) -> list[float]:
        counts = self._carved_by(excluded)
        # i's own carving taken off the count: a voxel is in the hull of the others when none of them carves it
        return [self.iou(i, hull=self.points[counts == (self.rejects[i] & (i not in excluded))])
                for i in range(len(self.masks))]

    def consistent_ious(self, bar: float) -> tuple[list[float], list[int]]:
        """Every camera's IoU against the hull of the others. One wrong camera or mask carves the hull all the
        others see (an empty mask carves it all), so while some camera is under ``bar``, the one whose leaving
        out of the hulls raises the others' mean IoU most is left out (greedy; n^2 projections a round).
        Returns (the IoUs, the cameras left out)."""
        n = len(self.masks)
        excluded: list[int] = []
        ious = self._ious(excluded)
        while len(excluded) + 4 <= n:  # a hull needs a few cameras that agree
            under = [i for i in range(n) if ious[i] < bar and i not in excluded]
            if not under:
                break
            trials = {}
            for j in range(n):
                if j not in excluded:
                    trial = self._ious(excluded + [j])
                    trials[j] = (float(np.mean([v for i, v in enumerate(trial) if i != j and i not in excluded])), trial)
            j = max(trials, key=lambda c: trials[c][0])
            excluded.append(j)
            ious = trials[j][1]
        return ious, excluded

    def iou(self, i: int, r: np.ndarray | None = None, hull: np.ndarray | None = None) -> float:
        """IoU of camera ``i``'s mask with the projection of the others' hull (camera rotation ``r`` if given)."""
        import cv2

        m = self.masks[i]
        hull = self.hull_without(i) if hull is None else hull
        vi, ui, inside = self._project(self.rotations[i] if r is None else r, self.centres[i], hull, m.shape)
        img = np.zeros(m.shape, np.uint8)
        img[vi[inside], ui[inside]] = 1
        # voxel centres land a few pixels apart: close the gaps by the voxel's footprint
        depth = float(np.median((hull - self.centres[i]) @ (self.rotations[i] if r is None else r)[2])) if len(hull) else 1.0
        px = int(np.ceil(self.k[0] * self.voxel / max(depth, 1e-12)))
        if px > 1:
            img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, np.ones((px + 1, px + 1), np.uint8))
        proj = img > 0
        union = int((proj | m).sum())
        return float((proj & m).sum()) / union if union else 0.0
