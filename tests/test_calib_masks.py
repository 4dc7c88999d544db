"""Automatic object masks (calib/masks.py): a synthetic turntable object on a dark background against the
renderer's own masks, the ``auto`` decision, masks on an existing capture folder, and the Middlebury
temple and dino (real photos on black) against a threshold reference and their ground-truth boxes."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from texstream.calib.masks import MaskConfig, compute_mask, make_masks, mask_iou, masks_for_images
from texstream.capture.capture_json import read_capture

from conftest import need_data


@pytest.fixture(scope="module")
def turntable(tmp_path_factory):
    """6 sRGB 8-bit photos (160 px) of the specular, banded ornament on a turntable ring, lit from the camera,
    composited onto a dark, slightly graded, noisy background; and the renderer's true masks."""
    from texstream.capture.imageio import write_image
    from texstream.capture.synthetic.synth import SynthConfig, load_scene, render_scene

    sc = load_scene("ornament")
    sc["cameras"] = {"layout": "ring", "count": 6, "rings": [15.0], "distance": 5.0, "fov_deg": 30.0,
                     "width": 160, "height": 160, "target": [0.0, 0.0, 0.15]}
    sc["light"] = {"type": "point", "mode": "camera", "offset": [0.0, 0.0, 0.0], "intensity": 30.0}
    sc["texture"] = {"width": 220, "height": 110, "padding": 2}
    res = render_scene(sc, SynthConfig(progress=False, bits=32, shadows=False))
    rng = np.random.default_rng(0)
    src = tmp_path_factory.mktemp("turntable") / "photos"
    for i, (img, m) in enumerate(zip(res.images, res.masks)):
        h, w = m.shape
        ramp = (1 + 0.5 * np.arange(w) / w)[None, :, None]
        bg = 0.003 * ramp * np.array([1.0, 0.9, 1.1]) + rng.normal(0, 0.001, (h, w, 3))
        write_image(src / f"view{i:02d}.png", np.where(m[..., None], img, bg).astype(np.float32), bits=8)
    return src, res.masks


def test_auto_masks_match_the_renderers_masks(turntable, tmp_path):
    from texstream.calib.ingest import IngestConfig, ingest
    from texstream.capture.imageio import read_image, read_mask

    src, truth = turntable
    res = ingest(src, tmp_path / "cap", IngestConfig(auto_masks="auto"))
    am = res.summary["auto_masks"]
    assert am["mode"] == "grabcut" and am["masks"] == 6 and "uniform background" in am["decision"]
    cap = read_capture(tmp_path / "cap")
    ious = [mask_iou(read_mask(cap.mask_path(f)), t) for f, t in zip(cap.frames, truth)]
    # Done-when: IoU >= 0.98 per photo. Measured 0.990-0.991: what is left is the one-pixel rim where the
    # surface turns away from the camera light (as dark as the background, sRGB ~0.05).
    assert min(ious) >= 0.98, ious
    # previews/masks.png: the 6 photos as 160 px tiles (3 x 2, 2 px gaps), each with its mask's outline
    # drawn in pure green (codes 0, 255, 0): 372 pixels in each tile measured, the object's silhouette at
    # 160 px; a missing or empty mask draws none
    sheet = read_image(tmp_path / "cap" / "previews" / "masks.png", linear=False)
    assert sheet.shape == (2 * 162 + 2, 3 * 162 + 2, 3)
    green = np.all(sheet == (0.0, 1.0, 0.0), axis=2)
    for k in range(6):
        r, c = divmod(k, 3)
        assert green[2 + r * 162:2 + r * 162 + 160, 2 + c * 162:2 + c * 162 + 160].sum() > 200, k
    rep = json.loads((tmp_path / "cap" / "ingest_report.json").read_text())
    assert set(rep["auto_masks"]["photos"]) == {f"view{i:02d}" for i in range(6)}


def test_border_mode_and_masks_on_an_existing_capture(turntable, tmp_path):
    from texstream.calib.ingest import IngestConfig, ingest
    from texstream.capture.imageio import read_mask

    src, truth = turntable
    ingest(src, tmp_path / "cap", IngestConfig(auto_masks="none"))
    assert all(f.mask_path is None for f in read_capture(tmp_path / "cap").frames)
    res = make_masks(tmp_path / "cap", MaskConfig(mode="border"))
    assert res.summary["written"] == 6 and res.summary["mode"] == "border"
    cap = read_capture(tmp_path / "cap")
    ious = [mask_iou(read_mask(cap.mask_path(f)), t) for f, t in zip(cap.frames, truth)]
    assert min(ious) >= 0.97, ious  # a threshold alone: measured 0.987
    assert cap.extra["auto_masks"]["mode"] == "border"
    # Masks already there are kept unless asked.
    assert make_masks(tmp_path / "cap").summary["kept"] == 6


def test_auto_declines_textured_backgrounds(tmp_path):
    rng = np.random.default_rng(1)
    imgs = []
    for _ in range(3):
        noise = cv2.GaussianBlur(rng.uniform(0, 1, (96, 128, 3)).astype(np.float32), (0, 0), 3)
        imgs.append(np.clip((noise - noise.min()) / np.ptp(noise), 0, 1))
    masks, s = masks_for_images(imgs, MaskConfig(mode="auto"))
    assert masks == [None] * 3 and s["mode"] == "none"
    assert "not uniform" in s["decision"]
    # A uniform grey background with nothing on it: no object, no masks.
    masks, s = masks_for_images([np.full((64, 64, 3), 0.4, np.float32)] * 2, MaskConfig(mode="auto"))
    assert masks == [None, None] and "no distinct object" in s["decision"]


def test_sfm_seeds_decide_dark_holes():
    """A background-coloured hole inside the object stays open (a real gap, as between the temple's columns)
    unless SfM points of the object lie in it (a dark shadow on the object)."""
    rng = np.random.default_rng(2)
    img = np.repeat(rng.uniform(0.0, 0.08, (120, 160, 1)), 3, axis=2).astype(np.float32)  # sRGB codes: noisy black
    img[30:90, 20:110] = 0.6
    img[45:75, 40:90] = np.repeat(rng.uniform(0.0, 0.08, (30, 50, 1)), 3, axis=2)  # hole, as dark as the background
    hole, obj = np.zeros((120, 160), bool), np.zeros((120, 160), bool)
    hole[45:75, 40:90] = obj[30:90, 20:110] = True
    obj &= ~hole
    m0, _ = compute_mask(img, MaskConfig(mode="grabcut"), eight_bit_codes=True)
    pts = np.array([[x + 0.5, y + 0.5] for x in range(45, 86, 10) for y in range(50, 71, 10)])
    m1, info = compute_mask(img, MaskConfig(mode="grabcut"), points=pts, eight_bit_codes=True)
    assert info["seed_points"] == len(pts)
    assert mask_iou(m0, obj) > 0.97  # the hole stays open without seeds
    assert m1[30:90, 20:110].all()


# ------------------------------------------------------------------------------------ real photos

_BOXES = {"temple": [(-0.073568, 0.021728, -0.012445), (0.028855, 0.181892, 0.062736)],
          "dino": [(-0.061897, -0.018874, -0.057845), (0.010897, 0.068227, 0.015495)]}


def _middlebury(folder, name, every=4):
    """Photos (sRGB codes in [0, 1]) and the projected ground-truth bounding boxes (convex hull of the 8
    corners, grown by 3 px), every ``every``-th view."""
    lines = (folder / f"{name}SR_par.txt").read_text().split("\n")[1:]
    lo, hi = map(np.array, _BOXES[name])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    imgs, boxes = [], []
    for line in [ln.split() for ln in lines if ln.strip()][::every]:
        k, r, t = (np.array(line[1:10], float).reshape(3, 3), np.array(line[10:19], float).reshape(3, 3),
                   np.array(line[19:22], float))
        im = cv2.imread(str(folder / line[0]))[:, :, ::-1].astype(np.float32) / 255
        p = (corners @ r.T + t) @ k.T
        hull = np.zeros(im.shape[:2], np.uint8)
        cv2.fillConvexPoly(hull, cv2.convexHull(np.round(p[:, :2] / p[:, 2:]).astype(np.int32)), 1)
        imgs.append(im)
        boxes.append(cv2.dilate(hull, np.ones((7, 7), np.uint8)) > 0)
    return imgs, boxes


@pytest.mark.parametrize("name", ["temple", "dino"])
def test_middlebury_masks_cover_the_object(data_dir, name):
    folder = need_data(data_dir, f"middlebury_{name}_sparse")
    imgs, boxes = _middlebury(folder, name)
    masks, s = masks_for_images(imgs, MaskConfig(mode="auto"), eight_bit_codes=[True] * len(imgs))
    assert s["mode"] == "grabcut" and s["masks"] == len(imgs), s["decision"]
    for m, box, im in zip(masks, boxes, imgs):
        # Reference: Middlebury's own silhouette threshold (0.19), inside the projected box (the lit cloth
        # at the side reaches 0.19 too).
        ref = (im.max(2) > 0.19) & box
        outside = (m & ~box).sum() / m.sum()
        covered = (m & ref).sum() / ref.sum()
        # Measured over all 16 views: temple IoU 0.93-0.98 (the masks also hold the dark column shadows the
        # threshold misses), <= 2.6% outside the box; dino IoU 0.95-0.98 against the threshold, nothing
        # outside. The gaps between the temple's columns stay open (background-coloured holes).
        assert outside < 0.04, outside
        assert covered > 0.96, covered
        assert mask_iou(m, ref) > 0.9


# ------------------------------------------------------------------------------ masks that fail safe


@pytest.fixture(scope="module")
def dim_room():
    """8 photos (160 px) of a dark glossy ornament (albedo 0.01, strong specular lobe) with a flash on the
    camera, in a dim textured room with a lit wall panel and a window (capture/synthetic/dim_room.py)."""
    from texstream.capture.synthetic.dim_room import dim_room_photos

    return dim_room_photos(8, 160)


def test_dark_glossy_object_in_a_dim_room_gets_no_inverted_masks(dim_room, tmp_path, capsys):
    """The issue's bronze: the room's dark walls pass the border test, and what is distinct from them is the
    window, the lit wall and the flash highlights. The masks must be the object's (IoU >= 0.95 with the
    renderer's) or none, with the reason said; never masks that keep the background and drop the object."""
    from texstream.core.progress import reporting

    lines = []
    with reporting(lines.append, bars=False):
        masks, s = masks_for_images(dim_room.images, MaskConfig(mode="auto"), eight_bit_codes=[True] * 8,
                                    names=[f"v{i}" for i in range(8)])
    for m, truth in zip(masks, dim_room.masks):
        assert m is None or mask_iou(m, truth) >= 0.95
    # what the masks made before judging kept: the highlight or the window (IoU with the object 0.03-0.08);
    # 5 of 8 are doubtful on their own (a highlight or a window), and their areas vary by 81% across views
    assert s["mode"] == "none" and s["masks"] == 0
    assert "then undone" in s["decision"] and len(s["doubtful"]) >= 3
    assert any("highlight or a window" in why for why in s["doubtful"].values())
    assert len(lines) == 1 and lines[0].startswith("  masks: no automatic masks:")


def test_ingest_records_why_masks_were_undone(dim_room, tmp_path):
    from texstream.calib.ingest import ingest
    from texstream.capture.imageio import write_image

    src = tmp_path / "photos"
    for i, img in enumerate(dim_room.images[:6]):
        write_image(src / f"v{i}.png", np.round(img * 255).astype(np.uint8), bits=8)
    res = ingest(src, tmp_path / "cap")
    assert res.summary["masks"] == 0 and "then undone" in res.summary["auto_masks"]["decision"]
    rep = json.loads((tmp_path / "cap" / "ingest_report.json").read_text())
    assert rep["auto_masks"]["doubtful"] and rep["auto_masks"]["mode"] == "none"
    assert all(f.mask_path is None for f in read_capture(tmp_path / "cap").frames)


def test_each_doubt_on_its_own():
    """Border, coverage, highlight and SfM-outline doubts, one photo each (a dark 120 x 160 frame)."""
    from texstream.calib.masks import doubt

    cfg = MaskConfig()
    img = np.full((120, 160, 3), 0.08, np.float32)
    img[:, 100:] = 0.9  # a lit wall on the right, from top to bottom edge
    m, info = compute_mask(img, cfg, eight_bit_codes=True)
    assert "border" in doubt(info, cfg)
    img = np.full((120, 160, 3), 0.08, np.float32)
    yy, xx = np.mgrid[0:120, 0:160]
    img += (np.exp(-((xx - 80) ** 2 + (yy - 60) ** 2) / 60.0) * 1.2)[..., None]  # a flash highlight only
    m, info = compute_mask(np.clip(img, 0, 1), cfg, eight_bit_codes=True)
    assert m is not None and "highlight" in doubt(info, cfg)
    # an object (a grey disc) whose SfM points lie elsewhere: the mask misses their outline
    img = np.full((120, 160, 3), 0.05, np.float32)
    img[(xx - 40) ** 2 + (yy - 60) ** 2 < 400] = 0.5
    pts = np.array([[x + 0.5, y + 0.5] for x in (100, 130) for y in (30, 90)], float)
    m, info = compute_mask(img, cfg, eight_bit_codes=True, points=pts)
    assert "outline of the photo's SfM object points" in doubt(info, cfg)
    assert doubt({"mask_fraction": 0.95}, cfg).startswith("the mask covers 95%")
    assert doubt({"border_fraction": 0.1, "highlight_fraction": 0.2, "mask_fraction": 0.3}, cfg) is None
