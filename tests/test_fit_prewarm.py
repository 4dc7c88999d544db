"""A cold fit builds the default run's Warp modules up front (fit/stages/prewarm.py), and the run after it builds
nothing more: every module a tiny default ``texstream run`` launches is on the prewarm's list, with the hash
the prewarm built (a generic kernel's overload added at a launch would change it: fit/kernels/overloads.py)."""

from __future__ import annotations

import dataclasses

import pytest
import warp as wp

from texstream.core.progress import reporting
from texstream.fit.kernels import build_notice
from texstream.fit.stages import prewarm
from texstream.pipelines.run import RunConfig, run_pipeline

from conftest import tiny_sphere_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return tiny_sphere_capture(tmp_path_factory.mktemp("prewarm"), photos=16)


def record_loads(monkeypatch) -> list:
    """(module name, hash, device, block size) of every module load from now on (a module loaded again with
    another hash was rehashed: an overload or a kernel added after its build)."""
    loads = []
    load = wp.Module.load

    def recorded(self, device, block_dim=None, *args, **kwargs):
        exec_ = load(self, device, block_dim, *args, **kwargs)
        loads.append((self.name, exec_.module_hash.hex(), str(exec_.device), exec_.block_dim))
        return exec_

    monkeypatch.setattr(wp.Module, "load", recorded)
    return loads


def test_a_default_run_after_the_prewarm_builds_no_module(capture, device, tmp_path, monkeypatch):
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    monkeypatch.setattr(build_notice, "_marker", lambda dev: tmp_path / "absent.warm")  # a cold cache, as said
    loads = record_loads(monkeypatch)
    lines = []
    with reporting(lines.append):
        prewarm.build_kernels_if_cold("fit", device, "lafortune")
    built = set(loads)
    assert len(built) == len(prewarm.default_run_modules(device)), built
    assert "compiling its Warp kernels" in lines[0] and "Warp modules at once" in lines[0], lines
    assert "fit: kernels built: " in lines[1] and len(lines) == 2, lines
    loads.clear()

    cfg = RunConfig(device=device, mesh_file=str(capture / "ground_truth"))  # the README run's options, ...
    cfg.fit = dataclasses.replace(cfg.fit, renders=1, fit=dataclasses.replace(cfg.fit.fit, max_iterations=3))  # short
    summary = run_pipeline(capture, tmp_path / "out", cfg, log=lambda m: None)
    assert summary["fit"]["selection"]["validation"].keys() >= {"lafortune", "diffuse"}  # the default run's models
    launched = {load for load in loads if load[2] == device}
    assert launched, "the run loaded no module: the recording missed its launches"
    assert launched <= built, f"launched but not prewarmed (or rehashed after it): {sorted(launched - built)}"


def test_a_warm_cache_builds_nothing_ahead(tmp_path, monkeypatch):
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    monkeypatch.setattr(build_notice, "_marker", lambda dev: tmp_path / "present.warm")
    (tmp_path / "present.warm").touch()
    loads = record_loads(monkeypatch)
    lines = []
    with reporting(lines.append):
        prewarm.build_kernels_if_cold("fit", "cpu", "lafortune")
    assert loads == [] and lines == []
