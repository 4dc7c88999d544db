"""What a run's summary and report say about its light and resolutions (issue 39): which light the fit assumed
(the flash's intensity from a colour chart, given, or per photo), how many photos were taken with the flash off and
what said so (EXIF, ``--no-flash``), whether the room's light got a per-texel ambient term and why, and the photos'
and the atlas's sizes with the level the fit read. Entries in the
``{input: {source, why}}`` form of :mod:`texstream.pipelines.provenance` (printed, and in the report's inputs)."""

from __future__ import annotations

import json
from pathlib import Path

from texstream.capture.capture_json import NO_FLASH_KEY, no_flash_frames


def _model_json(model_dir: Path) -> dict:
    try:
        return json.loads((Path(model_dir) / "model.json").read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def _light(capture, flash_summary: dict) -> dict:
    if flash_summary:
        inten = ", ".join(f"{v:.4g}" for v in flash_summary["intensity"])
        return {"source": f"flash at the camera, intensity ({inten}) from the colour chart", "why": flash_summary["why"]}
    coloc = capture.extra.get("colocated_light")
    if isinstance(coloc, dict):
        return {"source": "flash at the camera, intensity given",
                "why": "--colocated-light (the irradiance at the object's median distance when the cameras' scale "
                       "is SfM's); no colour chart fixed it, so albedos are relative to that guess"}
    dark = len(no_flash_frames(capture.frames))
    unlit = f", intensity 0 on the {dark} photos taken with the flash off (the room lights them alone)" if dark else ""
    if capture.extra.get("lights_source"):
        return {"source": str(capture.extra["lights_source"]) + unlit, "why": "the lights stage"}
    return {"source": "known per photo" + unlit if capture.has_lights else "none known", "why": "as the capture states"}


def _no_flash(capture) -> dict:
    """{"no_flash": {source, why}} when some photos were taken with the flash off, else {} (most captures)."""
    dark = no_flash_frames(capture.frames)
    if not dark:
        return {}
    entry = capture.extra.get(NO_FLASH_KEY)
    why = entry.get("why") if isinstance(entry, dict) else "capture.json marks them no_flash"
    return {"no_flash": {"source": f"{len(dark)} of {len(capture.frames)} photos taken with the flash off (the room's "
                                  "light alone)", "why": str(why)}}


def _ambient(model: dict) -> dict:
    amb = model.get("ambient")
    if not amb:
        return {"source": "none", "why": "the model has no ambient term (a kind without one, or no fit)"}
    source = {"on": "flash plus a per-texel ambient term (the room's light)",
              "room": "flash plus the room's light as one global SH environment lighting the same albedo"}
    return {"source": source.get(amb.get("chosen"), "flash alone"),
            "why": f"--ambient {amb.get('mode', amb.get('chosen'))}: {amb.get('reason', '')}"}


def _resolutions(capture, model: dict, fit_geometry: Path) -> dict:
    sizes = sorted({(f.intrinsics.width, f.intrinsics.height) for f in capture.frames}, key=lambda s: -s[0] * s[1])
    atlas = model.get("atlas") or {}
    level = (model.get("photos") or {}).get("resolution")
    source = (f"photos {', '.join(f'{w}x{h}' for w, h in sizes)}; atlas {atlas.get('width')}x{atlas.get('height')} "
              f"({atlas.get('texels', 0):,} texels)")
    if isinstance(level, dict) and level.get("size"):
        why = (f"the fit read the photos at level {level.get('level', 0)} ({level['size'][0]}x{level['size'][1]}), "
               f"{float(level.get('level_texel_pixels') or 0):.2f} pixels a texel's side")
    else:
        why = f"the fit read the photos at {level}" if level else "the fit read the photos as stored"
    return {"source": source, "why": f"{why}; the atlas from {fit_geometry}"}


def light_and_resolution_inputs(capture, model_dir: Path, fit_geometry: Path, flash_summary: dict) -> dict:
    """{"light", "no_flash" (only when some photos were taken with the flash off), "ambient", "resolutions"}: each
    {source, why} (module doc)."""
    model = _model_json(model_dir)
    return {"light": _light(capture, flash_summary), **_no_flash(capture), "ambient": _ambient(model),
            "resolutions": _resolutions(capture, model, fit_geometry)}
