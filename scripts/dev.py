#!/usr/bin/env python3
"""Set-up and run texstream from a clean clone with only Python (3.11 or 3.12) and pip.

    python3 scripts/dev.py demo   # make .venv, install, run the main job on the built-in synthetic set
    python3 scripts/dev.py test   # make .venv if needed, install (and chromium), run the test suite

Standard library only. The venv is reused; it is reinstalled when pyproject.toml changes.
Extra arguments after the verb go to ``texstream run`` or ``pytest``.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VENV = Path(os.environ.get("TEXSTREAM_VENV", ROOT / ".venv"))
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / "python"


def ensure_env() -> None:
    if sys.version_info[:2] not in ((3, 11), (3, 12)):
        sys.exit(f"texstream needs Python 3.11 or 3.12, this is {sys.version.split()[0]}; "
                 "run this script with python3.11 or python3.12")
    if not PY.exists():
        print(f"[dev] creating virtual environment {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    stamp = VENV / ".texstream-installed"
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if not stamp.exists() or stamp.read_text().strip() != want:
        print("[dev] installing texstream and its dependencies (first run takes a few minutes)", flush=True)
        subprocess.check_call([str(PY), "-m", "pip", "install", "-q", "--upgrade", "pip"])
        # no -q here: pip prints a line per package it collects (and a download bar on a terminal), so a
        # first run of several minutes shows progress; its version-check and script-location notices stay off
        print(f"[dev] pip install -e {ROOT}[test]", flush=True)
        subprocess.check_call([str(PY), "-m", "pip", "install", "--disable-pip-version-check",
                               "--no-warn-script-location", "-e", f"{ROOT}[test]"])
        print("[dev] installed", flush=True)
        stamp.write_text(want)


def apt_install(package: str, missing: str, why: str, without: str) -> None:
    """Install a Debian package for a test (root only; elsewhere say what to run and what ``without`` it)."""
    if hasattr(os, "geteuid") and os.geteuid() != 0:
        print(f"[dev] {missing} is missing and this is not root: {without} (sudo apt-get install {package})", flush=True)
        return
    print(f"[dev] installing {package} (Debian package) for {why}", flush=True)
    subprocess.call(["apt-get", "update", "-qq"])
    subprocess.call(["apt-get", "install", "-y", "-qq", "--no-install-recommends", package],
                    env=dict(os.environ, DEBIAN_FRONTEND="noninteractive"))


def ensure_browser() -> None:
    """Headless Chromium for the report viewer's browser test (Debian's package; root installs it)."""
    import shutil

    if shutil.which("chromium") or shutil.which("chromium-browser") or not shutil.which("apt-get"):
        return
    apt_install("chromium", "chromium", "the report viewer's browser test", "the viewer's browser test will skip")


def ensure_llvm() -> None:
    """libLLVM 16 or newer for Mitsuba 3's CPU backend (Dr.Jit's LLVM variant; the peers' test): Debian 12's
    default LLVM (14, 15) cannot compile its kernels ("Cannot select fminimum"), so its libllvm19 is
    installed (root only). benchmarks/peers/peer_mitsuba.py points Dr.Jit at the newest libLLVM found."""
    import glob
    import re
    import shutil

    versions = [int(m.group(1)) for p in glob.glob("/usr/lib/*-linux-gnu/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*")
                if (m := re.search(r"LLVM[-.](?:so\.)?(\d+)", p))]
    if (versions and max(versions) >= 16) or not shutil.which("apt-get"):
        return
    apt_install("libllvm19", "libLLVM >= 16", "Mitsuba's CPU backend (the peers' test)",
                "the Mitsuba peer's test will fail")


def main() -> int:
    verb = sys.argv[1] if len(sys.argv) > 1 else "help"
    extra = sys.argv[2:]
    if verb not in ("demo", "test"):
        print(__doc__)
        return 2
    ensure_env()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if verb == "demo":
        cmd = [str(BIN / "texstream"), "run", *(extra or ["--out", str(ROOT / "out" / "demo")])]
    else:
        ensure_browser()
        ensure_llvm()
        # two workers: Warp's CPU launches use one core each (pytest-xdist)
        # the slowest tests listed, so a CI log shows where its time goes
        cmd = [str(PY), "-m", "pytest", "-q", "-rs", "--durations=20", *(extra or ["-n", "2"])]
    print("[dev] " + " ".join(cmd), flush=True)
    return subprocess.call(cmd, cwd=ROOT, env=env)


if __name__ == "__main__":
    sys.exit(main())
