"""The model folder: one writer for every fit stage, and the checks a model passes before it is written.

A model folder holds the parameter maps (EXR, :func:`texstream.capture.synthetic.param_maps.write_param_maps`),
``seen.png`` (texels no photo saw keep their defaults and are flagged here), ``trace.json`` and
``error_vs_time.png`` (error against run time), ``renders/`` (fitted renders beside photos),
``model.json`` (kind, parameter layout, figures) and the stage's resolved config. Stages add their
geometry (a mesh and bake, or a normal map) beside these.

Nothing out of bounds or non-finite is ever written: :func:`check_model` runs on the maps and on
the renders before the folder is moved into place, and fails with the count and the cause.

numpy at module level; OpenImageIO (inside capture.imageio's functions) and matplotlib inside functions
(the fit stage draws the plot in a child process, :func:`trace_plot`).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from texstream.capture.imageio import write_image
from texstream.capture.synthetic.param_maps import write_param_maps
from texstream.core.config import save_config
from texstream.core.errors import StageError
from texstream.core.outputs import write_json_atomic

from texstream.render.layout import ModelLayout

# relative slack on the bounds: float32 maps of float64 fits, and seam averaging's eps residual
BOUND_SLACK = 1e-5


def check_model(grid: np.ndarray, layout: ModelLayout, what: str = "model") -> None:
    """Raise StageError unless every value of ``grid`` (..., P) is finite and inside its bounds."""
    flat = np.asarray(grid, np.float64).reshape(-1, layout.n_params)
    bad_finite = ~np.isfinite(flat)
    if bad_finite.any():
        cols = sorted({layout.names[c] for c in np.nonzero(bad_finite.any(axis=0))[0]})
        raise StageError(f"{what} has {int(bad_finite.any(axis=1).sum())} texels with non-finite values "
                         f"({', '.join(cols)}); nothing was written",
                         fix="report this with the command that made it; --debug shows where it came from")
    lo, hi = layout.lower(), layout.upper()
    slack = BOUND_SLACK * np.maximum(1.0, np.maximum(np.abs(lo), np.abs(hi)))
    below, above = flat < lo - slack, flat > hi + slack
    if below.any() or above.any():
        worst = []
        for c in np.nonzero((below | above).any(axis=0))[0]:
            worst.append(f"{layout.names[c]} in [{flat[:, c].min():.6g}, {flat[:, c].max():.6g}] "
                         f"outside [{lo[c]:g}, {hi[c]:g}]")
        raise StageError(f"{what} has {int((below | above).any(axis=1).sum())} texels outside the parameter bounds "
                         f"({'; '.join(worst)}); nothing was written",
                         fix="report this with the command that made it; --debug shows where it came from")


def bound_report(params: np.ndarray, layout: ModelLayout, seen: np.ndarray, warn_fraction: float = 0.05) -> tuple[dict, list]:
    """Share of seen texels sitting on each free parameter's bounds, and a warning line for every
    parameter where more than ``warn_fraction`` of them do (an albedo pinned at its upper bound
    usually means the light's intensity is in the wrong units, not a material)."""
    p = np.asarray(params, np.float64)[np.asarray(seen, bool)]
    lo, hi, names = layout.lower(), layout.upper(), layout.names
    report, warnings = {}, []
    if len(p) == 0:
        return report, warnings
    for c in np.nonzero(~layout.frozen())[0]:
        span = max(hi[c] - lo[c], 1e-12)
        at_lo = float(np.mean(p[:, c] <= lo[c] + 1e-6 * span))
        at_hi = float(np.mean(p[:, c] >= hi[c] - 1e-6 * span))
        report[names[c]] = {"at_lower": at_lo, "at_upper": at_hi}
        if at_hi > warn_fraction:
            hint = " (the lights' intensity may be in the wrong units)" if ".rho_d." in names[c] else ""
            warnings.append(f"{100 * at_hi:.0f}% of seen texels have {names[c]} at its upper bound {hi[c]:g}{hint}")
    return report, warnings


def check_render(image: np.ndarray, frame_name: str) -> None:
    """Raise StageError when a render of the model holds a non-finite or negative value."""
    bad = ~np.isfinite(image) | (image < 0)
    if bad.any():
        raise StageError(f"the render of {frame_name} has {int(bad.any(axis=-1).sum())} pixels that are negative or "
                         "not finite; nothing was written", fix="report this with the command that made it")


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as None, recursively (JSON has no inf: a fit whose samples
    it reproduces exactly records an infinite PSNR)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        return None
    return value


def plot_trace(trace: list[dict], path: Path, title: str) -> None:
    """Objective and sample PSNR against wall time (the error-against-run-time plot), as a PNG."""
    Path(path).write_bytes(trace_plot_png(trace, title))


def start_plotter() -> subprocess.Popen | None:
    """A child process that imports matplotlib now and draws the error-against-time plot when
    :func:`trace_plot` sends it the trace (a request on its stdin), so that the import happens while the
    stage reads the photos and fits. It exits without drawing when its stdin closes first (the stage
    failed, or this process ended). None when no child could be started."""
    code = "from texstream.fit.common.model_folder import serve_plot; serve_plot()"
    try:
        return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:
        return None


def serve_plot() -> None:
    """(The child of :func:`start_plotter`.) Import the plot's modules, then draw the one request that comes
    on stdin: a JSON line {"trace", "png", "title"}."""
    import matplotlib.backends.backend_agg  # noqa: F401 - imported before the request comes
    import matplotlib.figure  # noqa: F401
    import matplotlib.ticker  # noqa: F401

    line = sys.stdin.readline()
    if line.strip():
        request = json.loads(line)
        plot_trace_file(request["trace"], request["png"], request["title"])


def stop_plotter(child: subprocess.Popen | None) -> None:
    """End a child of :func:`start_plotter` that is still running (no request came, or its drawing is no
    longer wanted)."""
    if child is None:
        return
    if child.poll() is None:
        child.kill()
    child.wait()
    if child.stdin is not None:
        try:
            child.stdin.close()
        except OSError:
            pass


@contextmanager
def trace_plot(folder: Path, trace: list[dict], title: str,
               plotter: subprocess.Popen | None = None) -> Iterator[subprocess.Popen | None]:
    """Write ``trace.json`` into ``folder`` and have a child process draw ``error_vs_time.png`` from it while
    the stage renders: ``plotter`` (:func:`start_plotter`, its imports done by now) or, without one or when it
    has ended, a child started here. Yields the child (None when none could be started) for
    :func:`write_model_folder`, which waits for it and draws the plot itself if the child failed; a stage
    that fails first stops it."""
    write_json_atomic(folder / "trace.json", json_safe(trace))
    request = {"trace": str(folder / "trace.json"), "png": str(folder / "error_vs_time.png"), "title": title}
    if plotter is not None and plotter.poll() is not None:
        stop_plotter(plotter)
        plotter = None
    child = plotter or start_plotter()
    if child is not None:
        try:
            child.stdin.write((json.dumps(request) + "\n").encode())
            child.stdin.close()
        except OSError:  # the child ended before the request: write_model_folder draws the plot itself
            stop_plotter(child)
    try:
        yield child
    finally:
        if child is not None and child.poll() is None:
            stop_plotter(child)


def plot_trace_file(trace_path: str, png_path: str, title: str) -> None:
    """:func:`plot_trace` of a ``trace.json`` (the child process of :func:`trace_plot`)."""
    plot_trace(json.loads(Path(trace_path).read_text()), Path(png_path), title)


def trace_plot_png(trace: list[dict], title: str) -> bytes:
    """:func:`plot_trace`'s PNG as bytes, drawn with matplotlib's object API (no pyplot: neither its import
    nor its global figure state). The log axis's labels are plain text and the margins fixed: mathtext
    labels and ``tight_layout`` measure every label and cost more than the drawing."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import LogFormatter

    fig = Figure(figsize=(10, 3.6))
    FigureCanvasAgg(fig)
    ax = fig.subplots(1, 2)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.15, top=0.88, wspace=0.25)
    t = [r["time_s"] for r in trace]
    ax[0].semilogy(t, [max(r["objective"], 1e-300) for r in trace], "o-", ms=3)
    ax[0].yaxis.set_major_formatter(LogFormatter())
    ax[0].yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False))  # labels within one decade
    ax[0].set_xlabel("wall time (s)")
    ax[0].set_ylabel("objective")
    psnr = [r["psnr_db"] if r["psnr_db"] is not None and math.isfinite(r["psnr_db"]) else float("nan") for r in trace]
    ax[1].plot(t, psnr, "o-", ms=3)
    ax[1].set_xlabel("wall time (s)")
    ax[1].set_ylabel("sample PSNR (dB)")
    fig.suptitle(title)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=110, format="png")
    return buf.getvalue()


def image_metrics(render: np.ndarray, photo: np.ndarray, mask: np.ndarray, peak: float = 1.0) -> dict:
    """PSNR (dB, against ``peak``) and APE (%) over foreground pixels."""
    m = mask.astype(bool)
    if not m.any():
        return {"psnr_db": float("nan"), "ape_percent": float("nan"), "pixels": 0}
    d = (render[m] - photo[m]).astype(np.float64)
    mse = float(np.mean(d * d))
    scale = float(np.abs(photo[m]).sum())  # 0: a black view (the unlit side under a fixed light): APE undefined
    ape = 100.0 * float(np.abs(d).sum()) / scale if scale > 0 else float("nan")
    return {"psnr_db": 10 * math.log10(peak * peak / mse) if mse > 0 else float("inf"), "ape_percent": ape,
            "pixels": int(m.sum())}


def pooled_psnr(views: Sequence[dict], peak: float = 1.0) -> dict:
    """Held-out error as users meet it: the PSNR of the pixel-weighted mean squared error over the
    views, the worst view and the mean of the per-view PSNRs (which hides a broken view)."""
    rows = [v for v in views if v.get("pixels")]
    if not rows:
        return {"views": 0, "pooled_psnr_db": None, "worst_psnr_db": None, "mean_psnr_db": None}
    mse = [peak * peak * 10 ** (-v["psnr_db"] / 10) for v in rows]
    w = np.array([v["pixels"] for v in rows], np.float64)
    pooled = float(np.dot(mse, w) / w.sum())
    worst = min(rows, key=lambda v: v["psnr_db"])
    return {"views": len(rows), "pooled_psnr_db": 10 * math.log10(peak * peak / pooled) if pooled > 0 else float("inf"),
            "worst_psnr_db": worst["psnr_db"], "worst_view": worst.get("frame"),
            "mean_psnr_db": float(np.mean([v["psnr_db"] for v in rows]))}


def render_comparisons(folder: Path, frames: Sequence, photos: Sequence[np.ndarray], held: Sequence,
                       render: Callable[[Any], tuple[np.ndarray, np.ndarray]], images: int | None = None) -> list[dict]:
    """Render the model for each frame (``render(frame)`` -> (image, foreground mask)), check the
    render, score it against the photo and write ``<frame>_fit_vs_photo.png`` into ``folder`` (for
    the first ``images`` frames; None: all). The PNGs are encoded on threads while the next frames
    render (the encoder releases Python's lock)."""
    import concurrent.futures
    import os

    folder.mkdir(exist_ok=True)
    rows = []
    with concurrent.futures.ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as writers:
        written = []
        for k, (f, photo) in enumerate(zip(frames, photos)):
            image, mask = render(f)
            check_render(image, f.file_path)
            rows.append({"frame": f.file_path, "held_out": f in held, **image_metrics(image, photo, mask)})
            if images is None or k < images:
                written.append(writers.submit(write_image, folder / f"{f.name}_fit_vs_photo.png",
                                              np.clip(np.concatenate([image, photo], axis=1), 0, 1), bits=8))
        for w in written:
            w.result()  # a write's error raised here
    return rows


def write_model_folder(folder: Path, grid: np.ndarray, layout: ModelLayout, seen: np.ndarray, trace: list[dict],
                       title: str, manifest: dict, config: Any, plot: subprocess.Popen | None = None,
                       maps: bool = True) -> dict[str, str]:
    """Write the maps, seen.png, trace, error-against-time plot, model.json and the config into
    ``folder`` (a stage's temporary output folder), after :func:`check_model`.

    Args:
        grid: (H, W, P) parameter maps (padding filled).
        seen: (H, W) bool, texels some photo saw.
        manifest: model.json's stage-specific fields; kind, layout and maps are added here.
        config: the stage's resolved config, saved as fit_config.json.
        plot: the child of :func:`trace_plot` drawing ``trace``'s plot into ``folder`` (None: drawn here).
        maps: False for a model judged by its scores alone (the model choice's validation fit): model.json, the
            trace and the config, no maps, seen.png or plot (a plot's child is waited for).

    Returns:
        The map files by name (as model.json lists them).
    """
    check_model(grid, layout)
    files = write_param_maps(folder, grid, layout) if maps else {}
    if maps:
        write_image(folder / "seen.png", np.repeat(seen.astype(np.float32)[..., None], 3, axis=2), bits=8)
    if plot is None:  # else trace_plot wrote it for its child
        write_json_atomic(folder / "trace.json", json_safe(trace))
    if plot is not None and not maps:
        plot.wait()  # its child's plot is not needed, its exit is
    elif maps and (plot is None or plot.wait() != 0 or not (folder / "error_vs_time.png").is_file()):
        plot_trace(trace, folder / "error_vs_time.png", title)
    write_json_atomic(folder / "model.json",
                      json_safe({"kind": layout.kind, "layout": layout.to_json(), "maps": files, **manifest}))
    save_config(config, folder / "fit_config.json")
    return files
