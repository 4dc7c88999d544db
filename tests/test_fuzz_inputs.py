"""Issue 41's fuzz harness in CI, inputs: every command's options at out-of-range and generated values,
contradictory options, damaged and odd photos, capture.json / transforms.json, COLMAP models, meshes and
TOML run configs. The property (tests/fuzz_harness.py): exit status 0 with a valid output, or one error
line naming the path or option and the fix; never a traceback; never a half-written output.

Cases whose failure lies in another engineer's files are listed in fuzz_harness.KNOWN_H1 / KNOWN_H4 and
counted apart; every other violation fails here. The larger run is ``scripts/fuzz.py``. Hypothesis runs
derandomized with few examples, so CI is reproducible and quick.
"""

from __future__ import annotations

import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fuzz_cases as C
import fuzz_damage as D
import fuzz_harness as H

CI = settings(max_examples=40, derandomize=True, deadline=None, database=None,
              suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
"""Hypothesis in CI: derandomized (the same examples every run), few of them, no example database"""


def _unexpected(cases) -> list[str]:
    """Run cases; the violations of those not on a known list, each with its reproduction."""
    bad = []
    for case in cases:
        found, _ = C.run_case(case)
        if found and not H.known_owner(case.key):
            bad.append(f"{case.reproduction()}: {found}")
    return bad


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    return H.option_fixtures(tmp_path_factory.mktemp("options"))


def test_every_option_refuses_its_out_of_range_values(fx):
    """Each option of each command at its first out-of-range value (NaN for floats): one line naming the
    option, before the stage starts (scripts/fuzz.py tries every out-of-range value)."""
    firsts = {}
    for case in C.option_cases(fx):
        firsts.setdefault(case.key, case)
    assert len(firsts) > 120, "the option catalogue lost options"  # 143 options with a range or a float today
    assert _unexpected(firsts.values()) == []


def _value_strategy(spec: H.OptionSpec):
    if spec.kind == "int":
        near = [int(b) for b in (spec.lo, spec.hi) if b is not None]
        return st.one_of(st.integers(min_value=-2 ** 63, max_value=2 ** 63), *[st.integers(b - 2, b + 2) for b in near])
    if spec.kind == "float":
        return st.floats(allow_nan=True, allow_infinity=True, width=64)
    if spec.kind == "choice":
        return st.sampled_from([*spec.choices, "nonsense"])
    if spec.kind == "list":
        return st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=1, max_size=4)
    if spec.kind == "bool":
        return st.sampled_from([spec.flag, spec.flag.replace("--", "--no-", 1)])
    if spec.kind == "switch":
        return st.just(spec.flag)
    return st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=12)


@st.composite
def _option_case(draw, fx):
    command = draw(st.sampled_from(H.COMMANDS))
    spec = draw(st.sampled_from(H.option_specs(command)))
    value = draw(_value_strategy(spec))
    argv = H.base_argv(command, fx)
    if spec.kind in ("bool", "switch"):
        return C.Case("option_generated", (command, spec.dest), argv + [value], stub=True)
    must_fail = not C.in_range(spec, value)
    return C.Case("option_generated", (command, spec.dest), argv + [spec.flag, *H.format_value(value)], stub=True,
                  must_fail=must_fail, names=tuple(spec.names()) if must_fail else ())


def test_generated_option_values(fx):
    """Hypothesis draws a command, one of its options and a value of the option's type (any int, any float
    with NaN and Inf, text, unknown choices): accepted in range, refused in one line out of it."""
    @CI
    @given(_option_case(fx))
    def check(case):
        found, _ = C.run_case(case)
        assert not found or H.known_owner(case.key), f"{case.reproduction()}: {found}"
    check()


def test_contradictory_options(fx):
    assert _unexpected(C.contradiction_cases(fx)) == []


def test_photo_readers_on_damaged_and_odd_photos(tmp_path):
    """Truncated JPEG/PNG/EXR, random bytes, empty, a decompression bomb's header, NaN/Inf EXR: an InputError
    naming the file; 1x1, 16-bit, grey+alpha, CMYK JPEG and TIFF, EXIF rotations, a PNG named .jpg: read,
    finite, and the CMYK ones in the colours they hold."""
    assert _unexpected(C.photo_reader_cases(tmp_path)) == []


def test_ingest_with_one_damaged_or_odd_photo(tmp_path):
    """ingest on three good photos and one damaged or odd one: the odd one a frame of its true size, the
    damaged one dropped and listed, or one error line naming it."""
    assert _unexpected(C.ingest_cases(tmp_path)) == []


def test_register_on_photos_with_nothing_to_match(tmp_path):
    assert _unexpected(C.register_cases(tmp_path)) == []


def test_damaged_capture_texts(tmp_path):
    cases = [c for c in C.capture_reader_cases(tmp_path) if c.key[1] in D.damaged_json_texts({})]
    assert len(cases) == len(D.damaged_json_texts({}))
    assert _unexpected(cases) == []


_JSON_VALUES = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=True, allow_infinity=True),
                         st.text(max_size=8), st.lists(st.floats(allow_nan=True), max_size=5),
                         st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=4, max_size=4),
                                  min_size=3, max_size=4),
                         st.dictionaries(st.text(max_size=4), st.integers(), max_size=2))


def test_generated_capture_json(tmp_path):
    """Hypothesis replaces or deletes any field of a valid capture.json (intrinsics, poses, lights, paths,
    exposure) by any JSON value: read_capture returns a sane capture or an InputError naming the file."""
    from texstream.capture.capture_json import read_capture

    doc = D.valid_capture_doc()
    paths = D.capture_paths(doc)
    target = tmp_path / "capture.json"

    @settings(CI, max_examples=150)
    @given(st.sampled_from(paths), st.sampled_from(["set", "delete"]), _JSON_VALUES)
    def check(path, action, value):
        target.write_text(json.dumps(D.mutate(doc, path, action, value)))
        case = C.Case("capture_json", ("read_capture", str(path)), call=lambda: read_capture(target),
                      names=(target.name,))
        found, _ = C.run_case(case)
        assert not found, f"{path} {action} {value!r}: {found}"
    check()


def test_nerfstudio_import_of_damaged_transforms(tmp_path):
    assert _unexpected(C.nerfstudio_cases(tmp_path, limit=6, seed=0)) == []


def test_damaged_colmap_models(tmp_path):
    """Truncated, junk and missing cameras/images/points3D (.bin and .txt), NaN or zero-size cameras, a zero
    quaternion: one line naming the model; a junk points3D.bin no longer hangs pycolmap."""
    assert _unexpected(C.colmap_cases(tmp_path)) == []


def test_damaged_meshes(tmp_path):
    assert _unexpected(C.mesh_cases(tmp_path)) == []


def test_damaged_run_configs(tmp_path):
    cap = tmp_path / "cap"
    cap.mkdir()
    assert _unexpected(C.toml_cases(tmp_path, cap)) == []


def test_the_property_catches_what_it_must(tmp_path):
    """Checks of the checks: a traceback, two lines, a line without a fix, a silent acceptance, a temporary
    file left and a failed command's changed output are each reported."""
    ok = H.Outcome(["x"], 1, "", "texstream x: error: p: bad. Fix: do y.\n")
    assert H.violations(ok, names=("p",)) == []
    assert H.violations(H.Outcome(["x"], None, "", "", error="Traceback\nE: e"))[0].startswith("traceback")
    assert H.violations(H.Outcome(["x"], 1, "", "log line\ntexstream x: error: bad. Fix: y.\n"))
    assert "no fix" in H.violations(H.Outcome(["x"], 1, "", "texstream x: error: bad.\n"))[0]
    assert H.violations(ok, names=("q",))[0].startswith("the error line names none")
    assert H.violations(H.Outcome(["x"], 0, "", ""), must_fail=True)[0].startswith("silent")
    (tmp_path / ".model.abc123.partial").mkdir()
    assert H.violations(ok, root=tmp_path)[0].startswith("half-written")
    out = tmp_path / "out.json"
    before = {out: H.tree_digest(out)}
    out.write_text("{}")
    assert "changed its output" in H.violations(ok, outputs=before)[-1]
