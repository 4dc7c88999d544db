"""Registration, interrupted after feature extraction or after matching, resumes from the COLMAP database its
work folder kept (calib/register.py: ``.<out>.register-work/features.db``, ``matched.db``) and registers the
same cameras as an uninterrupted run, to the last bit.

The interruption is raised in-process right after the kept copy is written (the state a SIGKILL anywhere
before the next copy leaves: the work after it is lost either way), without a subprocess's start-up.
scripts/kill_resume.py kills a real ``texstream run`` with SIGKILL at random times."""

from __future__ import annotations

import json

import pytest

import texstream.calib.register as reg
from texstream.calib.register import RegisterConfig, register
from texstream.core.checkpoint import work_dir_for
from texstream.core.progress import reporting


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """24 sRGB photos (128 px, two rings) of the noise-textured sphere and its intrinsics file (the renderer's K):
    small photos that still register every view."""
    from texstream.capture.capture_json import read_capture
    from texstream.capture.synthetic.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("register_resume")
    synthesize("textured_sphere", root / "sphere", SynthConfig(image_size=128, progress=False, preview=False))
    i = read_capture(root / "sphere").frames[0].intrinsics
    (root / "K.json").write_text(json.dumps({"w": i.width, "h": i.height, "fl_x": i.fx, "fl_y": i.fy,
                                             "cx": i.cx, "cy": i.cy}))
    return root / "sphere"


def config(photos, features: int = 1000) -> RegisterConfig:
    # one thread: COLMAP's matching and mapping are then the same run to run (bit-identical poses)
    return RegisterConfig(max_num_features=features, num_threads=1, photometric="off",
                          intrinsics=str(photos.parent / "K.json"))


@pytest.fixture(scope="module")
def whole(photos, tmp_path_factory):
    """An uninterrupted registration: what every resumed one must give."""
    out = tmp_path_factory.mktemp("register_whole") / "posed"
    res = register(photos, out, config(photos))
    assert len(res.summary["registered"]) >= 5  # a model of several cameras to compare (7 of 24 at 128 px)
    assert not work_dir_for(out, "register").exists()  # removed once the output is in place
    return out


def poses(folder):
    return [(f["file_path"], f["transform_matrix"]) for f in json.loads((folder / "capture.json").read_text())["frames"]]


@pytest.mark.parametrize("copies, said", [(1, "features kept, matching again"),
                                          (2, "features and matches kept, only the mapping runs again")])
def test_an_interrupted_registration_resumes_from_its_database(photos, whole, tmp_path, monkeypatch, copies, said):
    real, calls = reg._keep_database, []

    def keep_then_stop(db, copy):
        real(db, copy)
        calls.append(copy)
        if len(calls) == copies:
            raise KeyboardInterrupt

    monkeypatch.setattr(reg, "_keep_database", keep_then_stop)
    with pytest.raises(KeyboardInterrupt):
        register(photos, tmp_path / "again", config(photos))
    monkeypatch.undo()
    lines = []
    with reporting(lines.append, bars=False):
        register(photos, tmp_path / "again", config(photos))
    assert any("resuming from" in line and said in line for line in lines), lines
    assert poses(tmp_path / "again") == poses(whole)


def test_a_database_of_other_options_is_ignored_with_a_line(photos, tmp_path, monkeypatch):
    def stop(db, copy):
        raise KeyboardInterrupt

    monkeypatch.setattr(reg, "_keep_database", stop)  # interrupted after extraction, its copy not yet kept
    with pytest.raises(KeyboardInterrupt):
        register(photos, tmp_path / "out", config(photos))
    lines = []
    other = config(photos, features=900)
    with reporting(lines.append, bars=False), pytest.raises(KeyboardInterrupt):  # stopped again: the lines matter
        register(photos, tmp_path / "out", other)
    assert any("work of other inputs or options: ignored" in line for line in lines), lines
    assert not any("resuming" in line for line in lines)
