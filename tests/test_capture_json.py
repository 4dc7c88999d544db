"""capture.json: round trips, nerfstudio transforms.json compatibility, and bad input."""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path

import numpy as np
import pytest

from texstream.capture import conventions
from texstream.capture.capture_json import Capture, Frame, Intrinsics, Light, read_capture, write_capture
from texstream.core.errors import InputError, StageError

# Poses go c2w -> (R, t) -> c2w through a transpose and a matrix product: float64 rounding only.
POSE_ATOL = 1e-12


def _c2w(eye, target) -> list:
    r, t = conventions.look_at_w2c(np.asarray(eye, float), np.asarray(target, float))
    return conventions.w2c_cv_to_c2w_gl(r, t).tolist()


def _ns_transforms() -> dict:
    """A transforms.json as nerfstudio's ns-process-data (COLMAP path) writes it."""
    return {
        "w": 960, "h": 540, "fl_x": 771.3, "fl_y": 770.9, "cx": 481.2, "cy": 268.7,
        "k1": -0.0123, "k2": 0.0045, "p1": 0.0002, "p2": -0.0001, "camera_model": "OPENCV",
        "frames": [
            {"file_path": "images/frame_00001.png", "transform_matrix": _c2w([1.0, 2.0, 0.5], [0, 0, 0]),
             "colmap_im_id": 1},
            {"file_path": "images/frame_00002.png", "transform_matrix": _c2w([-1.5, 0.3, 0.8], [0.1, 0, 0]),
             "colmap_im_id": 2},
            {"file_path": "images/frame_00003.png", "transform_matrix": _c2w([0.2, -2.0, 1.0], [0, 0.2, 0]),
             "colmap_im_id": 3},
        ],
        "applied_transform": [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [-0.0, -0.0, -1.0, -0.0]],
        "ply_file_path": "sparse_pc.ply",
    }


def _assert_json_close(a, b, path="$"):
    """Equal structure and keys; numbers equal to POSE_ATOL."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{path}: keys {sorted(a)} vs {sorted(b)}"
        for k in a:
            _assert_json_close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{path}: lengths differ"
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_json_close(x, y, f"{path}[{i}]")
    elif isinstance(a, (int, float)) and not isinstance(a, bool):
        assert isinstance(b, (int, float)) and abs(a - b) <= POSE_ATOL, f"{path}: {a} vs {b}"
    else:
        assert a == b, f"{path}: {a!r} vs {b!r}"


def _write(folder: Path, doc, name="capture.json") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return p


def _captures_equal(a: Capture, b: Capture) -> None:
    assert a.extra == b.extra and len(a.frames) == len(b.frames)
    for fa, fb in zip(a.frames, b.frames):
        assert fa.file_path == fb.file_path and fa.mask_path == fb.mask_path
        np.testing.assert_allclose(fa.R, fb.R, atol=POSE_ATOL)
        np.testing.assert_allclose(fa.t, fb.t, atol=POSE_ATOL)
        assert fa.intrinsics == fb.intrinsics
        assert fa.exposure == fb.exposure and fa.saturation == fb.saturation and fa.extra == fb.extra
        if fa.light is None:
            assert fb.light is None
        else:
            assert fa.light.type == fb.light.type
            np.testing.assert_array_equal(fa.light.intensity, fb.light.intensity)
            for attr in ("position", "direction"):
                va, vb = getattr(fa.light, attr), getattr(fb.light, attr)
                assert (va is None and vb is None) or np.allclose(va, vb, atol=1e-15)


# ---------------------------------------------------------------- round trips


def _texstream_capture(root: Path) -> Capture:
    intr = Intrinsics(width=64, height=48, fx=80.0, fy=81.0, cx=32.5, cy=24.0)
    frames = []
    for i, eye in enumerate(([2.0, 0, 1], [0, 2.0, 1], [-2.0, 0.5, 0.3])):
        r, t = conventions.look_at_w2c(np.array(eye), np.zeros(3))
        light = (Light.point(np.array(eye) * 1.5, [3.0, 2.5, 2.0]) if i != 1
                 else Light.directional([0.3, -0.2, -1.0], [1.0, 1.0, 1.0]))
        frames.append(Frame(file_path=f"images/{i:04d}.png", R=r, t=t, intrinsics=intr, light=light,
                            exposure=[1.0, 0.5, 2.0][i], mask_path=f"masks/{i:04d}.png",
                            saturation=None if i == 0 else 0.98, extra={"note": i}))
    return Capture(root=root, frames=frames, extra={"scene": "test", "bounding_box": {"min": [-1, -1, -1]}})


def test_round_trip_read_write_read(tmp_path):
    cap = _texstream_capture(tmp_path / "a")
    p = write_capture(cap, tmp_path / "a")
    first = read_capture(tmp_path / "a")
    _captures_equal(cap, first)
    write_capture(first, tmp_path / "b")
    second = read_capture(tmp_path / "b" / "capture.json")
    _captures_equal(first, second)
    # the documents themselves are equal (not just what they parse to)
    _assert_json_close(json.loads(p.read_text()), json.loads((tmp_path / "b" / "capture.json").read_text()))
    # shared intrinsics are written once at the top level, nerfstudio style
    doc = json.loads(p.read_text())
    assert doc["fl_x"] == 80.0 and "fl_x" not in doc["frames"][0]
    assert doc["frames"][1]["light"]["type"] == "directional" and "exposure" not in doc["frames"][0]


def test_nerfstudio_transforms_loads_keeps_unknown_keys_and_writes_back(tmp_path):
    src = _ns_transforms()
    _write(tmp_path / "ns", src, name="transforms.json")
    cap = read_capture(tmp_path / "ns")  # a folder holding only transforms.json
    assert len(cap.frames) == 3
    f0 = cap.frames[0]
    assert f0.intrinsics.camera_model == "OPENCV" and f0.intrinsics.width == 960
    assert f0.intrinsics.distortion == {"k1": -0.0123, "k2": 0.0045, "p1": 0.0002, "p2": -0.0001}
    assert not f0.intrinsics.is_pinhole
    assert f0.extra == {"colmap_im_id": 1}
    assert cap.extra["applied_transform"] == src["applied_transform"] and cap.extra["ply_file_path"] == "sparse_pc.ply"
    assert cap.image_path(f0) == tmp_path / "ns" / "images" / "frame_00001.png"
    # pose convention: the point one unit along the nerfstudio camera's -z axis projects to (cx, cy)
    for fd, fr in zip(src["frames"], cap.frames):
        m = np.asarray(fd["transform_matrix"])
        ahead = m[:3, 3] - m[:3, 2]
        uv, z = conventions.project(ahead[None], fr.R, fr.t, 771.3, 770.9, 481.2, 268.7)
        np.testing.assert_allclose(uv[0], [481.2, 268.7], atol=1e-9)  # float64 rounding of ~1e3 pixels
        assert z[0] == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(fr.center, m[:3, 3], atol=POSE_ATOL)
    write_capture(cap, tmp_path / "out")
    _assert_json_close(src, json.loads((tmp_path / "out" / "capture.json").read_text()))


def test_per_frame_intrinsics(tmp_path):
    src = _ns_transforms()
    for k in ("w", "h", "fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2", "camera_model"):
        del src[k]
    for i, fd in enumerate(src["frames"]):
        fd.update({"w": 100 + i, "h": 80, "fl_x": 90.0 + i, "fl_y": 91.0, "cx": 50.0, "cy": 40.0,
                   "camera_model": "PINHOLE"})
    _write(tmp_path / "pf", src)
    cap = read_capture(tmp_path / "pf")
    assert [f.intrinsics.width for f in cap.frames] == [100, 101, 102]
    assert [f.intrinsics.fx for f in cap.frames] == [90.0, 91.0, 92.0]
    write_capture(cap, tmp_path / "pf2")
    doc = json.loads((tmp_path / "pf2" / "capture.json").read_text())
    assert "fl_x" not in doc and doc["frames"][2]["fl_x"] == 92.0
    _assert_json_close(src, doc)


def test_frame_overrides_top_level_intrinsics(tmp_path):
    src = _ns_transforms()
    src["frames"][1]["fl_x"] = 700.0  # a frame may override part of the shared intrinsics
    _write(tmp_path / "ov", src)
    cap = read_capture(tmp_path / "ov")
    assert [f.intrinsics.fx for f in cap.frames] == [771.3, 700.0, 771.3]
    assert cap.frames[1].intrinsics.fy == 770.9 and cap.frames[1].intrinsics.distortion["k1"] == -0.0123


# ---------------------------------------------------------------- bad input


def _bad(mutate):
    doc = _ns_transforms()
    mutate(doc)
    return doc


BAD_DOCS = {
    "missing_file_path": (_bad(lambda d: d["frames"][1].pop("file_path")), "frames\\[1\\] lacks 'file_path'"),
    "missing_transform": (_bad(lambda d: d["frames"][0].pop("transform_matrix")), "lacks 'transform_matrix'"),
    "missing_intrinsics": (_bad(lambda d: d.pop("fl_y")), "lacks intrinsics field"),
    "no_frames": (_bad(lambda d: d.pop("frames")), "no 'frames' list"),
    "empty_frames": (_bad(lambda d: d.update(frames=[])), "empty 'frames'"),
    "scaled_transform": (_bad(lambda d: d["frames"][2].update(
        transform_matrix=(np.diag([2.0, 2.0, 2.0, 1.0]) @ np.asarray(d["frames"][2]["transform_matrix"])).tolist())),
        "not a rigid transform"),
    "reflection": (_bad(lambda d: d["frames"][0].update(
        transform_matrix=(np.diag([-1.0, 1.0, 1.0, 1.0]) @ np.asarray(d["frames"][0]["transform_matrix"])).tolist())),
        "not a rigid transform"),
    "projective_row": (_bad(lambda d: d["frames"][0]["transform_matrix"].__setitem__(3, [0.1, 0.0, 0.0, 1.0])),
                       "last row"),
    "bad_matrix_shape": (_bad(lambda d: d["frames"][0].update(transform_matrix=[[1, 0], [0, 1]])), "4x4"),
    "bad_light_type": (_bad(lambda d: d["frames"][0].update(light={"type": "spot", "intensity": [1, 1, 1]})),
                       "'spot'"),
    "light_missing_position": (_bad(lambda d: d["frames"][0].update(light={"type": "point", "intensity": [1, 1, 1]})),
                               "malformed light"),
    "light_short_intensity": (_bad(lambda d: d["frames"][0].update(
        light={"type": "directional", "direction": [0, 0, -1], "intensity": [1, 1]})), "malformed light"),
    "light_zero_direction": (_bad(lambda d: d["frames"][0].update(
        light={"type": "directional", "direction": [0, 0, 0], "intensity": [1, 1, 1]})), "malformed light"),
    "negative_exposure": (_bad(lambda d: d["frames"][0].update(exposure=-1.0)), "exposure"),
    "text_exposure": (_bad(lambda d: d["frames"][0].update(exposure="bright")), "exposure"),
    "text_saturation": (_bad(lambda d: d["frames"][0].update(saturation="high")), "saturation"),
    "zero_focal": (_bad(lambda d: d.update(fl_x=0.0)), "non-positive"),
    "text_focal": (_bad(lambda d: d.update(fl_x="big")), "non-numeric"),
}


@pytest.mark.parametrize("name", list(BAD_DOCS))
def test_bad_capture_json_names_file(tmp_path, name):
    doc, pattern = BAD_DOCS[name]
    p = _write(tmp_path / name, doc)
    with pytest.raises(InputError, match=pattern) as e:
        read_capture(p)
    assert str(p) in str(e.value) and "Fix:" in str(e.value)


@pytest.mark.parametrize("text", ["{not json", "", "\xff\xfe"])
def test_non_json(tmp_path, text):
    p = tmp_path / "capture.json"
    p.write_bytes(text.encode("latin-1"))
    with pytest.raises(InputError, match="not valid JSON") as e:
        read_capture(tmp_path)
    assert str(p) in str(e.value)


def test_missing_capture(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_capture(tmp_path / "nothing")


def test_failed_write_leaves_previous_file(tmp_path):
    cap = _texstream_capture(tmp_path)
    p = write_capture(cap)
    before = p.read_text()
    bad = copy.deepcopy(cap)
    bad.extra["oops"] = float("nan")  # not representable in strict JSON: the write must fail cleanly
    with pytest.raises(StageError, match="oops is nan"):  # one line naming the file and the key
        write_capture(bad)
    assert p.read_text() == before and sorted(os.listdir(tmp_path)) == ["capture.json"]
