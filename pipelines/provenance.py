"""What a run's model was built from: the cameras, intrinsics, masks and mesh, each with its source and why.

A model is only as good as its inputs, and on real captures the inputs are where things go wrong silently
(a focal length 8x too long from stale EXIF, masks that kept the room and dropped the object, a mesh of 600
faces from sparse points). The run reads what each stage recorded and states, per input, one source and one
reason; ``texstream run`` prints them, ``run.json`` keeps them (``inputs``) and the report shows them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from texstream.capture.capture_json import masks_are_silhouettes

INPUTS = ("cameras", "intrinsics", "masks", "mesh")


def _summary(records: list, name: str) -> tuple[str | None, dict]:
    """(status, summary) of the last record of stage ``name``; (None, {}) when the run has none."""
    for r in reversed(records):
        if r.name == name:
            return r.status, dict(r.summary or {})
    return None, {}


def _cameras(records: list, source_kind: str, capture) -> dict:
    status, reg = _summary(records, "register")
    if status is not None and reg.get("registered") is not None:
        n_posed = len(reg.get("registered") or [])  # the photos placed on a ring are among them
        n_all = n_posed + len(reg.get("unregistered") or [])
        placed = len(reg.get("placed") or [])
        why = f"{n_posed - placed} of {n_all} photos registered by structure from motion (pycolmap)"
        if placed:
            why += f"; {placed} more placed on the turntable ring the registered cameras lie on"
        if reg.get("ring"):
            why += f" (ring: {reg['ring']})"
        if reg.get("alignment"):
            why += "; aligned to the known camera centres"
        return {"source": "registered", "why": why}
    imported = (capture.extra.get("source") if capture is not None else None) or {}
    if isinstance(imported, dict) and imported.get("format"):
        exported = imported.get("cameras") or imported.get("xmp") or "the export"
        return {"source": f"imported ({imported['format']})",
                "why": f"cameras read from {exported}"
                       + ("; photos undistorted to pinhole cameras" if capture.extra.get("undistorted") else "")}
    if source_kind == "colmap":
        return {"source": "imported (COLMAP model)", "why": "the input is a COLMAP model"}
    return {"source": "given", "why": "every frame of the capture folder has a pose"}


def _intrinsics(records: list, capture) -> dict:
    _, ing = _summary(records, "ingest")
    _, reg = _summary(records, "register")
    src = ing.get("intrinsics_source") or (capture.extra.get("intrinsics_source") if capture is not None else None)
    why_parts = []
    prior = ing.get("focal_prior") or []  # ingest: one decision per distinct EXIF case (calib/sensors.py)
    why_parts += [str(d) for d in (prior if isinstance(prior, list) else [prior])]
    mapped = reg.get("focal_prior") or {}  # registration: mapped again without a doubtful prior? (focal_check)
    if isinstance(mapped, dict) and (mapped.get("decision") or mapped.get("retried")):
        why_parts.append(str(mapped.get("decision") or mapped.get("reason")))
    hold = reg.get("focal_hold") or {}  # registration: the EXIF focal length held? (calib/register_selfcal.py)
    if hold.get("held"):
        why_parts.append(str(hold.get("reason")))
    elif reg.get("registered") is not None:
        why_parts.append("refined by bundle adjustment")
    if not src:
        src = "given with the cameras"
    return {"source": str(src), "why": "; ".join(why_parts) or "as the capture states them"}


def _masks(records: list, capture) -> dict:
    status, ing = _summary(records, "ingest")
    auto = ing.get("auto_masks") or {}
    n = sum(1 for f in capture.frames if f.mask_path) if capture is not None else 0
    total = len(capture.frames) if capture is not None else 0
    if status is not None and auto.get("decision"):
        source = f"automatic ({auto.get('mode')})" if auto.get("masks") else "none"
        return {"source": source, "why": str(auto["decision"]) + (f" ({n} of {total} photos)" if n else "")}
    if n and capture is not None and not masks_are_silhouettes(capture):
        return {"source": "pixels with data only", "why": f"{n} of {total} undistorted photos have pixels outside "
                                                           "the original photo, masked out; no object masks"}
    if n:
        return {"source": "given", "why": f"{n} of {total} photos have a mask in the capture folder"}
    return {"source": "none", "why": "the capture has no masks"}


def _mesh(records: list, mesh_file: str | None, capture) -> dict:
    status, mesh = _summary(records, "mesh")
    carried = capture.extra.get("mesh_source") if capture is not None else None
    if mesh_file and isinstance(carried, dict) and Path(mesh_file).name == Path(str(capture.extra.get("mesh"))).name:
        return {"source": "imported with the cameras",
                "why": f"{carried.get('file')} ({carried.get('frame')} frame), used as it is"}
    if mesh_file:
        return {"source": "given", "why": f"--mesh-file {mesh_file}"}
    if status is None:
        return {"source": "unknown", "why": "no mesh stage ran"}
    source = str(mesh.get("source", "unknown"))
    dense = mesh.get("dense") or {}
    if source == "sfm":
        source = "Poisson of dense stereo points" if dense.get("used") else "Poisson of SfM points"
    source = {"hull": "visual hull", "scan": "given mesh file"}.get(source, source)
    faces = ((mesh.get("clean") or {}).get("after") or {}).get("faces")
    why = str(mesh.get("reason", ""))
    if dense.get("used"):
        why += f"; dense stereo masks: {dense.get('masks')}; depth range from {dense.get('depth_range_from')}"
    elif dense.get("fallback"):
        why += f"; dense stereo not used: {dense['fallback']}"
    if faces:
        why += f" ({faces:,} faces)"
    return {"source": source, "why": why}


def run_inputs(records: list, source_kind: str, capture, mesh_file: str | Path | None = None) -> dict[str, Any]:
    """{input: {source, why}} for the cameras, intrinsics, masks and mesh of a run (module doc).

    ``records``: the run's StageRecords (name, status, summary); ``capture``: the capture the fit read.
    """
    return {"cameras": _cameras(records, source_kind, capture), "intrinsics": _intrinsics(records, capture),
            "masks": _masks(records, capture), "mesh": _mesh(records, str(mesh_file) if mesh_file else None, capture)}


def inputs_lines(inputs: dict) -> list[str]:
    """One printed line per input: ``cameras: registered (12 of 16 photos registered ...)``."""
    return [f"{k}: {v['source']} ({v['why']})" if v.get("why") else f"{k}: {v['source']}"
            for k, v in inputs.items()]
