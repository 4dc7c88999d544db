"""Turntable / ring completion: photos that structure from motion left out, placed on the ring of the others.

An object photographed on a turntable (or by a gantry stepping round it) gives cameras that are one camera
turned about a fixed axis by an angle that grows by a constant step from photo to photo: with world-to-camera
rotations ``R_n`` and centres ``C_n``, ``R_n^T = Rot(a, theta n) Q0`` and ``C_n = p + Rot(a, theta n) c0``. An
untextured object (the Middlebury dino) gives SfM too few features to chain the photos all round: it registers
a few neighbouring photos, or several small models that share no match. Those models still pin the ring down:

1. :func:`fit_ring`: the axis ``a`` is the common fixed direction of the relative rotations ``R_j^T R_i``, the
   step ``theta`` the best fit of their angles to the photos' index differences (wrapped; verified against every
   pair, so an uneven ring is refused), then ``Q0`` by a chordal rotation mean and ``p``, ``c0`` by least squares.
   Rotations come first because SfM gets them right even where the narrow field of view leaves the camera
   distance and focal length loose.
2. :func:`merge_models`: a second model (its own frame and scale) is brought into the first's by the similarity
   that maps its cameras onto the ring's prediction for their indices, then the ring is refitted to all.
3. :func:`RingFit.pose`: each left-out photo's camera at its index.
4. :mod:`.silhouettes` checks every placed camera against the visual hull of the others and refines it over a
   small search of angle, height and roll; a placement whose silhouette overlap stays under the bar is dropped.

The photo index is the number in the file name when every name has a distinct one (``dinoSR0007.png`` -> 7),
else the position in the capture's order (:func:`photo_indices`).
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` radians about the unit ``axis`` (Rodrigues)."""
    a = np.asarray(axis, np.float64)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``m`` in the Frobenius norm (the chordal mean of rotations summed into ``m``)."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def signed_angle(m: np.ndarray, axis: np.ndarray) -> float:
    """The angle of rotation ``m`` about ``axis`` (radians, in (-pi, pi]); exact when ``m`` turns about ``axis``."""
    s = 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) @ axis
    return float(np.arctan2(s, 0.5 * (np.trace(m) - 1.0)))


def _wrap(x: np.ndarray) -> np.ndarray:
    return (np.asarray(x) + np.pi) % (2.0 * np.pi) - np.pi


def photo_indices(names: list[str]) -> list[int]:
    """Each photo's place on the ring: the last number in its file name when every name has a distinct one,
    else its position in ``names`` (the capture's order)."""
    nums = []
    for n in names:
        found = re.findall(r"\d+", n.rsplit(".", 1)[0])
        nums.append(int(found[-1]) if found else None)
    if None not in nums and len(set(nums)) == len(nums):
        return nums
    return list(range(len(names)))


@dataclasses.dataclass
class RingFit:
    """A turntable ring: camera ``n`` is ``R_n = (Rot(axis, step n) base_rotation)^T``,
    ``C_n = centre + Rot(axis, step n) base_offset`` (world-to-camera R, centre C)."""

    axis: np.ndarray
    step: float                 # radians per index
    centre: np.ndarray          # on the axis, in the plane of the camera centres
    base_rotation: np.ndarray   # camera-to-world rotation at index 0
    base_offset: np.ndarray     # camera centre at index 0 minus ``centre`` (perpendicular to the axis)
    indices: list[int]          # the photos it was fitted to
    rotation_rms_deg: float     # RMS angle between fitted and given camera rotations
    centre_rms: float           # RMS distance of given centres to the fitted ones, over the radius
    step_rms_deg: float         # RMS of the pairwise angles about the axis against step * index difference

    @property
    def radius(self) -> float:
        return float(np.linalg.norm(self.base_offset))

    def pose(self, index: float) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera (R, t) of the camera at ``index`` on the ring."""
        turn = rotation_about(self.axis, self.step * index)
        r = (turn @ self.base_rotation).T
        c = self.centre + turn @ self.base_offset
        return r, -r @ c

    def report(self) -> dict:
        return {"step_deg": float(np.degrees(self.step)), "radius": self.radius, "fitted_to": len(self.indices),
                "rotation_rms_deg": self.rotation_rms_deg, "centre_rms_over_radius": self.centre_rms,
                "step_rms_deg": self.step_rms_deg}


def _axis_and_step(indices: np.ndarray, qs: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Axis, step (radians per index) and the RMS step misfit (radians) from camera-to-world rotations."""
    pairs = [(i, j) for i in range(len(qs)) for j in range(i + 1, len(qs)) if indices[j] != indices[i]]
    stack = np.concatenate([qs[j] @ qs[i].T - np.eye(3) for i, j in pairs])
    axis = np.linalg.svd(stack)[2][-1]
    angles = np.array([signed_angle(qs[j] @ qs[i].T, axis) for i, j in pairs])
    dn = np.array([indices[j] - indices[i] for i, j in pairs], np.float64)
    # brute force over the step, then least squares on the unwrapped angles: index gaps of several photos
    # alias (their angles are known only modulo 2 pi), the fine grid picks the consistent branch
    grid = np.linspace(-np.pi, np.pi, 7201)
    cost = (_wrap(angles[None, :] - grid[:, None] * dn[None, :]) ** 2).sum(1)
    step = float(grid[int(np.argmin(cost))])
    for _ in range(3):
        unwrapped = step * dn + _wrap(angles - step * dn)
        step = float(unwrapped @ dn / (dn @ dn))
    misfit = float(np.sqrt(np.mean(_wrap(angles - step * dn) ** 2)))
    if step < 0:  # the axis pointed the other way: make the step positive
        axis, step = -axis, -step
    return axis, step, misfit


def fit_ring(indices, rotations, centres) -> RingFit:
    """Fit a turntable ring to registered cameras.

    Args:
        indices: each camera's place on the ring (:func:`photo_indices`), at least 3 distinct.
        rotations: world-to-camera rotations (N, 3, 3).
        centres: camera centres (N, 3).

    Returns:
        The fitted :class:`RingFit` with its residuals (judged by the caller).
    """
    idx = np.asarray(indices, np.float64)
    qs = np.transpose(np.asarray(rotations, np.float64), (0, 2, 1))
    cs = np.asarray(centres, np.float64)
    if len(set(idx.tolist())) < 3:
        raise ValueError("a ring needs at least 3 cameras at distinct indices")
    axis, step, misfit = _axis_and_step(idx, qs)
    turns = [rotation_about(axis, step * n) for n in idx]
    base_rotation = nearest_rotation(sum(t.T @ q for t, q in zip(turns, qs)))
    # C_k = p + T_k c0, with c0 perpendicular to the axis (else p and c0 trade along it): linear in (p, c0)
    rows = np.concatenate([np.hstack([np.eye(3), t]) for t in turns] + [np.hstack([np.zeros((1, 3)), axis[None]])])
    rhs = np.concatenate([cs.reshape(-1), [0.0]])
    sol = np.linalg.lstsq(rows, rhs, rcond=None)[0]
    centre, offset = sol[:3], sol[3:]
    fit = RingFit(axis, step, centre, base_rotation, offset, [int(n) for n in idx], 0.0, 0.0, float(np.degrees(misfit)))
    rot_err, c_err = [], []
    for n, q, c in zip(idx, qs, cs):
        r, t = fit.pose(n)
        rot_err.append(rotation_angle_deg(r, q.T))
        c_err.append(np.linalg.norm(-r.T @ t - c))
    fit.rotation_rms_deg = float(np.sqrt(np.mean(np.square(rot_err))))
    fit.centre_rms = float(np.sqrt(np.mean(np.square(c_err))) / max(fit.radius, 1e-12))
    return fit


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees of the rotation between two rotation matrices."""
    return float(np.degrees(np.arccos(np.clip(0.5 * (np.trace(a @ b.T) - 1.0), -1.0, 1.0))))


def similarity_onto(src_r, src_c, dst_r, dst_c) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, Rw, tw) taking cameras (world-to-camera rotations, centres) of one frame onto the same
    cameras in another: x -> s Rw x + tw. The rotation from the camera rotations (a chordal mean, well posed
    from one camera on), scale and translation from the centres (least squares, needs two)."""
    rw = nearest_rotation(sum(rd.T @ rs for rs, rd in zip(src_r, dst_r)))
    a = np.asarray(src_c, np.float64) @ rw.T
    b = np.asarray(dst_c, np.float64)
    am, bm = a - a.mean(0), b - b.mean(0)
    s = float((am * bm).sum() / max((am * am).sum(), 1e-300))
    return s, rw, b.mean(0) - s * a.mean(0)


def transform_cameras(sim, rotations, centres) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Cameras (world-to-camera rotations, centres) carried by the similarity ``x -> s Rw x + tw``."""
    s, rw, tw = sim
    return [r @ rw.T for r in rotations], [s * rw @ c + tw for c in centres]


def merge_models(models: list[dict[int, tuple[np.ndarray, np.ndarray]]], rounds: int = 3
                 ) -> tuple[RingFit, dict[int, tuple[np.ndarray, np.ndarray]], list[dict]]:
    """Fit one ring to several models of the same turntable, each in its own frame.

    Args:
        models: per model, index -> (world-to-camera R, centre); the first (largest) sets the frame and
            must hold at least 3 cameras; others with at least 2 are brought in.
        rounds: fit-align rounds (the first alignment extrapolates the first model's ring; each refit on
            the union tightens it).

    Returns:
        (ring fitted to every camera, index -> (R, centre) in the first model's frame, one report per model).
    """
    base = models[0]
    merged = dict(base)
    ring = fit_ring(list(base), [v[0] for v in base.values()], [v[1] for v in base.values()])
    reports = [{"cameras": len(base), "role": "frame"}]
    others = [m for m in models[1:] if len(m) >= 2 and not set(m) & set(base)]
    sims = {}
    for _ in range(rounds if others else 0):
        for k, m in enumerate(others):
            pred = [ring.pose(n) for n in m]
            dst_r = [p[0] for p in pred]
            dst_c = [-p[0].T @ p[1] for p in pred]
            sims[k] = similarity_onto([v[0] for v in m.values()], [v[1] for v in m.values()], dst_r, dst_c)
            rs, cs = transform_cameras(sims[k], [v[0] for v in m.values()], [v[1] for v in m.values()])
            merged.update({n: (r, c) for n, r, c in zip(m, rs, cs)})
        ring = fit_ring(list(merged), [v[0] for v in merged.values()], [v[1] for v in merged.values()])
    for k, m in enumerate(others):
        reports.append({"cameras": len(m), "role": "merged", "scale": float(sims[k][0])})
    return ring, merged, reports
