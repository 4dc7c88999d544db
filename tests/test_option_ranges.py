"""Every numeric option is checked against its documented range when the command line is parsed (issue 41):
``fit --texture-size 7`` and ``eval --holdout-every -1`` used to be accepted without a word."""

from __future__ import annotations

import argparse
import dataclasses
import typing

import pytest

from texstream.core.config import Number, check_config
from texstream.core.errors import ConfigError
from texstream.pipelines.cli import SUBCOMMANDS, _field_type, build_parser, main
from texstream.pipelines.run import RunConfig

EXEMPT = {
    "LightsConfig.sphere": "mirror-ball centres and radii in world coordinates: any real number is a place "
                           "(the radius is checked positive where the balls are read, calib/lights.py)",
}
"""numeric options with no range, each with why"""


def _subparser(name: str) -> argparse.ArgumentParser:
    parser = build_parser(only=name)
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]


def _numeric_actions():
    for name in SUBCOMMANDS:
        for action in _subparser(name)._actions:
            if action.type in (int, float) or isinstance(action.type, Number):
                yield name, action


def test_every_numeric_option_of_every_command_is_checked_at_parse_time():
    exempt = {k.split(".")[1] for k in EXEMPT}
    plain = [f"texstream {name} {a.option_strings[-1]}" for name, a in _numeric_actions()
             if not isinstance(a.type, Number) and not a.choices and a.dest.split("__")[-1] not in exempt]
    assert plain == [], f"numeric options without a range: {plain}"
    numbers = [a for _, a in _numeric_actions() if isinstance(a.type, Number)]
    assert len(numbers) > 150  # the walk saw the configs' options, not only the plain ones
    for a in numbers:
        assert a.type.min is not None or a.type.max is not None, a.option_strings
        if isinstance(a.default, (int, float)) and not isinstance(a.default, bool):
            a.type(str(a.default))  # the default is in its own range


def _configs(cls, seen):
    if cls in seen:
        return
    seen.add(cls)
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        t = _field_type(hints[f.name])
        if dataclasses.is_dataclass(t):
            _configs(t, seen)


def test_every_numeric_config_field_has_a_documented_range():
    """The fields of every config a command or `texstream run --config` reads (the TOML path: check_config)."""
    import importlib

    seen: set = set()
    _configs(RunConfig, seen)
    for module, _ in SUBCOMMANDS.values():
        for v in vars(importlib.import_module(module)).values():
            if isinstance(v, type) and dataclasses.is_dataclass(v) and v.__module__.startswith("texstream.") \
                    and "Config" in v.__name__:
                _configs(v, seen)
    missing = []
    for cls in seen:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            t = _field_type(hints[f.name])
            if typing.get_origin(t) in (tuple, list):
                t = typing.get_args(t)[0]
            meta = f.metadata or {}
            if t in (int, float) and meta.get("min") is None and meta.get("max") is None \
                    and not meta.get("choices") and f"{cls.__name__}.{f.name}" not in EXEMPT:
                missing.append(f"{cls.__module__}.{cls.__name__}.{f.name}")
        try:
            cfg = cls()
        except TypeError:  # a config with required fields: its defaults are not all given
            continue
        check_config(cfg)  # every default in its own range
    assert len(seen) > 15
    assert missing == [], f"numeric config fields without a documented range: {missing}"


@pytest.mark.parametrize("argv,message", [
    (["fit", "cap", "--mesh", "m", "-o", "o", "--texture-size", "7"],
     "--texture-size 7 is out of range [8, 16384] (or 0)"),
    (["eval", "model", "cap", "--holdout-every", "-1"], "--holdout-every -1 is out of range [0, inf]"),
    (["run", "--iterations", "0"], "--iterations 0 is out of range [1, inf]"),
    (["synth", "sphere", "-o", "o", "--image-size", "4"], "--image-size 4 is out of range [8, 16384] (or 0)"),
    (["atlas", "m.ply", "-o", "o", "--resolution", "4"], "--resolution 4 is out of range [8, 16384]"),
    (["fit", "cap", "--mesh", "m", "-o", "o", "--rel-tol", "nan"], "--rel-tol nan is out of range [0.0, 1.0]"),
    (["fit", "cap", "--mesh", "m", "-o", "o", "--texel-pixels", "inf"], "--texel-pixels inf is out of range"),
    (["mesh", "-o", "o", "--faces", "many"], "--faces 'many' is not an integer"),
    (["preview", "cap", "--thumb", "0"], "--thumb 0 is out of range [8, 4096]"),
])
def test_named_out_of_range_values_fail_at_parse_time_in_one_line(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing is read or written: the parser refuses first
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and "Fix: give " in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_values_in_range_parse(tmp_path):
    fit = _subparser("fit")
    for size in ("0", "8", "256", "16384"):
        assert fit.parse_args(["cap", "--mesh", "m", "-o", "o", "--texture-size", size]).texture_size == int(size)
    assert _subparser("eval").parse_args(["m", "c", "--holdout-every", "0"]).holdout_every == 0


def test_argparse_errors_are_one_line_too(capsys):
    with pytest.raises(SystemExit) as e:
        main(["fit", "cap", "--mesh", "m", "-o", "o", "--optimizer", "newton"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "invalid choice: 'newton'" in err[0]
    assert "Fix: see 'texstream fit --help'" in err[0]


def test_a_config_file_value_out_of_range_fails_before_work():
    """Values from `texstream run --config` are checked by the same ranges (check_config at the stage start)."""
    cfg = RunConfig()
    cfg.atlas = dataclasses.replace(cfg.atlas, resolution=7)
    with pytest.raises(ConfigError, match=r"--atlas\.resolution 7 is out of range \[8, 16384\]"):
        check_config(cfg)
