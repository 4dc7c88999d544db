"""The end-to-end run's report: one self-contained HTML page (``OUT/report/index.html``).

:func:`write_report` writes, atomically, a folder that opens from disk with no network:

- the stages of the run: what each did or skipped and why, and its time;
- the fit: error against run time (trace.json), final figures;
- held-out PSNR: pooled (PSNR of the mean MSE over the held-out views), the worst view and the
  mean, per view; held-out photos beside the fitted renders with error images;
- the parameter maps as PNG previews, the cameras and lights around the mesh;
- an interactive relightable WebGL2 viewer (``report_assets/viewer.js``) that evaluates the
  fitted model from its parameter textures with the fit's own shading (docs/report.md). Its
  data (mesh, float parameter textures, cameras, lights, a few photos) is inlined as base64 in a
  JSON script block, and the JS and CSS are inlined too, so ``file://`` loading needs nothing else.
  The model's plugin gives the viewer its per-texel data, extra textures and GLSL shading function
  (fit/models/registry.py ``ViewerModel``); the report never asks which kind a model is.

Heavy imports (matplotlib, OpenImageIO through capture.imageio, warp through the renderer) are
inside the functions.
"""

from __future__ import annotations

import base64
import datetime
import html
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from texstream.capture.capture_json import read_capture
from texstream.capture.conventions import w2c_cv_to_c2w_gl
from texstream.capture.imageio import linear_to_srgb, read_image
from texstream.core.errors import ConfigError, InputError, TexstreamError
from texstream.core.outputs import StageResult, atomic_output_dir, read_json
from texstream.core.progress import bar
from texstream.fit.models import registry
from texstream.fit.stages.stage import image_metrics
from texstream.pipelines.resolutions import resolutions_html, stage_resolutions

ASSETS = Path(__file__).with_name("report_assets")
STAGE_STATUSES = ("ran", "skipped")
MAX_VIEWER_FRAMES = 400
"""cameras and lights listed in the viewer's photo menu (poses only: a few hundred bytes each)"""


# --------------------------------------------------------------------------- model loading


def load_report_model(model_dir: str | Path):
    """(mesh with normals, viewer grid (H, W, P) float32, info dict, model.json) of a model folder, read by
    the plugin of its kind (model.json's ``layout.kind``, or ``kind`` for a folder without a layout).

    ``info``: kind, layout (the per-texel ModelLayout, or None for a model without one), model (the
    FittedModel) and viewer (its ViewerModel, whose grid the viewer grid is).
    """
    model = registry.load_model_folder(model_dir)
    vm = model.viewer()
    return model.mesh, vm.grid, {"kind": model.kind, "layout": getattr(model, "layout", None), "model": model,
                                 "viewer": vm}, model.manifest


def _b64(a: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear -> sRGB 8-bit codes (clip, encode, round half up), as capture.imageio writes PNGs."""
    return np.floor(np.clip(linear_to_srgb(np.clip(linear, 0.0, 1.0)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def viewer_frame(frame, held_out: bool = False, photo: np.ndarray | None = None, photo_max_side: int = 512) -> dict:
    """A capture frame as the viewer takes it: camera_to_world (capture.json's OpenGL axes),
    pinhole intrinsics (pixels, centres at +0.5), light, exposure; ``photo`` (linear, H x W x 3)
    is embedded as sRGB 8-bit, downscaled to at most ``photo_max_side`` pixels."""
    k = frame.intrinsics
    out = {"name": frame.name, "camera_to_world": w2c_cv_to_c2w_gl(frame.R, frame.t).tolist(),
           "fx": float(k.fx), "fy": float(k.fy), "cx": float(k.cx), "cy": float(k.cy),
           "width": int(k.width), "height": int(k.height), "exposure": float(frame.exposure),
           "light": frame.light.to_json() if frame.light is not None else None, "held_out": bool(held_out),
           "photo": None}
    if photo is not None:
        img = np.asarray(photo, dtype=np.float32)[..., :3]
        s = photo_max_side / max(img.shape[:2])
        if s < 1:
            import cv2

            img = cv2.resize(img, (max(1, round(img.shape[1] * s)), max(1, round(img.shape[0] * s))),
                             interpolation=cv2.INTER_AREA)
        out["photo"] = {"width": int(img.shape[1]), "height": int(img.shape[0]), "data": _b64(_srgb8(img), "u1")}
    return out


def face_tangents(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """(F, 3) dp/du of each face's UV mapping (zero where the UVs are degenerate), as surface_frame in
    render/shading.py computes it before making it orthogonal to the shading normal."""
    p = np.asarray(vertices, np.float64)[faces]
    t = np.asarray(uvs, np.float64)[faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    ok = np.abs(det) > 1e-20
    tan = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / np.where(ok, det, 1.0)[:, None]
    return np.where(ok[:, None], tan, 0.0)


def viewer_model_data(mesh, info: dict, frames: list[dict] | None = None, seen: np.ndarray | None = None,
                      default_frame: int = 0) -> dict:
    """The viewer's model block: mesh (positions, vertex normals as the renderer computes them,
    UVs, triangle indices), parameters as RGBA32F texture layers (parameter k in layer k // 4,
    channel k % 4; row 0 = top row of the texel grid), the seen map and the frames, with the plugin's
    GLSL (``shader``) and data (``uniforms``: integer uniforms; ``textures``: RGBA32F textures of their
    own, bound to units 3, 4, ...)."""
    vm = info["viewer"]
    g = np.asarray(vm.grid, dtype=np.float32)
    if g.ndim != 3 or g.shape[0] < 2 or g.shape[1] < 2:
        raise ConfigError(f"parameter grid has shape {g.shape}, expected (H >= 2, W >= 2, P)")
    if not np.all(np.isfinite(g)):
        raise InputError("parameter maps hold NaN or Inf", fix="re-run the fit (padding texels must be filled)")
    h, w, p = g.shape
    layers = (p + 3) // 4
    tex = np.zeros((h, w, layers * 4), np.float32)
    tex[..., :p] = g
    tex = tex.reshape(h, w, layers, 4).transpose(2, 0, 1, 3)  # (layers, H, W, 4)
    if mesh.uvs is None:
        raise InputError("the model's mesh has no UVs", fix="re-run the fit from an atlas folder")
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    faces = np.asarray(mesh.faces, np.int64)
    data = {
        "kind": info["kind"], "n_params": int(p), "shader": vm.shader, "uniforms": {}, "textures": [],
        "texture": {"width": int(w), "height": int(h), "layers": int(layers), "data": _b64(tex, "<f4")},
        # one vertex per face corner, so each face carries its own tangent (dp/du, what fit/kernels/
        # shading.py surface_frame computes): derivatives taken on screen break where a 2x2 pixel quad
        # straddles two charts of the atlas
        "mesh": {"positions": _b64(v[faces].reshape(-1, 3), "<f4"),
                 "normals": _b64(mesh.vertex_normals()[faces].reshape(-1, 3), "<f4"),
                 "uvs": _b64(np.asarray(mesh.uvs)[faces].reshape(-1, 2), "<f4"),
                 "tangents": _b64(np.repeat(face_tangents(v, faces, mesh.uvs), 3, axis=0), "<f4"),
                 "indices": _b64(np.arange(faces.size, dtype=np.uint32), "<u4"),
                 "n_vertices": int(faces.size), "n_faces": len(faces)},
        "center": ((lo + hi) / 2).tolist(), "radius": float(max(np.linalg.norm(hi - lo) / 2, 1e-9)),
        "seen": None, "frames": frames or [], "default_frame": int(default_frame),
    }
    if seen is not None:
        s = np.asarray(seen)
        if s.shape[:2] == (h, w):
            data["seen"] = _b64((s.reshape(h, w, -1)[..., 0] > 0.5).astype(np.uint8) * 255, "u1")
    data.update(vm.data)
    return data


# --------------------------------------------------------------------------- held-out evaluation


def pooled_psnr(psnrs) -> float:
    """PSNR of the mean MSE over views (each view's MSE from its PSNR, peak 1)."""
    v = [x for x in psnrs if x is not None and math.isfinite(x)]
    if not v:
        return float("nan")
    return float(-10.0 * math.log10(np.mean([10.0 ** (-x / 10.0) for x in v])))


def _holdout_every(model_dir: Path) -> int:
    p = model_dir / "fit_config.json"
    if not p.is_file():
        return 0
    return int(read_json(p, what="fit config").get("holdout_every", 0) or 0)


def evaluate_views(model, capture, frames, device: str) -> list[dict]:
    """Render the model (its plugin's renderer) for each frame; foreground = render coverage and the photo's
    mask."""
    rows = []
    render_frame = model.renderer(device)
    for f in bar(frames, "report: held-out renders", unit="view"):
        photo = read_image(capture.image_path(f), channels=3, response=capture.response)
        render, rmask = render_frame(f)
        m = capture.within_mask(f, rmask.astype(bool))
        rows.append({"frame": f.file_path, "name": f.name, **image_metrics(render, photo, m),
                     "_render": render, "_photo": photo, "_mask": m})
    return rows


def _split_fit_vs_photo(path: Path):
    """(render, photo) linear from a renders/*_fit_vs_photo.png (render | photo side by side)."""
    img = read_image(path, channels=3)
    w = img.shape[1] // 2
    return img[:, :w], img[:, w:2 * w]


# --------------------------------------------------------------------------- figures


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_error_vs_time(trace: list[dict], path: Path) -> None:
    """Objective (and, where the trace has it, the fitted samples' PSNR) against the fit's run time."""
    plt = _plt()
    has_psnr = all("psnr_db" in r for r in trace)
    fig, ax = plt.subplots(1, 2 if has_psnr else 1, figsize=(10 if has_psnr else 5, 3.4), squeeze=False)
    ax = ax[0]
    t = [r["time_s"] for r in trace]
    ax[0].semilogy(t, [max(float(r["objective"]), 1e-300) for r in trace], "o-", ms=3)
    ax[0].set_xlabel("fit run time (s)")
    ax[0].set_ylabel("objective (sum of squared residuals)")
    ax[0].grid(alpha=0.3)
    if not has_psnr:
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        return
    ax[1].plot(t, [r["psnr_db"] for r in trace], "o-", ms=3, color="C1")
    ax[1].set_xlabel("fit run time (s)")
    ax[1].set_ylabel("PSNR of the fitted samples (dB)")
    ax[1].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_heldout_psnr(rows: list[dict], pooled: float, path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(4.0, 0.35 * len(rows) + 2), 3.0))
    vals = [r["psnr_db"] for r in rows]
    worst = int(np.nanargmin(vals))
    ax.bar(range(len(rows)), vals, color=["C3" if i == worst else "C0" for i in range(len(rows))])
    ax.axhline(pooled, color="k", ls="--", lw=1, label=f"pooled {pooled:.2f} dB")
    ax.set_xticks(range(len(rows)), [r["name"] for r in rows], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("PSNR (dB)")
    lo = np.nanmin(vals)
    ax.set_ylim(max(0.0, lo - 5), np.nanmax(vals) + 2)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_comparison(photo: np.ndarray, render: np.ndarray, mask: np.ndarray | None, title: str, path: Path) -> None:
    """Photo | fitted render | error (per-pixel RMS over RGB of render - photo, linear)."""
    plt = _plt()

    err = np.sqrt(np.mean((render.astype(np.float64) - photo) ** 2, axis=2))
    if mask is not None:
        err = np.where(mask, err, np.nan)
    vmax = float(np.nanpercentile(err, 99)) if np.any(np.isfinite(err)) else 1.0
    fig, ax = plt.subplots(1, 3, figsize=(8.4, 2.7))
    for a, img, name in ((ax[0], photo, "photo"), (ax[1], render, "fitted render")):
        a.imshow(linear_to_srgb(np.clip(img, 0, 1)), interpolation="nearest")
        a.set_title(name, fontsize=9)
    cm = plt.get_cmap("magma").with_extremes(bad="#3a5f7a")
    im = ax[2].imshow(err, cmap=cm, vmin=0, vmax=max(vmax, 1e-6), interpolation="nearest")
    ax[2].set_title("|render - photo| (linear RMS; blue = background)", fontsize=9)
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax:
        a.set_axis_off()
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def param_map_figures(model, seen: np.ndarray | None, folder: Path, model_dir: Path | None = None) -> list[tuple[str, str]]:
    """PNG previews of each parameter map (the plugin's ``report_maps``; and, from ``model_dir``, the lobe
    uncertainty and the shared materials when the fit wrote them); returns (file name, caption) pairs."""
    plt = _plt()

    out = []

    def save(name, img, caption, cmap=None, vmin=None, vmax=None, colorbar_label=None):
        fig, ax = plt.subplots(figsize=(4.2, 3.6))
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        if cmap is not None:
            fig.colorbar(im, ax=ax, fraction=0.046, label=colorbar_label)
        ax.set_title(name, fontsize=9)
        ax.set_axis_off()
        fig.tight_layout()
        fig.savefig(folder / f"{name}.png", dpi=90)
        plt.close(fig)
        out.append((f"maps/{name}.png", caption))

    model.report_maps(save, seen)
    if seen is not None:
        save("seen", seen.reshape(seen.shape[0], seen.shape[1], -1)[..., 0], "texels some fitted photo saw (1) "
             "or none did (0: they keep default values)", cmap="gray", vmin=0, vmax=1)
    if model_dir is not None and (Path(model_dir) / "uncertainty.exr").is_file():
        unc = read_image(Path(model_dir) / "uncertainty.exr", channels=3)
        save("uncertainty_n", np.log10(np.clip(unc[..., 1], 1e-4, 1e6)),
             "how well the photos constrain each texel's lobe exponent: log10 of the relative standard deviation "
             "of n from J^T J (above -1, i.e. 10%: the texel borrows its material's lobe; 6: not seen at all)",
             cmap="magma", vmin=-4, vmax=2, colorbar_label="log10 std(n) / n")
    if model_dir is not None and (Path(model_dir) / "materials.png").is_file():
        lobes = (read_image(Path(model_dir) / "lobes.png", channels=3) if (Path(model_dir) / "lobes.png").is_file()
                 else None)
        save("materials", read_image(Path(model_dir) / "materials.png", channels=3, linear=False),
             "shared materials: each texel's material (one colour each)")
        if lobes is not None:
            save("lobes", lobes[..., 0], "lobes: own (white), borrowed from the material (grey), none (dark grey)",
                 cmap="gray", vmin=0, vmax=1)
    return out


def plot_rig(mesh, frames, path: Path) -> None:
    """Cameras (centres and viewing directions) and lights around the mesh: 3D, top and side."""
    plt = _plt()
    v = np.asarray(mesh.vertices, np.float64)
    step = max(1, len(v) // 3000)
    vs = v[::step]
    lo, hi = v.min(axis=0), v.max(axis=0)
    c0 = (lo + hi) / 2
    size = float(np.linalg.norm(hi - lo)) or 1.0
    centres = np.array([f.center for f in frames]) if frames else np.zeros((0, 3))
    fwd = np.array([np.asarray(f.R)[2] for f in frames]) if frames else np.zeros((0, 3))  # OpenCV +z, world
    pts = [l for l in (f.light for f in frames) if l is not None]
    lp = np.array([l.position for l in pts if l.type == "point"]).reshape(-1, 3)
    ld = np.array([l.direction for l in pts if l.type == "directional"]).reshape(-1, 3)
    arrow = 0.15 * size
    fig = plt.figure(figsize=(13, 4.3))
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    ax.scatter(*vs.T, s=1, c="0.55", alpha=0.5)
    if len(centres):
        ax.scatter(*centres.T, s=14, c="C0", label="cameras")
        ax.quiver(*centres.T, *(fwd * arrow).T, color="C0", lw=0.8)
    if len(lp):
        ax.scatter(*lp.T, s=22, c="C1", marker="*", label="point lights")
    if len(ld):
        start = c0 - ld * size
        ax.quiver(*start.T, *(ld * 0.5 * size).T, color="C3", lw=0.8, label="directional lights")
    allp = np.concatenate([vs, centres, lp, c0 - ld * size if len(ld) else np.zeros((0, 3))])
    mid, half = (allp.max(0) + allp.min(0)) / 2, float((allp.max(0) - allp.min(0)).max()) / 2 or 1.0
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.legend(fontsize=7, loc="upper left")
    for k, (a, b, name) in enumerate(((0, 1, "top view (x, y)"), (0, 2, "side view (x, z)"))):
        ax2 = fig.add_subplot(1, 3, 2 + k)
        ax2.scatter(vs[:, a], vs[:, b], s=1, c="0.55", alpha=0.5)
        if len(centres):
            ax2.scatter(centres[:, a], centres[:, b], s=12, c="C0")
            ax2.quiver(centres[:, a], centres[:, b], fwd[:, a], fwd[:, b], color="C0", width=0.003,
                       scale=1.0 / arrow, scale_units="xy", angles="xy")
        if len(lp):
            ax2.scatter(lp[:, a], lp[:, b], s=24, c="C1", marker="*")
        if len(ld):
            s2 = c0 - ld * size
            ax2.quiver(s2[:, a], s2[:, b], ld[:, a], ld[:, b], color="C3", width=0.003,
                       scale=2.0 / size, scale_units="xy", angles="xy")
        ax2.set_aspect("equal", adjustable="datalim")
        ax2.set_title(name, fontsize=9)
        ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --------------------------------------------------------------------------- HTML


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _fmt(x: Any) -> str:
    if isinstance(x, bool) or x is None:
        return str(x)
    if isinstance(x, float):
        return "nan" if not math.isfinite(x) else f"{x:.4g}"
    if isinstance(x, (list, tuple)) and len(x) <= 6:
        return ", ".join(_fmt(v) for v in x)
    if isinstance(x, (list, tuple, dict)):
        s = json.dumps(x, default=str)
        return s if len(s) < 160 else s[:157] + "..."
    return str(x)


def _check_stages(stages) -> list[dict]:
    out = []
    for i, s in enumerate(stages or []):
        if not isinstance(s, dict) or "name" not in s or s.get("status") not in STAGE_STATUSES:
            raise ConfigError(f"stage {i} is {s!r}",
                              fix="pass dicts {name, status: 'ran'|'skipped', reason, seconds, summary}")
        out.append(s)
    return out


def _inputs_html(inputs: dict) -> str:
    rows = "".join(f"<tr><td>{_e(k)}</td><td>{_e(v.get('source', ''))}</td><td>{_e(v.get('why', ''))}</td></tr>"
                   for k, v in inputs.items())
    return ("<h2>What the model was built from</h2><table><tr><th>input</th><th>source</th><th>why</th></tr>"
            + rows + "</table>")


def _stages_html(stages: list[dict]) -> str:
    if not stages:
        return "<p class='note'>No stage list was given.</p>"
    rows = []
    for s in stages:
        summ = s.get("summary") or {}
        if isinstance(summ, dict):
            summ_html = "<br>".join(f"{_e(k)}: {_e(_fmt(v))}" for k, v in summ.items() if not str(k).startswith("_"))
        else:
            summ_html = _e(summ)
        sec = s.get("seconds")
        rows.append(f"<tr class='{_e(s['status'])}'><td>{_e(s['name'])}</td>"
                    f"<td class='status-{_e(s['status'])}'>{_e(s['status'])}</td>"
                    f"<td>{_e(s.get('reason') or '')}</td>"
                    f"<td class='num'>{'' if sec is None else f'{float(sec):.1f} s'}</td><td>{summ_html}</td></tr>")
    total = sum(float(s.get("seconds") or 0) for s in stages)
    return ("<table><tr><th>stage</th><th>status</th><th>what / why</th><th>time</th><th>summary</th></tr>"
            + "".join(rows) + f"<tr><th colspan=3>total</th><td class='num'>{total:.1f} s</td><td></td></tr></table>")


def _fig(src: str, caption: str) -> str:
    return f"<figure><img src='{_e(src)}' alt='{_e(caption)}' loading='lazy'><figcaption>{_e(caption)}</figcaption></figure>"


VIEWER_HTML = """
<section id="viewer-section">
<h2>Interactive relightable viewer</h2>
<p class="note">The fitted model rendered by WebGL2 from its parameter textures with the fit's shading
(Lafortune BRDF of render/shading.py, evaluated at the four texels around each pixel and blended
bilinearly; pixel = exposure &times; f<sub>r</sub> &times; E &times; cos&theta;<sub>i</sub>, sRGB for display).
Drag to orbit, wheel to zoom, shift-drag (or right-drag) to move the light. No cast shadows.
%%KIND_NOTE%%</p>
<div id="viewer-panel">
<canvas id="viewer-canvas" width="512" height="512"></canvas>
<div id="viewer-controls">
<label>view <select id="ctl-frame"></select></label>
<label>show <select id="ctl-mode">
<option value="full">full model</option><option value="diffuse">diffuse term only</option>
<option value="specular">specular lobes only</option><option value="error">error |render - photo| x4</option>
<option value="photo">photo</option><option value="unseen">texels no photo saw (magenta)</option>
</select></label>
<label>light azimuth <input id="ctl-laz" type="range" min="-180" max="180" step="1"></label>
<label>light elevation <input id="ctl-lel" type="range" min="-89" max="89" step="1"></label>
<label>exposure <input id="ctl-exp" type="range" min="-6" max="6" step="0.1" value="0"> <span id="ctl-exp-out"></span></label>
<p id="viewer-note" class="note"></p>
<pre id="viewer-status">{"ready": false, "errors": ["viewer script did not run"]}</pre>
</div>
</div>
</section>
"""


def _page(title: str, body: str, model_data: dict) -> str:
    tpl = (ASSETS / "report.html").read_text()
    css = (ASSETS / "report.css").read_text()
    js = (ASSETS / "viewer.js").read_text()
    model_json = json.dumps(model_data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    # one pass over the placeholders, so text inside the inserted parts is never substituted
    parts = {"%%TITLE%%": _e(title), "%%CSS%%": css, "%%BODY%%": body, "%%MODEL_JSON%%": model_json,
             "%%VIEWER_JS%%": js.replace("</script", "<\\/script")}
    import re

    return re.sub("|".join(re.escape(k) for k in parts), lambda m: parts[m.group(0)], tpl)


# --------------------------------------------------------------------------- the report


def write_report(out_dir: str | Path, stages: list[dict], model_dir: str | Path, capture_dir: str | Path | None = None,
                 *, device: str = "cpu", inputs: dict | None = None, title: str = "texstream run report",
                 max_comparisons: int = 4,
                 max_photos: int = 8, photo_max_side: int = 512) -> StageResult:
    """Write ``out_dir/report/`` (index.html plus its PNG figures) atomically.

    Args:
        out_dir: the run's output folder; the report goes to ``out_dir/report``.
        stages: per stage a dict {name, status: "ran" | "skipped", reason, seconds, summary (dict)}.
        model_dir: a model folder written by ``texstream.fit.stages.stage.fit_stage``.
        capture_dir: the capture the model was fitted to; with it the held-out views (fit_config.json's
            holdout_every) are rendered and scored here, the viewer gets every camera and light and
            a few photos, and the rig is plotted. Without it the report uses model.json's render_eval
            and renders/ images.
        device: Warp device for the held-out renders.
        inputs: what the model was built from, {input: {source, why}} (pipelines/provenance.py).
        max_comparisons: held-out views shown as photo | render | error (the worst first).
        max_photos: photos embedded in the viewer (held-out first) for its error view.
        photo_max_side: embedded photos are downscaled to at most this many pixels.

    Returns:
        StageResult(output=report folder, summary: html path, held-out PSNR figures, views).
    """
    t0 = time.perf_counter()
    stages = _check_stages(stages)
    model_dir = Path(model_dir)
    mesh, grid, info, man = load_report_model(model_dir)
    trace = read_json(model_dir / "trace.json", what="fit trace") if (model_dir / "trace.json").is_file() else []
    trace = trace or man.get("trace") or []  # a fit with no trace.json may keep its trace in model.json
    seen = None
    if (model_dir / "seen.png").is_file():
        seen = read_image(model_dir / "seen.png", channels=1, linear=False)[..., 0]
    capture = None
    if capture_dir is not None:
        capture = read_capture(capture_dir)

    out_dir = Path(out_dir)
    summary: dict[str, Any] = {}
    with atomic_output_dir(out_dir / "report") as tmp:
        os.chmod(tmp, 0o755)  # mkdtemp makes it 0700; a report is for reading
        (tmp / "maps").mkdir()
        (tmp / "views").mkdir()
        when = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
        sections = [f"<h1>{_e(title)}</h1><p class='meta'>{_e(when)} &middot; model {_e(model_dir.resolve())}"
                    + (f" &middot; capture {_e(Path(capture_dir).resolve())}" if capture_dir else "") + "</p>",
                    *([_inputs_html(inputs)] if inputs else []), "<h2>Stages</h2>" + _stages_html(stages),
                    resolutions_html(stage_resolutions(stages, model_dir))]
        if man.get("warnings"):  # the fit's warnings (bounds, numerics), one line each
            sections.append("<h2>Warnings</h2><ul class='warnings'>"
                            + "".join(f"<li>{_e(w)}</li>" for w in man["warnings"]) + "</ul>")
        sections.append(_fit_section(info["model"], grid, trace, tmp))
        rows, source, k, held_names = _heldout_rows(info["model"], capture, model_dir, device)
        sections.append(_heldout_section(rows, source, k, model_dir, tmp, max_comparisons, summary))
        sections.append(_relit_section(info["model"], capture, rows, tmp, device))
        vframes, default = _viewer_frames(capture, held_names, max_photos, photo_max_side)
        model_data = viewer_model_data(mesh, info, vframes, seen, default)
        sections.append(VIEWER_HTML.replace("%%KIND_NOTE%%", _e(info["viewer"].note)))
        sections.append(_maps_section(info, grid, seen, tmp, model_dir))
        if capture is not None:
            plot_rig(mesh, capture.frames, tmp / "rig.png")
            sections.append("<h2>Cameras and lights</h2>" + _fig(
                "rig.png", f"{len(capture.frames)} cameras (blue: centre and viewing direction) and their lights "
                "(orange stars: point lights; red arrows: directional lights) around the mesh (grey)."))
        else:
            sections.append("<h2>Cameras and lights</h2><p class='note'>No capture folder was given.</p>")

        page = _page(title, "\n".join(sections), model_data)
        (tmp / "index.html").write_text(page, encoding="utf-8")
    html_path = out_dir / "report" / "index.html"
    summary.update({"html": str(html_path), "seconds": time.perf_counter() - t0,
                    "html_bytes": html_path.stat().st_size})
    return StageResult(out_dir / "report", summary)


def _fit_section(model, grid: np.ndarray, trace: list[dict], tmp: Path) -> str:
    """The fit's figures (the plugin's ``report_facts`` replace or add rows) and its error against time."""
    man = model.manifest
    fin = man.get("final") or {}
    atlas = man.get("atlas") or {}
    kp = [("model", model.kind),
          ("texels", f"{atlas.get('texels', '?')} of {grid.shape[1]}x{grid.shape[0]}"
           + (f", {atlas['unseen_texels']} unseen" if "unseen_texels" in atlas else "")),
          ("photos", (f"{(man.get('photos') or {}).get('fitted', '?')} fitted, "
                      f"{(man.get('photos') or {}).get('held_out', '?')} held out")),
          ("iterations", _fmt(fin.get("iteration"))), ("fit time", f"{_fmt(fin.get('time_s'))} s"),
          ("set-up time", f"{_fmt(man.get('setup_s'))} s"),
          ("sample PSNR", f"{_fmt(fin.get('psnr_db'))} dB"), ("device", man.get("device", "?"))]
    facts = dict(model.report_facts())
    kp = [(k, facts.pop(k, v)) for k, v in kp] + list(facts.items())
    fit_html = ["<h2>Fit</h2><div>" + "".join(f"<span class='kpi'>{_e(k)}<b>{_e(v)}</b></span>" for k, v in kp)
                + "</div>"]
    if trace:
        plot_error_vs_time(trace, tmp / "error_vs_time.png")
        fit_html.append(_fig("error_vs_time.png", "Objective and PSNR of the fitted samples against the fit's "
                             "run time (trace.json; set-up time not included)."))
    else:
        fit_html.append("<p class='note'>No trace.json in the model folder: no error-against-time plot.</p>")
    return "".join(fit_html)


def _heldout_rows(model, capture, model_dir: Path, device: str) -> tuple[list[dict], str, int, set[str]]:
    """(rows, their source, holdout_every, held-out frame names): the held-out views rendered here with the
    capture, else model.json's render_eval with the fit's renders/ images."""
    k = _holdout_every(model_dir)
    rows: list[dict] = []
    held_names: set[str] = set()
    source = ""
    if capture is not None:
        held = [f for i, f in enumerate(capture.frames) if k > 0 and i % k == k - 1]
        held_names = {f.name for f in held}
        try:
            rows = evaluate_views(model, capture, held, device)
            source = (f"rendered here for the {len(held)} photos held out of the fit "
                      f"(every {k}th photo, fit_config.json)")
        except TexstreamError as e:
            source = f"model.json render_eval (rendering here failed: {e})"
            rows = []
    if not rows:
        evals = [r for r in model.manifest.get("render_eval") or [] if r.get("held_out")]
        for r in evals:
            name = Path(r["frame"]).stem
            row = {"frame": r["frame"], "name": name, "psnr_db": r["psnr_db"], "ape_percent": r.get("ape_percent"),
                   "pixels": r.get("pixels")}
            png = model_dir / "renders" / f"{name}_fit_vs_photo.png"
            if png.is_file():
                row["_render"], row["_photo"] = _split_fit_vs_photo(png)
                row["_mask"] = None
            rows.append(row)
        if evals and not source:
            source = "model.json render_eval (held-out views the fit rendered)"
    return rows, source, k, held_names


def _heldout_section(rows: list[dict], source: str, k: int, model_dir: Path, tmp: Path, max_comparisons: int,
                     summary: dict) -> str:
    """Held-out PSNR: figures (added to ``summary``), per-view table and plot, photo | render | error."""
    ho = ["<h2>Held-out PSNR</h2>"]
    if not rows:
        ho.append("<p class='note'>No held-out views: the fit held no photo out (fit_config.json holdout_every = "
                  f"{k}) or no capture folder was given. Fitted-view renders follow.</p>")
        renders = sorted((model_dir / "renders").glob("*_fit_vs_photo.png")) if (model_dir / "renders").is_dir() else []
        for png in renders[:max(max_comparisons, 0)]:
            name = png.name[: -len("_fit_vs_photo.png")]
            rend, photo = _split_fit_vs_photo(png)
            plot_comparison(photo, rend, None, f"{name} (fitted view)", tmp / "views" / f"{name}.png")
            ho.append(_fig(f"views/{name}.png", f"{name} (a fitted view, not held out): photo, render, error"))
        return "".join(ho)
    ps = [r["psnr_db"] for r in rows]
    pooled = pooled_psnr(ps)
    wi = int(np.nanargmin(ps))
    summary.update({"heldout_views": len(rows), "heldout_pooled_psnr_db": pooled,
                    "heldout_worst_psnr_db": float(ps[wi]), "heldout_worst_view": rows[wi]["name"],
                    "heldout_mean_psnr_db": float(np.nanmean(ps))})
    ho.append("<div>" + "".join(f"<span class='kpi'>{_e(a)}<b>{_e(b)}</b></span>" for a, b in (
        ("pooled (PSNR of the mean MSE)", f"{pooled:.2f} dB"),
        ("worst view", f"{ps[wi]:.2f} dB ({rows[wi]['name']})"),
        ("mean of the views' PSNR", f"{np.nanmean(ps):.2f} dB"), ("views", len(rows)))) + "</div>")
    ho.append(f"<p class='note'>Source: {_e(source)}. PSNR against peak 1 over foreground pixels (render "
              "coverage and the photo's mask), linear values with the frame's exposure.</p>")
    plot_heldout_psnr(rows, pooled, tmp / "heldout_psnr.png")
    ho.append(_fig("heldout_psnr.png", "PSNR per held-out view (worst in red); dashed: pooled."))
    ho.append("<table><tr><th>view</th><th>PSNR (dB)</th><th>APE (%)</th><th>pixels</th></tr>" + "".join(
        f"<tr{' class=worst' if i == wi else ''}><td>{_e(r['name'])}</td><td class='num'>{_fmt(r['psnr_db'])}</td>"
        f"<td class='num'>{_fmt(r.get('ape_percent'))}</td><td class='num'>{_fmt(r.get('pixels'))}</td></tr>"
        for i, r in enumerate(rows)) + "</table>")
    order = [wi] + [i for i in range(len(rows)) if i != wi]
    shown = [i for i in order if "_render" in rows[i]][:max(max_comparisons, 0)]
    figs = []
    for i in shown:
        r = rows[i]
        plot_comparison(r["_photo"], r["_render"], r.get("_mask"),
                        f"{r['name']}: {r['psnr_db']:.2f} dB" + (" (worst)" if i == wi else ""),
                        tmp / "views" / f"{r['name']}.png")
        figs.append(_fig(f"views/{r['name']}.png", f"{r['name']}: photo, fitted render and error"
                         + (" (the worst held-out view)" if i == wi else "")))
    if figs:
        ho.append("<h3>Held-out photos beside the fitted renders</h3>" + "".join(figs))
    return "".join(ho)


def _relit_section(model, capture, rows: list[dict], tmp: Path, device: str) -> str:
    """A relightable model (its plugin's ``report_relit_lights``): a held-out photo, the model under the fitted
    light and under the plugin's other lights, from that photo's camera."""
    lights = model.report_relit_lights()
    row = next((r for r in rows if "_render" in r), None)
    frame = next((f for f in capture.frames if f.name == row["name"]), None) if capture and row else None
    if not lights or frame is None:
        return ""
    panels = [("photo (held out)", row["_photo"]), ("fitted light", row["_render"])]
    panels += [(caption, model.relit_renderer(light, device)(frame)[0]) for caption, light in lights]
    plt = _plt()
    fig, ax = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.9))
    for a, (caption, img) in zip(ax, panels):
        a.imshow(linear_to_srgb(np.clip(img, 0, 1)), interpolation="nearest")
        a.set_title(caption, fontsize=8, wrap=True)
        a.set_axis_off()
    fig.tight_layout()
    fig.savefig(tmp / "views" / "relit.png", dpi=100)
    plt.close(fig)
    return "<h2>Relit</h2>" + _fig("views/relit.png", f"{row['name']}: the photo, the model under its fitted light, "
                                   "and relit under " + "; ".join(c for c, _ in lights) + " (sRGB, clipped at 1).")


def _viewer_frames(capture, held_names: set[str], max_photos: int, photo_max_side: int) -> tuple[list[dict], int]:
    """The viewer's frames (every camera and light, photos for the held-out ones first) and the one it opens."""
    if capture is None:
        return [], 0

    vframes = []
    frames = capture.frames[:MAX_VIEWER_FRAMES]
    want = [f for f in frames if f.name in held_names][:max_photos]
    want += [f for f in frames if f not in want][:max(0, max_photos - len(want))]
    want_names = {f.name for f in want}
    for f in frames:
        photo = (read_image(capture.image_path(f), channels=3, response=capture.response) if f.name in want_names
                 else None)
        vframes.append(viewer_frame(f, f.name in held_names, photo, photo_max_side))
    default = next((i for i, vf in enumerate(vframes) if vf["held_out"] and vf["photo"]),
                   next((i for i, vf in enumerate(vframes) if vf["photo"]), 0))
    return vframes, default


def _maps_section(info: dict, grid: np.ndarray, seen, tmp: Path, model_dir: Path) -> str:
    """The parameter maps' previews and, for a model with a parameter layout, its table of parameters."""
    maps = param_map_figures(info["model"], seen, tmp / "maps", model_dir)
    lay_html = ""
    if info["layout"] is not None:
        lay = info["layout"]
        lay_html = ("<table><tr><th>parameter</th><th>unit</th><th>bounds</th><th>min</th><th>median</th><th>max</th>"
                    "</tr>" + "".join(
                        f"<tr><td>{_e(s.name)}</td><td>{_e(s.unit)}</td><td>[{_fmt(s.lower)}, {_fmt(s.upper)}]</td>"
                        f"<td class='num'>{_fmt(float(grid[..., c].min()))}</td>"
                        f"<td class='num'>{_fmt(float(np.median(grid[..., c])))}</td>"
                        f"<td class='num'>{_fmt(float(grid[..., c].max()))}</td></tr>"
                        for c, s in enumerate(lay.specs())) + "</table>")
    return ("<h2>Parameter maps</h2><div class='grid'>" + "".join(_fig(a, b) for a, b in maps)
            + "</div>" + lay_html)
