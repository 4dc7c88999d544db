"""The run's judgement of a refinement under known lights (pipelines/refine_judge.py): the fit's validation photos
decide whether refined cameras go on, and only where the refinement's own model differs from the fit's."""

import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import tiny_sphere_capture
from texstream.capture.capture_json import read_capture, write_capture
from texstream.geometry.refine import RefineConfig
from texstream.pipelines.refine_judge import choice_folder, hand_to_choice, judge_refinement, judged_by_fit
from texstream.pipelines.run import RunConfig


def _turned(capture, out, degrees: float):
    """The capture with every camera turned by ``degrees`` about its own x axis (its light, at the camera, kept
    there): what a refinement that followed something other than the surface hands on."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    turn = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    frames = []
    for f in capture.frames:
        rel = os.path.relpath(capture.root / f.file_path, out)
        mask = None if f.mask_path is None else os.path.relpath(capture.root / f.mask_path, out)
        frames.append(dataclasses.replace(f, R=turn @ np.asarray(f.R), t=turn @ np.asarray(f.t), file_path=rel,
                                          mask_path=mask))
    out.mkdir(parents=True)
    write_capture(dataclasses.replace(capture, root=out, frames=frames), out)
    return out


@pytest.fixture(scope="module")
def lit_sphere(tmp_path_factory):
    root = tmp_path_factory.mktemp("judge")
    cap = tiny_sphere_capture(root, photos=24, image_size=48)
    capture = read_capture(cap)
    assert all(f.light is not None for f in capture.frames)  # the scene's photos have a known light each
    return cap, _turned(capture, root / "turned", 2.0)


def test_judge_keeps_the_geometry_the_fit_predicts_better(lit_sphere, tmp_path):
    """True cameras against cameras turned by 2 degrees (about 1.4 px at the photos' 48 px: the sphere's texture
    no longer lines up between views): the validation photos prefer the true ones whichever side they are on, so
    the judgement is neither always yes nor always no."""
    cap, turned = lit_sphere
    fit_cfg = dataclasses.replace(RunConfig().fit, device="cpu")
    geometry = cap / "ground_truth"
    kept, record = judge_refinement((cap, geometry), (turned, geometry), tmp_path / "a", fit_cfg)
    assert not kept and "registered ones are kept" in record["why"]
    assert record["validation"]["registered"]["pooled_psnr_db"] > record["validation"]["refined"]["pooled_psnr_db"]
    hand_to_choice(tmp_path / "a", kept, tmp_path / "model")
    assert not (tmp_path / "a").exists() and (choice_folder(tmp_path / "model") / "model.json").is_file()
    kept, record = judge_refinement((turned, geometry), (cap, geometry), tmp_path / "b", fit_cfg)
    assert kept and "refined against" in record["why"]


def test_the_model_choice_takes_the_judged_fit(lit_sphere, tmp_path, monkeypatch):
    """The kept side's validation fit is the model choice's fit of its first candidate, same inputs and options:
    the choice the run then makes takes it without fitting it again (any fit_model call here would fail)."""
    from texstream.fit.stages import stage
    from texstream.fit.stages.choice import fit_choice, plan_choice
    from texstream.pipelines import run as run_module

    class Stop(Exception):
        pass

    cap, turned = lit_sphere
    geometry, model = cap / "ground_truth", tmp_path / "model"
    capture = read_capture(cap)
    fit_cfg = run_module._fit_config(dataclasses.replace(RunConfig(), device="cpu"), capture)  # as the run's fit
    kept, _ = judge_refinement((turned, geometry), (cap, geometry), tmp_path / "work", fit_cfg)
    hand_to_choice(tmp_path / "work", kept, model)
    folders = []

    def fit_one(capture_dir, mesh_path, out_dir, cfg):
        folders.append(Path(out_dir))
        if Path(out_dir) != choice_folder(model):
            raise Stop  # the candidates after the first: not what this test is about
        return stage.fit_candidate(capture_dir, mesh_path, out_dir, cfg, progress=False)

    def no_fit(*args, **kwargs):
        raise AssertionError("the judged fit was fitted again")

    monkeypatch.setattr(stage, "fit_model", no_fit)
    with pytest.raises(Stop):
        fit_choice(cap, geometry, model, fit_cfg, plan_choice(capture, "auto", fit_cfg), fit_one)
    assert folders[0] == choice_folder(model) and len(folders) == 2


def test_judged_only_under_known_lights_with_a_split(lit_sphere):
    cap, _ = lit_sphere
    capture = read_capture(cap)
    cfg = dataclasses.replace(RefineConfig(), holdout_every=8)
    assert judged_by_fit(capture, cfg) is None
    assert judged_by_fit(capture, dataclasses.replace(cfg, judge="off")) == "refine judge off"
    unlit = dataclasses.replace(capture, frames=[dataclasses.replace(f, light=None) for f in capture.frames])
    assert "radiance model" in judged_by_fit(unlit, cfg)
    few = dataclasses.replace(capture, frames=capture.frames[:5])
    assert "too few" in judged_by_fit(few, cfg)


def test_the_run_judges_an_unchanged_refinement_once(lit_sphere, tmp_path, monkeypatch):
    """The run keeps its judgement beside its stages (refine_judged.json, keyed by the refinement's stamp, the
    registered inputs and the judge's fit options): a rerun that reused the refinement reads it instead of two more
    fits, also where only an option the judge overrides changed; a changed option of its fit, or the refinement run
    again, judges again. The kept side's fit waits for the model choice, the work folder is gone."""
    from texstream.pipelines import run as run_module

    cap, turned = lit_sphere
    calls = []
    real = run_module.judge_refinement

    def counted(*args, **kwargs):
        calls.append(args[1])
        return real(*args, **kwargs)

    monkeypatch.setattr(run_module, "judge_refinement", counted)
    capture = read_capture(turned)
    refined = tmp_path / "refine"  # a refine stage's folder: its capture and its geometry side by side
    shutil.copytree(cap, refined)
    for name in ("mesh.obj", "bake.npz"):
        shutil.copy(cap / "ground_truth" / name, refined / name)
    cfg = dataclasses.replace(RunConfig(), device="cpu")
    refine_cfg = dataclasses.replace(cfg.refine, holdout_every=8)

    def judged(run_cfg, refine_status="skipped"):  # "skipped": a rerun reusing the refinement's folder
        pipe = run_module.Pipeline(tmp_path, None, lambda m: None)
        pipe.records.append(run_module.StageRecord("refine", refine_status, "refined", output=str(refined)))
        got = run_module._judged_refinement(pipe, run_cfg, refine_cfg, capture, (turned, cap / "ground_truth"),
                                            refined, tmp_path)
        return got, pipe.records[-1]

    first, rec = judged(cfg, "ran")
    assert first == (refined, refined) and rec.summary["judged"]["kept"]  # the "refined" side holds the true cameras
    assert (choice_folder(tmp_path / "model") / "model.json").is_file() and not (tmp_path / "refine_judged").exists()
    again, rec = judged(cfg)
    assert again == first and len(calls) == 1 and rec.summary["judged"]["kept"]
    judged(dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, renders=1)))  # an option the judge overrides
    assert len(calls) == 1
    judged(dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, fit=dataclasses.replace(cfg.fit.fit,
                                                                                            max_iterations=20))))
    assert len(calls) == 2
    judged(cfg, "ran")  # the refinement run again (``--from refine``): judged again, whatever its stamp
    assert len(calls) == 3


def test_a_rejected_refinement_hands_on_the_registered_inputs(lit_sphere, tmp_path):
    """Cameras turned by 2 degrees as the refinement's output against the true ones registered: the run's fit gets
    the registered capture and geometry, and the refine line says why."""
    from texstream.pipelines import run as run_module

    cap, _ = lit_sphere
    refined = _turned(read_capture(cap), tmp_path / "refine", 2.0)
    for name in ("mesh.obj", "bake.npz"):
        shutil.copy(cap / "ground_truth" / name, refined / name)
    cfg = dataclasses.replace(RunConfig(), device="cpu")
    pipe = run_module.Pipeline(tmp_path, None, lambda m: None)
    pipe.records.append(run_module.StageRecord("refine", "ran", "refined", output=str(refined)))
    registered = (cap, cap / "ground_truth")
    got = run_module._judged_refinement(pipe, cfg, dataclasses.replace(cfg.refine, holdout_every=8),
                                        read_capture(cap), registered, refined, tmp_path)
    assert got == registered and "not kept" in pipe.records[-1].reason
    assert not pipe.records[-1].summary["judged"]["kept"]


def test_a_side_the_fit_cannot_take_loses(lit_sphere, tmp_path, monkeypatch):
    from texstream.core.errors import InputError
    from texstream.pipelines import refine_judge

    cap, turned = lit_sphere
    real = refine_judge.fit_candidate

    def refined_fails(capture_dir, mesh_path, out_dir, cfg, progress=True):
        if Path(out_dir).name == "refined":
            raise InputError("no texel is seen", capture_dir, "check the mesh")
        return real(capture_dir, mesh_path, out_dir, cfg, progress)

    monkeypatch.setattr(refine_judge, "fit_candidate", refined_fails)
    fit_cfg = dataclasses.replace(RunConfig().fit, device="cpu")
    geometry = cap / "ground_truth"
    kept, record = judge_refinement((turned, geometry), (cap, geometry), tmp_path / "w", fit_cfg)
    assert not kept and "could not take the refined geometry" in record["why"] and "no texel" in record["why"]
