"""Kill ``texstream run`` with SIGKILL at random times, run the same command again, and check that the result
matches an uninterrupted run (issue 41: resume after any interruption).

    python scripts/kill_resume.py --trials 3 --work /tmp/kill_resume

Makes a small synthetic capture (``texstream synth``), runs it once uninterrupted (the reference), then per
trial starts the same run into a fresh folder and kills it (SIGKILL) at a random point of a random stage (one the
reference ran for more than 2 s: once the stage's line appears, after a random fraction of the reference's time
for it; ``--kills`` times), runs it again to the end, and compares the files the stages wrote (meshes, bakes,
parameter maps, posed cameras; pixels and arrays, not file headers) with the reference's, and the held-out PSNR. Files that hold
timings (run.json, trace.json, the report, plots) are not compared. Prints which stage each kill hit (from
the log), the rerun's "resuming" lines, and one line per trial; exits 1 on any mismatch.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

COMPARED = ("mesh/mesh.ply", "atlas/mesh.obj", "atlas/bake.npz", "refine/mesh.obj", "refine/bake.npz",
            "refine/capture.json", "model/mesh.obj", "model/bake.npz")
"""files of the run folder compared byte for byte (with every parameter map model/*.exr)"""


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "texstream.pipelines.cli", *args]


def run_command(capture: Path, out: Path, a) -> list[str]:
    return cli("run", str(capture), "-o", str(out), "--iterations", str(a.iterations), "--model", a.model,
               "--no-progress")


def compared_files(out: Path) -> dict[str, bytes]:
    """Each compared file's content: an EXR's pixels (its header holds the time it was written), an npz's arrays,
    other files' bytes."""
    import numpy as np

    from texstream.capture.imageio import read_image

    names = [n for n in COMPARED if (out / n).is_file()] + sorted(
        str(p.relative_to(out)) for p in (out / "model").glob("*.exr"))
    content = {}
    for n in names:
        if n.endswith(".exr"):
            content[n] = read_image(out / n).tobytes()
        elif n.endswith(".npz"):
            with np.load(out / n, allow_pickle=False) as z:
                content[n] = b"".join(k.encode() + z[k].tobytes() for k in sorted(z.files))
        else:
            content[n] = (out / n).read_bytes()
    return content


def heldout(out: Path):
    return json.loads((out / "model" / "model.json").read_text()).get("heldout", {}).get("pooled_psnr_db")


def stage_seconds(ref: Path) -> dict[str, float]:
    """Seconds of each stage the reference ran (its run.json)."""
    stages = json.loads((ref / "run.json").read_text())["stages"]
    return {st["name"]: st["seconds"] for st in stages if st["status"] == "ran" and st["seconds"] > 2.0}


def killed_run(cmd: list[str], stage: str, after_s: float, log: Path) -> str:
    """Start ``cmd``; once its log shows ``stage`` starting, SIGKILL it ``after_s`` seconds later (unless it ended
    first); return the last progress line before the kill (what it was doing)."""
    with open(log, "a") as fh:
        start = log.stat().st_size
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
        while proc.poll() is None and not any(
                line.startswith(f"[{stage}] ") and "done in" not in line and "unchanged" not in line
                for line in log.read_bytes()[start:].decode(errors="replace").splitlines()):
            time.sleep(0.2)
        try:
            proc.wait(timeout=after_s)
            return "finished before the kill"
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
    lines = [line for line in log.read_bytes()[start:].decode(errors="replace").splitlines()
             if line.startswith("[") or line.startswith("  ")]
    return lines[-1].strip() if lines else "(no output yet)"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("kill_resume_work"))
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--kills", type=int, default=1, help="kills per trial before the run may finish")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scene", default="sphere")
    ap.add_argument("--scale", default="0.02")
    ap.add_argument("--photos", default="8")
    ap.add_argument("--image-size", default="24")
    ap.add_argument("--iterations", type=int, default=12,
                    help="fit iterations (checkpoints every 5: sync_every)")
    ap.add_argument("--model", default="diffuse")
    a = ap.parse_args()
    rng = random.Random(a.seed)
    a.work.mkdir(parents=True, exist_ok=True)
    capture = a.work / "capture"
    if not capture.is_dir():
        subprocess.run(cli("synth", a.scene, "--scale", a.scale, "--photos", a.photos, "--image-size",
                           a.image_size, "-o", str(capture)), check=True, capture_output=True)
    ref = a.work / "reference"
    if not (ref / "run.json").is_file():
        t0 = time.perf_counter()
        subprocess.run(run_command(capture, ref, a), check=True, capture_output=True)
        (a.work / "reference_seconds.txt").write_text(f"{time.perf_counter() - t0:.1f}\n")
    ref_s = float((a.work / "reference_seconds.txt").read_text())
    want, want_psnr, seconds = compared_files(ref), heldout(ref), stage_seconds(ref)
    print(f"reference: {ref_s:.1f} s, {len(want)} files compared, held-out PSNR {want_psnr}")
    failures = 0
    for trial in range(a.trials):
        out, log = a.work / f"trial_{trial}", a.work / f"trial_{trial}.log"
        for leftover in [out, *a.work.glob(f".trial_{trial}.*")]:  # an earlier invocation's trial folder
            shutil.rmtree(leftover, ignore_errors=True)
        log.write_text("")
        hits = []
        order = list(seconds)  # run.json lists the stages in the order they ran
        planned = sorted((rng.choice(order) for _ in range(a.kills)), key=order.index)
        for stage in planned:  # a stage the reference ran for seconds, then a random point inside it
            hits.append(f"{stage}: " + killed_run(run_command(capture, out, a), stage,
                                                  rng.uniform(0.05, 0.9) * seconds[stage], log))
        before = len(log.read_text().splitlines()) if log.exists() else 0
        with open(log, "a") as fh:
            done = subprocess.run(run_command(capture, out, a), stdout=fh, stderr=subprocess.STDOUT)
        rerun = log.read_text().splitlines()[before:]
        resumed = [line.strip() for line in rerun
                   if "resuming" in line or "was finished by an interrupted run" in line
                   or (line.startswith("[") and "unchanged since" in line)]
        got = compared_files(out) if done.returncode == 0 else {}
        differ = sorted(n for n in set(want) | set(got) if want.get(n) != got.get(n))
        same_psnr = done.returncode == 0 and heldout(out) == want_psnr
        ok = done.returncode == 0 and not differ and same_psnr
        failures += not ok
        print(f"trial {trial}: killed at {hits}; rerun exit {done.returncode}; "
              + ("result identical" if ok else f"MISMATCH: {differ or ''} psnr same {same_psnr}"))
        for line in resumed:
            print(f"    {line}")
    print(f"{a.trials - failures} of {a.trials} trials matched the uninterrupted run")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
