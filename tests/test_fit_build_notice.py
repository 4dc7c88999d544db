"""A fit says when it compiles its Warp kernels (a cold kernel cache), once, and not after a fit succeeded."""

from __future__ import annotations

import warp as wp

from texstream.fit.kernels import build_notice


def test_the_notice_shows_on_a_cold_cache_only(tmp_path, monkeypatch):
    wp.init()
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    assert build_notice.kernels_cold("cpu")
    assert not build_notice.kernels_cold("cpu")  # once per process and device
    line = build_notice.kernel_build_line("cpu", "12 Warp modules at once on 2 threads")
    assert "compiling its Warp kernels" in line and str(tmp_path) in line and "12 Warp modules at once" in line
    build_notice.mark_kernels_built("cpu")
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    assert not build_notice.kernels_cold("cpu")  # warm: nothing to build or say


def test_the_key_follows_the_kernel_sources():
    key = build_notice.kernel_sources_key()
    assert len(key) == 16 and key == build_notice.kernel_sources_key()


def test_each_group_of_models_has_its_own_marker(tmp_path, monkeypatch):
    """A run of real photos first (the radiance models) leaves the default run's models cold: the README demo
    after it still builds its own modules ahead (fit/stages/prewarm.py KERNEL_GROUPS)."""
    wp.init()
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    build_notice.mark_kernels_built("cpu", "fp32", "unknown_light")
    assert not build_notice.kernels_cold("cpu", "fp32", "unknown_light")
    assert build_notice.kernels_cold("cpu", "fp32", "default") and build_notice.kernels_cold("cpu", "fp32", None)
