"""The large run of the fuzz and fault harness (issue 41; tests/fuzz_harness.py holds the property).

    PYTHONPATH=.pkg python scripts/fuzz.py --cases 2000 --faults 200 --signals 10 --seed 1 --out results.json

Runs every fixed case family once (every option at its out-of-range values, contradictory options, damaged
photos through the readers and ingest, damaged capture.json / transforms.json, COLMAP models, meshes and TOML
configs), then generated option and TOML cases (seeded) until ``--cases`` cases have run; then ``--faults``
injected faults (ENOSPC, EACCES, EROFS, Ctrl-C at the Nth write of synth, import, ingest, export, eval,
atlas, fit and run) and ``--signals`` runs of ``texstream run`` killed by SIGINT or SIGKILL at a random time.
Writes the counts as JSON: cases run, per family and per command, tracebacks, half-written outputs, silent
acceptances, message-form violations, the ones KNOWN_H1 / KNOWN_H4 / KNOWN_UNASSIGNED list apart (and the
entries no case failed on any more: ``known_now_passing``), and each failing case's
reproduction (command line, fault and seed). Exit status 1 when a violation outside the known lists was
found.
"""

from __future__ import annotations

import argparse
import collections
import json
import random
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import fuzz_cases as C  # noqa: E402 - the harness lives beside the tests
import fuzz_faults as F  # noqa: E402
import fuzz_harness as H  # noqa: E402


def kind_of(violation: str) -> str:
    for prefix, kind in (("traceback", "tracebacks"), ("half-written", "half_written"),
                         ("silent acceptance", "silent_acceptances")):
        if violation.startswith(prefix):
            return kind
    return "message_form"


class Tally:
    """Counts and failing cases."""

    def __init__(self) -> None:
        self.counts = collections.Counter()
        self.families = collections.Counter()
        self.commands = collections.Counter()
        self.known = collections.Counter()
        self.failures: list[dict] = []
        self.known_seen: set = set()
        self.known_failing: set = set()
        self.known_examples: dict = {}

    def add(self, case: C.Case, found: list[str], fired: bool = False) -> None:
        self.counts["faults" if case.family == "fault" else "cases"] += 1
        self.counts["faults_fired"] += fired
        self.families[case.family] += 1
        self.commands[case.key[0]] += 1
        match = H.known_entry(case.key)
        owner = match[0] if match else None
        if match:
            self.known_seen.add(match[1])
        for v in found:
            if owner:
                self.known[f"{owner}:{kind_of(v)}"] += 1
                self.known_failing.add(match[1])
                self.known_examples.setdefault(" ".join(match[1]), f"{case.reproduction()}: {v}"[:400])
                continue
            self.counts[kind_of(v)] += 1
        if found and not owner:
            self.failures.append({"family": case.family, "key": list(map(str, case.key)), "violations": found,
                                  "reproduction": case.reproduction()})

    def result(self) -> dict:
        return {"cases": self.counts["cases"], "faults": self.counts["faults"],
                "faults_fired": self.counts["faults_fired"],
                "tracebacks": self.counts["tracebacks"], "half_written": self.counts["half_written"],
                "silent_acceptances": self.counts["silent_acceptances"], "message_form": self.counts["message_form"],
                "per_family": dict(self.families), "per_command": dict(self.commands), "known": dict(self.known),
                "known_now_passing": sorted(map(list, self.known_seen - self.known_failing)),
                "known_examples": self.known_examples,
                "failures": self.failures}


def run_all(cases, tally: Tally, log, deadline: float) -> None:
    for case in cases:
        if time.monotonic() > deadline:
            log("time budget spent: stopping this family")
            return
        found, outcome = C.run_case(case)
        tally.add(case, found, fired=bool(case.fault) and outcome.fault_fired)
        if found and not H.known_owner(case.key):
            log(f"FAIL {case.family} {case.key}: {found[0][:200]}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=2000, help="cases to run (fixed families, then generated ones)")
    p.add_argument("--faults", type=int, default=200, help="injected faults")
    p.add_argument("--signals", type=int, default=10, help="runs of texstream run killed by SIGINT / SIGKILL")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default="fuzz_results.json")
    p.add_argument("--work", default=None, help="work folder (default: a temporary one)")
    p.add_argument("--minutes", type=float, default=60.0, help="stop starting new cases after this long")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    deadline = t0 + 60 * args.minutes
    root = Path(args.work or tempfile.mkdtemp(prefix="texstream-fuzz-"))
    root.mkdir(parents=True, exist_ok=True)
    log = lambda m: print(f"[{time.monotonic() - t0:7.1f} s] {m}", flush=True)  # noqa: E731
    tally = Tally()
    fx = H.option_fixtures(root / "opts")
    inputs = F.tiny_inputs(root / "tiny")
    log(f"work folder {root}")
    fixed = [("option_range", C.option_cases(fx)), ("contradiction", C.contradiction_cases(fx)),
             ("photo_reader", C.photo_reader_cases(root)), ("photo_ingest", C.ingest_cases(root)),
             ("capture_json", C.capture_reader_cases(root)), ("nerfstudio", C.nerfstudio_cases(root, 24, args.seed)),
             ("colmap", C.colmap_cases(root)), ("mesh", C.mesh_cases(root)), ("register", C.register_cases(root)),
             ("toml", C.toml_cases(root, inputs["capture"]))]
    for name, cases in fixed:
        run_all(cases, tally, log, deadline)
        log(f"{name}: {tally.families[name]} cases")
    rng = random.Random(args.seed)
    generated = 0
    while tally.counts["cases"] < args.cases and time.monotonic() < deadline:
        seed = rng.randrange(2 ** 32)
        case_rng = random.Random(seed)
        case = (C.generated_toml_case(root, case_rng, seed, inputs["capture"]) if generated % 10 == 9
                else C.generated_option_case(fx, case_rng, seed))
        run_all([case], tally, log, deadline)
        generated += 1
    log(f"generated: {generated} cases")
    per = {c: args.faults // len(F.FAULT_COMMANDS) for c in F.FAULT_COMMANDS}
    for c in F.FAULT_COMMANDS[: args.faults % len(F.FAULT_COMMANDS)]:
        per[c] += 1
    for command, n in per.items():
        run_all(F.fault_cases(inputs, root / "faults", {command: n}, args.seed), tally, log, deadline)
        log(f"faults in {command}: {n}")
    signals = F.signal_cases(inputs, root / "signals", args.signals, args.seed, log) if args.signals else []
    result = tally.result()
    result["signals"] = {"runs": len(signals), "violations": sum(len(s["violations"]) for s in signals),
                         "temporary_folders_left_by_sigkill": sum(s.get("temporary_left", 0) for s in signals),
                         "runs_detail": signals}
    for s in signals:
        for v in s["violations"]:
            result[kind_of(v)] += 1
        if s["violations"]:
            result["failures"].append({"family": "signal", "key": ["run", s["case"]], "violations": s["violations"],
                                       "reproduction": s["reproduction"]})
    result.update(seed=args.seed, seconds=round(time.monotonic() - t0, 1), work=str(root))
    Path(args.out).write_text(json.dumps(result, indent=2, default=str) + "\n")
    log(F.summary_line(result) + f" -> {args.out}")
    bad = result["tracebacks"] + result["half_written"] + result["silent_acceptances"] + result["message_form"]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
