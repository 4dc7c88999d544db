"""Image and mask IO through OpenImageIO, with sRGB decoding to linear and back.

Conventions (see :mod:`texstream.capture.conventions`): arrays are (H, W, C) float32, row 0 at the
top, values linear. On read:

- 8-bit integer files (PNG, JPEG, TIFF) are sRGB-encoded and decoded to linear with the exact
  IEC 61966-2-1 curve, unless the file's colour space metadata says linear (then value / 255);
  a file tagged with a pure gamma (``g22_rec709``, ``Gamma2.2``) is decoded with that power.
- 16-bit integer files are linear: value / 65535.
- Float files (EXR, HDR, float TIFF) are returned as stored.

A capture with a photo response (``capture.json``'s ``response``, :mod:`texstream.capture.response`) decodes
its 8- and 16-bit photos through that curve instead (``read_image(..., response=)``, :class:`PhotoReader`); float
files hold radiance already and are returned as stored.

Alpha is returned as stored by the format: straight (unassociated) for PNG / TIFF, associated for
EXR. OpenImageIO would otherwise premultiply PNG colours on read, which would break the sRGB decode.

On write the format comes from the extension (:func:`write_image`); files are written to a
temporary name in the same folder and renamed into place, so a crash never leaves half a file.

OpenImageIO is imported inside the functions (``texstream.fit`` must not need it).
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from texstream.core.errors import ConfigError, InputError, StageError

# IEC 61966-2-1 piecewise sRGB transfer function constants.
_SRGB_DECODE_THRESHOLD = 0.04045
_SRGB_ENCODE_THRESHOLD = 0.0031308
_SRGB_SLOPE = 12.92
_SRGB_A = 0.055
_SRGB_GAMMA = 2.4

# extension -> (OpenImageIO format name, allowed bit depths, default bits)
_WRITE_FORMATS: dict[str, tuple[str, tuple[int, ...], int]] = {
    ".exr": ("openexr", (16, 32), 16),
    ".hdr": ("hdr", (32,), 32),
    ".png": ("png", (8, 16), 8),
    ".jpg": ("jpeg", (8,), 8),
    ".jpeg": ("jpeg", (8,), 8),
    ".tif": ("tiff", (8, 16, 32), 8),
    ".tiff": ("tiff", (8, 16, 32), 8),
}

_READ_FIX = "re-export or re-copy the image (PNG, JPEG, TIFF, EXR or HDR)"


# --------------------------------------------------------------------------- sRGB


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Exact IEC 61966-2-1 sRGB decoding.

    Args:
        x: sRGB-encoded values, nominally in [0, 1]; any shape. Float arrays keep their dtype
            (float64 stays float64); integer or other input is returned as float64.

    Returns:
        Linear values, same shape. Negative inputs follow the linear segment.
    """
    a = np.asarray(x)
    dtype = a.dtype if a.dtype in (np.float32, np.float64) else np.float64
    a64 = a.astype(np.float64, copy=False)
    with np.errstate(invalid="ignore"):
        hi = ((np.maximum(a64, _SRGB_DECODE_THRESHOLD) + _SRGB_A) / (1.0 + _SRGB_A)) ** _SRGB_GAMMA
    out = np.where(a64 <= _SRGB_DECODE_THRESHOLD, a64 / _SRGB_SLOPE, hi)
    return out.astype(dtype, copy=False)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Exact IEC 61966-2-1 sRGB encoding (inverse of :func:`srgb_to_linear`).

    Args:
        x: linear values; any shape. Values above 1 follow the power segment (clip before
            quantising). Float arrays keep their dtype; other input is returned as float64.

    Returns:
        sRGB-encoded values, same shape.
    """
    a = np.asarray(x)
    dtype = a.dtype if a.dtype in (np.float32, np.float64) else np.float64
    a64 = a.astype(np.float64, copy=False)
    hi = (1.0 + _SRGB_A) * np.maximum(a64, _SRGB_ENCODE_THRESHOLD) ** (1.0 / _SRGB_GAMMA) - _SRGB_A
    out = np.where(a64 <= _SRGB_ENCODE_THRESHOLD, a64 * _SRGB_SLOPE, hi)
    return out.astype(dtype, copy=False)


# 8-bit decode table: code -> linear, computed once in float64.
_SRGB8_LUT = srgb_to_linear(np.arange(256, dtype=np.float64) / 255.0)


# --------------------------------------------------------------------------- reading


def _open(path: Path):
    """Open an image for reading with straight alpha; InputError naming the file on failure."""
    import OpenImageIO as oiio

    if not path.exists():
        raise InputError("image not found", path, "check the path (file_path / mask_path in capture.json)")
    if path.is_dir():
        raise InputError("is a folder, not an image", path, "give an image file")
    if path.stat().st_size == 0:
        raise InputError("image file is empty (0 bytes)", path, _READ_FIX)
    cfg = oiio.ImageSpec()
    cfg.attribute("oiio:UnassociatedAlpha", 1)  # raw stored values, no premultiplication
    inp = oiio.ImageInput.open(str(path), cfg)
    if inp is None:
        msg = oiio.geterror().strip().splitlines()
        raise InputError(f"cannot read image ({msg[0] if msg else 'unknown format'})", path, _READ_FIX)
    spec = inp.spec()
    if spec.width <= 0 or spec.height <= 0 or spec.nchannels <= 0:
        inp.close()
        raise InputError(f"image has zero size ({spec.width}x{spec.height}x{spec.nchannels})", path,
                         _READ_FIX)
    return inp


def _size_error(spec, size: tuple[int, int], path: Path, kind: str) -> InputError:
    """The one-line error for an image whose header size is not the expected (H, W)."""
    if kind == "mask":
        return InputError(f"mask is {spec.width}x{spec.height} but its photo is "
                          f"{int(size[1])}x{int(size[0])}", path, "make the mask the same size as its photo")
    return InputError(f"image is {spec.width}x{spec.height} but {int(size[1])}x{int(size[0])} is expected "
                      "(its camera's size)", path,
                      "fix the frame's w/h in capture.json or re-export the photo")


def _read_raw(path: Path, rows: tuple[int, int] | None = None, size: tuple[int, int] | None = None,
              kind: str = "image") -> tuple[np.ndarray, object]:
    """Stored pixel values (H, W, C) in the file's own integer or float type, plus the spec.

    ``rows`` (y0, y1): only those rows, (y1 - y0, W, C) (scanline files decode just the blocks holding
    them; tiled files, data windows not at the origin and volumes are read whole and cut).
    ``size`` (H, W): the size the caller expects, checked against the header before any pixel is
    decoded (InputError naming the file; ``kind`` "mask" words it for a mask)."""
    import OpenImageIO as oiio

    inp = _open(path)
    try:
        spec = inp.spec()
        if size is not None and (spec.height, spec.width) != tuple(int(v) for v in size[:2]):
            raise _size_error(spec, size, path, kind)
        basetype = spec.format.basetype
        if basetype in (oiio.UINT8, oiio.INT8):
            fmt = "uint8"
        elif basetype in (oiio.UINT16, oiio.INT16):
            fmt = "uint16"
        else:
            fmt = "float"
        if inp.format_name() == "png" and not _png_complete(path):
            raise InputError("PNG file is truncated (it has no end chunk)", path, _READ_FIX)
        if rows is not None and not (0 <= rows[0] < rows[1] <= spec.height):
            raise InputError(f"rows {rows[0]}..{rows[1]} lie outside the image's {spec.height}", path,
                             "report this with the command that made it")
        whole = rows is None or spec.tile_width > 0 or spec.x != 0 or spec.y != 0 or spec.depth > 1
        if whole:
            px = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        else:
            px = inp.read_scanlines(0, 0, int(rows[0]), int(rows[1]), 0, 0, spec.nchannels, fmt)
        if px is None or inp.has_error:
            msg = inp.geterror().strip().splitlines()
            raise InputError(f"image is corrupt or truncated ({msg[0] if msg else 'read failed'})", path,
                             _READ_FIX)
        px = np.asarray(px)
        if px.ndim == 2:
            px = px[:, :, None]
        elif px.ndim == 4:  # volume images: (depth, H, W, C); take the first slice
            px = px[0]
        if whole and rows is not None:
            px = px[rows[0]:rows[1]]
        if _is_cmyk(spec):
            px = _cmyk_to_rgb(px)
        return px, spec
    finally:
        inp.close()
        oiio.geterror()  # clear the global error buffer so nothing is reported at exit


def _png_complete(path: Path) -> bool:
    """Whether a PNG file holds its end chunk (IEND) near its end: a truncated PNG does not, and decoding one
    makes libpng print its error on stderr besides the one-line error."""
    with open(path, "rb") as fh:
        fh.seek(max(0, path.stat().st_size - 4096))
        return b"IEND\xaeB`\x82" in fh.read()


def _is_cmyk(spec) -> bool:
    """A TIFF of inks (PhotometricInterpretation 5, separated) with C, M, Y, K first: OpenImageIO returns its
    four ink channels as they are (labelled RGBA), where a CMYK JPEG comes back converted to RGB."""
    return spec.nchannels >= 4 and spec.getattribute("tiff:PhotometricInterpretation") == 5


def _cmyk_to_rgb(px: np.ndarray) -> np.ndarray:
    """Stored ink amounts (0 = no ink) -> RGB codes as OpenImageIO converts CMYK JPEGs: R = (1 - C)(1 - K);
    channels after K (alpha) kept."""
    full = 1.0 if px.dtype.kind == "f" else float(np.iinfo(px.dtype).max)
    ink = px[..., :4].astype(np.float64) / full
    rgb = (1.0 - ink[..., :3]) * (1.0 - ink[..., 3:4]) * full
    rgb = rgb.astype(px.dtype) if px.dtype.kind == "f" else np.round(rgb).astype(px.dtype)
    return np.concatenate([rgb, px[..., 4:]], axis=-1)


def _gamma_from_colorspace(name: str | None) -> float | None:
    """1.0 for linear, a power for pure-gamma names, None for sRGB / unknown (treated as sRGB)."""
    if not name:
        return None
    n = name.lower()
    if n.startswith("lin") or n in ("scene_linear", "raw", "acescg", "aces2065-1"):
        return 1.0
    m = re.match(r"^(?:g|gamma)(\d)\.?(\d+)", n)
    if m:
        return float(f"{m.group(1)}.{m.group(2)}")
    return None


def _to_linear(px: np.ndarray, spec, path: Path, linear: bool, first_row: int = 0, response=None) -> np.ndarray:
    """Stored values -> float32, decoding 8-bit sRGB when ``linear`` (``first_row``: the image row of
    ``px``'s first, for the NaN message); integer codes through ``response`` (a PhotoResponse) when given."""
    if linear and response is not None and px.dtype in (np.uint8, np.uint16):
        return response.lut(256 if px.dtype == np.uint8 else 65536)[px]
    if px.dtype == np.uint8:
        gamma = _gamma_from_colorspace(spec.getattribute("oiio:ColorSpace"))
        if not linear or gamma == 1.0:
            return px.astype(np.float32) / np.float32(255.0)
        if gamma is None:
            return _SRGB8_LUT[px].astype(np.float32)
        lut = (np.arange(256, dtype=np.float64) / 255.0) ** gamma
        return lut[px].astype(np.float32)
    if px.dtype == np.uint16:
        return (px.astype(np.float64) / 65535.0).astype(np.float32)
    out = px.astype(np.float32, copy=False)
    bad = ~np.isfinite(out)
    if bad.any():
        n = int(bad.sum())
        y, x = np.argwhere(bad)[0][:2]
        raise InputError(f"image holds {n} NaN/Inf value(s), first at pixel (x={x}, y={y + first_row})", path,
                         "re-export the image without NaN/Inf (e.g. clamp in the renderer or compositor)")
    return out


def _split_alpha(px: np.ndarray, spec) -> tuple[np.ndarray, np.ndarray | None]:
    c = px.shape[2]
    a = spec.alpha_channel
    if a < 0 and c in (2, 4):  # grey+alpha or RGBA without an explicit alpha tag
        a = c - 1
    if 0 <= a < c:
        colour = np.delete(px, a, axis=2)
        return colour, px[:, :, a]
    return px, None


def read_image(path: str | os.PathLike, *, channels: int = 3, linear: bool = True,
               rows: tuple[int, int] | None = None, size: tuple[int, int] | None = None,
               response=None) -> np.ndarray:
    """Read an image as linear float32.

    Args:
        path: PNG, JPEG, TIFF (8/16-bit or float), EXR or HDR file.
        channels: 3 -> RGB (grey replicated, alpha dropped); 4 -> RGBA (alpha 1 when the file has
            none); 1 -> one channel (grey as is; RGB -> Rec. 709 luminance of the linear values).
        linear: decode 8-bit sRGB to linear (True) or return code / 255 (False).
        rows: (y0, y1) to read only those rows (a photo cropped to the object: an EXR decodes only
            the blocks that hold them); NaN/Inf are then checked in those rows only.
        size: the expected (H, W), checked against the header before decoding.
        response: the capture's photo response (:class:`texstream.capture.response.PhotoResponse`): with
            ``linear``, 8- and 16-bit colour decoded through it instead of sRGB or value / 65535 (whatever the
            file's colour space tag says: the response was measured on these codes); None: the rules above.

    Returns:
        (H, W, channels) float32 ((y1 - y0, W, channels) with ``rows``); linear radiance (see the
        module doc for the per-type rules).

    Raises:
        InputError: missing, empty, unreadable, corrupt or truncated file, zero size, NaN/Inf, a size
            other than ``size``.
    """
    if channels not in (1, 3, 4):
        raise ConfigError(f"channels must be 1, 3 or 4, got {channels}")
    path = Path(path)
    px, spec = _read_raw(path, rows, size)
    colour, alpha = _split_alpha(px, spec)
    if colour.shape[2] == 0:  # alpha-only image: treat the alpha as grey
        colour, alpha = alpha[:, :, None], None
    colour = _to_linear(colour, spec, path, linear, rows[0] if rows else 0, response)
    if alpha is not None:  # alpha is coverage, never sRGB-encoded
        alpha = _to_linear(alpha[:, :, None], spec, path, False)[:, :, 0]
    if channels == 1:
        if colour.shape[2] == 1:
            out = colour
        else:
            w = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
            out = (colour[:, :, :3] @ w)[:, :, None]
        return np.ascontiguousarray(out, dtype=np.float32)
    if colour.shape[2] == 1:
        colour = np.repeat(colour, 3, axis=2)
    elif colour.shape[2] == 2:  # unusual 2-channel colour: pad with zeros
        colour = np.concatenate([colour, np.zeros_like(colour[:, :, :1])], axis=2)
    colour = colour[:, :, :3]
    if channels == 4:
        a = np.ones(colour.shape[:2], np.float32) if alpha is None else alpha
        colour = np.concatenate([colour, a[:, :, None]], axis=2)
    return np.ascontiguousarray(colour, dtype=np.float32)


class PhotoReader:
    """``read_image`` of a capture's photos through its response, as the fit's photo files call a reader:
    (path, rows, size) -> (H, W, 3) linear float32. A module-level class so the decoding pool's worker
    processes receive it (fit/stream/decode_pool.py)."""

    def __init__(self, response):
        self.response = response
        self.cache_key = f"response-{response.key}"
        """names the curve in the decoded photos' cache key (fit/stream/photo_stream.PhotoCache)"""

    def __call__(self, path, rows=None, size=None, channels: int = 3) -> np.ndarray:
        return read_image(path, channels=channels, rows=rows, size=size, response=self.response)


def photo_reader(response):
    """The reader of a capture's photos: :func:`read_image` (sRGB) without a response, else a
    :class:`PhotoReader`."""
    return read_image if response is None else PhotoReader(response)


def read_alpha(path: str | os.PathLike) -> np.ndarray | None:
    """The alpha channel of an image as (H, W) float32 in [0, 1], or None when it has none."""
    path = Path(path)
    px, spec = _read_raw(path)
    _, alpha = _split_alpha(px, spec)
    if alpha is None:
        return None
    return _to_linear(alpha[:, :, None], spec, path, False)[:, :, 0]


def read_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None,
              rows: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask: a pixel is object where any colour channel is nonzero (nerfstudio's rule).

    A mask file holding only alpha (grey+alpha or RGBA with black colour) uses its alpha.

    Args:
        path: mask image (any readable format).
        shape: expected (H, W) (the photo's size); a mismatch is an InputError.
        rows: (y0, y1) to read only those rows.

    Returns:
        (H, W) bool, True = object ((y1 - y0, W) with ``rows``).
    """
    path = Path(path)
    px, spec = _read_raw(path, rows, shape, kind="mask")
    colour, alpha = _split_alpha(px, spec)
    if colour.shape[2] == 0 or (alpha is not None and not colour.any()):
        colour = alpha[:, :, None]
    if colour.dtype.kind == "f":
        colour = _to_linear(colour, spec, path, False)
    return np.any(colour != 0, axis=2)


def image_size(path: str | os.PathLike) -> tuple[int, int, int]:
    """(width, height, channels) from the file header, without reading the pixels."""
    import OpenImageIO as oiio

    path = Path(path)
    inp = _open(path)
    try:
        s = inp.spec()
        return int(s.width), int(s.height), int(s.nchannels)
    finally:
        inp.close()
        oiio.geterror()


# --------------------------------------------------------------------------- writing


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _quantise(x: np.ndarray, maxval: int, dtype) -> np.ndarray:
    """Clip to [0, 1], scale and round to nearest (half up) -> integer dtype."""
    return np.floor(np.clip(x, 0.0, 1.0) * maxval + 0.5).astype(dtype)


def _refuse_nonfinite(a: np.ndarray, path: Path, integer: bool) -> None:
    """No NaN or Inf reaches a file: a float format would store it for every reader to trip on, an integer
    one cannot store NaN (Inf clips to the format's range, as any bright value does). The error names the
    file and the first bad pixel, so the stage that made it can be found."""
    bad = np.isnan(a) if integer else ~np.isfinite(a)
    if not bad.any():
        return
    y, x, ch = (int(i) for i in np.argwhere(bad)[0])
    n = int(bad.any(axis=2).sum())
    raise StageError(f"image holds {n} pixel(s) with {'NaN' if integer else 'NaN or Inf'} (first: x={x}, y={y}, "
                     f"channel {ch} is {a[y, x, ch]}); nothing was written", path,
                     "report this with the command that made it; --debug shows where it came from")


def write_image(path: str | os.PathLike, img: np.ndarray, *, bits: int | None = None,
                metadata: dict | None = None) -> Path:
    """Write a linear image; the format comes from the extension.

    ========== =============== ===========================================================
    extension  bits (default)  stored as
    ========== =============== ===========================================================
    .exr       16 (16, 32)     half (16) or float32 (32), linear
    .hdr       32              RGBE, linear (RGB only: grey is replicated, alpha dropped)
    .png       8 (8, 16)       8: sRGB-encoded; 16: linear, tagged linear
    .jpg       8               sRGB-encoded, quality 95 (alpha dropped)
    .tif       8 (8, 16, 32)   8: sRGB-encoded; 16: linear; 32: float, linear
    ========== =============== ===========================================================

    Integer formats clip to [0, 1] and round to the nearest code. A uint8 array written with 8
    bits (or uint16 with 16 bits) is taken as already-encoded codes and stored unchanged. Alpha
    (the 4th channel, or the 2nd of a 2-channel image) is never sRGB-encoded. The file is written
    to a temporary name in the same folder and renamed into place.

    Args:
        path: output file; its folder is created if needed.
        img: (H, W), (H, W, 1), (H, W, 2), (H, W, 3) or (H, W, 4) finite linear values (or
            stored codes, see above).
        bits: bit depth (see the table); None = the format's default.
        metadata: header attributes as OpenImageIO names them (``"Exif:FocalLength"``, ``"Make"``,
            ...), written where the format has a place for them (EXIF in PNG, JPEG, TIFF).

    Returns:
        The path written.

    Raises:
        ConfigError: unknown extension, unsupported bit depth, bad array shape.
    """
    import OpenImageIO as oiio

    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _WRITE_FORMATS:
        raise ConfigError(f"cannot write images with extension {ext!r}", path,
                          f"use one of {', '.join(sorted(_WRITE_FORMATS))}")
    fmt_name, allowed, default_bits = _WRITE_FORMATS[ext]
    bits = default_bits if bits is None else int(bits)
    if bits not in allowed:
        raise ConfigError(f"{ext} cannot be written with {bits} bits", path, f"use bits in {allowed}")
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ConfigError(f"image array has shape {np.asarray(img).shape}", path,
                          "pass (H, W) or (H, W, C) with C in 1..4")
    codes = (bits == 8 and a.dtype == np.uint8) or (
        bits == 16 and a.dtype == np.uint16 and fmt_name != "openexr")
    if not codes:
        a = a.astype(np.float32, copy=False)
    if fmt_name in ("hdr", "jpeg"):
        if a.shape[2] in (2, 4):
            a = a[:, :, :-1]
        if fmt_name == "hdr" and a.shape[2] == 1:
            a = np.repeat(a, 3, axis=2)
    c = a.shape[2]
    has_alpha = c in (2, 4)

    if not codes:
        _refuse_nonfinite(a, path, integer=bits in (8, 16) and fmt_name != "openexr")
    if codes:
        data = a
        oformat = "uint8" if bits == 8 else "uint16"
        cspace = "srgb_rec709_scene" if bits == 8 else "lin_rec709_scene"
    elif bits == 8:
        enc = a.copy()
        colour = slice(0, c - 1) if has_alpha else slice(0, c)
        enc[:, :, colour] = linear_to_srgb(np.clip(a[:, :, colour], 0.0, 1.0))
        data, oformat, cspace = _quantise(enc, 255, np.uint8), "uint8", "srgb_rec709_scene"
    elif bits == 16 and fmt_name != "openexr":
        data, oformat, cspace = _quantise(a, 65535, np.uint16), "uint16", "lin_rec709_scene"
    else:
        data = np.ascontiguousarray(a, dtype=np.float32)
        oformat = "half" if bits == 16 else "float"
        cspace = "lin_rec709_scene"

    spec = oiio.ImageSpec(int(data.shape[1]), int(data.shape[0]), c, oformat)
    if has_alpha:
        spec.channelnames = ("Y", "A") if c == 2 else ("R", "G", "B", "A")
        spec.alpha_channel = c - 1
        spec.attribute("oiio:UnassociatedAlpha", 0 if fmt_name == "openexr" else 1)
    elif c == 1:
        spec.channelnames = ("Y",)
    spec.attribute("oiio:ColorSpace", cspace)
    if fmt_name == "jpeg":
        spec.attribute("Compression", "jpeg:95")
    if fmt_name == "openexr":
        spec.attribute("compression", "zip")
    for key, value in (metadata or {}).items():
        spec.attribute(str(key), value)

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{ext}", dir=path.parent)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(fmt_name)
        if out is None:
            raise ConfigError(f"OpenImageIO has no {fmt_name} writer ({oiio.geterror()})", path,
                              "install an OpenImageIO build with this format")
        if not out.open(tmp, spec):
            raise InputError(f"cannot write image ({out.geterror()})", path, "check the folder is writable")
        ok = out.write_image(np.ascontiguousarray(data))
        err = out.geterror() if not ok else ""
        out.close()
        if not ok:
            raise InputError(f"cannot write image ({err})", path, "check free disk space and permissions")
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        oiio.geterror()
        raise
    return path


def copy_with_metadata(src: str | os.PathLike, dst: str | os.PathLike, metadata: dict) -> Path:
    """Copy an image, its stored values unchanged, adding header attributes (e.g. EXIF, see
    :func:`write_image`'s ``metadata``); written atomically.

    Raises:
        InputError: ``src`` is unreadable. ConfigError: ``dst``'s extension cannot be written.
    """
    px, spec = _read_raw(Path(src))
    bits = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}.get(px.dtype, 32)
    if bits == 32 and Path(dst).suffix.lower() == ".exr":
        bits = 32 if spec.format.size() >= 4 else 16
    return write_image(dst, px, bits=bits, metadata=metadata)
