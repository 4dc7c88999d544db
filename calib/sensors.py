"""The EXIF focal-length prior, cross-checked: sensor widths of common camera bodies and :func:`focal_prior`.

A focal length in pixels can be read from EXIF three ways, and real exports break each of them somewhere:

* ``focal_plane``: FocalLength x FocalPlaneXResolution. Raw converters that export at a fraction of the
  sensor's resolution keep the full sensor's focal-plane resolution, so this is 4-8x too long unless scaled
  by the photo's width over ``PixelXDimension`` (when that tag also still names the full sensor);
* ``sensor_table``: FocalLength / the body's sensor width (this table) x the photo's width;
* ``35mm``: FocalLengthIn35mmFilm over the 43.27 mm diagonal of a 36 x 24 mm frame x the photo's diagonal
  (or over 36 mm x the photo's width, the convention nearer the other sources).

:func:`focal_prior` takes the value the sources agree on and says what it did.

The widths (millimetres, the sensor's longer side) are those of COLMAP's camera database
(``src/colmap/sensor/specs.cc`` in https://github.com/colmap/colmap, BSD-3-Clause; ``camera_specs.cc`` in
older versions), which COLMAP itself uses for the same purpose, cut down to the bodies most used for
object captures, with a few newer bodies from their makers' specification sheets (marked). Keys are
cleaned as COLMAP cleans them (lower case, no spaces or dashes, the make removed from the model), and a
model is found as COLMAP finds it: an exact match, else the one table entry contained in the model
string or containing it (two or more such entries: no answer, rather than a guess).
"""

from __future__ import annotations

import math
import statistics
from typing import Any

# make -> {cleaned model: sensor width in mm}
SENSOR_WIDTH_MM: dict[str, dict[str, float]] = {
    "canon": {
        "eos5dmarkiv": 36.0, "eos5dmarkiii": 36.0, "eos5dmarkii": 36.0, "eos5dsr": 36.0, "eos5ds": 36.0,
        "eos5d": 35.8, "eos6dmarkii": 35.9, "eos6d": 35.8, "eos1dx": 36.0, "eosr5": 36.0, "eosr6": 35.9,
        "eosr": 36.0, "eosrp": 35.9, "eos7dmarkii": 22.4, "eos7d": 22.3, "eos80d": 22.5, "eos90d": 22.3,
        "eos70d": 22.5, "eos60d": 22.3, "eos700d": 22.3, "eos750d": 22.3, "eos800d": 22.3, "eosm50": 22.3,
        "eosrebelt5i/700d": 22.3, "eosrebelt6i/750d": 22.3, "eosr7": 22.3, "eosr10": 22.3,
    },
    "nikon": {
        "d850": 35.9, "d810": 35.9, "d800e": 35.9, "d800": 35.9, "d750": 35.9, "d780": 35.9, "d610": 35.9,
        "d600": 35.9, "d5": 35.9, "d4": 36.0, "z7ii": 35.9, "z7": 35.9, "z6ii": 35.9, "z6": 35.9, "z8": 35.9,
        "z9": 35.9, "zf": 35.9, "d7500": 23.5, "d7200": 23.5, "d7100": 23.5, "d5600": 23.5, "d5300": 23.5,
        "d3500": 23.5, "d3400": 23.5, "z50": 23.5, "zfc": 23.5,
    },
    "sony": {
        "ilce7rm4": 35.7, "ilce7rm3": 35.9, "ilce7rm2": 35.9, "ilce7r": 35.9, "ilce7m4": 35.9, "ilce7m3": 35.6,
        "ilce7m2": 35.8, "ilce7": 35.8, "ilce7sm3": 35.6, "ilce1": 35.9, "ilce6000": 23.5, "ilce6400": 23.5,
        "ilce6500": 23.5, "ilce6600": 23.5, "dscrx100": 13.2, "dscrx10": 13.2,
    },
    "fujifilm": {
        "xt1": 23.6, "xt2": 23.6, "xt3": 23.5, "xt4": 23.5, "xt5": 23.5, "xt30": 23.5, "xh2": 23.5,
        "xe3": 23.5, "xe4": 23.5, "xpro2": 23.6, "xs10": 23.5, "x100v": 23.5, "gfx50s": 43.8, "gfx100s": 43.8,
    },
    "panasonic": {
        "dmcgh4": 17.3, "dcgh5": 17.3, "dcg9": 17.3, "dmcg9": 17.3, "dmcgx8": 17.3, "dmcg7": 17.3,
        "dcs1r": 36.0, "dcs1": 35.6, "dcs5": 35.6, "dmclx100": 17.3,
    },
    "olympus": {
        "em1markii": 17.4, "em1markiii": 17.4, "em1": 17.3, "em5markii": 17.3, "em5markiii": 17.4, "em5": 17.3,
        "em10markiii": 17.3, "em10": 17.3,
    },
    "omdigitalsolutions": {"om1": 17.4, "om5": 17.4},
    # phones: the main (wide) camera; phones also write FocalLengthIn35mmFilm, the usual prior for them
    "apple": {
        "iphone6": 4.8, "iphone7": 4.8, "iphone8": 4.8, "iphonex": 4.8, "iphone11": 5.6, "iphone12": 5.6,
        "iphone13": 7.0, "iphone14": 7.0, "iphone15": 9.8,
    },
    "samsung": {"smg991": 8.2, "smg996": 8.2, "sms901": 9.6, "sms911": 9.6},
    "google": {"pixel4": 5.6, "pixel5": 5.6, "pixel6": 9.8, "pixel7": 9.8, "pixel8": 9.8},
    "dji": {
        "fc6310": 13.2, "fc6310s": 13.2, "fc220": 6.17, "fc300x": 6.17, "fc330": 6.17, "fc3170": 6.4,
        "fc3411": 13.2, "fc7303": 6.4, "l1d20c": 13.2, "l2d20c": 17.3, "zenmusep1": 35.9,
    },
}


def _clean(s: str) -> str:
    return s.lower().replace(" ", "").replace("-", "").replace("_", "")


def sensor_width_mm(make: str | None, model: str | None) -> float | None:
    """The sensor width (mm, longer side) of the body EXIF names, or None when the table does not know it
    (or knows several candidates for it)."""
    if not make or not model:
        return None
    mk, md = _clean(make), _clean(model)
    for short in ("nikon", "olympus"):  # "NIKON CORPORATION", "OLYMPUS IMAGING CORP."
        if mk.startswith(short):
            mk = short
    md = md.replace(mk, "")
    if mk == "olympus":
        md = md.replace("omd", "")  # "E-M1MarkII" is also written "OM-D E-M1 Mark II"
    found: list[float] = []
    for make_name, models in SENSOR_WIDTH_MM.items():
        if make_name not in mk and mk not in make_name:
            continue
        for model_name, width in models.items():
            if md == model_name:
                return width
            if model_name in md or md in model_name:
                found.append(width)
    # several entries match by containment (e.g. "fc6310" and "fc6310s"): an answer only when they agree
    return found[0] if found and max(found) - min(found) <= 0.01 * max(found) else None


# Sources agreeing within 5% count as one value. Honest sources differ by up to a few per cent: the 35 mm tag is
# an integer (+-0.5 mm: +-2% at 24 mm), zoom lenses write a rounded focal length (+-2% at 24-50 mm), a body's
# sensor width is rounded to 0.1 mm and bodies of one name differ by a few tenths (+-1%); a 3:2 sensor
# cropped to 16:9 or 4:3 changes the diagonal by about 1.5%. The errors this catches are a crop factor
# (1.5-2x) or a resized export (2-8x), all 50% or more; registration refines the few per cent left where the
# photos tell it better (calib/register_selfcal.py hold_focal_prior). The value is
# taken from the agreeing sources other than the 35 mm tag when there are any: its whole millimetres (+-1.3% at
# 39 mm) are coarser than the focal-plane resolution's rational tags.
AGREE_TOLERANCE = 0.05
FRAME_35MM_DIAGONAL = math.hypot(36.0, 24.0)
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF FocalPlaneResolutionUnit: inch, cm, mm, um


def _focal_plane(exif: dict, long_side: int, short_side: int) -> tuple[float | None, str]:
    """The focal-plane candidate (pixels) and a note on how it was made (or why there is none)."""
    unit = _UNIT_MM.get(int(exif.get("focal_plane_unit", 0) or 0))
    if not (exif.get("focal_mm") and exif.get("focal_plane_xres") and unit):
        return None, "no FocalPlaneXResolution"
    f = float(exif["focal_mm"]) * float(exif["focal_plane_xres"]) / unit
    px, py = exif.get("pixel_x"), exif.get("pixel_y")
    if not px or not py:
        return f, "PixelXDimension absent: not checked against the image size"
    tag_long, tag_short = max(float(px), float(py)), min(float(px), float(py))
    if abs(tag_long - long_side) < 0.5:
        return f, "PixelXDimension matches the image"
    if abs(tag_long / tag_short - long_side / short_side) > 0.01 * long_side / short_side:
        return None, (f"PixelXDimension {int(tag_long)}x{int(tag_short)} has another aspect than the image "
                      f"{long_side}x{short_side} (cropped?): focal-plane resolution not usable")
    return f * long_side / tag_long, f"scaled by the image width over PixelXDimension ({long_side}/{int(tag_long)})"


def focal_prior(exif: dict[str, Any], width: int, height: int) -> dict[str, Any]:
    """The EXIF focal length in pixels for a ``width`` x ``height`` photo, cross-checked across its sources.

    Args:
        exif: ``focal_mm``, ``focal_35mm``, ``focal_plane_xres``, ``focal_plane_unit``, ``pixel_x``,
            ``pixel_y``, ``make``, ``model`` (any may be missing).
        width, height: the photo's size as stored (either orientation: the longer side is the sensor's width).

    Returns:
        dict: ``focal_px`` (None: no prior), ``candidates`` (source -> pixels), ``used`` (the sources that agreed;
        the value is their median, the 35 mm tag left out when a finer one agrees),
        ``notes`` (per source, how it was made), ``decision`` (one line: which and why), ``checked``
        (whether two sources agreed).
    """
    long_side, short_side = max(width, height), min(width, height)
    cands: dict[str, float] = {}
    notes: dict[str, str] = {}
    f, notes["focal_plane"] = _focal_plane(exif, long_side, short_side)
    if f:
        cands["focal_plane"] = f
    sensor = sensor_width_mm(exif.get("make"), exif.get("model"))
    if exif.get("focal_mm") and sensor:
        cands["sensor_table"] = float(exif["focal_mm"]) / sensor * long_side
        notes["sensor_table"] = f"{exif.get('model')}: sensor {sensor:g} mm wide"
    if exif.get("focal_35mm"):
        # CIPA defines the equivalent on the frame's diagonal, some writers on its width (36 mm); the two agree
        # on a 3:2 photo and differ by 4% at 4:3, 18% on a square one: the one nearer the other sources is taken
        f35 = float(exif["focal_35mm"])
        by = {"diagonal": f35 / FRAME_35MM_DIAGONAL * math.hypot(width, height), "width": f35 / 36.0 * long_side}
        ref = statistics.median(cands.values()) if cands else by["diagonal"]
        conv = min(by, key=lambda k: abs(math.log(by[k] / ref)))
        cands["35mm"] = by[conv]
        notes["35mm"] = f"{f35:g} mm equivalent (on the frame's {conv})"
    out: dict[str, Any] = {"candidates": {k: round(v, 2) for k, v in cands.items()}, "notes": notes}
    if not cands:
        return {**out, "focal_px": None, "used": [], "checked": False,
                "decision": "no focal length in EXIF: COLMAP's guess (1.2 x the longer side)"}
    # the largest group of sources agreeing with one another (ties: the order above, the 35 mm tag last)
    groups = []
    for k, v in cands.items():
        g = [j for j, u in cands.items() if abs(u - v) <= AGREE_TOLERANCE * min(u, v)]
        groups.append(g)
    best = max(groups, key=len)
    desc = ", ".join(f"{k} {v:.0f} px" for k, v in cands.items())
    if "focal_plane" in cands and notes["focal_plane"].startswith("scaled"):
        desc += f"; focal_plane {notes['focal_plane']}"
    if len(cands) == 1:
        (k, v), = cands.items()
        return {**out, "focal_px": v, "used": [k], "checked": False,
                "decision": f"{k} {v:.0f} px ({notes[k]}); the only source, not cross-checked"}
    if len(best) < 2:
        return {**out, "focal_px": None, "used": [], "checked": False,
                "decision": f"EXIF focal sources disagree by more than {100 * AGREE_TOLERANCE:g}% ({desc}): prior "
                            "dropped, COLMAP's guess (1.2 x the longer side) refined by registration"}
    # the value from the finer sources of the group: the 35 mm tag, whole millimetres, only cross-checks them
    finer = [k for k in best if k != "35mm"] or best
    value = float(statistics.median(cands[k] for k in finer))
    left = [k for k in cands if k not in best]
    why = (f"; {', '.join(left)} disagree{'s' if len(left) == 1 else ''} by more than {100 * AGREE_TOLERANCE:g}% "
           f"and {'is' if len(left) == 1 else 'are'} ignored") if left else ""
    checks = [k for k in best if k not in finer]
    source = " + ".join(finer) + (f", checked by {' + '.join(checks)}" if checks else "")
    return {**out, "focal_px": value, "used": best, "checked": True,
            "decision": f"{value:.0f} px from {source} ({desc}){why}"}
