"""A fit says when it compiles its Warp kernels (a cold kernel cache), once, and not after a fit succeeded."""

from __future__ import annotations

import warp as wp

from texstream.core.progress import reporting
from texstream.fit.kernels import build_notice


def test_the_notice_shows_on_a_cold_cache_only(tmp_path, monkeypatch):
    wp.init()
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    lines = []
    with reporting(lines.append):
        build_notice.announce_kernel_build("fit", "cpu")
        build_notice.announce_kernel_build("fit", "cpu")  # once per process and device
    assert len(lines) == 1 and "compiling its Warp kernels" in lines[0] and str(tmp_path) in lines[0]
    build_notice.mark_kernels_built("cpu")
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    with reporting(lines.append):
        build_notice.announce_kernel_build("fit", "cpu")
    assert len(lines) == 1  # warm: nothing more said


def test_the_key_follows_the_kernel_sources():
    key = build_notice.kernel_sources_key()
    assert len(key) == 16 and key == build_notice.kernel_sources_key()
