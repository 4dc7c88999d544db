"""Photos that form separate groups (no verified match between them) told apart before mapping: one object
seen from views that do not overlap, or photos of different objects mixed in one folder
(``RegisterConfig.disconnected``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from texstream.capture.imageio import read_image, read_mask
from texstream.core.errors import InputError
from texstream.core.progress import say

from .files import write_failure_report

if TYPE_CHECKING:
    from .register import RegisterConfig, _Photo


def match_groups(db: Path, min_inliers: int) -> list[list[str]]:
    """The photos of a COLMAP database joined by verified matches (at least ``min_inliers`` inlier
    matches per pair, COLMAP's own bar for a verified pair): connected groups of names, largest first."""
    import pycolmap

    database = pycolmap.Database.open(str(db))
    try:
        names = {int(im.image_id): im.name for im in database.read_all_images()}
        pair_ids, inliers = database.read_two_view_geometry_num_inliers()
    finally:
        database.close()
    parent = {i: i for i in names}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for pid, n in zip(pair_ids, inliers):
        if n >= min_inliers:
            a, b = (int(x) for x in pycolmap.pair_id_to_image_pair(int(pid)))
            if a in parent and b in parent:
                parent[root(a)] = root(b)
    groups: dict[int, list[str]] = {}
    for i, name in names.items():
        groups.setdefault(root(i), []).append(name)
    return sorted((sorted(g) for g in groups.values()), key=lambda g: (-len(g), g[0]))


def _few(names: list[str], n: int = 3) -> str:
    return ", ".join(names[:n]) + (f" and {len(names) - n} more" if len(names) > n else "")


def _colour_signature(photo: _Photo) -> np.ndarray:
    """Square root of a photo's brightness-weighted chromaticity histogram (12 x 12 bins of r and g over
    r+g+b; inside its mask when it has one): dark background pixels weigh little, exposure cancels."""
    img = read_image(photo.path, channels=3)
    keep = np.ones(img.shape[:2], bool)
    if photo.mask is not None:
        keep = read_mask(photo.mask).reshape(img.shape[:2]) > 0
    step = max(1, int(np.sqrt(img.shape[0] * img.shape[1] / 65536)))  # ~65k pixels are plenty for 144 bins
    px = img[::step, ::step][keep[::step, ::step]].reshape(-1, 3).astype(np.float64)
    s = px.sum(1)
    c = px[:, :2] / np.maximum(s, 1e-9)[:, None]
    h, _ = np.histogramdd(c, bins=(12, 12), range=((0, 1), (0, 1)), weights=s)
    return np.sqrt(h.ravel() / max(h.sum(), 1e-30))


def groups_look_different(groups: list[list[str]], photos: list[_Photo]) -> tuple[bool, dict]:
    """Whether match groups show different objects: for some two groups, the mean Hellinger distance
    between their photos' colour signatures is above 0.3 and twice the larger mean distance within them.

    Measured on the Middlebury sparse rings mixed in one folder: the temple's 16 photos and the dino's
    two groups of 7 (the untextured dino's photos form two groups without a verified match between them)
    lie 0.88 apart; within the groups 0.17, 0.06 and 0.09, and the dino's two groups 0.12 from each
    other: one object."""
    by_name = {p.name: p for p in photos}
    sig = {n: _colour_signature(by_name[n]) for g in groups for n in g}

    def mean_dist(a: list[str], b: list[str]) -> float:
        d = [np.linalg.norm(sig[x] - sig[y]) / np.sqrt(2) for x in a for y in b if x != y]
        return float(np.mean(d)) if d else 0.0

    within = [mean_dist(g, g) for g in groups]
    pairs = {(i, j): mean_dist(groups[i], groups[j]) for i in range(len(groups)) for j in range(i + 1, len(groups))}
    different = any(d > 0.3 and d > 2 * max(within[i], within[j]) for (i, j), d in pairs.items())
    return different, {"colour_distance_within": [round(w, 3) for w in within],
                       "colour_distance_between": {f"{i + 1}-{j + 1}": round(d, 3) for (i, j), d in pairs.items()}}


def check_groups(groups: list[list[str]], photos: list[_Photo], folder: Path, out: Path, cfg: RegisterConfig,
                 report: dict) -> None:
    """Stop before mapping when the photos split into two or more sizeable groups that share no verified
    match and look like different objects (``cfg.disconnected``: auto; error stops whatever they look
    like, largest never). A group counts when it holds at least a fifth of the photos (and
    ``min_model_size``): a single object's stray photos (a blurred one, a close-up) form small groups
    of their own and only go unregistered."""
    report["match_groups"] = [len(g) for g in groups]
    big = [g for g in groups if len(g) >= max(cfg.min_model_size, math.ceil(0.2 * len(photos)))]
    if len(big) < 2:
        return
    info: dict[str, Any] = {"groups": big, "mode": cfg.disconnected}
    report["disconnected"] = info
    sizes = ", ".join(str(len(g)) for g in big)
    if cfg.disconnected == "auto":
        different, stats = groups_look_different(big, photos)
        info.update(stats)
        if not different:
            info["decision"] = "similar colours: one object with too little overlap between the groups"
            say("register", f"{len(big)} groups of photos ({sizes}) share no features but look alike: one object "
                            "seen from views that do not overlap; every group is mapped, and photos the largest model leaves out "
                            "may be placed on a turntable ring (ring auto)")
            return
        info["decision"] = "different colours: photos of different objects"
    elif cfg.disconnected == "largest":
        info["decision"] = "largest group registered (disconnected = largest)"
        say("register", f"{len(big)} groups of photos ({sizes}) share no features; the largest is registered")
        return
    report["registered"], report["unregistered"] = [], [n for g in groups for n in g]
    path = write_failure_report(out, report)
    desc = "; ".join(f"group {k + 1}, {len(g)} photos: {_few(g)}" for k, g in enumerate(big))
    raise InputError(f"the photos form {len(big)} groups that share no features, photos of different objects? "
                     f"({desc}; every group in {path})", folder,
                     "put each object's photos in a folder of its own and run once per folder, or keep the largest "
                     "group with --disconnected largest (texstream run: [register] disconnected = \"largest\")")
