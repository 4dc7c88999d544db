"""The console script's error contract: one stderr line naming the file, exit code 1, no output
folder left behind; ``--debug`` (before or after the subcommand) lets the exception through."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import read_image
from texstream.capture.synthetic.synth import SynthConfig, synthesize
from texstream.pipelines.cli import main
from texstream.core.errors import InputError


@pytest.fixture(autouse=True)
def _no_debug_env(monkeypatch):
    monkeypatch.delenv("TEXSTREAM_DEBUG", raising=False)


@pytest.fixture
def nan_capture(tmp_path):
    """A 2-photo synthetic sphere (32-bit EXR photos) whose second photo holds one NaN pixel."""
    cap = synthesize("sphere", tmp_path / "cap", SynthConfig(scale=0.02, progress=False, preview=False)).output
    frames = read_capture(cap).frames
    assert len(frames) == 2 and frames[1].file_path.endswith(".exr")
    bad = read_capture(cap).image_path(frames[1])
    img = read_image(bad)
    img[3, 5] = np.nan
    import OpenImageIO as oiio  # write_image refuses NaN (issue 41); a photo from elsewhere need not

    out = oiio.ImageOutput.create(str(bad))
    assert out.open(str(bad), oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], "float"))
    assert out.write_image(np.ascontiguousarray(img, np.float32))
    out.close()
    return cap, bad


def _leftovers(folder, name):
    """The output and any temporary sibling (`.name.*.partial`) of an atomic output folder."""
    return sorted(p.name for p in folder.iterdir() if p.name == name or p.name.startswith(f".{name}."))


def test_nan_photo_fails_the_fit_stage_in_one_line(nan_capture, tmp_path, capsys):
    cap, bad = nan_capture
    model = tmp_path / "model"
    rc = main(["fit", str(cap), "--mesh", str(cap / "ground_truth"), "-o", str(model), "--max-iterations", "1"])
    err = capsys.readouterr().err
    assert rc == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert str(bad) in lines[0] and "NaN" in lines[0] and "Fix:" in lines[0]
    assert _leftovers(tmp_path, "model") == []


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_lets_the_exception_through(nan_capture, tmp_path, capsys, where):
    cap, bad = nan_capture
    args = ["fit", str(cap), "--mesh", str(cap / "ground_truth"), "-o", str(tmp_path / "model")]
    argv = ["--debug", *args] if where == "before" else [*args, "--debug"]
    with pytest.raises(InputError, match="NaN") as e:
        main(argv)
    assert e.value.path == str(bad)
    assert "error:" not in capsys.readouterr().err  # no one-line summary: Python prints the traceback
    assert _leftovers(tmp_path, "model") == []


def test_debug_is_accepted_after_any_subcommand(tmp_path, capsys):
    # no subcommand rejects --debug (argparse used to: "unrecognized arguments: --debug")
    from texstream.pipelines.cli import SUBCOMMANDS, build_parser

    for name in SUBCOMMANDS:
        p = build_parser(only=name)
        with pytest.raises(SystemExit) as e:
            p.parse_args([name, "--debug", "--help"])
        assert e.value.code == 0, name
    capsys.readouterr()
    # bad input: one line and rc 1 by default; --debug in either position raises
    out = tmp_path / "o"
    assert main(["synth", "no_such_scene", "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_such_scene" in err[0]
    for argv in (["--debug", "synth", "no_such_scene", "-o", str(out)],
                 ["synth", "no_such_scene", "-o", str(out), "--debug"]):
        with pytest.raises(InputError, match="no_such_scene"):
            main(argv)
    assert not out.exists()


def test_debug_shows_the_traceback_from_the_console_script(tmp_path):
    cmd = [sys.executable, "-m", "texstream.pipelines.cli", "synth", "no_such_scene", "-o", str(tmp_path / "o")]
    plain = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert plain.returncode == 1 and len(plain.stderr.strip().splitlines()) == 1
    debug = subprocess.run([*cmd, "--debug"], capture_output=True, text=True, timeout=60)
    assert debug.returncode == 1  # Python's own exit code for an uncaught exception
    assert "Traceback" in debug.stderr and "InputError: unknown scene 'no_such_scene'" in debug.stderr


def test_console_script_exits_with_main_s_code_and_flushed_output(tmp_path):
    """The console script (``console_main``) ends without the interpreter's teardown: its exit code is
    main's, and what it printed reaches a pipe in full."""
    run = [sys.executable, "-c", "from texstream.pipelines.cli import console_main; console_main()"]
    bad = subprocess.run(run + ["fit", str(tmp_path / "missing"), "--mesh", "x", "-o", str(tmp_path / "m")],
                         capture_output=True, text=True)
    assert bad.returncode == 1
    assert "missing: capture file not found" in bad.stderr.strip().splitlines()[-1]
    ok = subprocess.run(run + ["synth", "sphere", "-o", str(tmp_path / "cap"), "--scale", "0.02"],
                        capture_output=True, text=True)
    assert ok.returncode == 0 and ok.stdout.strip().splitlines()[-1].startswith("wrote ")
    assert (tmp_path / "cap" / "capture.json").is_file()


def test_eval_refuses_a_negative_holdout_every_before_reading_anything(tmp_path):
    """Issue 41: ``eval --holdout-every -1`` scored every frame without a word."""
    from texstream.core.errors import ConfigError
    from texstream.fit.stages.stage import eval_stage

    with pytest.raises(ConfigError, match="negative"):
        eval_stage(tmp_path / "no model", tmp_path / "no capture", holdout_every=-1)


def test_synth_flash_options_belong_to_the_flash_capture(tmp_path, capsys):
    """--object and --no-flash-pairs are options of ``texstream synth flash_capture``: given to another scene they
    are a one-line error naming the fix, and nothing is written."""
    for flag in (["--object", "flash_sphere_resolved"], ["--no-flash-pairs"]):
        assert main(["synth", "sphere", "-o", str(tmp_path / "out"), *flag]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"{flag[0]} is an option of flash_capture" in err, err
        assert not (tmp_path / "out").exists()
