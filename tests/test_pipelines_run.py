"""``texstream run``: the end-to-end pipeline's decisions, stamps and config file, on a tiny
synthetic capture with its true atlas (the stages before the fit are the subcommands' own tests)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from texstream.core.errors import ConfigError, InputError
from texstream.pipelines.run import RunConfig, detect_source, run_config_from_dict, run_pipeline

from conftest import SCENE_DEVICE, tiny_sphere_capture  # noqa: E402


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return tiny_sphere_capture(tmp_path_factory.mktemp("run"), photos=16)


def tiny_config(**top) -> RunConfig:
    cfg = RunConfig(device=SCENE_DEVICE, **top)
    cfg.fit = dataclasses.replace(cfg.fit, renders=1, fit=dataclasses.replace(cfg.fit.fit, max_iterations=3))
    return cfg


def statuses(summary: dict) -> dict:
    return {s["name"]: s["status"] for s in summary["stages"]}


def test_known_cameras_and_atlas_skip_their_stages_and_a_rerun_skips_everything(capture, tmp_path):
    out = tmp_path / "out"
    cfg = tiny_config(mesh_file=str(capture / "ground_truth"))
    first = run_pipeline(capture, out, cfg, log=lambda m: None)
    st = statuses(first)
    assert st["ingest"] == st["register"] == st["mesh"] == st["atlas"] == "skipped"
    # the sphere's photos have lights: diffuse, Lafortune and (where the photos can support it) two-lobe
    # Lafortune judged on a validation split of the fitted photos, the best kept; the held-out photos score
    # only the kept model, and model.json records the choice
    assert st["fit"] == "ran" and first["model"] in ("lafortune", "diffuse")
    # the split keeps two validation photos: every 8th of 16 fitted photos or more, a shorter period below
    every = first["fit"]["selection"]["validation_every"]
    assert "light" in first["model_reason"]
    assert f"validation pooled PSNR (every {every}th fitted photo) diffuse" in first["model_reason"]
    assert "lafortune" in first["fit"]["selection"]["validation"]  # the glossy sphere's photos show highlights
    sel = first["fit"]["selection"]
    assert set(sel["validation"]) | set(sel["left_out"]) == {"lafortune", "diffuse", "lafortune_2lobes"}
    assert sel["heldout_pooled_db"] == first["heldout"]["pooled_psnr_db"]
    manifest = json.loads((out / "model" / "model.json").read_text())
    assert manifest["kind"] == first["model"] and manifest["selection"]["chosen"] == sel["chosen"]
    kept = manifest["kind"]
    # the validation fits go once the choice is made; the full fits not kept stay beside the model
    assert not list(out.glob("model_*_validation"))
    reasons = {s["name"]: s["reason"] for s in first["stages"]}
    assert "cameras known" in reasons["register"]
    # what the model was built from, said once per input (run.json and the report)
    inputs = first["inputs"]
    assert inputs["cameras"]["source"] == "given" and inputs["mesh"]["source"] == "given"
    assert inputs["masks"]["source"] == "given" and "16 of 16" in inputs["masks"]["why"], inputs["masks"]
    assert "What the model was built from" in (out / "report" / "index.html").read_text()
    assert st["refine"] == "skipped" and "cameras and mesh given" in reasons["refine"]
    # held-out error as users meet it: every 8th of 16 photos, pooled and worst view
    assert first["heldout"]["views"] == 2 and first["heldout"]["pooled_psnr_db"] > 20
    assert json.loads((out / "run.json").read_text())["model"] == kept
    model_mtime = (out / "model" / "model.json").stat().st_mtime_ns
    second = run_pipeline(capture, out, cfg, log=lambda m: None)
    fit = next(s for s in second["stages"] if s["name"] == "fit")
    assert fit["status"] == "skipped" and "unchanged" in fit["reason"]
    assert (out / "model" / "model.json").stat().st_mtime_ns == model_mtime
    third = run_pipeline(capture, out, cfg, from_stage="fit", log=lambda m: None)
    assert statuses(third)["fit"] == "ran"
    # a changed option reruns the fit
    cfg2 = dataclasses.replace(cfg, fit=dataclasses.replace(cfg.fit, fit=dataclasses.replace(cfg.fit.fit, max_iterations=2)))
    assert statuses(run_pipeline(capture, out, cfg2, log=lambda m: None))["fit"] == "ran"


def test_unknown_lighting_chooses_the_radiance_model(capture, tmp_path):
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(capture, cap)
    data = json.loads((cap / "capture.json").read_text())
    for f in data["frames"]:
        f.pop("light", None)
    data.pop("light", None)
    (cap / "capture.json").write_text(json.dumps(data))
    summary = run_pipeline(cap, tmp_path / "out", tiny_config(mesh_file=str(cap / "ground_truth")), log=lambda m: None)
    # fixed unknown lighting: the radiance model, and with held-out photos the view-dependent one beside
    # it, each judged by a fit of the validation split (both figures recorded), the better one fitted to
    # every fitted photo and kept; the validation fits go
    assert summary["model"] in ("radiance", "view_radiance") and "unknown" in summary["model_reason"]
    sel = summary["fit"]["selection"]
    assert set(sel["validation"]) == {"radiance", "view_radiance"} and sel["refit"]
    assert all(v["judged_by"] == "a fit of the validation split" for v in sel["validation"].values())
    man = json.loads((tmp_path / "out" / "model" / "model.json").read_text())
    assert man["kind"] == summary["model"] and man["photos"]["fitted"] == 14  # every fitted photo
    assert not list((tmp_path / "out").glob("model_*"))
    with pytest.raises(InputError, match="needs a light"):
        run_pipeline(cap, tmp_path / "out2", tiny_config(mesh_file=str(cap / "ground_truth"), model="lafortune"),
                     log=lambda m: None)


def test_the_resolved_config_reads_back_and_unknown_fields_fail(capture, tmp_path):
    from texstream.core.toml import read_toml

    from texstream.core.config import config_to_dict
    from texstream.core.toml import dumps

    out = tmp_path / "out"
    with pytest.raises(InputError, match="mesh file not found"):  # checked before any work or output
        run_pipeline(capture, out, tiny_config(mesh_file=str(tmp_path / "missing.obj")), log=lambda m: None)
    assert not out.exists()
    (tmp_path / "run_config.toml").write_text(dumps(config_to_dict(tiny_config())))  # as run_pipeline writes it
    data = read_toml(tmp_path / "run_config.toml")
    cfg = run_config_from_dict(data)
    assert cfg.fit.fit.max_iterations == 3 and cfg.fit.holdout_every == 8 and cfg.device == SCENE_DEVICE
    with pytest.raises(ConfigError, match="bogus"):
        run_config_from_dict({**data, "bogus": 1})
    with pytest.raises(ConfigError, match="colour"):
        run_config_from_dict({**data, "fit": {**data["fit"], "colour": 1}})


def test_bad_inputs_are_one_line_errors(tmp_path):
    from texstream.pipelines.cli import main

    assert detect_source(tmp_path) == "photos"
    with pytest.raises(InputError, match="not found"):
        detect_source(tmp_path / "nope")
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(InputError, match="output path exists"):
        run_pipeline(tmp_path, tmp_path / "file.txt", tiny_config(), log=lambda m: None)
    assert main(["run", str(tmp_path / "nope"), "-o", str(tmp_path / "o")]) == 1
    assert main(["run", str(tmp_path), "-o", str(tmp_path / "o"), "--iterations", "-3"]) == 1


def test_turntable_object_under_unknown_lighting_to_a_valid_radiance_model(capture, tmp_path):
    """Photos of an object on a dark background with known cameras and masks but no lights and no
    mesh: the mesh comes from the masks (visual hull, facing the cameras), the atlas from xatlas,
    and the radiance fit gives a finite, in-bounds model that reproduces the held-out views."""
    import shutil

    import numpy as np

    from texstream.capture.synthetic.param_maps import read_param_maps
    from texstream.render.layout import ModelLayout

    cap = tmp_path / "cap"
    shutil.copytree(capture, cap, ignore=shutil.ignore_patterns("ground_truth"))
    data = json.loads((cap / "capture.json").read_text())
    for f in data["frames"]:
        f.pop("light", None)
    (cap / "capture.json").write_text(json.dumps(data))
    cfg = tiny_config()
    cfg.mesh = dataclasses.replace(cfg.mesh, faces=2000)
    cfg.atlas = dataclasses.replace(cfg.atlas, resolution=64)
    summary = run_pipeline(cap, tmp_path / "out", cfg, log=lambda m: None)
    st = statuses(summary)
    assert st["mesh"] == st["atlas"] == st["fit"] == "ran" and summary["model"] in ("radiance", "view_radiance")
    # known cameras stay; the mesh the run made is refined against the photos
    refine = next(s for s in summary["stages"] if s["name"] == "refine")
    assert refine["status"] == "ran" and refine["reason"].startswith("mesh refined"), refine
    assert refine["summary"]["residual_after"]["fit_rms"] < refine["summary"]["residual_before"]["fit_rms"]
    # no light: the shading normals (smoothing or photometric) stay out
    assert refine["summary"]["shading_normals"] == {"smoothing_rounds": 0, "intensity_rms_by_rounds": {}}
    mesh = next(s for s in summary["stages"] if s["name"] == "mesh")["summary"]
    assert summary["inputs"]["mesh"]["source"] in ("visual hull", "Poisson of SfM points",
                                                   "Poisson of dense stereo points"), summary["inputs"]["mesh"]
    assert "faces" in summary["inputs"]["mesh"]["why"]
    assert mesh["facing"]["after"]["back_fraction"] < 0.01  # the stage itself fails above 5%
    model = tmp_path / "out" / "model"
    lay = ModelLayout.from_json(json.loads((model / "model.json").read_text())["layout"])
    grid = read_param_maps(model, lay)
    assert np.isfinite(grid).all() and (grid >= lay.lower()).all() and (grid <= lay.upper()).all()
    # the sphere is lit by a light beside each camera, so its radiance is view dependent: a
    # view-independent model cannot reproduce it exactly; 20 dB rules out a broken fit (a constant
    # grey scores about 10 dB here)
    assert summary["heldout"]["worst_psnr_db"] > 20


def test_too_few_photos_and_a_bad_config_file_fail_before_any_work(tmp_path, capsys):
    import shutil

    from texstream.pipelines.cli import main

    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(2):
        shutil.copy(__file__, photos / f"p{k}.png")  # never read: the count is checked first
    assert main(["run", str(photos), "-o", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "2 photo(s) found" in err and str(photos) in err and not (tmp_path / "o" / "capture").exists()
    (tmp_path / "c.toml").write_text("bogus = 1\n")
    assert main(["run", str(photos), "-o", str(tmp_path / "o"), "--config", str(tmp_path / "c.toml")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "c.toml" in err and "bogus" in err


def test_run_warnings_say_what_a_finished_run_lacks():
    from texstream.pipelines.run import StageRecord, run_warnings

    reg = StageRecord("register", "ran", "", summary={"registered": ["a", "b"], "unregistered": ["c", "d", "e"]})
    w = run_warnings([reg], {"views": 0}, {"warnings": ["9% of seen texels have x at its upper bound 10"]})
    assert any("only 2 of 5 photos registered" in x for x in w) and any("no held-out view" in x for x in w)
    assert w[-1].startswith("9% of seen texels")
    every = StageRecord("register", "ran", "", summary={"registered": ["a"] * 9, "unregistered": []})
    assert run_warnings([every], {"views": 2}, {}) == []


def _config_file(cfg: RunConfig, path):
    from texstream.core.config import config_to_dict
    from texstream.core.toml import dumps

    path.write_text(dumps(config_to_dict(cfg)))
    return str(path)


def test_a_full_disk_is_one_line_leaves_nothing_half_written_and_the_rerun_reuses_the_fit(capture, tmp_path,
                                                                                         monkeypatch, capsys):
    import errno

    from texstream.core import outputs
    from texstream.pipelines.cli import main

    out = tmp_path / "out"
    cfg_file = _config_file(tiny_config(mesh_file=str(capture / "ground_truth")), tmp_path / "run.toml")
    real = outputs.write_atomic_with

    def disk_full_on_glb(p, write):
        if p.suffix != ".glb":
            return real(p, write)

        def half(fh):  # some bytes reach the disk, then it is full
            fh.write(b"glTF" * 64)
            raise OSError(errno.ENOSPC, "No space left on device", str(p))
        return real(p, half)

    monkeypatch.setattr(outputs, "write_atomic_with", disk_full_on_glb)
    assert main(["run", str(capture), "-o", str(out), "--config", cfg_file]) == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "Traceback" not in err, err
    assert "No space left on device" in err and "model.glb" in err and "free space" in err
    # the export stage failed inside its temporary folder: no export folder, no temporary file or folder left
    assert not (out / "export").exists()
    assert [p.name for p in out.rglob("*") if p.name.endswith((".tmp", ".partial"))] == []
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []
    assert (out / "model" / ".texstream_stage.json").is_file() and not (out / "run.json").exists()
    model_mtime = (out / "model" / "model.json").stat().st_mtime_ns

    monkeypatch.setattr(outputs, "write_atomic_with", real)  # space freed: the same command again
    assert main(["run", str(capture), "-o", str(out), "--config", cfg_file]) == 0
    summary = json.loads((out / "run.json").read_text())
    st = statuses(summary)
    assert st["fit"] == "skipped" and st["export"] == "ran" and (out / "export" / "model.glb").is_file()
    assert (out / "model" / "model.json").stat().st_mtime_ns == model_mtime


def test_stages_print_phase_lines_to_the_log_and_no_bars_off_a_terminal(capture, tmp_path, capsys):
    lines: list[str] = []
    run_pipeline(capture, tmp_path / "out", tiny_config(mesh_file=str(capture / "ground_truth")), log=lines.append)
    assert any(m.startswith("  export: glTF binary") for m in lines), lines
    assert any(m.startswith("[lights] skipped: every photo has a known light") for m in lines), lines
    # pytest's captured stderr is not a terminal: no bar is drawn there (tqdm's disable=None)
    assert "it/s" not in capsys.readouterr().err


def _mirror_ball_capture(root, light_pos):
    """A small sphere capture lit by one fixed point light, its lights removed from capture.json, plus four
    photos of a mirror ball (the helper of tests/test_calib_lights.py) under the same light."""
    import numpy as np

    from conftest import SCENE_DEVICE
    from test_calib_lights import make_ball_capture
    from texstream.capture.capture_json import read_capture, write_capture
    from texstream.capture.synthetic.synth import SynthConfig, load_scene, synthesize

    scene = load_scene("sphere")
    scene["light"] = {"type": "point", "mode": "fixed", "position": list(light_pos), "intensity": 12.0}
    cap_dir = root / "cap"
    synthesize(scene, cap_dir, SynthConfig(scale=0.05, photos=16, image_size=40, progress=False, preview=False,
                                           device=SCENE_DEVICE))
    balls = make_ball_capture(root / "balls", [(np.zeros(3), 0.25)], ("point", np.asarray(light_pos), 0.15),
                              [-100, -60, -10, 40])
    cap, ball_cap = read_capture(cap_dir), read_capture(balls)
    for f in ball_cap.frames:
        (cap_dir / "images" / Path(f.file_path).name).write_bytes((balls / f.file_path).read_bytes())
    frames = [dataclasses.replace(f, light=None) for f in cap.frames] + list(ball_cap.frames)
    write_capture(dataclasses.replace(cap, frames=frames), cap_dir)
    return cap_dir, [f.name for f in ball_cap.frames]


def test_mirror_ball_lights_through_the_run(tmp_path, capsys):
    import numpy as np
    from test_calib_lights import _point_bound

    from texstream.pipelines.cli import main

    light = (1.8, -1.2, 2.1)  # 3 units from the ball and the object's centre
    cap, ball_names = _mirror_ball_capture(tmp_path, light)
    out = tmp_path / "out"
    cfg_file = _config_file(tiny_config(mesh_file=str(cap / "ground_truth")), tmp_path / "run.toml")
    assert main(["run", str(cap), "-o", str(out), "--config", cfg_file, "--mirror-ball", "0,0,0,0.25",
                 "--mirror-ball-frames", ",".join(ball_names)]) == 0
    summary = json.loads((out / "run.json").read_text())
    st = statuses(summary)
    assert st["lights"] == "ran" and st["fit"] == "ran"
    assert summary["lights"]["source"] == "mirror ball" and summary["lights"]["ball_photos"] == 4
    assert summary["lights"]["photos"] == 16 and summary["lights"]["kind"] == "point"
    # the bound of tests/test_calib_lights.py for a lamp this far from a 0.25-unit ball (~0.13 units)
    err = np.linalg.norm(np.array(summary["lights"]["light"]["position"]) - light)
    assert err < _point_bound(np.linalg.norm(light), 0.3), err
    assert summary["model"] in ("lafortune", "diffuse") and "mirror ball" in summary["model_reason"]
    lit = json.loads((out / "lights" / "capture.json").read_text())
    assert len(lit["frames"]) == 16 and all(f["light"]["type"] == "point" for f in lit["frames"])
    # the lit capture points at the photos where they are (no copies)
    assert not (out / "lights" / "images").exists()
    # a reflectance fit under the estimated light: held-out error near the known-light run's (> 20 dB there)
    assert summary["heldout"]["views"] == 2 and summary["heldout"]["pooled_psnr_db"] > 20, summary["heldout"]
    toml = (out / "run_config.toml").read_text()
    assert "[lights]" in toml and "sphere = [0.0, 0.0, 0.0, 0.25]" in toml
    # rerun: every stage reused
    assert main(["run", str(cap), "-o", str(out), "--config", str(out / "run_config.toml")]) == 0
    again = statuses(json.loads((out / "run.json").read_text()))
    assert again["lights"] == "skipped" and again["fit"] == "skipped"
    capsys.readouterr()
    assert main(["run", str(cap), "-o", str(tmp_path / "o2"), "--mirror-ball", "0,0,0"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "X,Y,Z,R" in err
