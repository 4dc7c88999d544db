"""A cold fit builds the default run's Warp modules up front (fit/stages/prewarm.py), and the run after it builds
nothing more: every module a tiny default ``texstream run`` launches is on the prewarm's list, with the hash
the prewarm built (a generic kernel's overload added at a launch would change it: fit/kernels/overloads.py)."""

from __future__ import annotations

import dataclasses

import pytest

from texstream.core.progress import reporting
from texstream.fit.kernels import build_notice
from texstream.fit.stages import prewarm
from texstream.pipelines.run import RunConfig, run_pipeline

from conftest import tiny_sphere_capture
from kernel_loads import record_loads


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return tiny_sphere_capture(tmp_path_factory.mktemp("prewarm"), photos=16)


def test_a_default_run_after_the_prewarm_builds_no_module(capture, device, tmp_path, monkeypatch):
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    # a cold cache, as said
    monkeypatch.setattr(build_notice, "_marker", lambda *_, **__: tmp_path / "absent.warm")
    loads = record_loads(monkeypatch.setattr)
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
    monkeypatch.setattr(build_notice, "_marker", lambda *_, **__: tmp_path / "present.warm")
    (tmp_path / "present.warm").touch()
    loads = record_loads(monkeypatch.setattr)
    lines = []
    with reporting(lines.append):
        prewarm.build_kernels_if_cold("fit", "cpu", "lafortune")
    assert loads == [] and lines == []


FLOAT64_FIT = r"""
import json, sys
from pathlib import Path

import warp as wp

wp.config.quiet = True
from texstream.fit.kernels import build_notice
from texstream.fit.kernels.overloads import declared_precisions
from texstream.fit.models.materials import MaterialConfig
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.stages.stage import FitStageConfig, fit_stage
from texstream.fit.stream.config import StreamConfig

capture, out, device, cold = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], sys.argv[4] == "cold"
build_notice._marker = lambda *_, **__: out.parent / ("absent.warm" if cold else "present.warm")
(out.parent / "present.warm").touch()
sys.path.insert(0, "tests")
from kernel_loads import record_loads

loads = record_loads()
cfg = FitStageConfig(device=device, renders=0, traced_polish=0, checkpoint=False, materials=MaterialConfig(mode="off"),
                     fit=FitConfig(model="lafortune", max_iterations=2,
                                   stream=StreamConfig(accumulate="fp64", shadow_map_size=48)))
import texstream.fit.stages.prewarm as prewarm
built = []
build = prewarm.build_kernels_if_cold

def recorded_build(*args, **kwargs):
    n = len(loads)
    build(*args, **kwargs)
    built.extend(loads[n:])

import texstream.fit.stages.stage as stage
stage.build_kernels_if_cold = recorded_build
fit_stage(capture, capture / "ground_truth", out, cfg, progress=False)
print(json.dumps({"loads": loads, "built": built, "precisions": declared_precisions()}))
"""


def test_a_float64_fit_declares_its_overloads_before_any_build_or_launch(capture, device, tmp_path):
    """A fit whose passes accumulate in float64 declares every generic kernel's float64 overloads before its prewarm
    and its first launch (fit/kernels/overloads.py ``declare_precision``): no module is loaded under two hashes
    (a launch that added an overload would rehash it and compile again), and on a cold cache (CUDA) every module the
    fit launches was built by its prewarm. In a child process: the declaration is for the rest of a process, and
    this worker's later tests would compile every module again. The CPU case skips the prewarm (the default
    modules with their float64 overloads take about 45 s of CI's two cores to build; measured 42.6 s against 28.9
    s for float32 alone) and checks the launches alone: about 30 s on a cold kernel cache, as CI's is (the fit's
    modules with both precisions' overloads, which no other test builds), 4 s warm."""
    import json
    import subprocess
    import sys

    from conftest import ROOT

    cold = str(device).startswith("cuda")
    run = subprocess.run([sys.executable, "-c", FLOAT64_FIT, str(capture), str(tmp_path / "model"), device,
                          "cold" if cold else "warm"], capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["precisions"] == ["fp32", "fp64"]
    hashes = {}
    for name, module_hash, dev, _ in got["loads"]:
        hashes.setdefault((name, dev), set()).add(module_hash)
    assert {k: v for k, v in hashes.items() if len(v) > 1} == {}, "rehashed after a launch added an overload"
    if cold:
        built = {tuple(x) for x in got["built"]}
        launched = {tuple(x) for x in got["loads"] if x[2] == device} - built
        assert built and not launched, f"launched but not prewarmed: {sorted(launched)}"


RADIANCE_RUN = r"""
import dataclasses, json, sys
from pathlib import Path

import warp as wp

wp.config.quiet = True
from texstream.fit.kernels import build_notice
from texstream.pipelines.run import RunConfig, run_pipeline

capture, out, device = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
build_notice._marker = lambda *_, **__: out.parent / "absent.warm"  # every group cold
sys.path.insert(0, "tests")
from kernel_loads import record_loads

loads = record_loads()
import texstream.fit.stages.prewarm as prewarm
built, groups = [], []
build = prewarm.build_kernels_if_cold

def recorded_build(stage, device, kind, *args, **kwargs):
    n = len(loads)
    build(stage, device, kind, *args, **kwargs)
    built.extend(loads[n:])
    groups.append(prewarm.kernel_group(kind))

import texstream.fit.stages.stage as stage
stage.build_kernels_if_cold = recorded_build
cfg = RunConfig(device=device, progress=False, mesh_file=str(capture / "ground_truth"))
lfm = dataclasses.replace(cfg.fit.fit.lfm, iterations=20)
cfg.fit = dataclasses.replace(cfg.fit, renders=1, fit=dataclasses.replace(cfg.fit.fit, max_iterations=3, lfm=lfm))
summary = run_pipeline(capture, out, cfg, log=lambda m: None)
print(json.dumps({"loads": loads, "built": built, "groups": groups,
                  "kinds": sorted(summary["fit"]["selection"]["validation"])}))
"""


def test_a_run_under_an_unknown_light_builds_its_radiance_models_ahead(device, tmp_path):
    """A run of photos under one fixed, unknown light (radiance, view_radiance and LFM compared on its validation
    photos) on a cold cache builds its group's modules ahead (fit/stages/prewarm.py ``radiance_run_modules``, the
    group's parameter counts declared first): every module the run's fit, export and report launch was built by
    the prewarm, and none is loaded under two hashes (before, view_radiance's 18 parameters rehashed the optimizer's
    8 modules and LFM's two generic passes its module twice: each a second compile). In a child process: the
    declared counts are for the rest of a process (this worker's later tests would build the default modules
    again). About 25 s on CI's cold cache (the group's modules, which no other test builds with these
    overloads), 8 s warm."""
    import json
    import subprocess
    import sys

    from conftest import ROOT
    from lfm_scenes import fixed_light_sphere_capture

    capture = fixed_light_sphere_capture(tmp_path, photos=24, device="cpu")
    run = subprocess.run([sys.executable, "-c", RADIANCE_RUN, str(capture), str(tmp_path / "out"), device],
                         capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["kinds"] == ["lfm", "radiance", "view_radiance"], got["kinds"]  # the whole group ran
    assert got["groups"][0] == "unknown_light"
    hashes = {}
    for name, module_hash, dev, _ in got["loads"]:
        hashes.setdefault((name, dev), set()).add(module_hash)
    assert {k: v for k, v in hashes.items() if len(v) > 1} == {}, "rehashed after a launch added an overload"
    built = {tuple(x) for x in got["built"]}
    launched = {tuple(x) for x in got["loads"] if x[2] == device} - built
    assert built and not launched, f"launched but not prewarmed: {sorted(launched)}"


def test_a_gpu_run_builds_the_fit_kernels_while_the_stages_before_it_run(capture, device, tmp_path, monkeypatch):
    """On a GPU with a cold cache the run starts the fit's modules compiling before its mesh and atlas stages
    (fit/stages/prewarm.py ``build_kernels_ahead``) and the fit waits for that build instead of starting its own;
    every module the fit then launches was built (none rehashed). On the CPU the fit builds them, as before: the
    stages' cores are their own."""
    monkeypatch.setattr(build_notice, "_ANNOUNCED", set())
    monkeypatch.setattr(build_notice, "_marker", lambda *_, **__: tmp_path / "absent.warm")
    monkeypatch.setattr(prewarm, "_AHEAD", {})
    loads = record_loads(monkeypatch.setattr)
    cfg = RunConfig(device=device, mesh_file=str(capture / "ground_truth"))
    cfg.fit = dataclasses.replace(cfg.fit, renders=1, fit=dataclasses.replace(cfg.fit.fit, max_iterations=3))
    lines = []
    with reporting(lines.append):
        run_pipeline(capture, tmp_path / "out", cfg, log=lines.append)
    ahead = [line for line in lines if "while the stages before the fit run" in line]
    if not device.startswith("cuda"):
        assert not ahead and any("Warp modules at once" in line for line in lines), lines
        return
    assert len(ahead) == 1 and any("kernels built ahead" in line for line in lines), lines
    hashes: dict = {}
    for name, module_hash, on, _ in loads:
        if on == device:
            hashes.setdefault(name, set()).add(module_hash)
    assert hashes and all(len(h) == 1 for h in hashes.values()), {n: h for n, h in hashes.items() if len(h) > 1}


def test_the_build_ahead_splits_its_modules_without_overlap(monkeypatch):
    """The lists of ``build_kernels_ahead`` (their compile stubbed, the device taken for a GPU): the mesh stage's
    modules and the shared ones first, at once; the atlas's, refinement's and the group's fit modules on the thread
    started ahead; no module in both (none is loaded from two threads), and the fit then waits for that thread."""
    from texstream.pipelines.run import mesh_modules

    built = []
    monkeypatch.setattr(prewarm, "_build", lambda modules, device, threads: built.append(modules) or 0.0)
    monkeypatch.setattr(prewarm, "kernels_cold", lambda *_, **__: True)
    monkeypatch.setattr(prewarm, "_AHEAD", {})
    monkeypatch.setattr(prewarm.wp, "init", lambda: None)
    lines = []
    with reporting(lines.append):
        prewarm.build_kernels_ahead("fit", "cuda:0", "radiance", "fp32", mesh_modules())
        prewarm.build_kernels_if_cold("fit", "cuda:0", "view_radiance", "fp32")  # the same group: waits
    now, ahead = built
    names = [m.name for m, _ in now], [m.name for m, _ in ahead]
    assert not set(names[0]) & set(names[1]), names
    assert {"texstream.geometry.mvs", "texstream.geometry.hull"} <= set(names[0])
    assert {"texstream.geometry.refine_kernels", "texstream.geometry.bake"} <= set(names[1])
    assert {m.name for m, _ in prewarm.radiance_run_modules("cuda:0")} <= set(names[0]) | set(names[1])
    assert any("kernels built ahead" in line for line in lines) and prewarm._AHEAD == {}, lines
