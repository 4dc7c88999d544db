"""Fault targets of the fuzz harness: real commands on a tiny synthetic capture, each run once clean (its
writes counted, its output kept as the one a faulted run must leave intact), then rerun with a fault at
one of its writes; and ``texstream run`` killed by a signal at a random time, then rerun.
"""

from __future__ import annotations

import json
import random
import shutil
import time
from pathlib import Path
from typing import Iterator

import fuzz_cases as C
import fuzz_damage as D
import fuzz_harness as H


def tiny_inputs(root: Path) -> dict[str, Path]:
    """A tiny synthetic sphere capture (and its nerfstudio copy), a model fitted to it, photos to ingest."""
    from texstream.pipelines import cli

    inputs = {"capture": root / "sphere", "model": root / "model", "photos": root / "photos", "ns": root / "ns"}
    if not (inputs["capture"] / "capture.json").is_file():
        with H._captured_fds():
            cli.main(["synth", "sphere", "-o", str(inputs["capture"]), *C.SYNTH_TINY])
    if not (inputs["model"] / "model.json").is_file():
        with H._captured_fds():
            cli.main(["fit", str(inputs["capture"]), "--mesh", str(inputs["capture"] / "ground_truth"), "-o",
                      str(inputs["model"]), "--model", "diffuse", "--max-iterations", "2", "--renders", "1"])
    if not inputs["ns"].is_dir():
        shutil.copytree(inputs["capture"], inputs["ns"], ignore=shutil.ignore_patterns("ground_truth", "previews"))
        (inputs["ns"] / "capture.json").rename(inputs["ns"] / "transforms.json")
    if not inputs["photos"].is_dir():
        D.good_photos(inputs["photos"], n=4)
    return inputs


FAULT_COMMANDS = ("synth", "import", "ingest", "export", "eval", "atlas", "fit", "run")
"""the commands faults are injected into, cheapest first"""


def fault_target(command: str, inputs: dict, root: Path) -> tuple[list[str], Path]:
    """(command line, output) of one fault target; the output lies in ``root`` (the folder faults count)."""
    cap, model = inputs["capture"], inputs["model"]
    out = root / f"{command}_out"
    argv = {"synth": ["synth", "sphere", "-o", str(out), *C.SYNTH_TINY],
            "import": ["import", "nerfstudio", str(inputs["ns"]), "-o", str(out)],
            "ingest": ["ingest", str(inputs["photos"]), "-o", str(out), "--auto-masks", "none"],
            "export": ["export", str(model), "-o", str(out)],
            "eval": ["eval", str(model), str(cap), "-o", str(out / "eval.json")],
            "atlas": ["atlas", str(cap / "ground_truth" / "mesh.obj"), "-o", str(out), "--force"],
            "fit": ["fit", str(cap), "--mesh", str(cap / "ground_truth"), "-o", str(out), "--model", "diffuse",
                    "--max-iterations", "2", "--renders", "1"],
            "run": ["run", str(cap), "-o", str(out), "--model", "diffuse", "--iterations", "2",
                    "--mesh-file", str(cap / "ground_truth"), "--no-progress"]}[command]
    return argv, out


def fault_cases(inputs: dict, root: Path, per_command: dict[str, int], seed: int) -> Iterator[C.Case]:
    """Per command, ``per_command[command]`` faults at writes drawn from its clean run's writes (every write
    once before any twice), kinds in turn; each case's folder starts with the clean run's output in place
    (``run`` starts from none: it keeps finished stages, and a rerun is judged instead)."""
    rng = random.Random(seed)
    for command, n_faults in per_command.items():
        if n_faults <= 0:
            continue
        folder = root / command
        folder.mkdir(parents=True, exist_ok=True)
        argv, out = fault_target(command, inputs, folder)
        n_writes, clean = H.count_writes(argv, folder)
        if command != "run" and clean.rc == 0:  # the faulted runs find the output in place: count those writes
            n_writes, clean = H.count_writes(argv, folder)
        if clean.rc != 0 or n_writes == 0:
            yield C.Case("fault_setup", (command, "clean run"), argv, must_fail=False,
                         valid=lambda clean=clean: f"the clean run failed: {clean.stderr.strip()[-300:]}")
            continue
        points = [n for _ in range(n_faults // n_writes + 1) for n in rng.sample(range(1, n_writes + 1), n_writes)]
        kinds = list(H.FAULTS)
        reference = run_stage_folders(out)
        for i, at in enumerate(points[:n_faults]):
            kind = kinds[(i + rng.randrange(len(kinds))) % len(kinds)]
            if command == "run":  # a run keeps the stages it finished: judged by what a rerun makes of them
                yield C.Case("fault", (command, kind), argv, root=folder, fault=(at, kind), seed=seed,
                             pre=lambda out=out: shutil.rmtree(out, ignore_errors=True),
                             post=lambda argv=argv, out=out, ref=reference: rerun_check(argv, out, ref))
            else:
                yield C.Case("fault", (command, kind), argv, root=folder, outputs=(out,), fault=(at, kind), seed=seed)


def run_stage_folders(out: Path) -> dict[str, set[str] | None]:
    """Per stage folder of a run's output: its files (names), None when absent."""
    folders = {"capture": out / "capture", "model": out / "model", "export": out / "export", "report": out / "report"}
    return {k: (None if not p.is_dir() else {str(q.relative_to(p)) for q in p.rglob("*") if q.is_file()})
            for k, p in folders.items()}


def rerun_check(argv: list[str], out: Path, reference: dict, subprocess_cwd: Path | None = None) -> list[str]:
    """After an interrupted run: every stage folder present must be complete (the reference run's files, the
    stamp aside), and the same command rerun must finish with the reference's files."""
    problems = []
    for name, files in run_stage_folders(out).items():
        ref = reference.get(name)
        if files is not None and ref is not None and (files - {H_STAMP}) != (ref - {H_STAMP}):
            missing = sorted((ref - files) - {H_STAMP})[:3]
            problems.append(f"half-written: {name}/ left without {missing or 'nothing'} (extra "
                            f"{sorted(files - ref - {H_STAMP})[:3]})")
    again = H.run_subprocess(argv, subprocess_cwd) if subprocess_cwd else H.run_cli(argv)
    if again.rc != 0:
        problems.append(f"the rerun failed (exit {again.rc}): {again.stderr.strip()[-300:]}")
        return problems
    for name, files in run_stage_folders(out).items():
        ref = reference.get(name)
        if (files is None) != (ref is None) or (files is not None and (files - {H_STAMP}) != (ref - {H_STAMP})):
            problems.append(f"half-written: after the rerun {name}/ differs from an uninterrupted run's")
    return problems


H_STAMP = ".texstream_stage.json"


def signal_cases(inputs: dict, root: Path, count: int, seed: int, log=print) -> list[dict]:
    """``texstream run`` on the tiny capture, sent SIGINT or SIGKILL at a random time of its clean duration,
    then checked (nothing half-written) and rerun (it finishes with an uninterrupted run's files)."""
    import signal

    rng = random.Random(seed)
    root.mkdir(parents=True, exist_ok=True)
    ref_out = root / "signal_reference"
    argv, _ = fault_target("run", inputs, root)
    argv = [a if a != str(root / "run_out") else str(ref_out) for a in argv]
    t0 = time.perf_counter()
    ref = H.run_subprocess(argv, root)
    duration = time.perf_counter() - t0
    if ref.rc != 0:
        return [{"case": "reference run", "violations": [f"the clean run failed: {ref.stderr.strip()[-300:]}"],
                 "reproduction": " ".join(argv)}]
    reference = run_stage_folders(ref_out)
    results = []
    for i in range(count):
        out = root / f"signal_{i}"
        shutil.rmtree(out, ignore_errors=True)
        run_argv = [a if a != str(ref_out) else str(out) for a in argv]
        sig = rng.choice([signal.SIGINT, signal.SIGKILL])
        after = rng.uniform(0.5, duration)
        o = H.run_subprocess(run_argv, root, signal_after=after, sig=sig)
        problems = []
        if o.rc not in (0, -signal.SIGKILL, 130, -signal.SIGINT) or "Traceback (most recent call last)" in o.stderr:
            problems.append(f"exit {o.rc} after {sig.name}: {o.stderr.strip()[-300:]}")
        if o.rc == 130 and not o.stderr.strip().splitlines()[-1].startswith("texstream: interrupted"):
            problems.append(f"SIGINT gave more than the one interrupted line: {o.stderr.strip()[-300:]}")
        litter = H.leftovers(out)
        if litter and sig != signal.SIGKILL:  # after SIGKILL nothing can remove them: litter, not an output
            problems.append(f"half-written: temporary files left: {litter[:3]}")
        problems += rerun_check(run_argv, out, reference, subprocess_cwd=root)
        results.append({"case": f"{sig.name} at {after:.2f} s of {duration:.1f} s", "exit": o.rc,
                        "violations": problems, "temporary_left": len(litter),
                        "reproduction": " ".join(run_argv) + f"  # {sig.name} after {after:.2f} s"})
        log(f"signal {i}: {results[-1]['case']}: exit {o.rc}, {len(problems)} violation(s)")
    return results


def summary_line(results: dict) -> str:
    return json.dumps({k: results[k] for k in ("cases", "faults", "faults_fired", "tracebacks", "half_written",
                                                "silent_acceptances", "message_form")})
