"""Contact sheets and the `texstream import` / `texstream preview` subcommands."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import need_data
from texstream.capture import conventions
from texstream.capture.capture_json import Capture, Frame, Intrinsics, write_capture
from texstream.capture.imageio import image_size, read_image, write_image
from texstream.capture.preview import write_contact_sheet
from texstream.pipelines.cli import main
from texstream.core.errors import InputError


def _capture(root, n=5, size=(40, 30), exposures=None):
    """n flat-colour frames; frame i has linear radiance 0.1 * (i + 1) times its exposure."""
    w, h = size
    intr = Intrinsics(width=w, height=h, fx=50.0, fy=50.0, cx=w / 2, cy=h / 2)
    frames = []
    for i in range(n):
        e = 1.0 if exposures is None else exposures[i]
        write_image(root / f"images/{i}.exr", np.full((h, w, 3), 0.1 * (i + 1) * e, np.float32))
        r, t = conventions.look_at_w2c(np.array([np.cos(i), np.sin(i), 0.5]) * 3, np.zeros(3))
        frames.append(Frame(file_path=f"images/{i}.exr", R=r, t=t, intrinsics=intr, exposure=e))
    write_capture(Capture(root=root, frames=frames))
    return root


def test_contact_sheet_grid_and_tone_mapping(tmp_path):
    cap = _capture(tmp_path / "cap", n=5, exposures=[1.0, 2.0, 0.5, 4.0, 1.0])
    out = write_contact_sheet(cap, tmp_path / "sheet.png", thumb=32, exposure=1.0, label=False)
    # 5 tiles -> 3 columns x 2 rows of 32 px with 2 px gaps
    assert image_size(out) == (3 * 34 + 2, 2 * 34 + 2, 3)
    sheet = read_image(out)
    # each tile shows its radiance (exposure divided out), 8-bit sRGB encoded: half a code step in linear
    for k in range(5):
        r, c = divmod(k, 3)
        y, x = 2 + r * 34 + 16, 2 + c * 34 + 16
        assert sheet[y, x, 0] == pytest.approx(0.1 * (k + 1), abs=4.5e-3)


def test_contact_sheet_auto_exposure_and_subsampling(tmp_path):
    cap = _capture(tmp_path / "cap", n=9)
    out = write_contact_sheet(cap, tmp_path / "s.png", max_images=4, thumb=16, label=False)
    w, h, _ = image_size(out)
    assert (w, h) == (2 * 18 + 2, 2 * 18 + 2)  # 4 tiles evenly spaced over 9 frames
    sheet = read_image(out)
    # auto exposure maps the 99th percentile (the brightest frame, 0.9) to 0.9
    assert sheet.max() == pytest.approx(0.9, abs=5e-3)  # 8-bit rounding near 0.9


def test_contact_sheet_bad_input(tmp_path):
    cap = _capture(tmp_path / "cap", n=2)
    (cap / "images/1.exr").write_bytes(b"junk")
    with pytest.raises(InputError, match="1.exr"):
        write_contact_sheet(cap, tmp_path / "s.png")
    assert not (tmp_path / "s.png").exists()


def test_cli_preview(tmp_path, capsys):
    cap = _capture(tmp_path / "cap", n=3)
    assert main(["preview", str(cap), "--thumb", "24"]) == 0
    # the 3 photos as tiles of 24 px (2 x 2 grid, 2 px gaps), auto exposure taking the brightest (0.3) to 0.9:
    # each tile's median (clear of its label) at 0.3, 0.6, 0.9 within half an 8-bit sRGB code
    sheet = read_image(cap / "contact_sheet.png")
    assert sheet.shape == (2 * 26 + 2, 2 * 26 + 2, 3)
    for k in range(3):
        r, c = divmod(k, 2)
        tile = sheet[2 + r * 26:2 + r * 26 + 24, 2 + c * 26:2 + c * 26 + 24, 0]
        assert np.median(tile) == pytest.approx(0.3 * (k + 1), abs=5e-3), k
    assert main(["preview", str(tmp_path / "missing")]) == 1
    err = capsys.readouterr().err
    assert "missing" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_cli_import_middlebury(tmp_path, data_dir, capsys):
    src = need_data(data_dir, "middlebury_temple_sparse")
    out = tmp_path / "temple"
    assert main(["import", "middlebury", str(src), "-o", str(out), "--no-make-masks"]) == 0
    assert "frames 16" in capsys.readouterr().out
    assert (out / "capture.json").exists() and not (out / "masks").exists()


def test_cli_import_errors(tmp_path, capsys):
    assert main(["import", "middlebury", str(tmp_path / "nowhere"), "-o", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "nowhere" in err and "Fix:" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    # colmap / nerfstudio import lives in texstream.calib.colmap_io (another module): either it runs
    # and reports a user error for this empty folder, or says it is not available yet; never a traceback
    (tmp_path / "empty").mkdir()
    for fmt in ("colmap", "nerfstudio"):
        assert main(["import", fmt, str(tmp_path / "empty"), "-o", str(tmp_path / fmt)]) == 1
        err = capsys.readouterr().err
        assert err.startswith("texstream import: error:") and "Traceback" not in err
        assert not (tmp_path / fmt).exists()


def test_cli_import_dispatches_to_colmap_io(tmp_path, monkeypatch, capsys):
    """colmap/nerfstudio go to texstream.calib.colmap_io with their own config (a stand-in module here)."""
    import dataclasses
    import sys
    import types

    from texstream.core.config import option
    from texstream.core.outputs import StageResult

    @dataclasses.dataclass
    class ColmapImportConfig:
        overwrite: bool = option(True, help="replace an existing output folder")
        min_track: int = option(2, help="points seen by fewer images are dropped")

    calls = []

    def import_colmap(src, out, config):
        calls.append((src, out, config))
        return StageResult(output=out, summary={"frames": 7})

    fake = types.ModuleType("texstream.calib.colmap_io")
    fake.ColmapImportConfig, fake.import_colmap = ColmapImportConfig, import_colmap
    monkeypatch.setitem(sys.modules, "texstream.calib.colmap_io", fake)
    assert main(["import", "colmap", "src_dir", "-o", str(tmp_path / "o"), "--min-track", "3",
                 "--no-overwrite"]) == 0
    assert calls == [("src_dir", str(tmp_path / "o"), ColmapImportConfig(overwrite=False, min_track=3))]
    assert "frames 7" in capsys.readouterr().out
    # the fake has no nerfstudio importer: a clear one-line error
    assert main(["import", "nerfstudio", "x", "-o", str(tmp_path / "n")]) == 1
    assert "not available yet" in capsys.readouterr().err


def test_import_formats_share_option_names_only_with_equal_types():
    """`texstream import` offers every format's options in one parser: a shared name must mean one type."""
    import dataclasses
    import typing

    from texstream.calib.colmap_io import ColmapImportConfig, NerfstudioImportConfig
    from texstream.capture.middlebury import MiddleburyImportConfig

    classes = [MiddleburyImportConfig, ColmapImportConfig, NerfstudioImportConfig]
    seen: dict[str, tuple[object, str]] = {}
    for cls in classes:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if f.name in seen:
                assert seen[f.name][0] == hints[f.name], (
                    f"--{f.name} is {seen[f.name][0]} in {seen[f.name][1]} but {hints[f.name]} in {cls.__name__}")
            else:
                seen[f.name] = (hints[f.name], cls.__name__)
