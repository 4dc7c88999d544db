"""The colour chart's response on tone-mapped synthetic photos (calib/colour_chart.py, issue 39): the linearised
patch values against reflectance x gain, and the same for plain sRGB decoding (what ingest applies to 8-bit photos
without a response). The photos are tests/test_calib_colour_chart.py's (four 1080x720 8-bit photos of a grey wall
with the chart, a filmic tone curve, sensor noise).

    python benchmarks/colour_chart_accuracy.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_calib_colour_chart as scene  # noqa: E402

from texstream.calib.colour_chart import chart_reflectance, find_chart, fit_response, srgb_to_linear  # noqa: E402


def relative_errors(sightings, linearise, gains) -> np.ndarray:
    refl = chart_reflectance()
    out = []
    for k, s in enumerate(sightings):
        ok = (s.patches > 0.03) & (s.patches < 0.97)  # the response's usable codes
        out.append(np.abs(linearise(s.patches) / gains(k, s, ok) / refl - 1.0)[ok])
    return np.concatenate(out)


if __name__ == "__main__":
    rng = np.random.default_rng(1)
    sightings = [find_chart(scene._photo(k, rng)) for k in range(len(scene.LIGHTS))]
    response = fit_response(sightings)
    refl = chart_reflectance()

    def srgb_gain(k, s, ok):  # the best single gain per photo for sRGB decoding (its most favourable case)
        lin = srgb_to_linear(s.patches)
        return np.exp(np.mean(np.log(lin[ok] / np.broadcast_to(refl, lin.shape)[ok])))

    for name, e in (("chart response", relative_errors(sightings, response.linearise, lambda k, s, ok: response.gains[k])),
                    ("sRGB decoding", relative_errors(sightings, srgb_to_linear, srgb_gain))):
        p50, p95, p100 = np.percentile(e, [50, 95, 100])
        print(f"{name}: {e.size} patch values, median {100 * p50:.2f}%, 95th percentile {100 * p95:.2f}%, "
              f"worst {100 * p100:.2f}%")
