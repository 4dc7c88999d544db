"""One writer per output (issue 41, core/lock.py): a second command on an output another process is writing
fails at once with one line naming that process and the fix; a lock left by a killed process is taken over
with one line; the lock is released on every exit and never left inside the output."""

from __future__ import annotations

import datetime
import json
import os
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest

from texstream.core.lock import FOREIGN_STALE_AGE_S, OutputLocked, lock_path, output_lock
from texstream.pipelines.cli import main


@pytest.fixture(autouse=True)
def _no_debug_env(monkeypatch):
    monkeypatch.delenv("TEXSTREAM_DEBUG", raising=False)


@pytest.fixture
def photos(tmp_path):
    """Three 48x40 noise photos: enough for ``texstream ingest`` (which needs no GPU, Warp or COLMAP), the
    cheapest command that writes an output folder."""
    import cv2

    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(folder / f"p{i}.png"), (rng.random((40, 48, 3)) * 255).astype(np.uint8))
    return folder


def _holder(out):
    """Another process holding the lock of ``out`` until killed; returns it once it holds the lock."""
    code = ("import sys, time; from texstream.core.lock import output_lock\n"
            f"with output_lock({str(out)!r}, 'texstream ingest photos -o out (the holder)'):\n"
            "    print('held', flush=True); time.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid  # reaped: no process has it (pids are not reused this soon)


def _holds_text(path) -> bool:
    try:
        return '"pid"' in path.read_text()
    except FileNotFoundError:
        return False


def _write_lock(out, **info):
    now = datetime.datetime.now(datetime.timezone.utc)
    info = {"pid": os.getpid(), "host": socket.gethostname(), "command": "texstream fit ... -o model",
            "started": now.strftime("%Y-%m-%d %H:%M:%S UTC"), "started_iso": now.isoformat(), **info}
    lock_path(out).parent.mkdir(parents=True, exist_ok=True)
    lock_path(out).write_text(json.dumps(info))


def test_a_second_command_fails_at_once_naming_the_other_then_takes_over_after_kill_9(photos, tmp_path, capsys):
    out = tmp_path / "capture"
    holder = _holder(out)
    try:
        assert main(["ingest", str(photos), "-o", str(out)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
        assert f"pid {holder.pid} on host {socket.gethostname()}" in err[0]
        assert "texstream ingest photos -o out (the holder)" in err[0] and "started 20" in err[0]
        assert "Fix: wait for it to end" in err[0] and str(lock_path(out)) in err[0]
        assert not out.exists()  # refused before any work
        # a command writing inside the held folder (a stage under a running `texstream run`) is refused too
        assert main(["ingest", str(photos), "-o", str(out / "inner")]) == 1
        err = capsys.readouterr().err
        assert "a folder above this output" in err and f"pid {holder.pid}" in err
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert lock_path(out).is_file()  # a killed process leaves its lock file
    assert main(["ingest", str(photos), "-o", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    took = [line for line in err if "took over the stale lock" in line]
    assert len(took) == 1 and f"pid {holder.pid} is no longer running" in took[0]
    assert (out / "capture.json").is_file()
    assert not lock_path(out).exists() and not list(out.rglob("*.lock"))  # released, never inside the output


def test_a_dead_pid_written_by_hand_is_taken_over_with_one_line(tmp_path):
    out = tmp_path / "model"
    pid = _dead_pid()
    _write_lock(out, pid=pid)
    lines = []
    with output_lock(out, "texstream fit", log=lines.append) as path:
        assert json.loads(path.read_text())["pid"] == os.getpid()
    assert len(lines) == 1 and f"pid {pid} is no longer running" in lines[0] and str(lock_path(out)) in lines[0]
    assert not lock_path(out).exists()


def test_another_host_s_lock_holds_until_it_is_old(tmp_path):
    """This host cannot check another host's pids (and a network file system may not share flock): its lock
    holds for FOREIGN_STALE_AGE_S, then is taken over."""
    out = tmp_path / "model"
    _write_lock(out, host="another-host", pid=1)
    with pytest.raises(OutputLocked, match="pid 1 on host another-host"):
        with output_lock(out, "texstream fit", log=print):
            pass
    old = datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(seconds=FOREIGN_STALE_AGE_S + 3600)
    _write_lock(out, host="another-host", pid=1, started_iso=old.isoformat())
    lines = []
    with output_lock(out, "texstream fit", log=lines.append):
        pass
    assert len(lines) == 1 and "another-host" in lines[0] and "older than" in lines[0]


@pytest.mark.parametrize("error", [KeyboardInterrupt, ValueError])
def test_the_lock_is_released_on_ctrl_c_and_errors(tmp_path, error):
    out = tmp_path / "model"
    with pytest.raises(error):
        with output_lock(out, "texstream fit", log=print):
            assert lock_path(out).is_file()
            raise error()
    assert not lock_path(out).exists()
    with output_lock(out, "texstream fit", log=print):  # free again, with no takeover line
        pass


def test_a_failing_command_leaves_no_lock(tmp_path, capsys):
    out = tmp_path / "model"
    assert main(["fit", str(tmp_path / "missing"), "--mesh", str(tmp_path / "x"), "-o", str(out)]) == 1
    assert "missing" in capsys.readouterr().err
    assert not lock_path(out).exists() and not out.exists()


def test_two_locks_in_one_process_exclude_each_other(tmp_path):
    """flock is per open file: a second lock of the same output in one process is refused too (the tests and
    the Python API take locks in one process)."""
    out = tmp_path / "model"
    with output_lock(out, "first", log=print):
        with pytest.raises(OutputLocked, match=f"pid {os.getpid()}"):
            with output_lock(out, "second", log=print):
                pass
    assert not lock_path(out).exists()


def test_every_command_that_writes_is_refused_on_a_held_output(tmp_path, capsys):
    """Each command's output (cmd_*.output_target) is locked before its work: with another process holding
    it, every command fails with the holder's line and writes nothing."""
    out = tmp_path / "out"
    t = str(tmp_path)
    commands = {
        "run": ["run", t], "ingest": ["ingest", t], "calibrate": ["calibrate", t], "register": ["register", t],
        "lights": ["lights", t], "chart": ["chart", t], "import": ["import", "colmap", t], "synth": ["synth", "sphere"],
        "mesh": ["mesh", t], "atlas": ["atlas", t], "refine": ["refine", t, t], "fit": ["fit", t, "--mesh", t],
        "export": ["export", t], "eval": ["eval", t, t], "preview": ["preview", t], "fpcheck": ["fpcheck"],
        "stiffcheck": ["stiffcheck"], "relight": ["relight", t, "--env", t, "--capture", t],
    }
    holder = _holder(out)
    try:
        for name, argv in commands.items():
            assert main([*argv, "-o", str(out)]) == 1, name
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and f"another texstream command is writing this output: pid {holder.pid}" in err[0], \
                (name, err)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert not out.exists()
    from texstream.pipelines.cli import SUBCOMMANDS

    assert set(commands) == set(SUBCOMMANDS)  # every subcommand writes an output, and each was tried


def test_ctrl_c_of_a_running_command_releases_its_lock(tmp_path):
    """A real SIGINT to the console script while it holds the lock: exit 130, no lock file, no output."""
    import time

    out = tmp_path / "cap"
    proc = subprocess.Popen([sys.executable, "-m", "texstream.pipelines.cli", "synth", "sphere", "-o", str(out),
                             "--scale", "0.05"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    while proc.poll() is None and not _holds_text(lock_path(out)):
        time.sleep(0.01)  # until the command holds its lock
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    if out.exists():
        # Python runs a signal's handler between bytecodes, so on a loaded box the tiny capture can be written whole
        # before it runs (seen twice on CI: exit 0, or the handler inside the lock's removal, the lock file left).
        # What must hold then: the output whole, and a lock left behind stale, which the next command takes over
        from texstream.core.lock import output_lock

        assert (out / "capture.json").is_file()
        with output_lock(out, "the next command", log=lambda line: None):
            pass
        assert not lock_path(out).exists()
        return
    assert not lock_path(out).exists()
    # 130 is the CLI's status; under pytest the process has also ended by SIGINT itself (-2) after printing
    # its line and releasing the lock (2 runs in 8 on the 2-core dev box, never outside pytest; not traced)
    assert proc.returncode in (130, -signal.SIGINT) and "interrupted" in err, (proc.returncode, err)


def test_leftovers_of_a_killed_command_go_when_the_lock_is_taken(tmp_path):
    """kill -9 during an atomic write leaves its temporary folder: the next command on that output (holding its
    lock, so nobody else writes there) removes it, and what it left inside a run's folder, but not the output."""
    from texstream.core.lock import output_lock

    out = tmp_path / "run"
    (out / "model").mkdir(parents=True)
    (out / "model" / "keep.json").write_text("{}")
    left = [tmp_path / ".run.abc123.partial", out / ".model.x1y2.partial", out / ".run_config.toml.q9.tmp",
            tmp_path / ".run.old.123.456"]
    for q in left[:2] + left[3:]:
        q.mkdir()
    left[2].write_text("half")
    said = []
    with output_lock(out, "texstream run", said.append):
        assert not any(q.exists() for q in left)
    assert (out / "model" / "keep.json").exists() and len(said) == 1 and "removed 4" in said[0]
