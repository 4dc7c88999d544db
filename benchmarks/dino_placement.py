"""The Middlebury dino from its 16 photos alone: how many photos get cameras, how right they are, and the
held-out PSNR of the run (JSON).

    python benchmarks/dino_placement.py --out /tmp/dino_h4 [--data ../shared/data/middlebury_dino_sparse]
    python benchmarks/dino_placement.py --out /tmp/dino_h4 --existing   # score a finished run again

Runs ``texstream run DATA -o OUT`` (ingest, registration with the turntable ring's placement of the photos
SfM leaves out, mesh, atlas, refine, fit with every 8th photo held out) and scores the cameras of
``OUT/posed/capture.json`` and of ``OUT/refine/capture.json`` (after the photometric refinement) against the set's
calibration ``dinoSR_par.txt``, which the method never reads: a similarity (rotation from the camera rotations,
scale and translation from the centres) takes the run's frame onto the calibration's, then per photo the angle
between the rotations (degrees) and the centre distance over the ring's radius. The held-out figures are the
run's own (``run.json``: pooled PSNR over the held-out views, the worst view). The reference, the run through the
calibrated cameras (``texstream import middlebury``), gave 24.85 dB pooled (docs/real-data.md).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from gitinfo import commit  # noqa: E402

REFERENCE_DB = 24.85


def load_par(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (world-to-camera R, centre) of a Middlebury ``*_par.txt``."""
    out = {}
    for line in path.read_text().splitlines()[1:]:
        p = line.split()
        if len(p) < 22:
            continue
        v = np.array(p[1:22], np.float64)
        r, t = v[9:18].reshape(3, 3), v[18:21]
        out[p[0]] = (r, -r.T @ t)
    return out


def camera_errors(capture_dir: Path, truth: dict) -> dict:
    """Per-photo rotation error (deg) and centre error over the ring radius after a similarity alignment."""
    from texstream.calib.turntable import fit_ring, photo_indices, rotation_angle_deg, similarity_onto, transform_cameras
    from texstream.capture.capture_json import read_capture

    cap = read_capture(capture_dir)
    got = {Path(f.file_path).name: (np.asarray(f.R), np.asarray(f.center)) for f in cap.frames}
    names = sorted(n for n in got if n in truth)
    if len(names) < 2:
        return {"cameras": len(names)}
    sim = similarity_onto([got[n][0] for n in names], [got[n][1] for n in names],
                          [truth[n][0] for n in names], [truth[n][1] for n in names])
    rs, cs = transform_cameras(sim, [got[n][0] for n in names], [got[n][1] for n in names])
    all_names = sorted(truth)
    ring = fit_ring(photo_indices(all_names), [truth[n][0] for n in all_names], [truth[n][1] for n in all_names])
    per = {n: {"rotation_deg": round(rotation_angle_deg(r, truth[n][0]), 3),
               "centre_over_radius": round(float(np.linalg.norm(c - truth[n][1]) / ring.radius), 4)}
           for n, r, c in zip(names, rs, cs)}
    rot = [v["rotation_deg"] for v in per.values()]
    cen = [v["centre_over_radius"] for v in per.values()]
    return {"cameras": len(names), "rotation_deg_median": float(np.median(rot)), "rotation_deg_max": float(max(rot)),
            "centre_over_radius_median": float(np.median(cen)), "centre_over_radius_max": float(max(cen)),
            "per_photo": per}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=os.environ.get("TEXSTREAM_DATA", "../shared/data") + "/middlebury_dino_sparse")
    ap.add_argument("--out", default="/tmp/dino_h4")
    ap.add_argument("--existing", action="store_true", help="score the run already in --out (no new run)")
    ap.add_argument("--json", default=None, help="JSON to write (default: OUT/dino_placement.json)")
    args = ap.parse_args()
    data, out = Path(args.data), Path(args.out)
    code = commit()  # read before the run: a commit made while it runs must not be named
    seconds = None
    if not args.existing:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "texstream.pipelines.cli", "run", str(data), "-o", str(out)], check=True)
        seconds = time.perf_counter() - t0
    truth = load_par(data / "dinoSR_par.txt")
    run = json.loads((out / "run.json").read_text())
    reg = json.loads((out / "posed" / "registration_report.json").read_text())
    ring = reg.get("ring", {})
    result = {
        "commit": code, "machine": platform.node(), "cpus": os.cpu_count(), "command": " ".join(sys.argv),
        "run_seconds": seconds, "photos": reg.get("photos"),
        "registered_by_sfm": len(reg.get("registered", [])) - len(reg.get("placed", [])) - sum(
            1 for e in ring.get("photos", {}).values() if e.get("method", "").startswith("sfm in a merged")),
        "from_merged_models": sum(1 for e in ring.get("photos", {}).values()
                                  if e.get("method", "").startswith("sfm in a merged")),
        "placed_by_ring": len(reg.get("placed", [])), "with_cameras": len(reg.get("registered", [])),
        "dropped_placements": ring.get("dropped", []), "ring": ring.get("fit"), "ring_decision": ring.get("decision"),
        "focal": reg.get("ring_focal", {}).get("focal"), "focal_truth": 3310.4,
        "silhouette_iou": {n: e.get("iou") for n, e in ring.get("photos", {}).items()},
        "cameras_registered": camera_errors(out / "posed", truth),
        "cameras_refined": camera_errors(out / "refine", truth) if (out / "refine" / "capture.json").is_file() else None,
        "heldout": run.get("heldout"), "model": run.get("model"), "reference_heldout_db": REFERENCE_DB,
    }
    path = Path(args.json) if args.json else out / "dino_placement.json"
    path.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k not in ("silhouette_iou",)}, indent=1)[:4000])


if __name__ == "__main__":
    main()
