"""Middlebury *_par.txt import: parsing, the temple conversion, its projection check, bad input."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import need_data
from texstream.capture import conventions
from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import read_mask, write_image
from texstream.capture.middlebury import (MiddleburyImportConfig, bbox_corners, import_middlebury,
                                          parse_par_file, parse_readme_bbox)
from texstream.core.errors import InputError
from texstream.core.config import load_config

TEMPLE = "middlebury_temple_sparse"


@pytest.fixture(scope="module")
def temple_capture(tmp_path_factory, data_dir) -> tuple[Path, Path]:
    src = need_data(data_dir, TEMPLE)
    out = tmp_path_factory.mktemp("mb") / "temple"
    result = import_middlebury(src, out, MiddleburyImportConfig())
    assert result.output == out and result.summary["frames"] == 16 and result.summary["masks"] == 16
    return src, out


def test_temple_conversion_layout(temple_capture):
    src, out = temple_capture
    assert sorted(os.listdir(out)) == ["capture.json", "images", "import_config.json", "masks"]
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temp folders left
    cap = read_capture(out)
    assert len(cap.frames) == 16
    for f in cap.frames:
        # PNG bytes copied unchanged
        assert cap.image_path(f).read_bytes() == (src / Path(f.file_path).name).read_bytes()
        assert f.light is None and f.mask_path == f"masks/{Path(f.file_path).stem}.png"
    assert cap.extra["lighting"] == "fixed unknown lamp"
    bb = cap.extra["bounding_box"]
    np.testing.assert_allclose(bb["min"], [-0.073568, 0.021728, -0.012445])
    np.testing.assert_allclose(bb["max"], [0.028855, 0.181892, 0.062736])
    assert isinstance(load_config(MiddleburyImportConfig, out / "import_config.json"), MiddleburyImportConfig)


def test_temple_cameras_match_par_file(temple_capture):
    src, out = temple_capture
    cap = read_capture(out)
    cams = parse_par_file(src / "templeSR_par.txt")
    for f, (name, k, r, t) in zip(cap.frames, cams):
        assert f.file_path == f"images/{name}"
        # R, t survive the GL camera-to-world round trip in capture.json to float64 rounding
        np.testing.assert_allclose(f.R, r, atol=1e-12)
        np.testing.assert_allclose(f.t, t, atol=1e-12)
        i = f.intrinsics
        assert (i.width, i.height, i.fx, i.fy) == (640, 480, k[0, 0], k[1, 1])
        # Middlebury puts pixel centres at integers; the capture convention at +0.5
        assert (i.cx, i.cy) == pytest.approx((k[0, 2] + 0.5, k[1, 2] + 0.5), abs=1e-12)
        # projecting with the capture convention equals Middlebury's K [R t] shifted by half a pixel
        x = np.array([[-0.02, 0.1, 0.03], [0.0, 0.05, 0.0]])
        ph = (x @ r.T + t) @ k.T
        uv_mb = ph[:, :2] / ph[:, 2:]
        uv, _ = conventions.project(x, f.R, f.t, i.fx, i.fy, i.cx, i.cy)
        np.testing.assert_allclose(uv, uv_mb + 0.5, atol=1e-9)  # float64 rounding of ~1e3 pixel values


def test_temple_bbox_corners_project_inside_every_image(temple_capture):
    src, out = temple_capture
    cap = read_capture(out)
    lo, hi = parse_readme_bbox(src / "README.txt")
    corners = bbox_corners(lo, hi)
    centre = (lo + hi) / 2
    for f in cap.frames:
        i = f.intrinsics
        uv, z = conventions.project(corners, f.R, f.t, i.fx, i.fy, i.cx, i.cy)
        assert np.all(z > 0), f"{f.file_path}: a corner is behind the camera"
        assert np.all((uv >= 0) & (uv <= [i.width, i.height])), f"{f.file_path}: corners at {uv}"
        # and the object is there: the box centre projects inside, the mask is not empty
        m = read_mask(cap.mask_path(f), shape=(i.height, i.width))
        uvc, _ = conventions.project(centre[None], f.R, f.t, i.fx, i.fy, i.cx, i.cy)
        u, v = uvc[0]
        assert 0 <= u < i.width and 0 <= v < i.height
        assert m.mean() > 0.05


def test_temple_masks_cut_background(temple_capture):
    src, out = temple_capture
    cap = read_capture(out)
    for f in cap.frames[::5]:
        m = read_mask(cap.mask_path(f))
        # image corners are backdrop (the temple sits in the middle of every view)
        assert not m[:10, :10].any() and not m[-10:, -10:].any()
        # the temple fills between ~10% and ~50% of the frame in this set
        assert 0.08 < m.mean() < 0.5


def test_no_masks_option_and_round_trip(tmp_path, data_dir):
    src = need_data(data_dir, TEMPLE)
    out = tmp_path / "nomask"
    import_middlebury(src, out, MiddleburyImportConfig(make_masks=False))
    cap = read_capture(out)
    assert all(f.mask_path is None for f in cap.frames) and not (out / "masks").exists()


def _mini_set(folder: Path, k2=None) -> Path:
    """A two-image Middlebury-format set with synthetic images (no data needed)."""
    folder.mkdir(parents=True)
    r0, t0 = conventions.look_at_w2c(np.array([0.0, -1.0, 0.2]), np.zeros(3))
    r1, t1 = conventions.look_at_w2c(np.array([1.0, 0.0, 0.2]), np.zeros(3))
    k = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    k2 = k if k2 is None else k2
    lines = ["2"]
    for name, kk, r, t in (("a.png", k, r0, t0), ("b.png", k2, r1, t1)):
        lines.append(" ".join([name, *(f"{x:.17g}" for x in (*kk.ravel(), *r.ravel(), *t))]))
        img = np.zeros((48, 64, 3), np.float32)
        img[16:32, 20:44] = 0.6
        write_image(folder / name, img)
    (folder / "mini_par.txt").write_text("\n".join(lines) + "\n")
    return folder


def test_mini_set_per_frame_intrinsics(tmp_path):
    k2 = np.array([[120.0, 0, 30.0], [0, 121.0, 22.0], [0, 0, 1]])
    src = _mini_set(tmp_path / "mini", k2=k2)
    out = tmp_path / "out"
    import_middlebury(src, out)
    doc = json.loads((out / "capture.json").read_text())
    assert "fl_x" not in doc and doc["frames"][1]["fl_x"] == 120.0 and doc["frames"][1]["cx"] == 30.5
    cap = read_capture(out)
    assert "bounding_box" not in cap.extra  # no README: no box, masks from the threshold alone
    m = read_mask(cap.mask_path(cap.frames[0]))
    np.testing.assert_array_equal(np.argwhere(m).min(0), [16, 20])
    np.testing.assert_array_equal(np.argwhere(m).max(0), [31, 43])


@pytest.mark.parametrize("case,pattern", [
    ("count", "says 3 images but 2 follow"),
    ("fields", "line 2 has 21 fields"),
    ("text", "non-numeric"),
    ("rotation", "R is not a rotation"),
    ("missing_image", "b.png listed in mini_par.txt is missing"),
    ("no_par", "no \\*_par.txt"),
    ("corrupt_image", "corrupt|cannot read"),
])
def test_bad_sets_leave_no_output(tmp_path, case, pattern):
    src = _mini_set(tmp_path / "mini")
    par = src / "mini_par.txt"
    lines = par.read_text().splitlines()
    if case == "count":
        lines[0] = "3"
    elif case == "fields":
        lines[1] = lines[1].rsplit(" ", 1)[0]
    elif case == "text":
        lines[1] = lines[1].replace(lines[1].split()[3], "abc", 1)
    elif case == "rotation":
        f = lines[1].split()
        f[10] = str(2 * float(f[10]) + 0.5)
        lines[1] = " ".join(f)
    elif case == "missing_image":
        (src / "b.png").unlink()
    elif case == "no_par":
        par.unlink()
    elif case == "corrupt_image":
        data = (src / "b.png").read_bytes()
        (src / "b.png").write_bytes(data[: len(data) // 2])
    if par.exists():
        par.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    with pytest.raises(InputError, match=pattern):
        import_middlebury(src, out)
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["mini"]


def test_existing_output_is_replaced_only_on_success(tmp_path):
    src = _mini_set(tmp_path / "mini")
    out = tmp_path / "out"
    import_middlebury(src, out)
    before = (out / "capture.json").read_text()
    shutil.copy(src / "b.png", tmp_path / "b_backup.png")
    (src / "b.png").write_bytes(b"broken")
    with pytest.raises(InputError):
        import_middlebury(src, out)
    assert (out / "capture.json").read_text() == before
    shutil.copy(tmp_path / "b_backup.png", src / "b.png")
    with pytest.raises(InputError, match="already exists"):
        import_middlebury(src, out, MiddleburyImportConfig(overwrite=False))
