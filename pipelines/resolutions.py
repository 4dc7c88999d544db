"""Which resolution of the photos each stage of a run used, and why, one line each (issue 40): the run's summary
(``run.json`` ``resolutions``) and its report say it.

A stage says its own in its summary's ``resolution`` (a line: the registration's SIFT size, the refinement's
pyramid levels), the mesh stage in its dense stereo report (the matching level, its size and planes); the fit says
it in ``model.json`` (``photos.resolution``: the pyramid level it streamed, chosen from the texels' footprint,
fit/common/inputs.py); the report scores the held-out views on the photos as they are.
"""

from __future__ import annotations

import html
from pathlib import Path

from texstream.core.outputs import read_json

HELDOUT_LINE = "held-out views rendered and scored on the photos as they are (the model judged on the real photos)"


def fit_resolution_line(level_info: dict | None) -> str | None:
    """The fit's line from its ``photos.resolution`` record (None: a fit that does not say)."""
    if not isinstance(level_info, dict) or "level" not in level_info:
        return None
    level, size, px = int(level_info["level"]), level_info.get("size") or ["?", "?"], level_info.get("texel_pixels")
    if int(level_info.get("requested", -1)) >= 0:
        why = f"--photo-level {level_info['requested']}"
    elif px is None:
        why = "auto: no photo sees the texels; the photos as they are"
    else:
        why = (f"auto: texels {px:.2f} px wide at full resolution (the tenth of the photos that see them smallest), "
               f"at least 2 px at level {level}")
    return f"{size[0]}x{size[1]} (level {level}; {why})"


def mesh_resolution_line(summary: dict) -> str | None:
    """The mesh stage's line from its dense stereo report (None: no dense stereo ran)."""
    dense = summary.get("dense") if isinstance(summary, dict) else None
    if not isinstance(dense, dict) or "level" not in dense or not dense.get("matched_size"):
        return None
    w, h = dense["matched_size"]
    return (f"dense stereo on {w}x{h} (level {int(dense['level'])}: mvs.level, auto: the coarsest level whose median "
            f"mask keeps mvs.level_min_mask_pixels pixels), {int(dense.get('depths', 0))} depth planes, "
            f"{int(dense.get('points', 0)):,} points")


def stage_resolutions(stages: list[dict], model_dir: str | Path | None = None) -> dict[str, str]:
    """{stage: the resolution it used and why} for the stages that say it (``stages``: the run's records as
    dicts with ``name``, ``status`` and ``summary``), the fit's from ``model_dir``'s model.json, and the
    report's held-out scoring."""
    out: dict[str, str] = {}
    for s in stages:
        line = (s.get("summary") or {}).get("resolution")
        if s.get("name") == "mesh" and not line:
            line = mesh_resolution_line(s.get("summary") or {})
        if isinstance(line, str) and line:
            out[s["name"]] = line + (" (unchanged since the last run)" if s.get("status") == "skipped" else "")
    manifest = Path(model_dir) / "model.json" if model_dir is not None else None
    if manifest is not None and manifest.is_file():
        photos = read_json(manifest, what="model manifest").get("photos")
        line = fit_resolution_line(photos.get("resolution") if isinstance(photos, dict) else None)
        if line is not None:
            out["fit"] = line
    out["report"] = HELDOUT_LINE
    return out


def resolutions_html(lines: dict[str, str]) -> str:
    """The report's section: one row per stage."""
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in lines.items())
    return ("<h2>Photo resolution per stage</h2><table><tr><th>stage</th><th>resolution and why</th></tr>"
            + rows + "</table>")
