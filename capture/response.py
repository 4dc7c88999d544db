"""A capture's photo response: how the stored code values of its 8- and 16-bit photos map to linear radiance
(issue 39). Exported JPEGs are tone-mapped, so decoding them as sRGB leaves radiance bent by the camera's curve;
a response recovered from a colour checker in view (:mod:`texstream.calib.colour_chart`) undoes it.

``capture.json``'s top-level ``"response"`` holds it (absent: sRGB, as every reader decoded before)::

    "response": {"kind": "colour_chart", "knots": [0.02, ..., 1.0], "log_radiance": [-7.1, ..., 0.0],
                 "source": "colour chart in 5 of 12 photos"}

``knots`` are code values in (0, 1], increasing; ``log_radiance`` the natural log of the radiance at each,
increasing (a camera's response is monotone); the curve is linear in log code between knots and continues the
first segment's power law below the first knot (code 0 is radiance 0). Float photos (EXR, HDR) hold radiance
already: the response never applies to them. numpy only.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from pathlib import Path

import numpy as np

from texstream.core.errors import InputError

RESPONSE_KEY = "response"
"""the capture.json field"""
RESPONSE_KINDS = ("colour_chart",)
_RESPONSE_FIX = ("write knots in (0, 1] and log_radiance, both increasing and finite, as `texstream chart` does, "
                 "or remove the 'response' field to decode the photos as sRGB")


def linearise_codes(knots, log_radiance, codes) -> np.ndarray:
    """Linear radiance of code values in [0, 1] (any shape) through a curve linear in log code between
    ``knots`` (their log radiance ``log_radiance``); below the first knot the first segment's power law continues
    down to 0."""
    c = np.clip(np.asarray(codes, np.float64), 0.0, 1.0)
    lk, lr = np.log(np.asarray(knots, np.float64)), np.asarray(log_radiance, np.float64)
    x = np.log(np.maximum(c, 1e-12))
    slope = (lr[1] - lr[0]) / (lk[1] - lk[0])
    log_r = np.where(x < lk[0], lr[0] + slope * (x - lk[0]), np.interp(x, lk, lr))
    return np.where(c > 0, np.exp(log_r), 0.0)


@functools.lru_cache(maxsize=8)
def _lut(knots: tuple, log_radiance: tuple, levels: int) -> np.ndarray:
    table = linearise_codes(knots, log_radiance, np.arange(levels, dtype=np.float64) / (levels - 1))
    table = table.astype(np.float32)
    table.flags.writeable = False
    return table


@dataclasses.dataclass(frozen=True)
class PhotoResponse:
    """The inverse response of a capture's integer photos (module doc). Immutable and made of tuples, so the
    decoding pool's worker processes receive it by pickling (fit/stream/decode_pool.py)."""

    knots: tuple
    log_radiance: tuple
    kind: str = "colour_chart"
    source: str = ""

    def linearise(self, codes) -> np.ndarray:
        return linearise_codes(self.knots, self.log_radiance, codes)

    def lut(self, levels: int) -> np.ndarray:
        """Radiance of each of ``levels`` integer codes (256 for 8-bit files, 65536 for 16-bit), float32."""
        return _lut(self.knots, self.log_radiance, int(levels))

    @property
    def key(self) -> str:
        """A short digest of the curve (not its source): names it in the decoded photos' cache keys."""
        return hashlib.sha256(repr((self.knots, self.log_radiance)).encode()).hexdigest()[:16]

    def to_json(self) -> dict:
        return {"kind": self.kind, "knots": list(self.knots), "log_radiance": list(self.log_radiance),
                "source": self.source}


def response_from_json(d, path: str | Path) -> PhotoResponse:
    """The response of a ``"response"`` field (or a ``texstream chart`` response.json), checked; ``path`` names
    the file in the one-line error.

    Raises:
        InputError: not an object, an unknown kind, knots or log_radiance missing, not finite, not increasing,
            of different lengths, fewer than 2, or knots outside (0, 1].
    """
    if not isinstance(d, dict):
        raise InputError(f"'response' is {type(d).__name__}, not an object", path, _RESPONSE_FIX)
    kind = d.get("kind", "colour_chart")
    if kind not in RESPONSE_KINDS:
        raise InputError(f"response kind {kind!r} is not one of {list(RESPONSE_KINDS)}", path, _RESPONSE_FIX)
    try:
        knots = np.asarray(d["knots"], np.float64)
        log_r = np.asarray(d["log_radiance"], np.float64)
    except KeyError as e:
        raise InputError(f"response lacks {e.args[0]!r}", path, _RESPONSE_FIX) from None
    except (TypeError, ValueError):
        raise InputError("response knots or log_radiance are not lists of numbers", path, _RESPONSE_FIX) from None
    problem = None
    if knots.ndim != 1 or log_r.shape != knots.shape or knots.size < 2:
        problem = f"response has {knots.size} knots and {log_r.size} log_radiance values (need 2+ of each, as many)"
    elif not (np.all(np.isfinite(knots)) and np.all(np.isfinite(log_r))):
        problem = "response holds a non-finite value"
    elif not (knots[0] > 0 and knots[-1] <= 1):
        problem = f"response knots span {knots[0]:g}..{knots[-1]:g}, not within (0, 1]"
    elif np.any(np.diff(knots) <= 0) or np.any(np.diff(log_r) <= 0):
        problem = "response knots or log_radiance are not increasing"
    if problem:
        raise InputError(problem, path, _RESPONSE_FIX)
    return PhotoResponse(tuple(float(v) for v in knots), tuple(float(v) for v in log_r), kind,
                         str(d.get("source", "")))
