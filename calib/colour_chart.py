"""A ColorChecker in view: find it (OpenCV contrib's ``mcc`` module) and recover the photos' response from its
patches (issue 39), so that exported, tone-mapped JPEGs become linear radiance again.

Photos exported from raw go through a tone curve: the fit's reflectance model needs radiance linear in the light.
The chart's 24 patches have known reflectances (:data:`COLORCHECKER_SRGB8`, the X-Rite ColorChecker Classic's
published sRGB values after 2014, linearised), so each photo that sees the chart gives 24 x 3 pairs (code value,
known reflectance times that photo's unknown light and white balance). :func:`fit_response` solves for one
monotone inverse response shared by the channels and photos (the camera's tone curve) and a gain per photo and
channel (its exposure, flash distance and white balance), in the log domain as Debevec and Malik do (SIGGRAPH
1997), with the curve piecewise linear in log radiance over knots in code value.

OpenCV (``cv2``) is imported inside the functions that need it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from texstream.capture.imageio import read_image
from texstream.capture.response import PhotoResponse, linearise_codes
from texstream.core.errors import InputError
from texstream.core.outputs import atomic_output_dir, write_json_atomic

from .files import list_images

COLORCHECKER_SRGB8 = np.array([
    [115, 82, 68], [194, 150, 130], [98, 122, 157], [87, 108, 67], [133, 128, 177], [103, 189, 170],
    [214, 126, 44], [80, 91, 166], [193, 90, 99], [94, 60, 108], [157, 188, 64], [224, 163, 46],
    [56, 61, 150], [70, 148, 73], [175, 54, 60], [231, 199, 31], [187, 86, 149], [8, 133, 161],
    [243, 243, 242], [200, 200, 200], [160, 160, 160], [122, 122, 121], [85, 85, 85], [52, 52, 52]], np.float64)
"""ColorChecker Classic patches in row-major order from dark skin to black, sRGB 8-bit (X-Rite, after 2014); the
same order as ``cv2.mcc``'s MCC24 chart"""

RESPONSE_KNOTS = np.unique(np.concatenate([np.geomspace(0.02, 0.5, 10), np.linspace(0.5, 1.0, 8)]))
"""code values where the inverse response's log radiance is a parameter, linear in log code between them (a power
law, as sRGB's encoding nearly is, is then exact): spaced by ratio in the shadows, where log radiance bends with
log code, and evenly towards white, where tone curves put their shoulder"""
MAX_DETECTION_COST = 0.03
"""``cv2.mcc``'s cost above which a sighting is a misread, not read: charts partly hidden by the object came out at
0.04-0.06 with their patches out of order, whole ones below 0.015 (the synthetic flash capture)"""
OUTLIER_LOG = 0.05
"""a patch value further than this from the fitted curve (in log radiance, ~5%; and 4 median deviations) is left
out: a patch the object hides in that photo, or a chart misread; 8-bit codes of usable patches miss by ~1%"""
USABLE_CODES = (0.03, 0.97)
"""patch code values used for the response: darker ones are mostly noise and quantisation, brighter ones may
be clipped"""


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def chart_reflectance() -> np.ndarray:
    """(24, 3) linear reflectance of the chart's patches (sRGB primaries, D65 white)."""
    return srgb_to_linear(COLORCHECKER_SRGB8 / 255.0)


@dataclasses.dataclass
class ChartSighting:
    """One chart found in one photo: its corners in the photo's pixels, its patches' mean code values (24, 3) in
    [0, 1] (RGB), their standard deviations, the detector's cost (lower is a better match) and the patches'
    centres (24, 2) in pixels, in patch order (the chart's pose: :mod:`.chart_flash`)."""

    corners: np.ndarray
    patches: np.ndarray
    patch_std: np.ndarray
    cost: float
    patch_centres: np.ndarray | None = None

    def to_json(self) -> dict:
        return {"corners": self.corners.tolist(), "patches": self.patches.tolist(),
                "patch_std": self.patch_std.tolist(), "cost": self.cost,
                "patch_centres": None if self.patch_centres is None else self.patch_centres.tolist()}

    @staticmethod
    def from_json(d: dict) -> "ChartSighting":
        centres = d.get("patch_centres")
        return ChartSighting(np.asarray(d["corners"], np.float64), np.asarray(d["patches"], np.float64),
                             np.asarray(d["patch_std"], np.float64), float(d["cost"]),
                             None if centres is None else np.asarray(centres, np.float64))


def find_chart(rgb_codes: np.ndarray) -> ChartSighting | None:
    """The ColorChecker Classic in a photo (H, W, 3 RGB code values in [0, 1], as stored, not linearised), or None.
    ``cv2.mcc`` finds the chart's patch grid by its squares and checks the colours' order, so a chart turned
    upside down reads in the same patch order."""
    import cv2

    bgr8 = np.ascontiguousarray(np.clip(np.round(rgb_codes[..., ::-1] * 255.0), 0, 255).astype(np.uint8))
    detector = cv2.mcc.CCheckerDetector_create()
    detector.setColorChartType(cv2.mcc.MCC24)
    if not detector.process(bgr8, 1):
        return None
    best = detector.getBestColorChecker()
    if best.getCost() > MAX_DETECTION_COST:
        return None
    stats = np.asarray(best.getChartsRGB(), np.float64).reshape(24, 3, -1)  # per patch and channel: count, mean, std, ...
    corners = np.asarray(best.getBox(), np.float64)
    h, w = rgb_codes.shape[:2]
    if np.any(corners < -0.5) or np.any(corners > [w - 0.5, h - 0.5]):
        return None  # a chart cut by the frame: the detector extrapolates the patches it cannot see
    centres = np.asarray(best.getColorCharts(), np.float64).reshape(24, 4, 2).mean(axis=1)
    return ChartSighting(corners, stats[:, :, 1] / 255.0, stats[:, :, 2] / 255.0, float(best.getCost()), centres)


@dataclasses.dataclass
class Response:
    """The photos' inverse response: code value (in [0, 1]) to linear radiance, shared by the channels, as log
    radiance at the :data:`RESPONSE_KNOTS` (linear in log code between them); 1.0 maps to radiance 1. ``gains`` (photos, 3):
    each fitted photo's light times white balance, in the response's units; ``residual_percent``: the RMS relative
    error of the linearised patches against reflectance x gain (over the ``patches_used``; ``patches_dropped``: the
    outliers left out)."""

    knots: np.ndarray
    log_radiance: np.ndarray
    gains: np.ndarray
    residual_percent: float
    patches_used: int
    patches_dropped: int = 0

    def linearise(self, codes: np.ndarray) -> np.ndarray:
        """Linear radiance of code values (any shape), through the curve; below the first knot the first segment's
        power law continues down to 0 (:func:`texstream.capture.response.linearise_codes`, what the readers of a
        capture with this response use)."""
        return linearise_codes(self.knots, self.log_radiance, codes)

    def photo_response(self, source: str) -> PhotoResponse:
        """The curve as a capture records it (capture.json's ``response``), ``source`` saying where it came from."""
        return PhotoResponse(tuple(float(v) for v in self.knots), tuple(float(v) for v in self.log_radiance),
                             "colour_chart", source)

    def to_json(self) -> dict:
        return {"knots": self.knots.tolist(), "log_radiance": self.log_radiance.tolist(),
                "gains": self.gains.tolist(), "residual_percent": self.residual_percent,
                "patches_used": self.patches_used, "patches_dropped": self.patches_dropped}


def fit_response(sightings: list[ChartSighting], smoothness: float = 1e-3) -> Response:
    """The inverse response and per-photo gains that make every sighting's patches reflectance x gain.

    Least squares in the log domain: log g(v) - log k_(photo, channel) = log r_(patch, channel), g piecewise linear
    at the knots (its value at a patch's code interpolated between the two nearest knots), the curve's second
    differences damped by ``smoothness`` (knots between the patches' codes follow their neighbours), g(1) = 1 fixing
    the scale the gains absorb. Each photo's light may vary across the chart (a flash's 1 / r^2 and its angle: a
    chart a third of the flash's distance wide sees +-30%): a log-linear slope per photo along the chart's columns and
    rows, shared by the channels, takes it up, and the gains are the light at the chart's centre. A curve that comes out decreasing anywhere is an error: the patches disagree with
    any camera response (a wrong chart, or clipped photos)."""
    if not sightings:
        raise InputError("no photo shows a colour chart", fix="photograph a ColorChecker Classic beside the object, "
                                                             "or leave the response alone")
    knots, n_knots = RESPONSE_KNOTS, len(RESPONSE_KNOTS)
    log_knots = np.log(knots)
    refl = np.log(chart_reflectance())
    rows, cols, vals, rhs = [], [], [], []
    n_photos = len(sightings)
    gain_col = n_knots  # then one column per (photo, channel)
    grad_col = gain_col + 3 * n_photos  # then two per photo: its light's log slope across the chart's columns, rows
    r = 0
    for p, s in enumerate(sightings):
        for i in range(24):
            for ch in range(3):
                v = float(s.patches[i, ch])
                if not USABLE_CODES[0] <= v <= USABLE_CODES[1]:
                    continue
                k0 = int(np.clip(np.searchsorted(knots, v) - 1, 0, n_knots - 2))
                w = (np.log(v) - log_knots[k0]) / (log_knots[k0 + 1] - log_knots[k0])
                slope = grad_col + 2 * p
                rows += [r] * 5
                cols += [k0, k0 + 1, gain_col + 3 * p + ch, slope, slope + 1]
                vals += [1.0 - w, w, -1.0, -((i % 6) - 2.5) / 2.5, -((i // 6) - 1.5) / 1.5]
                rhs.append(refl[i, ch])
                r += 1
    used = r
    if used < 2 * n_knots:
        raise InputError(f"the colour chart's patches give {used} usable values, too few for a response",
                         fix="photograph the chart larger, exposed so its patches are neither black nor clipped")
    n_cols = grad_col + 2 * n_photos
    a = np.zeros((used + n_knots - 2 + 1, n_cols))
    a[rows, cols] = vals
    b = np.zeros(a.shape[0])
    b[:used] = rhs
    weight = np.sqrt(smoothness * used)
    for k in range(1, n_knots - 1):  # second differences of log g in log code, for unequal steps
        h0, h1 = log_knots[k] - log_knots[k - 1], log_knots[k + 1] - log_knots[k]
        a[used + k - 1, k - 1:k + 2] = weight * np.array([1.0 / h0, -(1.0 / h0 + 1.0 / h1), 1.0 / h1]) * h1
    a[-1, n_knots - 1] = 1e3  # g(1) = 1
    keep = np.ones(a.shape[0], bool)
    for _ in range(4):  # patches the object hides in a photo (or misread) are outliers: refit without them
        x, *_ = np.linalg.lstsq(a[keep], b[keep], rcond=None)
        resid = a[:used] @ x - b[:used]
        spread = 4.0 * 1.4826 * float(np.median(np.abs(resid[keep[:used]])))
        new = keep.copy()
        new[:used] = np.abs(resid) <= max(OUTLIER_LOG, spread)
        if np.array_equal(new, keep):
            break
        keep = new
    log_g, log_k = x[:n_knots], x[gain_col:grad_col].reshape(n_photos, 3)
    if np.any(np.diff(log_g) <= 0):
        raise InputError("the colour chart's patches do not follow one increasing camera response",
                         fix="check that the chart is a ColorChecker Classic (24 patches) and that its patches "
                             "are not clipped")
    kept = keep[:used]
    return Response(knots, log_g, np.exp(log_k), float(100.0 * np.sqrt(np.mean(np.expm1(resid[kept]) ** 2))),
                    int(kept.sum()), int(used - kept.sum()))


def response_from_photos(paths: list[Path], read_codes) -> tuple[Response | None, list[dict]]:
    """Find the chart in each photo (``read_codes(path)``: its stored code values in [0, 1]) and fit the response
    to those that show it. Returns (response or None when no photo shows the chart, per photo {"photo", "found",
    "cost"} and, where found, "sighting" (:meth:`ChartSighting.to_json`: corners, patches, patch centres))."""
    sightings, report = [], []
    for path in paths:
        s = find_chart(read_codes(path))
        report.append({"photo": str(path), "found": s is not None, "cost": None if s is None else s.cost,
                       **({"sighting": s.to_json()} if s is not None else {})})
        if s is not None:
            sightings.append(s)
    return (fit_response(sightings) if sightings else None), report


def read_codes(path) -> np.ndarray:
    """A photo's stored code values in [0, 1] (8- or 16-bit files as stored; no decoding to linear)."""
    return read_image(path, channels=3, linear=False)


def chart_response(photos: str | Path, out: str | Path) -> dict:
    """``texstream chart PHOTOS -o OUT``: the chart in each photo of the folder, the response fitted to them,
    OUT/response.json (the curve and per-photo gains) and OUT/chart_report.json (per photo: found, cost), written
    atomically. Returns the summary."""
    files = list_images(photos)
    response, report = response_from_photos(files, read_codes)
    if response is None:
        raise InputError(f"none of the {len(files)} photos shows a ColorChecker Classic", Path(photos),
                         "photograph the chart (24 patches) in view, unobstructed, at least ~150 pixels wide")
    found = [r for r in report if r["found"]]
    summary = {"photos": len(files), "charts_found": len(found), "residual_percent": response.residual_percent,
               "patches_used": response.patches_used,
               "gains": {r["photo"]: g.tolist() for r, g in zip(found, response.gains)}}
    with atomic_output_dir(out) as tmp:
        write_json_atomic(tmp / "response.json", {"kind": "colour_chart", **response.to_json()})
        write_json_atomic(tmp / "chart_report.json", {**summary, "per_photo": report})
    return summary
