"""Raw photo folder -> capture folder (``texstream ingest PHOTOS -o CAPTURE``).

Scans PHOTOS (sorted by name), reads every photo with OpenImageIO (through
:mod:`texstream.capture.imageio`), reads EXIF (focal length, 35 mm equivalent, exposure time, ISO,
aperture, orientation, camera), applies the orientation, drops unreadable files and byte-identical
duplicates, groups exposure brackets of one view (only when EXIF says auto bracketing, or ``--brackets on``,
and the photos align: one viewpoint; every decision and its reason go to the report) and merges them to linear HDR (Debevec or
Robertson response for 8-bit, weighted linear merge for 16-bit / float), normalises exposure across
photos from EXIF (``exposure`` = relative t * ISO / N^2, median photo = 1), picks up masks by name
(``masks/NAME.png``, ``masks/NAME.EXT.png``) or from an alpha channel, and records each photo's
saturation level. Photos without a mask get automatic object masks (:mod:`.masks`) when their borders show a
uniform background (``--auto-masks``; the decision and its reason are in the summary).

Output: ``CAPTURE/images`` (8-bit photos copied as they are so COLMAP still sees their EXIF;
rotated or merged photos rewritten: 8-bit PNG or float EXR), ``masks/``, ``capture.json`` with
identity poses and ``"posed": false`` (``texstream register`` poses it), ``ingest_report.json``
(found / used / dropped and why), ``ingest_config.json``. Intrinsics come from ``--intrinsics``
(calibrated, fixed in registration), EXIF (a prior) or COLMAP's default guess. The EXIF focal length is
cross-checked across its sources (:func:`.sensors.focal_prior`: the focal-plane resolution scaled to the
photo's size, the camera body's sensor width, the 35 mm equivalent); a prior they disagree on is outvoted
or dropped, with one line saying which and why (the report's ``focal_prior``). Automatic masks that look
wrong (keeping the border, a highlight, sizes jumping across photos) are undone with their reason.
``--response`` records how the 8- and 16-bit photos' codes become linear radiance (capture.json's ``response``,
:mod:`texstream.capture.response`): sRGB (the default), a ``texstream chart`` response.json, or ``auto``, the
curve fitted to a colour checker found in the photos themselves (:mod:`.colour_chart`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from texstream.capture.capture_json import (MASK_KIND_KEY, NO_FLASH_KEY, VALID_PIXELS, Capture, Frame, Intrinsics,
                                             write_capture)
from texstream.capture.imageio import read_alpha, read_image, read_mask, srgb_to_linear, write_image
from texstream.capture.response import RESPONSE_KEY, response_from_json
from texstream.core.errors import InputError, StageError, TexstreamError
from texstream.core.config import option, save_config
from texstream.core.outputs import StageResult, atomic_output_dir, read_json, write_json_atomic
from texstream.core.progress import bar, say

from .chart_masks import charts_by_frame, mask_out_charts
from .colour_chart import response_from_photos
from .files import list_images, write_failure_report
from .lights import photo_lights
from .masks import MASK_MODES, MaskConfig, masks_for_images, write_mask_preview
from .no_flash import NO_FLASH_HELP, decide_no_flash, exif_flash_fired
from .hdr import (BRACKET_MODES, HDR_METHODS, bracket_alignment, calibrate_response, group_brackets, is_exif_bracket,
                  merge_brackets_8bit, merge_brackets_linear)
from .intrinsics import intrinsics_for_size, load_intrinsics
from .sensors import focal_prior

REPORT_FILE = "ingest_report.json"
MIN_PHOTO_SIDE = 16
"""the shortest photo side ingest takes, in pixels: a smaller photo holds too few pixels for a feature
(COLMAP's SIFT needs a 16-pixel window around each keypoint) or for the fit's filtered taps and mask border;
1x1 photos used to fail only at registration"""


@dataclasses.dataclass
class IngestConfig:
    """Options of the ingest stage."""

    masks: str | None = option(None, help="mask folder (default: PHOTOS/masks); masks are named NAME.png or NAME.EXT.png, "
                               "nonzero = object")
    auto_masks: str = option("auto", help="automatic object masks for photos without a mask file or alpha: auto "
                             "(GrabCut masks only when the photos' borders show a uniform background, e.g. an "
                             "object on black, and undone when they look wrong; the decision and its reason go "
                             "to the summary), none, border "
                             "(threshold against the border colour), grabcut (threshold refined by GrabCut)",
                             choices=MASK_MODES)
    alpha_masks: bool = option(True, help="use a photo's alpha channel as its mask when it has one and no mask file")
    brackets: str = option("auto", help="merge exposure brackets to HDR: auto (only photos whose EXIF says auto "
                           "bracketing, ExposureMode 2), on (the user says the candidate groups are brackets), "
                           "off; in every case only when the photos align (same viewpoint), else each photo "
                           "stands alone with its exposure normalised", choices=BRACKET_MODES)
    bracket_align_px: float = option(2.0, help="largest image-corner displacement (pixels, after exposure "
                                     "normalisation and ECC alignment) for photos to count as one viewpoint",
                                     min=0.0)
    bracket_size: int = option(0, help="photos per exposure bracket: 0 = auto (consecutive photos with different "
                               "exposure times), 1 = no brackets", min=0, max=64)
    hdr_method: str = option("debevec", help="response calibration and merge for 8-bit brackets", choices=HDR_METHODS)
    normalize_exposure: bool = option(True, help="set each frame's exposure from EXIF (t * ISO / N^2, median = 1)")
    intrinsics: str | None = option(None, help="intrinsics.json from 'texstream calibrate' (fixed during registration)")
    single_camera: bool = option(False, help="drop photos whose size differs from the most common one "
                                 "(default: keep them as a second camera)")
    lights: str | None = option(None, help="lights file (JSON): per-photo or default point/directional lights")
    colocated_light: float | None = option(None, help="light fixed to the camera (flash) with this intensity, a point "
                                           "light at each camera centre; when SfM's scale is arbitrary (no "
                                           "alignment) it is the irradiance at the median object distance",
                                           min=1e-12)
    no_flash: str | None = option(None, help=NO_FLASH_HELP + " (calib/no_flash.py); those photos' flash gets "
                                  "intensity 0")
    response: str = option("srgb", help="how the 8- and 16-bit photos' codes become linear radiance (the "
                           "fit's input): srgb (decoded as sRGB), auto (the curve fitted to a ColorChecker Classic "
                           "found in the photos, when it is found in at least 2 of them; else srgb, saying why), or "
                           "a response.json from 'texstream chart'; float photos (EXR) are radiance already")
    overwrite: bool = option(True, help="replace an existing output folder")


RESPONSE_MIN_CHARTS = 2
"""``--response auto`` uses the chart's curve only when at least this many photos show the chart: one photo's
24 patches pin the curve only at their own codes, and a second, under another light, fills the codes between
them and checks the first (a chart mistaken in one photo then shows as a large residual)"""


def _decide_response(infos: list[dict], cfg: IngestConfig):
    """(PhotoResponse or None for sRGB, the report's entry {"used", "why", ...}) for ``cfg.response``."""
    if cfg.response == "srgb":
        return None, {"used": "srgb", "why": "--response srgb (the default)"}
    if cfg.response != "auto":
        path = Path(cfg.response)
        if not path.is_file():
            raise InputError("response file not found", path, "pass a response.json from 'texstream chart', auto "
                                                              "or srgb to --response")
        response = response_from_json(read_json(path, what="response file"), path)
        response = dataclasses.replace(response, source=f"file {path}")
        say("ingest", f"photo response: {path} (--response)")
        return response, {"used": "colour_chart", "why": f"--response {path}", "source": response.source}
    coded = [i for i in infos if i["eight_bit"] or i["sixteen_bit"]]
    if not coded:
        return None, {"used": "none", "why": "every photo is float (radiance already): no response applies"}
    by_path = {str(i["path"]): i["img"] for i in coded}
    fitted, per_photo = None, []
    try:
        fitted, per_photo = response_from_photos([i["path"] for i in coded], lambda p: by_path[str(p)])
    except InputError as e:  # the patches fit no camera curve: sRGB, with the reason
        found = []
        why = f"colour chart found but its patches gave no response ({e.message}): photos decoded as sRGB"
    else:
        found = [Path(r["photo"]).name for r in per_photo if r["found"]]
        if len(found) < RESPONSE_MIN_CHARTS:
            fitted = None
            why = (f"colour chart found in {len(found)} of {len(coded)} photos, fewer than {RESPONSE_MIN_CHARTS}: "
                   "photos decoded as sRGB")
        else:
            why = (f"colour chart found in {len(found)} of {len(coded)} photos ({', '.join(found)}); its patches "
                   f"fit the curve to {fitted.residual_percent:.2f}% RMS")
    entry = {"used": "srgb" if fitted is None else "colour_chart", "why": why, "charts_found": found,
             "per_photo": [{**r, "photo": Path(r["photo"]).name} for r in per_photo]}
    say("ingest", f"photo response: {why}")
    if fitted is None:
        return None, entry
    entry.update(residual_percent=fitted.residual_percent, patches_used=fitted.patches_used)
    return fitted.photo_response(f"colour chart in {len(found)} of {len(coded)} photos"), entry


def _chart_masks(response_entry: dict, infos: list[dict], frames: list[Frame], tmp: Path) -> tuple[dict, dict]:
    """The colour chart (found by ``--response auto``) cleared from the frames' masks, kept out of the mesh and the
    fit (:mod:`.chart_masks`). Returns (capture.json fields: the sightings, for the flash's intensity once the
    cameras are known (:mod:`.chart_flash`), and ``mask_kind`` when every mask is one made here; the summary)."""
    upright = {i["path"].name for i in infos if int(i["exif"].get("orientation", 1) or 1) == 1}
    charts = charts_by_frame(response_entry.get("per_photo", []), upright)
    summary = mask_out_charts(tmp, frames, charts)
    extra: dict[str, Any] = {"colour_chart": {n: s.to_json() for n, s in charts.items()}} if charts else {}
    if charts and summary["made"] == sum(1 for f in frames if f.mask_path):  # every mask made here: no silhouettes
        extra[MASK_KIND_KEY] = VALID_PIXELS
    return extra, summary


def _exif(path: Path) -> dict[str, Any]:
    """EXIF fields texstream uses, from the file header (OpenImageIO); missing ones are absent."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        return {}
    try:
        spec = inp.spec()
        out: dict[str, Any] = {}
        for key, name in (("Exif:FocalLength", "focal_mm"), ("Exif:FocalLengthIn35mmFilm", "focal_35mm"),
                          ("ExposureTime", "exposure_time"), ("Exif:ExposureTime", "exposure_time"),
                          ("Exif:PhotographicSensitivity", "iso"), ("Exif:ISOSpeedRatings", "iso"),
                          ("FNumber", "f_number"), ("Exif:FNumber", "f_number"), ("Orientation", "orientation"),
                          ("Exif:ExposureMode", "exposure_mode"), ("Exif:Flash", "flash"),
                          ("Make", "make"), ("Model", "model"),
                          ("Exif:FocalPlaneXResolution", "focal_plane_xres"),
                          ("Exif:FocalPlaneResolutionUnit", "focal_plane_unit"),
                          ("Exif:PixelXDimension", "pixel_x"), ("Exif:PixelYDimension", "pixel_y")):
            v = spec.getattribute(key)
            if v is not None and name not in out:
                out[name] = v if isinstance(v, str) else float(np.ravel(v)[0])
        return out
    finally:
        inp.close()


def _no_flash_photos(groups: list[list[int]], infos: list[dict], cfg: IngestConfig) -> tuple[set[str], dict]:
    """(the file names of the views' lead photos taken with the flash off, capture.json's ``no_flash`` entry):
    ``--no-flash``, else the EXIF Flash tag (:mod:`.no_flash`); a bracket's lead photo speaks for it."""
    leads = [infos[g[len(g) // 2]] for g in groups]
    marked, entry = decide_no_flash({i["path"].name: exif_flash_fired(i["exif"].get("flash")) for i in leads},
                                    cfg.no_flash)
    if marked:
        say("ingest", f"no-flash photos: {entry['why']}")
    return marked, entry


def apply_orientation(img: np.ndarray, orientation: int) -> np.ndarray:
    """Rotate/flip an (H, W, C) image so it displays upright, per the EXIF Orientation tag (1-8)."""
    o = int(orientation or 1)
    ops = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: a.swapaxes(0, 1)[::-1, ::-1],
           8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(ops.get(o, ops[1])(img))


def _find_mask(mask_dir: Path, photo: Path) -> Path | None:
    for c in (mask_dir / (photo.stem + ".png"), mask_dir / (photo.name + ".png"), mask_dir / photo.name):
        if c.is_file():
            return c
    return None


def _decide_brackets(candidates: list[list[int]], infos: list[dict], cfg: IngestConfig) -> tuple[list[list[int]], list[dict]]:
    """Which candidate groups (same size, distinct exposure times) are merged: EXIF auto bracketing (or
    ``brackets="on"``) and one viewpoint (:func:`.hdr.bracket_alignment`); the others become single
    photos. Returns (groups, one decision {images, merged, reason} per candidate of 2+ photos)."""
    groups: list[list[int]] = []
    decisions: list[dict] = []
    for g in candidates:
        if len(g) < 2:
            groups.append(g)
            continue
        names = [infos[i]["path"].name for i in g]
        modes = [infos[i]["exif"].get("exposure_mode") for i in g]
        if cfg.brackets == "off":
            merged, reason = False, "bracket merging off (--brackets off)"
        elif cfg.brackets == "auto" and not is_exif_bracket(modes):
            merged = False
            reason = ("EXIF does not say exposure bracketing (ExposureMode "
                      f"{sorted({'none' if m is None else int(m) for m in modes}, key=str)}, 2 = auto bracket): "
                      "photos with different exposures taken separately (e.g. auto exposure); pass --brackets on "
                      "if they are brackets")
        else:
            lin = [srgb_to_linear(infos[i]["img"]) if infos[i]["eight_bit"] else infos[i]["img"] for i in g]
            al = bracket_alignment(lin, [float(infos[i]["exif"]["exposure_time"]) for i in g], cfg.bracket_align_px)
            merged = al["aligned"]
            why = "EXIF auto bracket" if cfg.brackets == "auto" else "--brackets on"
            reason = f"{why}; {al['reason']}"
        decisions.append({"images": names, "merged": merged, "reason": reason})
        groups.extend([g] if merged else [[i] for i in sorted(g)])
    return groups, decisions


def _auto_masks(entries: list, cfg: IngestConfig, tmp: Path) -> dict:
    """Automatic masks (calib/masks.py) for the frames without one; sets their ``mask_path``."""
    todo = [(fr, src) for fr, _, src in entries if fr.mask_path is None]
    if not todo:
        return {"mode": "none", "decision": "every frame has a mask file or alpha", "masks": 0}
    masks, summary = masks_for_images([src[0] for _, src in todo], MaskConfig(mode=cfg.auto_masks),
                                      eight_bit_codes=[src[1] for _, src in todo], names=[fr.name for fr, _ in todo])
    for (fr, _), m in zip(todo, masks):
        if m is None:
            continue
        rel = Path("masks") / (fr.name + ".png")
        write_image(tmp / rel, np.where(m, np.uint8(255), np.uint8(0)), bits=8)
        fr.mask_path = str(rel)
    return summary


def _read_photos(files: list[Path], dropped: list[dict]) -> list[dict]:
    """Each photo read once (sRGB codes as stored), with its EXIF, bit depth and upright size; duplicates (same
    bytes) and unreadable files go to ``dropped``."""
    import OpenImageIO as oiio

    infos: list[dict] = []
    hashes: dict[str, str] = {}
    for f in bar(files, "ingest: read", unit="photo"):
        digest = hashlib.sha1(f.read_bytes()).hexdigest()
        if digest in hashes:
            dropped.append({"image": f.name, "reason": f"duplicate of {hashes[digest]}"})
            continue
        try:
            img = read_image(f, channels=3, linear=False)
        except TexstreamError as e:
            dropped.append({"image": f.name, "reason": f"unreadable ({e.message})"})
            continue
        hashes[digest] = f.name
        if min(img.shape[:2]) < MIN_PHOTO_SIDE:
            dropped.append({"image": f.name, "reason": f"too small: {img.shape[1]}x{img.shape[0]} pixels, fewer than "
                                                       f"{MIN_PHOTO_SIDE} on its short side (registration and the fit "
                                                       "need more)"})
            continue
        inp = oiio.ImageInput.open(str(f))
        spec = inp.spec()
        fmt = spec.format
        inp.close()
        eight_bit = fmt == oiio.UINT8
        sixteen_bit = fmt == oiio.UINT16
        exif = _exif(f)
        infos.append({"path": f, "exif": exif, "eight_bit": eight_bit, "sixteen_bit": sixteen_bit, "img": img,
                      "size": (img.shape[1], img.shape[0]) if int(exif.get("orientation", 1) or 1) < 5
                      else (img.shape[0], img.shape[1])})
    return infos


def _write_view(members: list[dict], lead: dict, name: str, orient: int, tmp: Path,
                cfg: IngestConfig, response=None) -> tuple[Path, float | None, np.ndarray]:
    """A view's image into ``tmp/images``: a bracket merged to HDR (radiance per second, scaled to the middle
    exposure's level), else the photo copied (upright, re-encoded only when turned or of another format), its
    saturation in the units its readers decode it to (through ``response`` when given, else sRGB).
    Returns (its path in the capture, its saturation in linear units or None, the stored photo upright as
    automatic masks see it: 8-bit sRGB codes, else linear)."""
    sat = None
    if len(members) > 1:
        if any(m["exif"].get("exposure_time") is None for m in members):
            raise InputError("bracket without exposure times", lead["path"], "set --bracket-size 1")
        t = [float(m["exif"]["exposure_time"]) for m in members]
        if all(m["eight_bit"] for m in members):
            codes = [np.clip(np.round(m["img"] * 255), 0, 255).astype(np.uint8) for m in members]
            resp = calibrate_response(codes, t, cfg.hdr_method)
            hdr = merge_brackets_8bit(codes, t, resp, cfg.hdr_method)
        else:
            lin = [srgb_to_linear(m["img"]) if m["eight_bit"] else m["img"] for m in members]
            hdr = merge_brackets_linear(lin, t)
        # Radiance per second: scale so the middle exposure's level is kept (pixel ~ original).
        t_mid = float(lead["exif"]["exposure_time"])
        img = apply_orientation(hdr * t_mid, orient)
        rel = Path("images") / (name + ".exr")
        write_image(tmp / rel, img, bits=32)
    else:
        img_code = lead["img"]
        if orient != 1 or lead["path"].suffix.lower() not in (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr"):
            rot = apply_orientation(img_code, orient)
            if lead["eight_bit"]:
                rel = Path("images") / (name + ".png")
                write_image(tmp / rel, np.clip(np.round(rot * 255), 0, 255).astype(np.uint8), bits=8)
            else:
                rel = Path("images") / (name + ".exr")
                write_image(tmp / rel, rot, bits=32)
        else:
            rel = Path("images") / lead["path"].name
            shutil.copy2(lead["path"], tmp / rel)
        # Saturation in linear units of the stored image: the top code (clipped sensor).
        top = 254.5 / 255 if lead["eight_bit"] else 65534.5 / 65535 if lead["sixteen_bit"] else None
        if top is not None and response is not None:
            sat = float(response.linearise(top))
        elif lead["eight_bit"]:
            sat = float(srgb_to_linear(np.float32(top)))
        elif lead["sixteen_bit"]:
            sat = top
    return rel, sat, img if len(members) > 1 else apply_orientation(lead["img"], orient)


def _write_mask(mask_dir: Path, lead: dict, name: str, orient: int, size: tuple[int, int], tmp: Path,
                cfg: IngestConfig, dropped: list[dict]) -> Path | None:
    """A view's mask into ``tmp/masks`` (its path in the capture, or None): the mask file beside the photos
    (oriented like the photo; one that does not fit goes to ``dropped``), else the photo's alpha
    (``alpha_masks``)."""
    w, h = size
    mask_rel = None
    mp = _find_mask(mask_dir, lead["path"]) if mask_dir.is_dir() else None
    if mp is not None:
        try:
            m = read_mask(mp)
            m = m.reshape(m.shape[0], m.shape[1])
            if m.shape != (h, w):
                # A mask drawn on the file's stored pixels: orient it like the photo.
                m = apply_orientation(m[..., None], orient)[..., 0]
            if m.shape != (h, w):
                raise InputError(f"mask is {m.shape[1]}x{m.shape[0]}, photo is {w}x{h}", mp, "resize the mask")
            mask_rel = Path("masks") / (name + ".png")
            (tmp / "masks").mkdir(exist_ok=True)
            write_image(tmp / mask_rel, (m > 0).astype(np.uint8) * 255, bits=8)
        except TexstreamError as e:
            dropped.append({"image": mp.name, "reason": f"mask not used: {e.message}"})
    elif cfg.alpha_masks:
        a = read_alpha(lead["path"])
        if a is not None:
            a = apply_orientation(a.reshape(a.shape[0], a.shape[1], 1), orient)[..., 0]
            mask_rel = Path("masks") / (name + ".png")
            (tmp / "masks").mkdir(exist_ok=True)
            write_image(tmp / mask_rel, (a > 0.5).astype(np.uint8) * 255, bits=8)
    return mask_rel


def _view_intrinsics(lead: dict, w: int, h: int, cams, cfg: IngestConfig,
                     focal_decisions: dict) -> tuple[Intrinsics, str]:
    """A view's intrinsics and where they came from: the calibrated ones of its size (``cams``), else the EXIF
    focal length cross-checked across its sources (:func:`.sensors.focal_prior`), else COLMAP's guess; each
    distinct focal decision goes to ``focal_decisions`` (decision -> entry) and is printed once."""
    if cams is not None:
        return intrinsics_for_size(cams, w, h, cfg.intrinsics), "calibrated"
    prior = focal_prior(lead["exif"], w, h)
    f_px = prior["focal_px"]
    entry = focal_decisions.get(prior["decision"])
    if entry is None:
        entry = focal_decisions[prior["decision"]] = {k: prior[k] for k in ("decision", "focal_px", "candidates",
                                                                            "used", "notes", "checked")}
        entry.update(size=f"{w}x{h}", images=[])
        say("ingest", f"focal length: {prior['decision']}")
    entry["images"].append(lead["path"].name)
    # COLMAP's default guess when EXIF has no usable focal length: 1.2 x the longest side.
    f = f_px or 1.2 * max(w, h)
    return Intrinsics(width=w, height=h, fx=f, fy=f, cx=w / 2, cy=h / 2), "exif" if f_px else "guess"


def ingest(photos: str | os.PathLike, out: str | os.PathLike, config: IngestConfig | None = None) -> StageResult:
    """Read a raw photo folder into a capture folder (see the module doc).

    Args:
        photos: folder of photos (optionally with ``masks/``).
        out: capture folder to write atomically.
        config: options.

    Returns:
        StageResult; summary has ``found``, ``frames``, ``brackets`` (merged groups), ``dropped``
        (list of {image, reason}), ``masks``, ``intrinsics_source``, ``response`` (used, why).

    Raises:
        InputError: missing/empty folder, bad intrinsics or lights file. StageError: no usable photo
        (partial report at ``OUT.failed_report.json``).
    """
    cfg = config or IngestConfig()
    photos, out = Path(photos), Path(out)
    if out.exists() and not cfg.overwrite:
        raise InputError("output folder already exists", out, "remove it or pass --overwrite")
    files = list_images(photos)
    mask_dir = Path(cfg.masks) if cfg.masks else photos / "masks"
    dropped: list[dict] = []
    infos = _read_photos(files, dropped)
    report: dict[str, Any] = {"input": str(photos), "found": len(files), "dropped": dropped}
    if not infos:
        report["frames"] = []
        path = write_failure_report(out, report)
        first = f": {dropped[0]['image']} {dropped[0]['reason']}" if dropped else ""
        raise StageError(f"no usable photo among {len(files)} file(s) ({len(dropped)} dropped{first}); partial "
                         f"report {path}", photos / dropped[0]["image"] if len(files) == 1 and dropped else photos,
                         f"use photos OpenImageIO can read, at least {MIN_PHOTO_SIDE} pixels on their short side")
    sizes = [i["size"] for i in infos]
    common = max(set(sizes), key=sizes.count)
    if cfg.single_camera:
        keep = []
        for i in infos:
            if i["size"] != common:
                dropped.append({"image": i["path"].name, "reason": f"wrong size {i['size'][0]}x{i['size'][1]} "
                                f"(most photos are {common[0]}x{common[1]}; --single-camera)"})
            else:
                keep.append(i)
        infos = keep
    times = [i["exif"].get("exposure_time") for i in infos]
    candidates = group_brackets(times, [i["size"] for i in infos], cfg.bracket_size)
    groups, decisions = _decide_brackets(candidates, infos, cfg)
    response, response_entry = _decide_response(infos, cfg)
    no_flash, no_flash_entry = _no_flash_photos(groups, infos, cfg)
    cams = load_intrinsics(cfg.intrinsics) if cfg.intrinsics else None
    light_of = photo_lights(cfg.lights, no_flash)
    frames: list[Frame] = []
    sources: set[str] = set()
    focal_decisions: dict[str, dict] = {}
    with atomic_output_dir(out) as tmp:
        (tmp / "images").mkdir()
        entries = []
        for g in bar(groups, "ingest: write", unit="view"):
            members = [infos[i] for i in g]
            lead = members[len(members) // 2]  # the middle exposure names the view
            name = lead["path"].stem
            orient = int(lead["exif"].get("orientation", 1) or 1)
            w, h = lead["size"]
            rel, sat, mask_view = _write_view(members, lead, name, orient, tmp, cfg, response)
            # What automatic masks see: the stored photo, upright (8-bit: sRGB codes; else linear).
            mask_src = (mask_view, len(members) == 1 and lead["eight_bit"])
            mask_rel = _write_mask(mask_dir, lead, name, orient, (w, h), tmp, cfg, dropped)
            intr, source = _view_intrinsics(lead, w, h, cams, cfg, focal_decisions)
            sources.add(source)
            ex = lead["exif"]
            gain = None
            if ex.get("exposure_time"):
                # Sensor exposure ~ t * ISO / N^2 (N = 1 and ISO 100 when unknown: only ratios matter).
                gain = float(ex["exposure_time"]) * float(ex.get("iso", 100.0)) / 100.0 / float(ex.get("f_number", 1.0)) ** 2
            light = light_of(name, lead["path"].name)
            # per frame too: registration gives an EXIF prior as one, a guess as none
            extra = {"source_images": [m["path"].name for m in members], "focal_prior": source,
                     **({NO_FLASH_KEY: True} if lead["path"].name in no_flash else {})}
            if ex:
                extra["exif"] = {k: v for k, v in ex.items() if k in ("exposure_time", "iso", "f_number", "focal_mm",
                                                                        "focal_35mm", "orientation", "make", "model",
                                                                        "flash")}
            entries.append((Frame(file_path=str(rel), R=np.eye(3), t=np.zeros(3), intrinsics=intr, light=light,
                                  mask_path=None if mask_rel is None else str(mask_rel), saturation=sat, extra=extra),
                            gain, mask_src))
        auto = _auto_masks(entries, cfg, tmp)
        chart_extra, chart_masks = _chart_masks(response_entry, infos, [fr for fr, _, _ in entries], tmp)
        gains = [g for _, g, _ in entries if g]
        ref = float(np.median(gains)) if gains and cfg.normalize_exposure else None
        for fr, g, _ in entries:
            if ref and g:
                fr.exposure = g / ref
            frames.append(fr)
        extra_top: dict[str, Any] = {"posed": False, "intrinsics_source": "+".join(sorted(sources))}
        if focal_decisions:
            extra_top["focal_prior"] = [d["decision"] for d in focal_decisions.values()]
        if cfg.colocated_light is not None:
            extra_top["colocated_light"] = {"intensity": [float(cfg.colocated_light)] * 3, "offset": [0.0, 0.0, 0.0]}
        extra_top.update({RESPONSE_KEY: response.to_json()} if response is not None else {},
                         **({NO_FLASH_KEY: no_flash_entry} if no_flash else {}))
        extra_top.update(chart_extra)
        write_capture(Capture(root=tmp, frames=frames, extra=extra_top), tmp)
        report.update(response=response_entry, frames=[f.file_path for f in frames], no_flash=no_flash_entry)
        report["brackets"] = [[infos[i]["path"].name for i in g] for g in groups if len(g) > 1]
        report["bracket_decisions"] = decisions
        report["camera_sizes"] = sorted({f"{f.intrinsics.width}x{f.intrinsics.height}" for f in frames})
        report.update(auto_masks=auto, chart_masks=chart_masks, focal_prior=list(focal_decisions.values()))
        write_json_atomic(tmp / REPORT_FILE, report)
        save_config(cfg, tmp / "ingest_config.json")
        if auto.get("masks"):
            write_mask_preview(tmp)
    summary = {"found": len(files), "frames": len(frames), "brackets": len(report["brackets"]), "dropped": dropped,
               "bracket_decisions": decisions,
               "masks": sum(1 for f in frames if f.mask_path), "intrinsics_source": extra_top["intrinsics_source"],
               "camera_sizes": report["camera_sizes"],
               "focal_prior": [d["decision"] for d in focal_decisions.values()],
               "auto_masks": {k: auto.get(k) for k in ("mode", "decision", "masks")},
               "response": {k: response_entry[k] for k in ("used", "why")}, "chart_masks": chart_masks["why"],
               "no_flash": no_flash_entry}
    return StageResult(output=out, summary=summary)
