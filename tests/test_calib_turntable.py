"""The turntable ring (calib/turntable.py), its silhouette check (calib/silhouettes.py) and the placement of
photos registration left out (calib/ring_placement.py), on synthetic rings with known cameras."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from texstream.calib.ring_placement import RingConfig, focal_by_ring, place_on_ring
from texstream.calib.silhouettes import SilhouetteSet, nearest_point_to_axes
from texstream.calib.turntable import (fit_ring, merge_models, nearest_rotation, photo_indices, rotation_about,
                                       rotation_angle_deg, similarity_onto, transform_cameras)
from texstream.capture.capture_json import Intrinsics
from texstream.capture.imageio import write_image

STEP = np.radians(23.478)  # the Middlebury dino's step: 16 photos that do not close the circle evenly
N = 16


def _look_at(c: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera rotation (OpenCV axes) of a camera at ``c`` looking at ``target``."""
    z = (target - c) / np.linalg.norm(target - c)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _ring(seed: int = 0, rot_noise_deg: float = 0.0, centre_noise: float = 0.0):
    """16 cameras stepping by STEP round a tilted axis, 30 deg below its plane, looking at the object, then
    carried into an arbitrary frame (rotation, scale 3.7, offset), with optional noise; index -> (R, C)."""
    rng = np.random.default_rng(seed)
    axis = np.array([0.0, 0.0, 1.0])
    base_c = np.array([2.0, 0.0, -1.15])  # radius 2, 30 deg below
    target = np.array([0.0, 0.05, 0.1])   # the object sits slightly off the axis: the aim is not the axis
    base_r = _look_at(base_c, target, axis)
    frame = nearest_rotation(rng.normal(size=(3, 3)))
    cams = {}
    for n in range(1, N + 1):
        turn = rotation_about(axis, STEP * n)
        r = base_r @ turn.T
        c = turn @ base_c
        r = rotation_about(rng.normal(size=3) / np.sqrt(3), np.radians(rot_noise_deg) * rng.normal()) @ r
        c = c + centre_noise * 2.0 * rng.normal(size=3)
        cams[n] = transform_cameras((3.7, frame, np.array([0.3, -1.0, 2.0])), [r], [c])
        cams[n] = (cams[n][0][0], cams[n][1][0])
    return cams


def _errors(ring, cams, indices):
    """Largest rotation error (deg) and centre error over the radius of the ring's cameras at ``indices``."""
    rot, cen = [], []
    for n in indices:
        r, t = ring.pose(n)
        rot.append(rotation_angle_deg(r, cams[n][0]))
        cen.append(np.linalg.norm(-r.T @ t - cams[n][1]) / ring.radius)
    return max(rot), max(cen)


def test_ring_fit_recovers_removed_cameras():
    """Six neighbouring cameras (a third of the ring) predict the other ten. Exact data: exact up to
    rounding. With SfM-like noise (0.2 deg rotations, 0.5% of the radius on centres) the step comes within
    0.2 deg and the cameras 8 steps away (extrapolated: an axis error grows with the lever) within 1 deg and 4%."""
    cams = _ring()
    known = [7, 8, 9, 10, 11, 12]
    ring = fit_ring(known, [cams[n][0] for n in known], [cams[n][1] for n in known])
    assert abs(ring.step - STEP) < 1e-9
    assert ring.radius == pytest.approx(2.0 * 3.7, rel=1e-9)
    rot, cen = _errors(ring, cams, range(1, N + 1))
    assert rot < 1e-4 and cen < 1e-9  # angles from arccos of a trace: resolved to about 1e-6 deg
    noisy = _ring(seed=1, rot_noise_deg=0.2, centre_noise=0.005)
    ring = fit_ring(known, [noisy[n][0] for n in known], [noisy[n][1] for n in known])
    assert abs(np.degrees(ring.step - STEP)) < 0.2
    assert ring.rotation_rms_deg < 0.5 and ring.step_rms_deg < 0.5
    truth = _ring()
    sim = similarity_onto([ring.pose(n)[0] for n in known], [-ring.pose(n)[0].T @ ring.pose(n)[1] for n in known],
                          [truth[n][0] for n in known], [truth[n][1] for n in known])
    for n in range(1, N + 1):
        r, t = ring.pose(n)
        (r2,), (c2,) = transform_cameras(sim, [r], [-r.T @ t])
        assert rotation_angle_deg(r2, truth[n][0]) < 1.0
        assert np.linalg.norm(c2 - truth[n][1]) / (2.0 * 3.7) < 0.04


def test_gaps_in_the_indices_and_an_uneven_ring():
    """Cameras two and three steps apart (angles known only modulo 2 pi per pair) still give the step;
    cameras at random angles do not fit an even step, and the misfit says so (tens of degrees)."""
    cams = _ring()
    known = [1, 3, 6, 8]
    ring = fit_ring(known, [cams[n][0] for n in known], [cams[n][1] for n in known])
    assert abs(ring.step - STEP) < 1e-9
    rng = np.random.default_rng(3)
    uneven = {n: cams[n] for n in (1, 2, 3, 4, 5)}
    angles = rng.uniform(0, 2 * np.pi, 5)
    uneven = {n: (cams[1][0] @ rotation_about(np.array([0.0, 0, 1]), a).T, cams[1][1]) for n, a in zip(uneven, angles)}
    ring = fit_ring(list(uneven), [v[0] for v in uneven.values()], [v[1] for v in uneven.values()])
    assert ring.step_rms_deg > RingConfig().max_ring_misfit_deg * 5
    with pytest.raises(ValueError, match="at least 3"):
        fit_ring([1, 1, 2], [cams[1][0]] * 3, [cams[1][1]] * 3)


def test_two_models_in_their_own_frames_merge_into_one_ring():
    """Two SfM models on opposite sides of the ring (indices 7-12 and 15, 16, 1-4), the second in its own
    frame and scale: merged, every camera of both lands on the first's frame (exact data: to rounding)."""
    cams = _ring()
    a = {n: cams[n] for n in (7, 8, 9, 10, 11, 12)}
    moved = transform_cameras((0.4, rotation_about(np.array([0.6, 0.0, 0.8]), 1.0), np.array([5.0, 1.0, 0.0])),
                              [cams[n][0] for n in (15, 16, 1, 2, 3, 4)], [cams[n][1] for n in (15, 16, 1, 2, 3, 4)])
    b = {n: (r, c) for n, r, c in zip((15, 16, 1, 2, 3, 4), *moved)}
    ring, merged, reports = merge_models([a, b])
    assert len(merged) == 12 and reports[1]["scale"] == pytest.approx(1 / 0.4, rel=1e-6)
    for n in merged:
        assert rotation_angle_deg(merged[n][0], cams[n][0]) < 1e-4
        assert np.linalg.norm(merged[n][1] - cams[n][1]) < 1e-6
    assert _errors(ring, cams, range(1, N + 1))[0] < 1e-4


def test_photo_indices():
    assert photo_indices(["dinoSR0003.png", "dinoSR0010.png", "dinoSR0001.png"]) == [3, 10, 1]
    assert photo_indices(["a1.jpg", "b1.jpg", "c.jpg"]) == [0, 1, 2]  # repeated / missing numbers: capture order


def _sphere_masks(cams, k, size, centre, radius):
    """Masks of a sphere (analytic: a pixel is object where its ray meets the sphere)."""
    w, h = size
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - k[2]) / k[0], (v - k[3]) / k[1], np.ones_like(u)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    out = []
    for r, c in cams:
        oc = r @ (centre - c)  # the sphere's centre in camera axes
        along = rays @ oc
        out.append(along ** 2 - (oc @ oc - radius ** 2) >= 0)
    return out


def test_silhouettes_check_placements():
    """A sphere seen by the ring's cameras: the true cameras' masks agree with the hull of the others (IoU
    above 0.75: the hull of views from one elevation is larger than the sphere, and its voxels, 2.5 px wide
    in these 160x120 images, blur a 60 px wide silhouette's edge), a camera aimed 5 deg off does not (IoU
    under 0.5: its silhouette is shifted by 40% of the sphere's width)."""
    cams = _ring()
    k, size = (300.0, 300.0, 80.0, 60.0), (160, 120)
    centre = nearest_point_to_axes([v[0] for v in cams.values()], [v[1] for v in cams.values()])  # the aim
    # a sphere filling about half the image height at the cameras' distance
    dist = np.linalg.norm(cams[1][1] - centre)
    masks = _sphere_masks([cams[n] for n in sorted(cams)], k, size, centre, 0.25 * dist * size[1] / k[1])
    sil = SilhouetteSet(k, masks, [cams[n][0] for n in sorted(cams)], [cams[n][1] for n in sorted(cams)],
                        resolution=64, downscale=1)
    assert min(sil.iou(i) for i in range(N)) > 0.75  # measured 0.81-0.94
    off = rotation_about(np.array([0.0, 1.0, 0.0]), np.radians(5.0)) @ sil.rotations[3]
    assert sil.iou(3, off) < 0.5  # measured 0.28


def _fake_model(cams: dict) -> SimpleNamespace:
    """A stand-in for a pycolmap reconstruction holding the cameras index -> (R, C) as photos pNN.jpg."""
    def image(n):
        r, c = cams[n]
        pose = SimpleNamespace(rotation=SimpleNamespace(matrix=lambda: r))
        return SimpleNamespace(name=f"p{n:02d}.jpg", has_pose=True, cam_from_world=lambda: pose,
                               projection_center=lambda: c)

    return SimpleNamespace(images={n: image(n) for n in cams}, num_reg_images=lambda: len(cams))


def test_focal_by_ring_keeps_the_focal_length_whose_cameras_fit_a_ring():
    """Mapping at a focal length f gives cameras off the ring by 2 deg per doubling of f away from the true
    600 px (random turns), and one more model of 4 photos from 300 px on (the dino's behaviour): the search
    keeps the grid's focal length nearest the truth on a log scale (the grid's second round steps by 10%)."""
    cams = _ring()
    rng = np.random.default_rng(5)
    names = [f"p{n:02d}.jpg" for n in range(1, N + 1)]

    def models(f: float) -> dict:
        err = 2.0 * abs(np.log2(f / 600.0))
        bent = {n: (rotation_about(rng.normal(size=3) / np.sqrt(3), np.radians(err * rng.normal())) @ r, c)
                for n, (r, c) in cams.items()}
        out = {0: _fake_model({n: bent[n] for n in range(7, 13)})}
        if f >= 300:
            out[1] = _fake_model({n: bent[n] for n in (1, 2, 3, 4)})
        return out

    report: dict = {}
    recs, focal = focal_by_ring(models(160.0), models, names, 160, RingConfig(), report)
    assert focal == pytest.approx(600.0, rel=0.15) and len(recs) == 2
    assert "fit a ring" in report["ring_focal"]["decision"]
    report = {}
    recs, focal = focal_by_ring({0: _fake_model({n: cams[n] for n in range(1, 14)})}, models, names, 160,
                                RingConfig(), report)
    assert focal is None and "13 of 16" in report["ring_focal"]["decision"]  # 3/4 registered: no search


def test_place_on_ring_places_and_drops(tmp_path: Path):
    """The registration hook on fake SfM models: 6 registered photos of a sphere ring, 10 left out; every left-out
    photo gets its ring camera, except one whose mask is empty (dropped, with its IoU in the reason)."""
    cams = _ring()
    k, size = (300.0, 300.0, 80.0, 60.0), (160, 120)
    centre = nearest_point_to_axes([v[0] for v in cams.values()], [v[1] for v in cams.values()])
    dist = np.linalg.norm(cams[1][1] - centre)
    masks = _sphere_masks([cams[n] for n in range(1, N + 1)], k, size, centre, 0.25 * dist * size[1] / k[1])
    masks[4] = np.zeros_like(masks[4])  # photo 5: a mask that does not match its camera
    photos = []
    for n, m in zip(range(1, N + 1), masks):
        write_image(tmp_path / f"p{n:02d}.png", m.astype(np.uint8) * 255, bits=8)
        photos.append(SimpleNamespace(name=f"p{n:02d}.jpg", mask=tmp_path / f"p{n:02d}.png", width=160, height=120))
    intr = Intrinsics(fx=k[0], fy=k[1], cx=k[2], cy=k[3], width=160, height=120)
    rec = _fake_model({n: cams[n] for n in range(7, 13)})
    posed = {f"p{n:02d}.jpg": (cams[n][0], -cams[n][0] @ cams[n][1], intr) for n in range(7, 13)}
    report: dict = {}
    out = place_on_ring([rec], photos, posed, lambda p: intr, RingConfig(silhouette_resolution=48), report)
    assert sorted(out) == sorted(p.name for p in photos if p.name != "p05.jpg")
    assert report["ring"]["placed"] == 9 and report["ring"]["dropped"] == ["p05.jpg"]
    assert "under 0.7" in report["ring"]["photos"]["p05.jpg"]["dropped"]
    for p in photos:
        if p.name in out:
            n = int(p.name[1:3])
            assert rotation_angle_deg(out[p.name][0], cams[n][0]) < 1e-4
            assert report["ring"]["photos"][p.name]["iou"] > RingConfig().min_iou
