"""Which Warp modules a process loads, and under which hash (tests/test_fit_prewarm.py, in the test and in its
child process): a module loaded again with another hash was rehashed, an overload or a kernel added after its
build."""

from __future__ import annotations

from typing import Callable

import warp as wp


def record_loads(set_attribute: Callable = setattr) -> list:
    """(module name, hash, device, block size) of every module load from now on; ``set_attribute`` patches
    ``wp.Module.load`` (pytest's ``monkeypatch.setattr`` undoes it after the test)."""
    loads = []
    load = wp.Module.load

    def recorded(self, device, block_dim=None, *args, **kwargs):
        exec_ = load(self, device, block_dim, *args, **kwargs)
        loads.append((self.name, exec_.module_hash.hex(), str(exec_.device), exec_.block_dim))
        return exec_

    set_attribute(wp.Module, "load", recorded)
    return loads
