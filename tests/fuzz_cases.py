"""The fuzz cases: each family builds its inputs in a folder and yields :class:`Case` objects that
:func:`run_case` runs and judges by the harness's property (tests/fuzz_harness.py). The tests draw a
CI-sized sample of each family; scripts/fuzz.py runs them all, with generated ones on top.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random
import shutil
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

import fuzz_damage as D
import fuzz_harness as H

SYNTH_TINY = ["--scale", "0.02", "--photos", "8", "--image-size", "24", "--no-progress", "--no-preview"]
"""a synthetic sphere of 8 photos of 24x24 (issue 41's tiny run): seconds for every stage"""


@dataclasses.dataclass
class Case:
    """One fuzz case: a command line (or a reader call) and what its outcome must satisfy."""

    family: str
    key: tuple
    """(command, what): the name KNOWN_H1 lists it by"""
    argv: list | None = None
    call: Callable[[], Any] | None = None
    """a reader called directly (instead of a command line)"""
    stub: bool = False
    must_fail: bool = False
    must_pass: bool = False
    """a valid input: refusing it is a violation too"""
    names: tuple = ()
    root: Path | None = None
    outputs: tuple = ()
    valid: Callable[[], str | None] | None = None
    fault: tuple | None = None
    """(write number, fault kind) to inject"""
    seed: int | None = None
    pre: Callable[[], Any] | None = None
    """run before the case (e.g. clear its output)"""
    post: Callable[[], list[str]] | None = None
    """run after it: more violations (e.g. a rerun's)"""

    def reproduction(self) -> str:
        what = " ".join(map(str, self.argv)) if self.argv else f"{self.family} {self.key}"
        extra = f" [fault {self.fault[1]} at write {self.fault[0]} under {self.root}]" if self.fault else ""
        return what + extra + (f" [seed {self.seed}]" if self.seed is not None else "")


def run_case(case: Case) -> tuple[list[str], H.Outcome]:
    """Run a case; (its violations of the property, its outcome)."""
    if case.pre is not None:
        case.pre()
    before = {Path(p): H.tree_digest(Path(p)) for p in case.outputs}
    left_before = H.leftovers(case.root) if case.root is not None and Path(case.root).exists() else []
    faults = None
    if case.call is not None:
        outcome = _call(case)
    else:
        faults = H.FaultInjector(case.root, *case.fault) if case.fault else None
        outcome = H.run_cli(case.argv, stub=case.stub, faults=faults)
    found = H.violations(outcome, names=case.names, root=case.root, outputs=before, must_fail=case.must_fail,
                         valid=case.valid, left_before=left_before)
    if case.fault and outcome.fault_fired:  # the key says where it fired (KNOWN_H1 lists the renames into place)
        case.key = (case.key[0], f"{case.fault[1]}@{faults.site}")
    if case.fault and outcome.fault_fired and outcome.rc == 0:
        found.append("a fault fired but the command exited 0")
    if case.fault and outcome.fault_fired and case.fault[1] != "sigint" and outcome.form() == "line":
        where = Path(faults.where)
        if where.name not in outcome.stderr_lines[-1] and str(where.parent) not in outcome.stderr_lines[-1]:
            found.append(f"the full-disk / read-only error does not name {where}: {outcome.stderr_lines[-1][:200]!r}")
    if case.must_pass and outcome.rc != 0 and outcome.form() != "bad":
        found.append(f"refused a valid input: {outcome.stderr_lines[-1][:200] if outcome.stderr_lines else outcome.rc}")
    if case.post is not None:
        found += case.post()
    return found, outcome


def _call(case: Case) -> H.Outcome:
    """A reader called directly, its outcome in the CLI's terms (an InputError as its one line)."""
    import traceback

    from texstream.core.errors import TexstreamError

    with H._captured_fds() as read:
        rc, err, error = 0, "", None
        try:
            result = case.call()
            if case.valid is None:
                case.valid = lambda: None
            why = _valid_result(result)
            if why:
                case.valid = lambda why=why: why
        except TexstreamError as e:
            rc, err = 1, f"texstream read: error: {e.one_line()}\n"
        except BaseException:  # noqa: BLE001 - what escapes a reader is what the harness looks for
            error = traceback.format_exc()
        out, captured = read()
    return H.Outcome([case.family, *map(str, case.key)], rc, out, captured + err, error)


def _valid_result(result: Any) -> str | None:
    """What is wrong with a reader's return value (arrays finite, captures sane), or None."""
    if isinstance(result, np.ndarray) and result.dtype.kind == "f" and not np.all(np.isfinite(result)):
        return "the array holds NaN/Inf"
    frames = getattr(result, "frames", None)
    if frames is not None:
        for f in frames:
            k = f.intrinsics
            paths_ok = isinstance(f.file_path, str) and f.file_path and isinstance(f.mask_path, (str, type(None)))
            if not paths_ok:
                return f"frame paths {f.file_path!r} / {f.mask_path!r}"
            if not (0 < k.width <= 1 << 20 and 0 < k.height <= 1 << 20 and k.fx > 0 and k.fy > 0):
                return f"intrinsics {k}"
            if not (np.all(np.isfinite(f.R)) and np.all(np.isfinite(f.t)) and abs(np.linalg.det(f.R) - 1) < 1e-2):
                return "a pose that is not a rotation"
            if not (math.isfinite(f.exposure) and f.exposure > 0):
                return f"exposure {f.exposure}"
    return None


# --------------------------------------------------------------------------- options


def option_cases(fx: dict, commands=H.COMMANDS) -> Iterator[Case]:
    """Every option of every command at each of its out-of-range values (stage stubbed: must fail at parse
    time, with one line naming the option)."""
    for command in commands:
        for spec in H.option_specs(command):
            for v in spec.out_of_range():
                argv = H.base_argv(command, fx) + [spec.flag, *H.format_value(v)]
                yield Case("option_range", (command, spec.dest), argv, stub=True, must_fail=True,
                           names=tuple(spec.names()))


def in_range(spec: H.OptionSpec, v: Any) -> bool:
    if isinstance(v, float) and (v != v or (math.isinf(v) and (spec.lo is not None or spec.hi is not None))):
        return False  # NaN never; an infinity where a bound is documented
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return True
    if v in H.EXTRA_BAD.get((spec.command, spec.dest), ()):
        return False
    if spec.lo is not None and (v < spec.lo or (spec.lo_open and v == spec.lo)):
        return False
    return not (spec.hi is not None and v > spec.hi)


def random_value(spec: H.OptionSpec, rng: random.Random) -> Any:
    """A value for an option: mostly of its type (wide ints, floats with NaN/Inf, near its bounds), sometimes
    a word of another type or an unknown choice."""
    r = rng.random()
    if r < 0.1:
        return rng.choice(["abc", "", "1e999", "-", "--", "0x10", "1,2", "nan", "🙂", "' OR 1=1"])
    if spec.kind == "int":
        near = [b for b in (spec.lo, spec.hi) if b is not None]
        return int(rng.choice(near) + rng.randint(-2, 2)) if near and r < 0.5 else rng.choice(
            [0, -1, 1, 2 ** 31, -2 ** 63, rng.randint(-1000, 1000), 10 ** 30])
    if spec.kind == "float":
        near = [b for b in (spec.lo, spec.hi) if b is not None]
        if near and r < 0.5:
            return float(rng.choice(near)) + rng.choice([-1e-9, 0.0, 1e-9, -0.5, 0.5])
        return rng.choice([float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1e308, -1e-308,
                           rng.uniform(-1e3, 1e3)])
    if spec.kind == "choice":
        first = spec.choices[0]
        return rng.choice([*spec.choices, "nonsense", first.upper() if isinstance(first, str) else -1])
    if spec.kind == "list":
        return [random_value(dataclasses.replace(spec, kind="float"), rng) for _ in range(rng.randint(0, 4))] or ["x"]
    if spec.kind in ("bool", "switch"):
        return None
    return rng.choice(["x", "", "/nonexistent/path", "a" * 300, "../../etc", "cpu", "cuda:9"])


def generated_option_case(fx: dict, rng: random.Random, seed: int) -> Case:
    """One generated case: a command and one to three options with random values."""
    command = rng.choice(H.COMMANDS)
    specs = H.option_specs(command)
    argv = H.base_argv(command, fx)
    refused, names = [], []
    for spec in rng.sample(specs, min(len(specs), rng.randint(1, 3))):
        v = random_value(spec, rng)
        if spec.kind in ("bool", "switch"):
            negate = spec.kind == "bool" and rng.random() < 0.5
            argv.append(spec.flag.replace("--", "--no-", 1) if negate else spec.flag)
            continue
        argv += [spec.flag, *H.format_value(v)]
        # the command may refuse any of them first (a word where a number goes), naming the option or the value
        # it could not take (a path option's missing file, argparse's "unrecognized arguments: -inf")
        names += [*spec.names(), *(t for t in H.format_value(v) if len(t) > 2 and any(c.isalpha() for c in t))]
        if not in_range(spec, v):
            refused.append(spec.dest)
    # keyed by an out-of-range option, one not on a known list first (the command must refuse that one)
    refused.sort(key=lambda dest: H.known_owner((command, dest)) is not None)
    return Case("option_generated", (command, refused[0] if refused else "generated"), argv, stub=True,
                must_fail=bool(refused), names=tuple(names), seed=seed)


def contradiction_cases(fx: dict) -> Iterator[Case]:
    """Options that contradict each other or the command's inputs: each must fail with one line."""
    root, cap, atlas = fx["root"], str(fx["capture"]), str(fx["atlas"])
    nowhere = str(root / "nowhere")
    table = [
        (("fit", "mesh_and_normals"), ["fit", cap, "--mesh", atlas, "--normals", str(fx["mesh"]), "-o",
                                       str(root / "o")], True),
        (("fit", "neither_mesh_nor_normals"), ["fit", cap, "-o", str(root / "o")], True),
        (("import", "metashape_without_photos"), ["import", "metashape", str(fx["mesh"]), "-o", str(root / "o")], True),
        (("import", "colmap_with_photos"), ["import", "colmap", cap, str(fx["photos"]), "-o", str(root / "o")], True),
        (("run", "mirror_ball_words"), ["run", cap, "-o", str(root / "o"), "--mirror-ball", "a,b,c"], True),
        (("run", "mirror_ball_three_numbers"), ["run", cap, "-o", str(root / "o"), "--mirror-ball", "1,2,3"], True),
        (("run", "config_missing"), ["run", cap, "-o", str(root / "o"), "--config", nowhere], True),
        (("run", "out_is_a_file"), ["run", cap, "-o", str(fx["mesh"])], False),
        (("run", "input_missing"), ["run", nowhere, "-o", str(root / "o")], False),
        (("mesh", "no_capture_no_mesh"), ["mesh", "-o", str(root / "o")], False),
        (("mesh", "from_missing_file"), ["mesh", "-o", str(root / "o"), "--from", nowhere + ".obj"], False),
        (("atlas", "mesh_missing"), ["atlas", nowhere + ".obj", "-o", str(root / "o")], False),
        (("atlas", "out_is_a_file"), ["atlas", str(fx["mesh"]), "-o", str(fx["mesh"])], False),
        (("eval", "model_missing"), ["eval", nowhere, cap], False),
        (("export", "model_missing"), ["export", nowhere, "-o", str(root / "o")], False),
        (("export", "model_is_empty_folder"), ["export", str(fx["model"]), "-o", str(root / "o")], False),
        (("synth", "unknown_scene"), ["synth", "teapot_of_doom", "-o", str(root / "o")], False),
        (("synth", "scene_file_not_json"), ["synth", str(fx["mesh"]), "-o", str(root / "o")], False),
        (("calibrate", "photos_missing"), ["calibrate", nowhere, "-o", str(root / "o")], False),
        (("ingest", "photos_missing"), ["ingest", nowhere, "-o", str(root / "o")], False),
        (("ingest", "empty_folder"), ["ingest", str(fx["atlas"]), "-o", str(root / "o")], False),
        (("register", "capture_missing"), ["register", nowhere, "-o", str(root / "o")], False),
        (("refine", "capture_missing"), ["refine", nowhere, atlas, "-o", str(root / "o")], False),
        (("import", "nerfstudio_missing"), ["import", "nerfstudio", nowhere, "-o", str(root / "o")], False),
        (("import", "colmap_missing"), ["import", "colmap", nowhere, "-o", str(root / "o")], False),
        (("none", "no_command"), ["--debug-nothing"], False),
        (("none", "unknown_command"), ["frobnicate"], False),
    ]
    for key, argv, stub in table:
        yield Case("contradiction", key, argv, stub=stub, must_fail=True)


# --------------------------------------------------------------------------- damaged inputs


def photo_reader_cases(root: Path) -> Iterator[Case]:
    """Every damaged or odd photo through the three readers: valid arrays, or an InputError naming it."""
    from texstream.capture.imageio import image_size, read_image, read_mask

    for name, (build, expect) in D.PHOTO_CASES.items():
        d = root / "photos" / name
        d.mkdir(parents=True, exist_ok=True)
        p = build(d)
        for reader in (read_image, read_mask, image_size):
            must_fail = expect == "fail" and reader is not image_size  # the size is in the header
            if name in ("empty_png", "random_bytes_jpeg", "text_as_png", "bomb_png"):
                must_fail = True
            yield Case("photo_reader", ("read", f"{name}:{reader.__name__}"), call=lambda r=reader, p=p: r(p),
                       must_fail=must_fail, must_pass=expect != "fail", names=(p.name,))
    # the CMYK files must read as the colours they hold, not their inks
    yield Case("photo_reader", ("read", "cmyk_colours"), call=lambda: _cmyk_check(root / "photos"), must_pass=True)


def _cmyk_check(folder: Path) -> np.ndarray:
    from texstream.capture.imageio import read_image, srgb_to_linear

    want = srgb_to_linear(np.array(D.CMYK_JPEG_RGB8) / 255.0)
    for p in (folder / "cmyk_jpeg" / "cmyk.jpg", folder / "cmyk_tiff" / "cmyk.tif"):
        got = read_image(p)[0, 0]
        # 2/255 in code values: JPEG's lossy chroma and the two converters' rounding
        if not np.allclose(got, want, atol=srgb_to_linear(np.array([2 / 255.0]))[0] + 0.01):
            return np.array([np.nan])
    return np.zeros(1)


def ingest_cases(root: Path) -> Iterator[Case]:
    """``texstream ingest`` on three good photos and one damaged or odd one: exit 0 with the odd photo in the
    capture (or the damaged one dropped and listed), or one line naming it."""
    for name, (build, expect) in D.PHOTO_CASES.items():
        folder = root / "ingest" / name
        D.good_photos(folder, n=3, size=(24, 32))
        p = build(folder)
        out = root / "ingest_out" / name
        yield Case("photo_ingest", ("ingest", name), ["ingest", str(folder), "-o", str(out), "--auto-masks", "none"],
                   names=(p.name, str(folder)), root=root / "ingest_out", outputs=(out,), must_pass=expect == "read",
                   valid=lambda out=out, p=p, expect=expect: _ingest_valid(out, p, expect))


def _ingest_valid(out: Path, photo: Path, expect: str) -> str | None:
    from texstream.capture.capture_json import read_capture
    from texstream.capture.imageio import read_image

    cap = read_capture(out)
    names = [Path(f.file_path).stem for f in cap.frames]
    report = json.loads((out / "ingest_report.json").read_text())
    dropped = [d["image"] for d in report.get("dropped", [])]
    if expect in ("fail", "unusable") and photo.stem in names:
        return f"the {'damaged' if expect == 'fail' else 'unusable'} {photo.name} became a frame"
    if expect in ("fail", "unusable") and not any(photo.name in d for d in dropped):
        return f"the {'damaged' if expect == 'fail' else 'unusable'} {photo.name} is neither a frame nor dropped"
    for f in cap.frames:
        img = read_image(cap.image_path(f))
        if img.shape[:2] != (f.intrinsics.height, f.intrinsics.width):
            return f"{f.file_path} is {img.shape[:2]}, its camera {f.intrinsics.height}x{f.intrinsics.width}"
    return None


def register_cases(root: Path) -> Iterator[Case]:
    """``texstream register`` on three photos with nothing to match (smooth gradients): one error line."""
    photos = root / "register" / "photos"
    D.good_photos(photos, n=3)
    cap, out = root / "register" / "capture", root / "register" / "posed"
    yield Case("register", ("register", "ingest_for_it"),
               ["ingest", str(photos), "-o", str(cap), "--auto-masks", "none"])
    yield Case("register", ("register", "unusable_photos"), ["register", str(cap), "-o", str(out)], must_fail=True,
               names=(str(cap),), root=root / "register", outputs=(out,))


def capture_reader_cases(root: Path, rng: random.Random | None = None, limit: int | None = None) -> Iterator[Case]:
    """capture.json mutations (a key deleted, a value replaced by a wrong type, NaN, a singular pose, ...) and
    damaged texts, read by read_capture: a sane capture, or an InputError naming the file."""
    from texstream.capture.capture_json import read_capture

    doc = D.valid_capture_doc()
    mutations = [(p, "delete", None) for p in D.capture_paths(doc)]
    mutations += [(p, "set", v) for p in D.capture_paths(doc) for v in D.BAD_VALUES]
    if rng is not None and limit is not None:
        mutations = rng.sample(mutations, min(limit, len(mutations)))
    folder = root / "captures"
    folder.mkdir(parents=True, exist_ok=True)
    for i, (path, action, value) in enumerate(mutations):
        f = folder / f"m{i}.json"
        f.write_text(json.dumps(D.mutate(doc, path, action, value)))
        yield Case("capture_json", ("read_capture", f"{'.'.join(map(str, path))}:{action}:{value!r}"[:120]),
                   call=lambda f=f: read_capture(f), names=(f.name,))
    for name, text in D.damaged_json_texts(doc).items():
        f = folder / f"{name}.json"
        f.write_text(text)
        must_fail = name not in ("bom", "latin1")
        yield Case("capture_json", ("read_capture", name), call=lambda f=f: read_capture(f), names=(f.name,),
                   must_fail=must_fail and name != "bom")


def nerfstudio_cases(root: Path, limit: int = 12, seed: int = 0) -> Iterator[Case]:
    """``texstream import nerfstudio`` on damaged transforms.json files (the reader behind a real command)."""
    rng = random.Random(seed)
    doc = D.valid_capture_doc()
    texts = list(D.damaged_json_texts(doc).items())
    paths = D.capture_paths(doc)
    for i in range(limit):
        if i < len(texts) and i % 2 == 0:
            name, text = texts[i]
        else:
            path = rng.choice(paths)
            name = f"{'.'.join(map(str, path))}={i}"
            text = json.dumps(D.mutate(doc, path, "set", rng.choice(D.BAD_VALUES)))
        folder = root / "ns" / f"case{i}"
        D.write_capture_folder(folder, text, name="transforms.json")
        out = root / "ns_out" / f"case{i}"
        yield Case("nerfstudio", ("import", name), ["import", "nerfstudio", str(folder), "-o", str(out)],
                   names=("transforms.json", str(folder)), root=root / "ns_out", outputs=(out,), seed=seed,
                   valid=lambda out=out: _capture_valid(out))


def _capture_valid(out: Path) -> str | None:
    from texstream.capture.capture_json import read_capture

    cap = read_capture(out)
    missing = [f.file_path for f in cap.frames if not cap.image_path(f).is_file()]
    return _valid_result(cap) or (f"{missing[0]} missing" if missing else None)


def colmap_cases(root: Path) -> Iterator[Case]:
    """``texstream import colmap`` on damaged binary and text models."""
    for text in (False, True):
        base = root / f"colmap_{'txt' if text else 'bin'}"
        D.colmap_model(base / "sparse" / "0", text=text)
        D.good_photos(base / "images", n=3)
        intact = root / "colmap_out" / f"intact_{'txt' if text else 'bin'}"  # the checks refuse no good model
        yield Case("colmap", ("import", "intact"), ["import", "colmap", str(base), "-o", str(intact)],
                   root=root / "colmap_out", must_pass=True, valid=lambda out=intact: _capture_valid(out))
        for name in D.colmap_damages(base / "sparse" / "0"):
            case = root / "colmap" / f"{name}_{'txt' if text else 'bin'}"
            if not case.exists():
                shutil.copytree(base, case)
                D.colmap_damages(case / "sparse" / "0")[name]()
            out = root / "colmap_out" / case.name
            yield Case("colmap", ("import", name), ["import", "colmap", str(case), "-o", str(out)], must_fail=True,
                       names=(str(case),), root=root / "colmap_out", outputs=(out,))


def mesh_cases(root: Path) -> Iterator[Case]:
    """Damaged meshes given to ``atlas`` and to ``mesh --from``."""
    for name, build in D.MESH_CASES.items():
        d = root / "meshes" / name
        d.mkdir(parents=True, exist_ok=True)
        p = build(d)
        for command in ("atlas", "mesh"):
            out = root / "mesh_out" / f"{command}_{name}"
            argv = (["atlas", str(p), "-o", str(out)] if command == "atlas"
                    else ["mesh", "-o", str(out), "--from", str(p)])
            yield Case("mesh", (command, name), argv, must_fail=name != "degenerate_faces_obj", names=(p.name,),
                       root=root / "mesh_out", outputs=(out,))


def toml_cases(root: Path, capture: Path) -> Iterator[Case]:
    """``texstream run --config`` with damaged TOML (the run's stages stubbed: the config must fail first)."""
    folder = root / "toml"
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in D.TOML_CASES.items():
        p = folder / f"{name}.toml"
        p.write_text(text)
        argv = ["run", str(capture), "-o", str(root / "toml_out"), "--config", str(p)]
        yield Case("toml", ("run", f"toml:{name}"), argv, stub=True, must_fail=name not in D.TOML_MAY_PASS,
                   names=(p.name,))


def generated_toml_case(root: Path, rng: random.Random, seed: int, capture: Path) -> Case:
    """A run config with random tables, keys and values (some real option names, some not)."""
    from texstream.core.toml import dumps
    from texstream.core.config import config_to_dict
    from texstream.pipelines.run import RunConfig

    data = config_to_dict(RunConfig())
    data.pop("_type", None)
    flat = []

    def walk(d: dict, path: tuple) -> None:
        for k, v in d.items():
            (walk(v, path + (k,)) if isinstance(v, dict) else flat.append(path + (k,)))
    walk(data, ())
    doc: dict = {}
    for path in rng.sample(flat, rng.randint(1, 4)):
        node = doc
        for k in path[:-1]:
            node = node.setdefault(k, {})
        node[path[-1]] = rng.choice([-1, 0, 2 ** 40, float("nan"), float("inf"), -1e-9, "x", True, [1, "a"], 3.5])
    text = dumps(doc)
    if rng.random() < 0.2:
        text = text[: rng.randint(0, len(text))]
    p = root / "toml_gen" / f"{seed}.toml"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
    argv = ["run", str(capture), "-o", str(root / "toml_out"), "--config", str(p)]
    return Case("toml_generated", ("run", "toml_generated"), argv, stub=True, seed=seed, names=(p.name,))
