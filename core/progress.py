"""Progress of the long stages: bars over photos and iterations, and short phase lines.

Stages call :func:`bar` around their loops over photos (or iterations) and :func:`phase` around a
step with no loop to count (Poisson, xatlas, COLMAP's matching). What reaches the user depends on
the caller, not on the stage:

- bars (tqdm, on stderr) show only on a terminal, and not at all inside ``reporting(bars=False)``;
- phase lines go to the ``log`` that :func:`reporting` installs (``texstream run`` passes its own
  printer); without one, a stage called from a script or a test prints nothing.

Example:
    with reporting(print):
        for photo in bar(photos, "ingest", unit="photo"):
            ...
        with phase("mesh", "screened Poisson (depth 8)"):
            ...
"""

from __future__ import annotations

import contextlib
import contextvars
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

_LOG: contextvars.ContextVar[Callable[[str], None] | None] = contextvars.ContextVar("texstream_log", default=None)
_BARS: contextvars.ContextVar[bool] = contextvars.ContextVar("texstream_bars", default=True)
SLOW_S = 1.0  # a phase this long or longer also prints its time when it ends


@contextlib.contextmanager
def reporting(log: Callable[[str], None] | None = None, bars: bool = True) -> Iterator[None]:
    """Within the block, phase lines go to ``log`` and bars show (on a terminal) when ``bars``."""
    t_log, t_bars = _LOG.set(log), _BARS.set(bars)
    try:
        yield
    finally:
        _LOG.reset(t_log)
        _BARS.reset(t_bars)


def bars_enabled() -> bool:
    return _BARS.get()


def say(stage: str, message: str) -> None:
    """One phase line, ``  stage: message``, to the installed log (nothing without one)."""
    log = _LOG.get()
    if log is not None:
        log(f"  {stage}: {message}")


@contextlib.contextmanager
def phase(stage: str, message: str) -> Iterator[None]:
    """A phase line when the step starts and, when it took a second or more, one with its time."""
    say(stage, message)
    t0 = time.perf_counter()
    yield
    dt = time.perf_counter() - t0
    if dt >= SLOW_S:
        say(stage, f"{message.split(' (')[0]}: {dt:.1f} s")


def bar(iterable: Iterable | None = None, desc: str = "", total: int | None = None, unit: str = "photo",
        enabled: bool = True, file: Any = None) -> Any:
    """A tqdm bar over ``iterable`` (or a manual one with ``total``), cleared when done. Disabled when
    ``enabled`` is false, inside ``reporting(bars=False)``, or when the output is not a terminal."""
    on = enabled and _BARS.get()
    try:
        from tqdm import tqdm
    except ImportError:  # tqdm is a dependency; progress is optional all the same
        return _NoBar(iterable)
    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=False, disable=None if on else True, file=file,
                dynamic_ncols=True)


class _NoBar:
    def __init__(self, iterable):
        self.iterable = iterable
        self.n = 0

    def __iter__(self):
        return iter(self.iterable)

    def update(self, n: int = 1) -> None:
        self.n += n

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass
