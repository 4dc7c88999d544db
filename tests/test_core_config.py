"""The spine's config checks and TOML: ranges and choices fail with the option's CLI name."""

from __future__ import annotations

import dataclasses

import pytest

from texstream.core.config import check_config, config_to_dict, option
from texstream.core.errors import ConfigError
from texstream.core.toml import dumps, read_toml


@dataclasses.dataclass
class Inner:
    rate: float = option(0.5, "a fraction", min=0.0, max=1.0)
    kind: str = option("a", "a kind", choices=("a", "b"))
    path: str | None = option(None, "optional", choices=("x", "y"))


@dataclasses.dataclass
class Outer:
    steps: int = option(3, "how many", min=1)
    inner: Inner = option(default_factory=Inner, help="nested")


def test_defaults_pass_and_bad_values_name_the_option():
    check_config(Outer())
    with pytest.raises(ConfigError, match=r"--steps -3 is out of range \[1, inf\]"):
        check_config(Outer(steps=-3))
    with pytest.raises(ConfigError, match=r"--inner.rate 1.5 is out of range \[0.0, 1.0\]"):
        check_config(Outer(inner=Inner(rate=1.5)))
    with pytest.raises(ConfigError, match=r"--inner.kind 'c' is not one of"):
        check_config(Outer(inner=Inner(kind="c")))
    with pytest.raises(ConfigError, match="must be a number"):
        check_config(Outer(steps="3"))
    with pytest.raises(ConfigError, match="out of range"):
        check_config(Outer(inner=Inner(rate=float("nan"))))


def test_toml_round_trip(tmp_path):
    data = config_to_dict(Outer(steps=7, inner=Inner(rate=0.25, kind="b")))
    (tmp_path / "c.toml").write_text(dumps(data, header="a header"))
    back = read_toml(tmp_path / "c.toml")
    assert back == {"steps": 7, "inner": {"rate": 0.25, "kind": "b"}}  # None fields are left out
    (tmp_path / "bad.toml").write_text("steps = [")
    with pytest.raises(ConfigError, match="bad.toml"):
        read_toml(tmp_path / "bad.toml")


def test_fit_option_out_of_range_is_one_line_before_any_work(tmp_path, capsys):
    """`texstream fit ... --max-iterations -3` used to end in a Warp traceback."""
    from texstream.pipelines.cli import main

    rc = main(["fit", str(tmp_path / "no_capture"), "--mesh", str(tmp_path / "no_mesh"), "-o", str(tmp_path / "m"),
               "--max-iterations", "-3"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.splitlines() == [err] and "--max-iterations -3 is out of range" in err
    assert not (tmp_path / "m").exists()
