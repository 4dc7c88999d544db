"""The model folder's error-against-time plot, drawn by a child process while the stage renders
(fit/model_folder.py ``trace_plot``, ``start_plotter``). Host-only code: no device parameter."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from texstream.fit.common.model_folder import start_plotter, stop_plotter, trace_plot, trace_plot_png, write_model_folder
from texstream.render.layout import ModelLayout


@dataclasses.dataclass
class TinyConfig:
    """A stage config to save beside the maps."""
    device: str = "cpu"

TRACE = [{"iteration": k, "time_s": 0.1 * k, "objective": 10.0 / (k + 1), "psnr_db": 30.0 + k} for k in range(6)]
TRACE[0]["psnr_db"] = float("inf")  # a fit that reproduces its samples exactly: None in trace.json


def test_child_draws_the_plot_the_stage_would(tmp_path):
    with trace_plot(tmp_path, TRACE, "title") as child:
        assert child is not None and child.wait() == 0
    drawn = (tmp_path / "error_vs_time.png").read_bytes()
    # same code and matplotlib in both processes; the trace read back from JSON has None for inf
    assert drawn == trace_plot_png(TRACE, "title")
    # the trace the child drew from, as JSON allows it (inf is not a JSON number)
    assert json.loads((tmp_path / "trace.json").read_text()) == [dict(r, psnr_db=None) if k == 0 else r
                                                                  for k, r in enumerate(TRACE)]


def test_a_failing_stage_stops_the_child(tmp_path):
    with pytest.raises(RuntimeError):
        with trace_plot(tmp_path, TRACE, "title") as child:
            raise RuntimeError("render check failed")
    assert child.poll() is not None  # not left running into the removed output folder


def test_model_folder_draws_the_plot_itself_when_the_child_failed(tmp_path):
    failed = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    lay = ModelLayout("diffuse", 0)
    grid = np.full((2, 2, lay.n_params), 0.5, np.float32)
    write_model_folder(tmp_path, grid, lay, np.ones((2, 2), bool), TRACE, "title", {}, TinyConfig(), plot=failed)
    assert (tmp_path / "error_vs_time.png").read_bytes() == trace_plot_png(TRACE, "title")
    assert json.loads((tmp_path / "model.json").read_text())["kind"] == "diffuse"


def test_a_plotter_started_early_draws_the_same_plot(tmp_path):
    plotter = start_plotter()
    with trace_plot(tmp_path, TRACE, "title", plotter) as child:
        assert child is plotter and child.wait() == 0
    assert (tmp_path / "error_vs_time.png").read_bytes() == trace_plot_png(TRACE, "title")


def test_a_plotter_no_request_reaches_exits(tmp_path):
    plotter = start_plotter()
    plotter.stdin.close()  # the stage failed before its model folder (or this process ended)
    assert plotter.wait(timeout=60) == 0
    stop_plotter(plotter)
    killed = start_plotter()
    stop_plotter(killed)
    assert killed.poll() is not None


def test_a_plotter_that_ended_is_replaced(tmp_path):
    ended = start_plotter()
    stop_plotter(ended)
    with trace_plot(tmp_path, TRACE, "title", ended) as child:
        assert child is not ended and child.wait() == 0
    assert (tmp_path / "error_vs_time.png").read_bytes() == trace_plot_png(TRACE, "title")


def test_a_failing_fit_stage_stops_its_plotter(tmp_path, monkeypatch):
    from texstream.fit.common import model_folder
    from texstream.fit.stages import stage

    started = []
    monkeypatch.setattr(model_folder, "start_plotter", lambda: started.append(start_plotter()) or started[-1])
    with pytest.raises(Exception):
        stage.fit_stage(tmp_path / "no capture here", tmp_path / "no mesh", tmp_path / "out")
    assert started and started[0].poll() is not None and not (tmp_path / "out").exists()
