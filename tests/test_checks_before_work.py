"""Checks before work and one-line messages (issue 41): an output that cannot be written, or a disk without
room for it, fails before any long stage; no NaN or Inf reaches a JSON file; a full disk, a random-bytes mesh,
photos too small to use and photos COLMAP cannot register each give one line naming the path and the fix."""

from __future__ import annotations

import errno
import json

import numpy as np
import pytest

from texstream.core import outputs
from texstream.core.errors import StageError
from texstream.core.outputs import write_atomic_with, write_json_atomic
from texstream.pipelines.cli import main, os_error_line


@pytest.fixture(autouse=True)
def _no_debug_env(monkeypatch):
    monkeypatch.delenv("TEXSTREAM_DEBUG", raising=False)


# command -> (its module, the stage function it calls, its arguments before -o, the output's name): the long
# work each check must come before
LONG_COMMANDS = {
    "run": ("cmd_run", "run_pipeline", lambda t: ["run", str(t)], "run"),
    "fit": ("cmd_fit", "fit_stage", lambda t: ["fit", str(t), "--mesh", str(t)], "model"),
    "refine": ("cmd_refine", "refine_stage", lambda t: ["refine", str(t), str(t)], "refined"),
    "mesh": ("cmd_mesh", "make_mesh", lambda t: ["mesh", str(t)], "mesh"),
    "atlas": ("cmd_atlas", "atlas_stage", lambda t: ["atlas", str(t / "mesh.ply")], "atlas"),
    "eval": ("cmd_eval", "eval_stage", lambda t: ["eval", str(t), str(t)], "eval.json"),
    "export": ("cmd_export", "export_stage", lambda t: ["export", str(t)], "export"),
}


def _no_long_work(monkeypatch, command):
    """Make the command's stage fail the test if it is ever called."""
    import importlib

    module, stage, _, _ = LONG_COMMANDS[command]
    mod = importlib.import_module(f"texstream.pipelines.{module}")

    def called(*a, **k):
        raise AssertionError(f"{command} started its work before checking its output")

    monkeypatch.setattr(mod, stage, called)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("command", sorted(LONG_COMMANDS))
def test_an_output_inside_a_file_fails_before_the_work(command, tmp_path, monkeypatch, capsys):
    """Tests may run as root, where chmod does not make a folder read-only: an output path through a FILE
    cannot be written by anyone."""
    _no_long_work(monkeypatch, command)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    _, _, args, name = LONG_COMMANDS[command]
    assert main([*args(tmp_path), "-o", str(blocker / name)]) == 1
    line = _one_line(capsys)
    assert f"{blocker}: this part of the output path is a file" in line and "Fix: choose another -o path" in line


@pytest.mark.parametrize("command", ["fit", "export"])
def test_an_unwritable_folder_fails_before_the_work(command, tmp_path, monkeypatch, capsys):
    """The probe file's creation is made to fail as on a read-only file system (as root, chmod would not)."""
    _no_long_work(monkeypatch, command)

    def read_only(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(outputs.tempfile, "mkstemp", read_only)
    _, _, args, name = LONG_COMMANDS[command]
    assert main([*args(tmp_path), "-o", str(tmp_path / "out" / name)]) == 1
    line = _one_line(capsys)
    assert "cannot write the output here (Read-only file system)" in line
    assert "Fix: make the folder writable" in line


def test_a_disk_without_room_for_the_model_fails_before_the_fit(tmp_path, monkeypatch, capsys):
    _no_long_work(monkeypatch, "fit")
    real = outputs.shutil.disk_usage
    monkeypatch.setattr(outputs.shutil, "disk_usage", lambda p: real(p)._replace(free=1 << 20))
    assert main(["fit", str(tmp_path), "--mesh", str(tmp_path), "-o", str(tmp_path / "model"),
                 "--holdout-every", "8"]) == 1
    line = _one_line(capsys)
    # 256 x 256 texels at 256 bytes, four candidates (--model auto with held-out photos), 16 MiB of small
    # files: 80 MiB (pipelines/estimates.py)
    assert "the model needs about 80.0 MiB but its disk has 1.0 MiB free" in line and "Fix: free space" in line
    assert not (tmp_path / "model").exists()


def test_a_full_disk_names_the_file_and_the_fix(tmp_path):
    def full(fh):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError) as e:
        write_atomic_with(tmp_path / "bake.npz", full)
    line = os_error_line(e.value)
    assert line.startswith(f"{tmp_path / 'bake.npz'}: No space left on device. Fix: free space on that disk")
    assert list(tmp_path.iterdir()) == []  # the temporary file is gone
    with pytest.raises(OSError) as e:
        with outputs.atomic_output_dir(tmp_path / "model"):
            raise OSError(errno.ENOSPC, "No space left on device")  # a write that named no file
    assert e.value.filename == str(tmp_path / "model") and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("data,where", [
    ({"views": [{"residual": 0.1}] * 3 + [{"residual": float("nan")}]}, r"views\[3\]\.residual is nan"),
    ({"fit": {"rms": np.array([1.0, np.inf], np.float32)}}, r"fit\.rms\[1\] is inf"),
    ({"psnr": np.float64(-np.inf)}, r"psnr is -inf"),
])
def test_json_refuses_nan_and_inf_naming_the_file_and_the_key(tmp_path, data, where):
    with pytest.raises(StageError, match=rf"refine\.json: {where}: JSON cannot hold a non-finite number") as e:
        write_json_atomic(tmp_path / "refine.json", data)
    assert "Fix:" in e.value.one_line() and list(tmp_path.iterdir()) == []


def test_random_bytes_mesh_gives_one_line(tmp_path, capsys):
    mesh = tmp_path / "random.ply"
    mesh.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    assert main(["atlas", str(mesh), "-o", str(tmp_path / "atlas")]) == 1
    line = _one_line(capsys)
    assert f"{mesh}: cannot read mesh (Header not found)" in line and "Fix:" in line


def _noise_photos(folder, sizes):
    import cv2

    folder.mkdir()
    rng = np.random.default_rng(1)
    for i, (w, h) in enumerate(sizes):
        cv2.imwrite(str(folder / f"p{i}.png"), (rng.random((h, w, 3)) * 255).astype(np.uint8))
    return folder


def test_ingest_refuses_photos_too_small_to_use(tmp_path, capsys):
    from texstream.calib.ingest import MIN_PHOTO_SIDE

    one = _noise_photos(tmp_path / "one", [(1, 1)])
    assert main(["ingest", str(one), "-o", str(tmp_path / "cap1")]) == 1
    line = _one_line(capsys)
    assert f"{one / 'p0.png'}:" in line and f"too small: 1x1 pixels, fewer than {MIN_PHOTO_SIDE}" in line
    assert "Fix:" in line and not (tmp_path / "cap1").exists()
    # among usable photos a small one is dropped, and said so
    mixed = _noise_photos(tmp_path / "mixed", [(40, 32), (40, 32), (MIN_PHOTO_SIDE - 1, 32)])
    assert main(["ingest", str(mixed), "-o", str(tmp_path / "cap")]) == 0
    out = capsys.readouterr().out
    assert f"dropped: p2.png (too small: {MIN_PHOTO_SIDE - 1}x32 pixels" in out
    assert len(json.loads((tmp_path / "cap" / "capture.json").read_text())["frames"]) == 2


def test_register_on_unusable_photos_prints_only_its_error(tmp_path, capfd):
    """COLMAP's "Failed to create any sparse model" record (written to file descriptor 2 by its C++ code)
    used to come before the stage's own line."""
    photos = _noise_photos(tmp_path / "noise", [(160, 120)] * 4)
    assert main(["register", str(photos), "-o", str(tmp_path / "posed")]) == 1
    err = capfd.readouterr().err.strip().splitlines()
    err = [line for line in err if not line.startswith("Warp CUDA warning")]  # Warp's, on a machine without CUDA
    assert len(err) == 1 and "no model: none of the 4 photos could be registered" in err[0], err
