"""Issue 41's fuzz harness in CI, faults: a full disk (ENOSPC), a read-only or forbidden output (EROFS,
EACCES) and Ctrl-C at writes of synth, import and ingest (injected in-process at the Nth write, as SQLite's
test harness injects I/O errors: no root and no full disk needed), and SIGINT / SIGKILL sent to a real
``texstream synth`` process. The property: one error line naming the path and the fix (or the interrupted
line), the previous output untouched, nothing half-written, and the same command afterwards finishes.

scripts/fuzz.py injects faults at every write of these and of export, eval, atlas, fit and run, and kills
``texstream run`` at random times (checking that a rerun takes no half-done stage for finished).
"""

from __future__ import annotations

import signal

import pytest

import fuzz_cases as C
import fuzz_faults as F
import fuzz_harness as H


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("fault_inputs")
    from texstream.pipelines import cli

    cap = root / "sphere"
    with H._captured_fds():
        assert cli.main(["synth", "sphere", "-o", str(cap), *C.SYNTH_TINY]) == 0
    import shutil

    ns = root / "ns"
    shutil.copytree(cap, ns, ignore=shutil.ignore_patterns("ground_truth", "previews"))
    (ns / "capture.json").rename(ns / "transforms.json")
    import fuzz_damage as D

    D.good_photos(root / "photos", n=4)
    return {"capture": cap, "ns": ns, "photos": root / "photos", "model": root / "no_model"}


@pytest.mark.parametrize("command,n_faults", [("synth", 8), ("import", 8), ("ingest", 8)])
def test_faults_at_writes(inputs, tmp_path, command, n_faults):
    """Faults at writes drawn from the command's clean run (seeded): each fails in one line naming the path
    (ENOSPC / EACCES / EROFS) or stops with the interrupted line (Ctrl-C), leaving the previous output as it
    was and no temporary file (except at the renames into place, which can leave the temporary folder and lose
    the previous output: KNOWN_H1, core/outputs.py)."""
    cases = list(F.fault_cases(inputs, tmp_path, {command: n_faults}, seed=41))
    assert len(cases) == n_faults and all(c.family == "fault" for c in cases), [c.reproduction() for c in cases]
    bad, fired = [], 0
    for case in cases:
        found, outcome = C.run_case(case)
        fired += outcome.fault_fired
        if found and not H.known_owner(case.key):
            bad.append(f"{case.reproduction()}: {found}")
    assert fired == n_faults, "every drawn write happens in the faulted run too"
    assert bad == []  # each case also checked that the clean run's output, in place before it, is unchanged


def complete(out) -> bool:
    """A synth output with its capture, every photo it lists and its ground truth."""
    from texstream.capture.capture_json import read_capture

    if not ((out / "capture.json").is_file() and (out / "ground_truth" / "bake.npz").is_file()):
        return False
    cap = read_capture(out)
    return len(cap.frames) == 8 and all(cap.image_path(f).is_file() for f in cap.frames)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL])
def test_signal_during_synth(inputs, tmp_path, sig):
    """``texstream synth`` sent SIGINT or SIGKILL midway: no output folder (or a complete one), SIGINT exits 130
    with the one interrupted line, and the same command then finishes."""
    out = tmp_path / "synth_out"
    argv = ["synth", "sphere", "-o", str(out), *C.SYNTH_TINY]
    # the signal comes while synth writes its output (its temporary folder exists), not during its imports
    o = H.run_subprocess(argv, tmp_path, sig=sig, signal_after=0.05,
                         signal_when=lambda: any(tmp_path.glob(".synth_out.*.partial")))
    assert "Traceback" not in o.stderr, o.stderr
    if o.rc == 0:  # it finished before the signal (a fast machine): nothing to check but the output
        assert complete(out)
        return
    # SIGINT: 130 from the CLI's handler, or -2 where the process ends by the signal after that handler ran
    # (seen here about one run in three, with the handler's line printed: the exit status differs, not the output)
    assert o.rc in ((130, -signal.SIGINT) if sig == signal.SIGINT else (-signal.SIGKILL,)), (o.rc, o.stderr)
    if sig == signal.SIGINT:
        assert o.stderr_lines == ["texstream: interrupted; no output was left half-written"], o.stderr
    # killed before the rename into place: no output; after it (during the process's exit): a complete one
    assert not out.exists() or complete(out), "an interrupted synth left a half-written output folder"
    again = H.run_cli(argv)
    assert again.rc == 0, again.stderr
    assert complete(out)
    # a temporary folder the interrupted write left (always after SIGKILL; after SIGINT when the process ended by
    # the signal before its clean-up, one CI run in a few) is removed by the next command on the output, which
    # holds its lock (core/lock.py remove_leftovers)
    assert H.leftovers(tmp_path) == []
