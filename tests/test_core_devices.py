"""``--device auto`` (core/devices.py): the first CUDA device Warp sees, else the CPU; named devices checked."""

from __future__ import annotations

import re

import pytest

from texstream.core import devices
from texstream.core.errors import ConfigError


def test_auto_is_the_first_cuda_device_when_warp_sees_one_else_the_cpu(monkeypatch):
    monkeypatch.setattr(devices, "cuda_device_count", lambda: 0)
    assert devices.resolve_device("auto") == devices.resolve_device(None) == "cpu"
    monkeypatch.setattr(devices, "cuda_device_count", lambda: 2)
    assert devices.resolve_device("auto") == devices.resolve_device(" AUTO ") == "cuda:0"
    assert devices.resolve_device("cuda") == "cuda:0" and devices.resolve_device("cuda:1") == "cuda:1"
    assert devices.resolve_device("cpu") == "cpu"


@pytest.mark.parametrize("name, words", [("cuda:2", "not available (Warp sees 2 CUDA"), ("gpu", "unknown"),
                                         ("cuda:x", "is not cuda:N")])
def test_a_device_this_machine_lacks_is_a_one_line_error_naming_the_fix(monkeypatch, name, words):
    monkeypatch.setattr(devices, "cuda_device_count", lambda: 2)
    with pytest.raises(ConfigError, match=re.escape(words)) as err:
        devices.resolve_device(name)
    assert err.value.fix and "\n" not in str(err.value)


def test_auto_on_this_machine_matches_what_warp_sees():
    """CI (no GPU) resolves to the CPU; the GPU machine to cuda:0."""
    import warp as wp

    expected = "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    assert devices.resolve_device("auto") == expected
    assert wp.get_device(expected) is not None  # a device Warp can open
