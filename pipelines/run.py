"""The end-to-end run: photos (or a posed capture) in, a fitted model, exports and a report out.

``run_pipeline(source, out, config)`` chains the stage functions the subcommands call:

    ingest -> register -> mesh -> atlas -> lights -> refine -> fit -> export -> report

and leaves out what the scene does not need, deciding from the data and recording why:
- cameras known (capture.json / transforms.json with poses, a COLMAP model): no registration;
- a mesh given with UVs: no atlas (``mesh`` option);
- cameras this run registered and a mesh it made: refined against the photos (``refine``); given ones stay;
- a flash fixed to the camera and a colour chart found by ingest's ``--response auto``: the flash's intensity from
  the chart (the lights stage, calib/chart_flash.py), so albedos come out absolute;
- lights known for every photo -> a reflectance model (Lafortune SBRDF); one fixed unknown
  lighting -> the radiance model (``model`` "auto"); with held-out photos the view-dependent radiance
  model beside it and, when view dependence matters (view_radiance beats radiance on a validation split
  of the fitted photos by ``lfm_min_gain_db``), light field mapping too (``lfm``); the one that predicts
  the validation photos best is kept, and the held-out photos score it (fit/stages/choice.py).

Each stage writes its own folder under ``OUT`` with a stamp (``.texstream_stage.json``: a hash of
the stage's inputs and config); a rerun whose stamp matches skips the stage, ``from_stage`` reruns
from a stage on. The resolved config is written to ``OUT/run_config.toml`` and ``OUT/run.json``
records every stage's decision, reason and time.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import warp as wp

from texstream.calib.chart_flash import chart_flash_applies, flash_lit_capture
from texstream.calib.colmap_io import import_colmap
from texstream.calib.files import IMAGE_EXTS
from texstream.calib.ingest import IngestConfig, ingest
from texstream.calib.lights import LightsConfig, _world_balls, lit_capture
from texstream.calib.register import RegisterConfig, register
from texstream.capture.capture_json import no_flash_frames, read_capture
from texstream.core.checkpoint import inputs_key
from texstream.core.config import check_config, config_from_dict, config_to_dict, option
from texstream.core.devices import DEVICE_HELP, resolve_device
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import write_atomic_with, write_json_atomic
from texstream.core.progress import reporting
from texstream.core.toml import dumps
from texstream.fit.common.model_folder import json_safe
from texstream.fit.models import registry
from texstream.fit.optim.fitter import FitConfig
from texstream.fit.optim.lfm_config import LFMConfig
from texstream.fit.stages.choice import ModelChoiceConfig, fit_choice, plan_choice, requested_model
from texstream.fit.stages.export import ExportConfig, export_stage
from texstream.fit.stages.stage import (FitStageConfig, fit_candidate, fit_kernels_ahead, fit_stage,
                                        forget_candidates)
from texstream.geometry import hull, mvs, reconstruct, scene
from texstream.geometry import visibility as geometry_visibility
from texstream.geometry.atlas import AtlasConfig, atlas_stage
from texstream.geometry.make_mesh import MeshConfig, make_mesh
from texstream.geometry.mesh_frame import mesh_alignment
from texstream.geometry.mesh_io import load_mesh
from texstream.geometry.refine import RefineConfig, refine_stage
from texstream.pipelines.light_inputs import light_and_resolution_inputs
from texstream.pipelines.provenance import inputs_lines, run_inputs
from texstream.pipelines.refine_judge import (JUDGE_WORK, JUDGED_FILE, choice_folder, hand_to_choice, judge_config,
                                              judge_refinement, judged_by_fit)
from texstream.pipelines.report import write_report
from texstream.pipelines.resolutions import stage_resolutions

STAGES = ("ingest", "register", "mesh", "atlas", "lights", "refine", "fit", "export", "report")
STAMP = ".texstream_stage.json"
LFM_CANDIDATE = ("auto", "always", "never")
RUN_LFM_ITERATIONS = 50
"""the run's cap on the LFM candidate's streaming CG iterations (fit.lfm.iterations; docs/lfm.md gives
the temple's held-out PSNR at 20, 50 and 100)"""
MIN_PHOTOS = 3  # structure from motion needs two views to start and a third to check them


def model_choices() -> list[str]:
    """``auto`` and every kind of the model registry (fit/models/)."""
    return ["auto", *registry.kinds()]


def _fit_stage_config():
    return FitStageConfig(holdout_every=8, fit=FitConfig(lfm=LFMConfig(iterations=RUN_LFM_ITERATIONS)))


@dataclasses.dataclass
class RunConfig:
    """Every option of ``texstream run``, one table per stage (``--config run.toml`` reads it back)."""

    device: str = option("auto", DEVICE_HELP + "; every stage of the run uses it (mesh, atlas, refine, fit, report)")
    model: str = option("auto", "appearance model: auto (lafortune when every photo has a known light, radiance "
                                "when the lighting is fixed and unknown; with held-out photos the diffuse or the "
                                "view-dependent radiance model too, the one that predicts a validation split of the "
                                "fitted photos best kept and the held-out photos scoring it, and light field "
                                "mapping where view dependence matters, see lfm), lafortune, diffuse, radiance, "
                                "view_radiance or lfm (light field mapping, [fit.lfm] options): a kind of the model "
                                "registry (fit/models/)")
    lfm: str = option("auto", "fixed unknown lighting, model auto, held-out photos: fit a light field mapping model "
                              "([fit.lfm]: K=1 streaming CG, iterations capped at fit.lfm.iterations) beside radiance "
                              "and view_radiance and keep it when it predicts the validation photos (every "
                              "fit.materials.validation_every-th fitted photo) best: auto (only when view dependence "
                              "matters: view_radiance's validation pooled PSNR at least lfm_min_gain_db above "
                              "radiance's), always, or never", choices=LFM_CANDIDATE)
    lfm_min_gain_db: float = option(0.5, "lfm auto: the validation gain (dB) of view_radiance over radiance from "
                                         "which view dependence counts as mattering", min=-60.0, max=60.0)
    second_lobe: bool = option(True, "known lights, model auto, held-out photos: also fit a two-lobe Lafortune "
                                     "model (the second lobe kept per texel only where it lowers the texel's error "
                                     "on the fitted photos, fit lobe_support) and keep it only when it predicts the "
                                     "validation photos best; fitted only where the photos can support it "
                                     "(second_lobe_min_constrained)")
    second_lobe_min_constrained: float = option(0.3, "second_lobe: the two-lobe model is fitted only when at least "
                                                     "this share of the seen texels have a lobe their photos "
                                                     "constrain in the one-lobe fit (fit.materials."
                                                     "constrained_rel_std): only those can pin a second lobe down; "
                                                     "0: always fitted", min=0.0, max=1.0)
    relightable: bool = option(False, "fixed unknown lighting, model auto, held-out photos: also fit the relightable "
                                      "env_diffuse model (albedo and the light estimated, `texstream relight`) and keep "
                                      "it when its validation pooled PSNR is within relightable_margin_db of the best "
                                      "radiance model's")
    relightable_margin_db: float = option(1.0, "relightable: the margin (dB) below the best model within which the "
                                               "relightable model is kept", min=0.0, max=60.0)
    mesh_file: str | None = option(None, "a mesh of the object (OBJ/PLY) to use instead of one from the photos; "
                                         "with usable UVs it also skips the atlas")
    progress: bool = option(True, "progress bars over photos and iterations (shown on a terminal only); the stages' "
                                  "phase lines go to the run's log either way")
    ingest: IngestConfig = option(default_factory=IngestConfig, help="ingest")
    register: RegisterConfig = option(default_factory=RegisterConfig, help="registration")
    mesh: MeshConfig = option(default_factory=MeshConfig, help="mesh")
    atlas: AtlasConfig = option(default_factory=AtlasConfig, help="atlas")
    lights: LightsConfig = option(default_factory=LightsConfig,
                                  help="mirror-ball lights: with sphere (or ball_masks) the run estimates one light "
                                       "from the ball photos (frames: those photos, left out of the fit) and gives it "
                                       "to every photo")
    refine: RefineConfig = option(default_factory=RefineConfig,
                                  help="photometric refinement of registered cameras and a reconstructed mesh (its "
                                       "holdout_every follows the fit's)")
    fit: FitStageConfig = option(default_factory=_fit_stage_config,
                                 help="fit (holdout_every 8: every 8th photo is held out)")


SUBCONFIGS: dict[str, type] = {"ingest": IngestConfig, "register": RegisterConfig, "mesh": MeshConfig,
                               "atlas": AtlasConfig, "lights": LightsConfig, "refine": RefineConfig,
                               "fit": FitStageConfig}
"""the run's tables that are a stage's config"""


def run_config_from_dict(data: dict) -> RunConfig:
    """A RunConfig from plain data (a TOML file); unknown fields are a ConfigError naming them."""
    names = {f.name for f in dataclasses.fields(RunConfig)}
    unknown = sorted(set(data) - names - {"_type"})
    if unknown:
        raise ConfigError(f"unknown run option(s) {unknown}", fix=f"use only {sorted(names)}")
    kwargs = {}
    for k, v in data.items():
        if k == "_type":
            continue
        if k in SUBCONFIGS:
            if not isinstance(v, dict):
                raise ConfigError(f"[{k}] must be a table, got {v!r}", fix=f"write it as a [{k}] section")
            kwargs[k] = config_from_dict(SUBCONFIGS[k], v)
    # the top-level options read as config_from_dict reads a table (their types checked)
    cfg = config_from_dict(RunConfig, {k: v for k, v in data.items() if k not in SUBCONFIGS})
    cfg = dataclasses.replace(cfg, **kwargs)
    check_config(cfg)  # ranges and choices here, where the caller names the file
    if cfg.model not in model_choices():
        raise ConfigError(f"model {cfg.model!r} unknown", fix=f"use one of {model_choices()}")
    if cfg.lfm not in LFM_CANDIDATE:
        raise ConfigError(f"lfm {cfg.lfm!r} unknown", fix=f"use one of {LFM_CANDIDATE}")
    return cfg


@dataclasses.dataclass
class StageRecord:
    """What one stage did: ran or skipped, why, how long, and its summary."""

    name: str
    status: str
    reason: str
    seconds: float = 0.0
    output: str | None = None
    summary: dict = dataclasses.field(default_factory=dict)
    cpu_seconds: float = 0.0
    """the process's CPU time over the stage, every thread's: beside ``seconds``, a measure other jobs on the
    machine disturb less"""


def _hash(*parts: Any) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def _files_hash(folder: Path) -> str:
    """Names, sizes and modification times of a folder's files (cheap; changes when a photo does). Hidden
    files and folders (a stage's stamp, the fit's decoded-photo cache ``.texstream-cache``) are not inputs."""
    rows = sorted((str(p.relative_to(folder)), p.stat().st_size, p.stat().st_mtime_ns)
                  for p in folder.rglob("*")
                  if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts))
    return _hash(rows)


def detect_source(source: Path) -> str:
    """What kind of input a folder is: capture (capture.json or transforms.json), colmap or photos."""
    if not source.exists():
        raise InputError("input not found", source, "pass a folder of photos, a capture folder or a COLMAP model")
    if source.is_file():
        raise InputError("input is a file, not a folder", source, "pass the folder that holds the photos")
    if (source / "capture.json").is_file() or (source / "transforms.json").is_file():
        return "capture"
    for d in (source, source / "sparse", source / "sparse" / "0"):
        if any((d / f"cameras.{e}").is_file() for e in ("bin", "txt")):
            return "colmap"
    return "photos"


class Pipeline:
    """Runs the stages in order with stamps, skips and records (see the module doc)."""

    def __init__(self, out: Path, from_stage: str | None, log: Callable[[str], None]):
        self.out = out
        self.from_index = STAGES.index(from_stage) if from_stage else len(STAGES)
        self.records: list[StageRecord] = []
        self.log = log

    def skip(self, name: str, reason: str, output: Path | None = None) -> None:
        self.records.append(StageRecord(name, "skipped", reason, output=str(output) if output else None))
        self.log(f"[{name}] skipped: {reason}")

    def run(self, name: str, folder: Path, key: Any, reason: str, work: Callable[[], Any]) -> StageRecord:
        """Run ``work`` (a stage writing ``folder``) unless the folder's stamp matches ``key``."""
        stamp = folder / STAMP
        digest = _hash(name, key)
        forced = STAGES.index(name) >= self.from_index
        if not forced and stamp.is_file():
            try:
                old = json.loads(stamp.read_text())
            except (OSError, json.JSONDecodeError):
                old = {}
            if old.get("hash") == digest:
                rec = StageRecord(name, "skipped", "unchanged since the last run (same inputs and options)",
                                  output=str(folder), summary=old.get("summary", {}))
                self.records.append(rec)
                self.log(f"[{name}] {rec.reason}")
                return rec
        self.log(f"[{name}] {reason}")
        t0, c0 = time.perf_counter(), time.process_time()
        res = work()
        summary = getattr(res, "summary", None) or {}
        rec = StageRecord(name, "ran", reason, time.perf_counter() - t0, str(folder), _summary_safe(summary),
                          time.process_time() - c0)
        write_json_atomic(stamp, {"hash": digest, "summary": rec.summary, "seconds": rec.seconds})
        self.records.append(rec)
        self.log(f"[{name}] done in {rec.seconds:.1f} s")
        return rec

    def stamp_of(self, name: str) -> str:
        """The hash a stage ran with (the key of the stages after it)."""
        for r in reversed(self.records):
            if r.name == name and r.output:
                try:
                    return json.loads((Path(r.output) / STAMP).read_text())["hash"]
                except (OSError, KeyError, json.JSONDecodeError):
                    return "none"
        return "none"


def _summary_safe(summary: dict) -> dict:
    return json.loads(json.dumps(json_safe(summary), default=str))


def run_pipeline(source: str | Path, out: str | Path, config: RunConfig | None = None,
                 from_stage: str | None = None, log: Callable[[str], None] = print) -> dict:
    """Photos (or a capture / COLMAP folder) -> OUT/{capture,posed,mesh,atlas,model,export,report}.

    Returns the run summary written to ``OUT/run.json``. The stages' phase lines go to ``log`` and
    their bars show on a terminal when ``config.progress`` (:mod:`texstream.core.progress`).
    """
    cfg = config or RunConfig()
    with reporting(log, bars=cfg.progress):
        return _run_pipeline(source, out, cfg, from_stage, log)


def _run_pipeline(source: str | Path, out: str | Path, cfg: RunConfig, from_stage: str | None,
                  log: Callable[[str], None]) -> dict:
    check_config(cfg)
    src, out = Path(source), Path(out)
    if from_stage is not None and from_stage not in STAGES:
        raise ConfigError(f"--from {from_stage!r} is not a stage", fix=f"use one of {STAGES}")
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out, "choose another -o path")
    kind = detect_source(src)
    if cfg.mesh_file and not Path(cfg.mesh_file).exists():  # before any long work
        raise InputError("mesh file not found", cfg.mesh_file, "check --mesh-file")
    out.mkdir(parents=True, exist_ok=True)
    text = dumps(config_to_dict(cfg), header="texstream run: the resolved options (texstream run --config this file)")
    write_atomic_with(out / "run_config.toml", lambda fh: fh.write(text.encode()))
    t_start, c_start = time.perf_counter(), time.process_time()
    # run_config.toml keeps the option as asked (auto); every stage gets the device it resolves to
    asked = cfg.device
    cfg = dataclasses.replace(cfg, device=resolve_device(asked))
    log(f"[run] device {cfg.device}" + (f" ({asked}: the first CUDA device Warp sees, else the CPU)"
                                        if asked != cfg.device and asked.strip().lower() == "auto" else ""))
    pipe = Pipeline(out, from_stage, log)

    cap_dir = _ingest(pipe, src, kind, out, cfg)
    posed, posed_dir = _register(pipe, cap_dir, kind, out, cfg)
    capture = read_capture(posed_dir)
    cfg = _capture_mesh(cfg, capture, posed, posed_dir, log)
    if not (cfg.lights.sphere or cfg.lights.ball_masks):  # a mirror ball would give the capture lights later
        makes_mesh = cfg.mesh_file is None  # then the atlas and (for what it made) the refinement run too
        fit_kernels_ahead(posed_dir, dataclasses.replace(cfg.fit, device=cfg.device),
                          requested_model(capture, cfg.model)[0], mesh_modules() if makes_mesh else [], makes_mesh)
    fit_geometry = _mesh_and_atlas(pipe, posed, posed_dir, out, cfg)

    # lights: from mirror-ball photos when a ball is given
    posed_dir, lights_summary = _mirror_ball_lights(pipe, out, posed_dir, posed, capture, cfg)
    flash_summary = {}
    if not lights_summary and chart_flash_applies(capture):  # a flash and a colour chart: its intensity from it
        posed_dir, flash_summary = _chart_flash(pipe, out, posed_dir, posed)
    capture = read_capture(posed_dir)

    # refine: cameras registered here and a mesh made here, moved until the photos agree
    refine_cfg, why_refine = refine_decision(cfg, registered=not posed, mesh_made=cfg.mesh_file is None,
                                             atlas_folder=Path(fit_geometry).is_dir(), mesh_level=_mesh_level(pipe))
    if refine_cfg is None:
        pipe.skip("refine", why_refine)
    else:
        refine_dir = out / "refine"
        pipe.run("refine", refine_dir, [pipe.stamp_of("atlas"), pipe.stamp_of("mesh"), pipe.stamp_of("register"),
                                        pipe.stamp_of("lights"), _files_hash(posed_dir) if posed else "",
                                        str(fit_geometry), config_to_dict(refine_cfg), cfg.device], why_refine,
                 lambda: refine_stage(posed_dir, fit_geometry, refine_dir, refine_cfg, device=cfg.device, log=pipe.log))
        rec = pipe.records[-1]
        if rec.summary.get("kept") is False:  # its output is its input: the summary says so, not "refined"
            rec.reason += f"; not kept: {rec.summary.get('kept_why')}"
            posed_dir = fit_geometry = refine_dir
        else:
            posed_dir, fit_geometry = _judged_refinement(pipe, cfg, refine_cfg, capture, (posed_dir, fit_geometry),
                                                         refine_dir, out)
        capture = read_capture(posed_dir)

    model_dir = out / "model"
    fit_rec, model_kind, why = _fit(pipe, capture, posed, posed_dir, fit_geometry, model_dir, cfg, lights_summary)
    shutil.rmtree(choice_folder(model_dir), ignore_errors=True)  # a judged refinement's fit no choice took
    shutil.rmtree(out / JUDGE_WORK, ignore_errors=True)  # an interrupted judgement's, once the fit is done
    if isinstance((fit_rec.summary or {}).get("highlights"), dict):  # fit/common/highlights.py
        log(f"[fit] highlights: {fit_rec.summary['highlights']['line']}")

    inputs = dict(run_inputs(pipe.records, kind, capture, cfg.mesh_file), response=_response_input(pipe, capture),
                  **light_and_resolution_inputs(capture, model_dir, fit_geometry, flash_summary))
    for line in inputs_lines(inputs):
        log(f"[inputs] {line}")
    _export_and_report(pipe, out, model_dir, posed_dir, cfg.device, inputs)
    heldout = _heldout(model_dir)
    summary = {"source": str(src), "source_kind": kind, "device": cfg.device, "model": model_kind, "model_reason": why, "inputs": inputs,
               "total_s": time.perf_counter() - t_start, "total_cpu_s": time.process_time() - c_start,
               "heldout": heldout, "stages": [dataclasses.asdict(r) for r in pipe.records],
               "resolutions": stage_resolutions([dataclasses.asdict(r) for r in pipe.records], model_dir),
               "lights": lights_summary or flash_summary or {"source": _lights_source(capture)},
               "fit": fit_rec.summary, "warnings": run_warnings(pipe.records, heldout, fit_rec.summary)}
    write_json_atomic(out / "run.json", _summary_safe(summary))
    return summary


def _ingest(pipe: Pipeline, src: Path, kind: str, out: Path, cfg: RunConfig) -> Path:
    """The capture folder: photos ingested, a COLMAP model imported, or a capture folder read as it is."""
    if kind == "photos":
        n_photos = sum(1 for f in src.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_EXTS)
        if n_photos < MIN_PHOTOS:
            raise InputError(f"{n_photos} photo(s) found; registering cameras needs at least {MIN_PHOTOS}", src,
                             "add overlapping photos of the object (20 or more from all sides is typical)")
        cap_dir = out / "capture"
        pipe.run("ingest", cap_dir, [_files_hash(src), config_to_dict(cfg.ingest)],
                 f"photos in {src} -> capture folder (EXIF, masks, exposure)",
                 lambda: ingest(src, cap_dir, cfg.ingest))
        return cap_dir
    if kind == "colmap":
        cap_dir = out / "capture"
        pipe.run("ingest", cap_dir, [_files_hash(src)], f"COLMAP model in {src} -> capture folder",
                 lambda: import_colmap(src, cap_dir))
        return cap_dir
    pipe.skip("ingest", f"{src} is a capture folder already", src)
    return src


def mesh_modules() -> list:
    """The Warp modules of the mesh stage (dense stereo, the visual hull, its cleanup checks): built together on a
    cold GPU before the stage (fit/stages/prewarm.py ``build_kernels_ahead``), not one after another at launches."""
    return [wp.get_module(m.__name__) for m in (mvs, hull, reconstruct, scene, geometry_visibility)]


def _register(pipe: Pipeline, cap_dir: Path, kind: str, out: Path, cfg: RunConfig) -> tuple[bool, Path]:
    """(cameras given, the posed capture folder): registration skipped when every frame has a pose."""
    capture = read_capture(cap_dir)
    posed = capture.extra.get("posed", True) is not False and kind != "photos"  # ingest writes posed: false
    if posed:
        pipe.skip("register", "cameras known (every frame has a pose)", cap_dir)
        return True, cap_dir
    posed_dir = out / "posed"
    reg_cfg, why_reg = cfg.register, "cameras unknown: structure from motion (pycolmap)"
    fixed_light = not capture.has_lights and not capture.extra.get("colocated_light")
    if fixed_light and reg_cfg.photometric == "export":
        # one fixed lighting: an SfM point looks the same in every photo but for the photo's exposure and
        # white balance, so the gains the registration measures are the photos' (not so under a flash)
        reg_cfg = dataclasses.replace(reg_cfg, photometric="apply")
        why_reg += "; fixed unknown lighting: per-photo exposure gains from the SfM points applied"
    pipe.run("register", posed_dir, [pipe.stamp_of("ingest"), _files_hash(cap_dir) if kind == "capture" else "",
                                     config_to_dict(reg_cfg)], why_reg,
             lambda: register(cap_dir, posed_dir, reg_cfg, mesh_alignment=mesh_alignment))
    return False, posed_dir


def _capture_mesh(cfg: RunConfig, capture, posed: bool, posed_dir: Path, log: Callable[[str], None]) -> RunConfig:
    """The run's config with the mesh a posed capture carries (capture.json ``mesh``: an imported Metashape mesh,
    already in the cameras' frame) as its mesh file, unless one is given; it is used as it is, not aligned."""
    rel = capture.extra.get("mesh")
    if cfg.mesh_file is not None or not posed or not rel:
        return cfg
    path = posed_dir / str(rel)
    if not path.is_file():
        raise InputError(f"the capture names the mesh {rel}, which is missing", posed_dir / "capture.json",
                         "restore the file, or remove 'mesh' from capture.json to make a mesh from the photos")
    log(f"mesh: the capture's own ({path}), in its cameras' frame")
    return dataclasses.replace(cfg, mesh_file=str(path))


def _mesh_and_atlas(pipe: Pipeline, posed: bool, posed_dir: Path, out: Path, cfg: RunConfig) -> Path:
    """The fit's geometry: an atlas folder made here, the given atlas folder, or the given mesh with UVs."""
    mesh_dir, atlas_dir = out / "mesh", out / "atlas"
    mesh_path = Path(cfg.mesh_file) if cfg.mesh_file else None
    atlas_needed = True
    if mesh_path is not None:
        if not mesh_path.exists():
            raise InputError("mesh file not found", mesh_path, "check --mesh-file")
        pipe.skip("mesh", f"mesh given ({mesh_path})", mesh_path)
        if mesh_path.is_dir():  # an atlas folder (texstream atlas, a synthetic set's ground_truth/)
            if not (mesh_path / "bake.npz").is_file():
                raise InputError("folder has no bake.npz", mesh_path, "pass a mesh file or an atlas folder")
            atlas_needed = False
        else:
            atlas_needed = load_mesh(mesh_path).uvs is None
    cameras = pipe.stamp_of("register") if not posed else _files_hash(posed_dir)
    if mesh_path is None:
        pipe.run("mesh", mesh_dir, [cameras, pipe.stamp_of("ingest"), config_to_dict(cfg.mesh), cfg.device],
                 "mesh from the photos (dense stereo or SfM points, and masks)",
                 lambda: make_mesh(posed_dir, mesh_dir, dataclasses.replace(cfg.mesh, device=cfg.device)))
        mesh_path = mesh_dir / "mesh.ply"
    if atlas_needed:  # the posed photos cap its texel density (AtlasConfig.min_texel_pixels): their cameras key it
        pipe.run("atlas", atlas_dir, [pipe.stamp_of("mesh"), str(mesh_path), config_to_dict(cfg.atlas), cfg.device,
                                      cameras],
                 "UV atlas (xatlas) and texel bake",
                 lambda: atlas_stage(mesh_path, atlas_dir, cfg.atlas, device=cfg.device, photos=posed_dir))
        return atlas_dir
    pipe.skip("atlas", "the given mesh has UVs" if mesh_path.is_file() else "an atlas folder is given", mesh_path)
    return mesh_path


def run_choice_options(cfg: RunConfig) -> dict:
    """The model choice's options the run declares at its top level (``--second-lobe``, ``--lfm``, ...), by
    ModelChoiceConfig's own field names: they override ``cfg.fit.choice`` (tests/test_run_choice_options.py keeps
    their defaults and ranges the same as ModelChoiceConfig's)."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(ModelChoiceConfig) if hasattr(cfg, f.name)}


def _fit_config(cfg: RunConfig, capture, log=lambda m: None):
    """The fit stage's config for this capture: the run's device, model and top-level choice options; the ambient
    term at least auto where some photos were taken with the flash off."""
    fit_cfg = dataclasses.replace(cfg.fit, device=cfg.device, fit=dataclasses.replace(cfg.fit.fit, model=cfg.model),
                                  choice=dataclasses.replace(cfg.fit.choice, **run_choice_options(cfg)))
    if fit_cfg.fit.ambient == "off" and no_flash_frames(capture.frames):  # off would predict them black
        fit_cfg = dataclasses.replace(fit_cfg, fit=dataclasses.replace(fit_cfg.fit, ambient="auto"))
        log(f"[fit] ambient auto, not off: {len(no_flash_frames(capture.frames))} photos were taken with the "
            "flash off and see only the room's light")
    return fit_cfg


def _fit(pipe: Pipeline, capture, posed: bool, posed_dir: Path, fit_geometry: Path, model_dir: Path,
         cfg: RunConfig, lights_summary: dict | None):
    """(the fit stage's record, the kept model's kind, why): the model the scene needs (fit/stages/choice.py:
    with held-out photos, the candidates it calls for judged on a validation split of the fitted photos, the
    held-out ones scoring only the model kept: with known lights a specular lobe only where it generalises;
    under one fixed unknown lighting view dependence only where it does)."""
    fit_cfg = _fit_config(cfg, capture, pipe.log)
    plan = plan_choice(capture, cfg.model, fit_cfg)
    model_kind, why = plan.base, plan.reason
    if lights_summary:
        why += f" (from the mirror ball: {lights_summary['kind']} light, {lights_summary['views']} ball view(s))"
    escalates = plan.compare and registry.get(plan.base).escalate is not None

    def fit_work():
        if not plan.compare:
            return fit_stage(posed_dir, fit_geometry, model_dir, dataclasses.replace(
                fit_cfg, fit=dataclasses.replace(fit_cfg.fit, model=plan.base)))
        res = fit_choice(posed_dir, fit_geometry, model_dir, fit_cfg, plan, fit_candidate, pipe.log)
        forget_candidates(model_dir)  # candidates are kept only while their choice is unfinished
        return res

    fit_rec = pipe.run("fit", model_dir, [pipe.stamp_of("atlas"), pipe.stamp_of("mesh"), pipe.stamp_of("register"),
                                          pipe.stamp_of("lights"), pipe.stamp_of("refine"), str(posed_dir),
                                          str(fit_geometry), _files_hash(posed_dir) if posed else "",
                                          config_to_dict(fit_cfg), plan.compare]
                       + ([cfg.lfm, cfg.lfm_min_gain_db] if escalates else []),
                       f"{model_kind} model: {why}" + (f"; the {plan.also} model too, the best on a validation "
                                                       "split of the fitted photos kept" if plan.compare else ""),
                       fit_work)
    # which cameras and geometry it read (the refinement's, or the registered ones where it was not kept)
    fit_rec.summary["fitted_on"] = {"capture": str(posed_dir), "geometry": str(fit_geometry)}
    if plan.compare:
        chosen = fit_rec.summary.get("selection", {})
        if chosen.get("chosen"):
            model_kind = chosen["chosen_kind"]
            key = registry.get(plan.base).escalation_key
            why = f"{why}; " + (f"{chosen[key]}; " if chosen.get(key) else "") + chosen["reason"]
    return fit_rec, model_kind, why


def _mesh_level(pipe: Pipeline) -> int:
    """The pyramid level the run's mesh stage made its mesh at by dense stereo; -1: another source (sparse SfM points,
    the visual hull, a given mesh: RefineConfig ``mesh_level``)."""
    mesh = next((r.summary for r in pipe.records if r.name == "mesh"), None) or {}
    dense = mesh.get("dense") or {}
    return int(dense.get("level") or 0) if dense.get("used") else -1


def _judged_refinement(pipe: Pipeline, cfg: RunConfig, refine_cfg, capture, registered: tuple, refine_dir: Path,
                       out: Path) -> tuple[Path, Path]:
    """(capture folder, geometry) the fit gets after a refinement that kept its result: the refined ones, unless
    under known lights the fit predicts its validation photos better on the registered ones
    (pipelines/refine_judge.py); the run's refine line and summary say which and why."""
    rec = pipe.records[-1]
    why_not = judged_by_fit(capture, refine_cfg)
    if why_not:
        rec.summary["judged"] = {"by_fit": False, "why": why_not}
        return refine_dir, refine_dir
    fit_cfg = _fit_config(cfg, capture)
    key = inputs_key("refine judge", pipe.stamp_of("refine"), [str(p) for p in registered],
                     config_to_dict(judge_config(fit_cfg)), resolve_device(cfg.device))
    cache = out / JUDGED_FILE  # the judgement of an unchanged refinement is not fitted again
    try:
        earlier = json.loads(cache.read_text())
    except (OSError, json.JSONDecodeError):
        earlier = {}
    if earlier.get("key") == key and rec.status == "skipped":  # the refinement reused, not run again
        record = earlier["record"]
        pipe.log(f"[refine] judged by the fit (unchanged since the last run): {record['why']}")
    else:
        work = out / JUDGE_WORK
        record = judge_refinement(registered, (refine_dir, refine_dir), work, fit_cfg, pipe.log)[1]
        hand_to_choice(work, record["kept"], out / "model")  # the model choice's first fit, done
        if not any("error" in side for side in record["validation"].values()):  # a failed fit is tried again
            write_json_atomic(cache, {"key": key, "record": record})
    kept = record["kept"]
    rec.summary["judged"] = {"by_fit": True, **record}
    if kept:
        return refine_dir, refine_dir
    rec.reason += f"; not kept: {record['why']}"
    return registered


def refine_decision(cfg: RunConfig, registered: bool, mesh_made: bool, atlas_folder: bool, mesh_level: int = -1):
    """(the refine stage's config, or None to skip it; the reason). Auto refines cameras this run registered
    and a mesh it made; given ones are taken as exact. ``mesh_level``: the pyramid level the run's dense stereo
    made the mesh at (the vertices' bound is in its pixels, RefineConfig ``mesh_level``)."""
    rc = cfg.refine
    if rc.mode == "off":
        return None, "refine off"
    if not atlas_folder:
        return None, "the mesh's own UVs are used (no atlas folder to re-bake)"
    cameras, mesh = rc.cameras, rc.mesh
    if rc.mode == "auto":
        cameras, mesh = cameras and registered, mesh and mesh_made
    if not (cameras or mesh):
        return None, "cameras and mesh given (taken as exact)" if rc.mode == "auto" else "nothing to refine"
    what = " and ".join(x for x, on in (("cameras", cameras), ("mesh", mesh)) if on)
    rc = dataclasses.replace(rc, cameras=cameras, mesh=mesh, holdout_every=cfg.fit.holdout_every,
                             mesh_level=mesh_level if mesh else rc.mesh_level)
    held = (f"; held-out photos (every {rc.holdout_every}th) only aligned, moving no colour or vertex"
            if rc.holdout_every and rc.align_heldout and cameras else "")
    return rc, f"{what} refined against the photos (Gauss-Newton on one shared texture){held}"


def _response_input(pipe: Pipeline, capture) -> dict:
    """{source, why} of how the fitted photos' codes became radiance (capture.json's ``response``): ingest's
    decision when this run ingested the photos, else what the capture says."""
    ing = next((r.summary for r in pipe.records if r.name == "ingest" and r.summary.get("response")), {})
    response = capture.response
    if response is not None:
        return {"source": "colour chart", "why": str(ing.get("response", {}).get("why") or response.source)}
    if ing:
        return {"source": "sRGB" if ing["response"]["used"] == "srgb" else "none", "why": str(ing["response"]["why"])}
    return {"source": "sRGB", "why": "capture.json has no response: 8-bit photos decoded as sRGB"}


def _lights_source(capture) -> str:
    if capture.extra.get("lights_source"):
        return str(capture.extra["lights_source"])
    return "known per photo" if capture.has_lights else "none known"


def _mirror_ball_lights(pipe: Pipeline, out: Path, posed_dir: Path, posed: bool, capture, cfg: RunConfig
                        ) -> tuple[Path, dict]:
    """The lights stage: with a mirror ball (``[lights] sphere`` or ``ball_masks``), estimate the light
    from the ball photos of the posed capture (:func:`texstream.calib.lights.estimate_lights`) and
    write ``OUT/lights``: the estimate, and a capture of the other photos (``lights.frames`` names the
    ball photos; without it every photo shows the ball beside the object) lit by it, whose images
    stay where they are. Returns (the capture the fit reads, the lights summary or {})."""
    lcfg = cfg.lights
    if not (lcfg.sphere or lcfg.ball_masks):
        if chart_flash_applies(capture):
            return posed_dir, {}  # the lights stage is the chart's flash (_chart_flash)
        why = ("every photo has a known light" if capture.has_lights else
               "no light known and no mirror ball given (--mirror-ball X,Y,Z,R)")
        pipe.skip("lights", why)
        return posed_dir, {}

    if lcfg.sphere:
        _world_balls(lcfg)  # a bad ball fails here, before any long work
    lights_dir = out / "lights"
    ball = (f"mirror ball at {', '.join(f'{x:g}' for x in lcfg.sphere)}" if lcfg.sphere
            else f"mirror-ball masks in {lcfg.ball_masks}")
    rec = pipe.run("lights", lights_dir,
                   [pipe.stamp_of("register") if not posed else _files_hash(posed_dir), config_to_dict(lcfg)],
                   f"{ball}: the light from its photos"
                   + (" (overrides the capture's lights)" if capture.has_lights else ""),
                   lambda: lit_capture(posed_dir, lights_dir, lcfg))
    s = rec.summary
    pipe.log(f"[lights] {s['kind']} light from {s['views']} ball view(s); {s['photos']} photos lit by it")
    return lights_dir, {"source": "mirror ball", **s}


def _chart_flash(pipe: Pipeline, out: Path, posed_dir: Path, posed: bool) -> tuple[Path, dict]:
    """The lights stage of a flash capture with a colour chart in view (calib/chart_flash.py): OUT/lights, the posed
    capture with the flash's intensity from the chart. A chart too seldom seen, or misread, leaves the intensity
    as given, with the reason."""
    lights_dir = out / "lights"
    try:
        rec = pipe.run("lights", lights_dir, [pipe.stamp_of("register") if not posed else _files_hash(posed_dir)],
                       "a flash at the camera and a colour chart in view: the flash's intensity from the chart",
                       lambda: flash_lit_capture(posed_dir, lights_dir))
    except InputError as e:
        pipe.skip("lights", f"the flash's intensity stays as given: {e.message}")
        return posed_dir, {}
    pipe.log(f"[lights] {rec.summary['why']}")
    return lights_dir, {"source": "colour chart", **rec.summary}


def run_warnings(records: list[StageRecord], heldout: dict, fit_summary: dict) -> list[str]:
    """What a user must know about a run that finished: too few photos registered, no held-out view to
    judge the model by, parameters pinned at their bounds."""
    out = []
    reg = next((r for r in records if r.name == "register" and r.status == "ran"), None)
    if reg is not None:
        n_reg = len(reg.summary.get("registered") or [])
        n_all = n_reg + len(reg.summary.get("unregistered") or [])
        if n_all and n_reg < 0.5 * n_all:
            out.append(f"only {n_reg} of {n_all} photos registered: the model sees part of the object; more "
                       "overlapping photos (or a textured background) help structure from motion")
    if not heldout.get("views"):
        out.append("no held-out view: the held-out error is not measured (fewer photos than --holdout-every, "
                   "or holdout_every 0)")
    out += list(fit_summary.get("warnings") or [])
    return out


def _db(value) -> str:
    return "n/a" if value is None else f"{value:.2f} dB"


def _heldout(model_dir: Path) -> dict:
    try:
        return json.loads((model_dir / "model.json").read_text()).get("heldout", {})
    except (OSError, json.JSONDecodeError):
        return {}


def _export_and_report(pipe: Pipeline, out: Path, model_dir: Path, capture_dir: Path, device: str,
                       inputs: dict) -> None:
    """Exports (glTF binary, OBJ+MTL) and the HTML report (its held-out renders on the run's device)."""
    export_dir = out / "export"
    pipe.run("export", export_dir, [pipe.stamp_of("fit")], "glTF binary and OBJ+MTL",
             lambda: export_stage(model_dir, export_dir, ExportConfig(device=device)))
    t0, c0 = time.perf_counter(), time.process_time()
    stages = [dataclasses.asdict(r) for r in pipe.records]
    write_report(out, stages, model_dir, capture_dir, device=device, inputs=inputs)
    pipe.records.append(StageRecord("report", "ran", "HTML report with the relightable viewer",
                                    time.perf_counter() - t0, str(out / "report"),
                                    cpu_seconds=time.process_time() - c0))
    pipe.log(f"[report] {out / 'report' / 'index.html'}")
