"""Calibration boards: parse a board spec, detect it in a photo with sub-pixel corners.

Board specs (the ``--board`` option of ``texstream calibrate``):

- ``chessboard:COLSxROWS[:SQUARE]``: a chessboard with COLS x ROWS *inner* corners (OpenCV's
  ``patternSize``), squares SQUARE units wide (default 1; the unit of the extrinsics).
- ``charuco:COLSxROWS:SQUARE:MARKER[:DICT]``: a ChArUco board of COLS x ROWS *squares*, square and
  marker side lengths in the same unit, ArUco dictionary name (default ``DICT_5X5_100``;
  any ``cv2.aruco.DICT_*`` name). ``charuco-legacy:`` selects OpenCV's pre-4.6 layout.

Detections are returned in OpenCV pixel coordinates (pixel centres at integers); the intrinsics
stage converts the principal point to the capture convention (+0.5, see conventions).
OpenCV is imported inside the functions.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from texstream.core.errors import ConfigError

_SPEC_HELP = "use chessboard:9x6[:SQUARE] or charuco:COLSxROWS:SQUARE:MARKER[:DICT_5X5_100]"


@dataclasses.dataclass(frozen=True)
class BoardSpec:
    """A parsed board spec (see the module doc)."""

    kind: str  # "chessboard" | "charuco"
    cols: int
    rows: int
    square: float = 1.0
    marker: float = 0.0
    dictionary: str = "DICT_5X5_100"
    legacy: bool = False

    def __str__(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square:g}"
        kind = "charuco-legacy" if self.legacy else "charuco"
        return f"{kind}:{self.cols}x{self.rows}:{self.square:g}:{self.marker:g}:{self.dictionary}"

    def charuco_board(self):
        """The ``cv2.aruco.CharucoBoard`` for a ChArUco spec."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, d)
        board.setLegacyPattern(self.legacy)
        return board

    def object_points(self) -> np.ndarray:
        """(N, 3) float32 board-frame corner positions (z = 0), in detection id order."""
        if self.kind == "chessboard":
            grid = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)
            return np.concatenate([grid * self.square, np.zeros((len(grid), 1))], 1).astype(np.float32)
        return np.asarray(self.charuco_board().getChessboardCorners(), dtype=np.float32).reshape(-1, 3)


def parse_board(spec: str) -> BoardSpec:
    """Parse a ``--board`` spec string; raises ConfigError with the accepted forms."""
    parts = spec.strip().split(":")
    kind = parts[0].lower()
    try:
        cols, rows = (int(x) for x in parts[1].lower().split("x"))
        if kind == "chessboard":
            if len(parts) > 3:
                raise ValueError
            square = float(parts[2]) if len(parts) > 2 else 1.0
            if cols < 2 or rows < 2 or square <= 0:
                raise ValueError
            return BoardSpec("chessboard", cols, rows, square)
        if kind in ("charuco", "charuco-legacy"):
            if len(parts) not in (4, 5):
                raise ValueError
            square, marker = float(parts[2]), float(parts[3])
            dictionary = parts[4].upper() if len(parts) > 4 else "DICT_5X5_100"
            if not dictionary.startswith("DICT_"):
                dictionary = "DICT_" + dictionary
            import cv2

            if not hasattr(cv2.aruco, dictionary):
                raise ConfigError(f"unknown ArUco dictionary {dictionary!r} in board spec {spec!r}",
                                  fix="use a cv2.aruco name such as DICT_4X4_50, DICT_5X5_100, DICT_6X6_250")
            if cols < 2 or rows < 2 or not (0 < marker < square):
                raise ValueError
            return BoardSpec("charuco", cols, rows, square, marker, dictionary, legacy=kind == "charuco-legacy")
    except (IndexError, ValueError):
        pass
    raise ConfigError(f"cannot parse board spec {spec!r}", fix=_SPEC_HELP)


def load_gray8(path: str | Path) -> np.ndarray | None:
    """Read a photo as 8-bit grayscale for detection (16-bit / float scaled to 8 bits); None if unreadable."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if img is None:
        return None
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        f = np.nan_to_num(img.astype(np.float32))
        hi = float(np.percentile(f, 99.5)) or 1.0
        img = np.clip(f / hi * 255.0, 0, 255).astype(np.uint8)
    return img


def detect_board(gray: np.ndarray, board: BoardSpec, min_corners: int = 6) -> tuple[np.ndarray, np.ndarray] | None:
    """Find a board's corners with sub-pixel refinement.

    Args:
        gray: (H, W) uint8 image.
        board: the board.
        min_corners: fewest ChArUco corners accepted (a chessboard is all-or-nothing).

    Returns:
        (image_points (N, 2) float32 in OpenCV pixels, object_points (N, 3) float32) or None.
    """
    import cv2

    try:
        return _detect(gray, board, min_corners)
    except cv2.error:
        # Tiny or degenerate images make OpenCV's detectors assert; that is "no board here".
        return None


def _detect(gray: np.ndarray, board: BoardSpec, min_corners: int) -> tuple[np.ndarray, np.ndarray] | None:
    import cv2

    if board.kind == "chessboard":
        size = (board.cols, board.rows)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, size, flags=flags)
        if not found:
            # The sector-based detector copes with blur and strong perspective the classic one misses.
            found, corners = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_EXHAUSTIVE)
            if not found:
                return None
        else:
            # Window 11x11 (OpenCV's sample): a fifth of a typical square in a 640x480 photo.
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
            corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
        return corners.reshape(-1, 2).astype(np.float32), board.object_points()
    cb = board.charuco_board()
    det = cv2.aruco.CharucoDetector(cb)
    params = det.getDetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det.setDetectorParameters(params)
    ch_corners, ch_ids, _, _ = det.detectBoard(gray)
    if ch_ids is None or len(ch_ids) < min_corners:
        return None
    obj, img = cb.matchImagePoints(ch_corners, ch_ids)
    if obj is None or len(obj) < min_corners:
        return None
    # Collinear corners constrain nothing but a line: reject them (OpenCV's own check).
    if cb.checkCharucoCornersCollinear(ch_ids):
        return None
    return img.reshape(-1, 2).astype(np.float32), obj.reshape(-1, 3).astype(np.float32)
