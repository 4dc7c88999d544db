"""Image IO: sRGB curve, round trips per format and bit depth, and bad files."""

from __future__ import annotations

import os

import numpy as np
import pytest

from texstream.capture.imageio import (image_size, linear_to_srgb, read_alpha, read_image, read_mask,
                                       srgb_to_linear, write_image)
from texstream.core.errors import ConfigError, InputError


def _smooth(h: int = 24, w: int = 32, c: int = 3) -> np.ndarray:
    """A smooth linear test image in [0, 1] (smooth so JPEG's chroma subsampling barely changes it)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    chans = [(x / (w - 1)), (y / (h - 1)), 0.5 + 0.4 * np.sin(x / 7.0) * np.cos(y / 5.0), (x + y) / (w + h - 2)]
    return np.stack(chans[:c], axis=2).astype(np.float32)


def _write_exr_unchecked(path, img: np.ndarray):
    """A float EXR written by OpenImageIO itself: write_image refuses NaN and Inf, a camera or another
    program's file need not."""
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], "float"))
    assert out.write_image(np.ascontiguousarray(img, np.float32))
    out.close()
    return path


def test_write_image_refuses_nan_and_inf_naming_the_file_and_a_pixel(tmp_path):
    """Issue 41: no non-finite number reaches a file."""
    from texstream.core.errors import StageError

    img = _smooth()
    for bad, ext, bits in ((np.inf, "exr", 32), (np.nan, "exr", 16), (-np.inf, "tif", 32), (np.nan, "png", 8)):
        img[3, 5, 1] = bad
        with pytest.raises(StageError, match=rf"bad.{ext}: image holds 1 pixel.*x=5, y=3, channel 1 is"):
            write_image(tmp_path / f"bad.{ext}", img, bits=bits)
        assert list(tmp_path.iterdir()) == []  # nothing written, no temporary file left
    img[3, 5, 1] = np.inf  # an integer format clips a bright value, infinite ones too
    assert write_image(tmp_path / "bright.png", img, bits=8).is_file()


# ---------------------------------------------------------------- sRGB curve


def test_srgb_8bit_codes_round_trip_exactly():
    codes = np.arange(256)
    for dtype in (np.float32, np.float64):
        lin = srgb_to_linear((codes / 255.0).astype(dtype))
        assert lin.dtype == dtype
        back = np.floor(linear_to_srgb(lin).astype(np.float64) * 255 + 0.5).astype(int)
        np.testing.assert_array_equal(back, codes)


def test_srgb_float_round_trip_and_reference_values():
    x = np.linspace(0.0, 1.0, 10001)
    # 1e-6: float32 keeps ~7 digits; the float64 round trip is exact to ~1e-15
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x.astype(np.float32))), x, atol=1e-6)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    # IEC 61966-2-1 reference points: code 0.5 -> 0.214041..., linear 0.18 -> 0.461356...
    assert srgb_to_linear(np.float64(0.5)) == pytest.approx(0.21404114048223255, abs=1e-15)
    assert linear_to_srgb(np.float64(0.18)) == pytest.approx(0.46135612950044164, abs=1e-15)
    # the two pieces meet: the decode threshold maps to the encode threshold (continuity, to 1e-7)
    assert srgb_to_linear(np.float64(0.04045)) == pytest.approx(0.0031308, abs=1e-7)
    assert srgb_to_linear(np.float64(1.0)) == 1.0 and linear_to_srgb(np.float64(0.0)) == 0.0


# ---------------------------------------------------------------- round trips

# (extension, bits, tolerance, reason)
ROUND_TRIPS = [
    ("exr", None, 1e-3, "half float: 11-bit mantissa, relative error <= 2^-11 of values <= 1"),
    ("exr", 32, 0.0, "float32 stored exactly"),
    ("hdr", None, 1e-2, "RGBE: 8-bit mantissa shared per pixel, relative error <= 2^-8 of the largest channel"),
    ("png", 8, 4.5e-3, "8-bit sRGB: half a code step in linear is <= 0.5/255 * max d(lin)/d(srgb) = 0.5/255 * 2.275"),
    ("png", 16, 1e-5, "16-bit linear: half a code step = 0.5/65535"),
    ("tif", 8, 4.5e-3, "8-bit sRGB as for PNG"),
    ("tif", 16, 1e-5, "16-bit linear as for PNG"),
    ("tif", 32, 0.0, "float32 stored exactly"),
    ("tiff", 16, 1e-5, "16-bit linear as for PNG"),
]


@pytest.mark.parametrize("ext,bits,tol,reason", ROUND_TRIPS, ids=[f"{e}-{b}" for e, b, _, _ in ROUND_TRIPS])
def test_round_trip(tmp_path, ext, bits, tol, reason):
    img = _smooth()
    p = write_image(tmp_path / f"a.{ext}", img, bits=bits)
    back = read_image(p)
    assert back.dtype == np.float32 and back.shape == img.shape
    assert np.abs(back - img).max() <= tol, reason
    assert image_size(p) == (32, 24, 3)


def test_jpeg_round_trip(tmp_path):
    # near-neutral smooth image: JPEG subsamples chroma, so saturated colour edges would dominate
    base = _smooth()
    img = 0.8 * base.mean(axis=2, keepdims=True) + 0.2 * base
    back = read_image(write_image(tmp_path / "a.jpg", img))
    # 0.04: q95 DCT quantisation plus 8-bit sRGB rounding (measured max 0.026 on this image)
    assert np.abs(back - img).max() < 0.04
    assert image_size(tmp_path / "a.jpg") == (32, 24, 3)


def test_8bit_codes_written_exactly(tmp_path):
    # all 256 codes survive linear -> write PNG -> raw codes -> read -> linear
    codes = np.arange(256, dtype=np.float64).reshape(16, 16) / 255.0
    lin = srgb_to_linear(codes).astype(np.float32)
    p = write_image(tmp_path / "codes.png", lin)
    np.testing.assert_array_equal(read_image(p, linear=False, channels=1)[:, :, 0] * 255, codes * 255)
    np.testing.assert_array_equal(read_image(p, channels=1)[:, :, 0], lin)
    # uint8 input is written as codes unchanged
    p2 = write_image(tmp_path / "codes2.png", np.round(codes * 255).astype(np.uint8))
    np.testing.assert_array_equal(read_image(p2, channels=1)[:, :, 0], lin)


def test_quantisation_clips_and_rounds(tmp_path):
    img = np.array([[-0.5, 0.0, 0.5 / 65535, 0.49 / 65535, 1.0, 7.0]], np.float32)
    p = write_image(tmp_path / "q.png", img, bits=16)
    got = np.round(read_image(p, channels=1)[0, :, 0] * 65535).astype(int)
    np.testing.assert_array_equal(got, [0, 0, 1, 0, 65535, 65535])


@pytest.mark.parametrize("ext,bits", [("png", 8), ("png", 16), ("tif", 16), ("exr", 32)])
def test_alpha_and_grey(tmp_path, ext, bits):
    rgba = _smooth(c=4)
    p = write_image(tmp_path / f"rgba.{ext}", rgba, bits=bits)
    # tolerance: 8-bit alpha is linear codes (half a step 0.5/255); colour as in ROUND_TRIPS
    tol = 4.5e-3 if bits == 8 else 1e-5
    np.testing.assert_allclose(read_image(p, channels=4), rgba, atol=tol)
    np.testing.assert_allclose(read_image(p), rgba[:, :, :3], atol=tol)
    np.testing.assert_allclose(read_alpha(p), rgba[:, :, 3], atol=tol)
    grey = rgba[:, :, 1]
    pg = write_image(tmp_path / f"grey.{ext}", grey, bits=bits)
    assert read_alpha(pg) is None
    three = read_image(pg)
    assert three.shape == grey.shape + (3,)
    np.testing.assert_array_equal(three[:, :, 0], three[:, :, 2])
    np.testing.assert_allclose(three[:, :, 1], grey, atol=tol)
    np.testing.assert_allclose(read_image(pg, channels=4)[:, :, 3], 1.0)


def test_8bit_file_tagged_linear_is_not_decoded(tmp_path):
    import OpenImageIO as oiio

    p = str(tmp_path / "lin.png")
    out = oiio.ImageOutput.create(p)
    spec = oiio.ImageSpec(2, 1, 1, "uint8")
    spec.attribute("oiio:ColorSpace", "lin_rec709_scene")
    out.open(p, spec)
    out.write_image(np.array([[[51], [255]]], np.uint8))
    out.close()
    np.testing.assert_allclose(read_image(p, channels=1)[0, :, 0], [0.2, 1.0], atol=1e-7)


def test_masks(tmp_path):
    m = np.zeros((6, 8), np.float32)
    m[2:4, 3:7] = 1.0
    p = write_image(tmp_path / "m.png", m)
    got = read_mask(p, shape=(6, 8))
    assert got.dtype == bool
    np.testing.assert_array_equal(got, m > 0)
    with pytest.raises(InputError, match="m.png"):
        read_mask(p, shape=(8, 6))
    # a dim but nonzero value still counts as object (nerfstudio: nonzero = keep)
    m2 = m.copy()
    m2[0, 0] = 1.0 / 255 / 12.92  # decodes to code 1
    assert read_mask(write_image(tmp_path / "m2.png", m2))[0, 0]


def test_write_is_atomic_and_leaves_no_temp(tmp_path):
    write_image(tmp_path / "a.exr", _smooth())
    write_image(tmp_path / "a.exr", _smooth() * 2)  # overwrite in place
    assert sorted(os.listdir(tmp_path)) == ["a.exr"]
    np.testing.assert_allclose(read_image(tmp_path / "a.exr"), _smooth() * 2, rtol=1e-3)  # half precision
    with pytest.raises(ConfigError):
        write_image(tmp_path / "a.bmpx", _smooth())
    with pytest.raises(ConfigError):
        write_image(tmp_path / "a.jpg", _smooth(), bits=16)
    assert sorted(os.listdir(tmp_path)) == ["a.exr"]


# ---------------------------------------------------------------- bad files


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="nope.png.*not found"):
        read_image(tmp_path / "nope.png")


def test_truncated_png(tmp_path):
    p = write_image(tmp_path / "full.png", np.random.default_rng(0).random((64, 64, 3)).astype(np.float32))
    data = p.read_bytes()
    bad = tmp_path / "trunc.png"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="trunc.png.*(corrupt|truncated|cannot read)"):
        read_image(bad)


def test_garbage_jpg_and_empty(tmp_path):
    g = tmp_path / "garbage.jpg"
    g.write_bytes(np.random.default_rng(1).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="garbage.jpg.*cannot read"):
        read_image(g)
    e = tmp_path / "empty.png"
    e.write_bytes(b"")
    with pytest.raises(InputError, match="empty.png.*empty"):
        read_image(e)
    with pytest.raises(InputError, match="empty.png"):
        image_size(e)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_in_exr(tmp_path, bad):
    img = _smooth()
    img[3, 5, 1] = bad
    p = _write_exr_unchecked(tmp_path / "nan.exr", img)
    with pytest.raises(InputError, match=r"nan.exr.*NaN/Inf.*x=5, y=3"):
        read_image(p)


# ---------------------------------------------------------------- rows (photos cropped to the object)


@pytest.mark.parametrize("ext,bits", [("exr", 32), ("exr", None), ("png", 8), ("png", 16), ("jpg", 8),
                                      ("tif", 32)])
def test_rows_equal_the_rows_of_the_whole_image(tmp_path, ext, bits):
    """Reading rows y0..y1 gives those rows of the whole image to the bit (the same decoder, only the
    blocks holding them decoded), for scanline formats of every depth."""
    img = _smooth(40, 28)
    p = write_image(tmp_path / f"rows.{ext}", img, **({} if bits is None else {"bits": bits}))
    whole = read_image(p)
    for y0, y1 in ((0, 40), (7, 23), (39, 40)):
        np.testing.assert_array_equal(read_image(p, rows=(y0, y1), size=(40, 28)), whole[y0:y1])
    m = write_image(tmp_path / "mask.png", (img[..., :1] > 0.5).repeat(3, axis=2).astype(np.float32), bits=8)
    np.testing.assert_array_equal(read_mask(m, (40, 28), rows=(5, 30)), read_mask(m)[5:30])


def test_rows_of_a_tiled_exr(tmp_path):
    """A tiled EXR has no scanlines to pick: it is read whole and cut, the same values."""
    import OpenImageIO as oiio

    img = _smooth(40, 28)
    spec = oiio.ImageSpec(28, 40, 3, "float")
    spec.tile_width = spec.tile_height = 16
    out = oiio.ImageOutput.create(str(tmp_path / "tiled.exr"))
    assert out.open(str(tmp_path / "tiled.exr"), spec) and out.write_image(img)
    out.close()
    assert image_size(tmp_path / "tiled.exr") == (28, 40, 3)
    np.testing.assert_array_equal(read_image(tmp_path / "tiled.exr", rows=(9, 33)), img[9:33])


def test_rows_check_the_size_first_and_nan_only_in_them(tmp_path):
    img = _smooth(40, 28)
    img[2, 3, 0] = np.nan  # outside the rows read: never decoded, never a sample
    p = _write_exr_unchecked(tmp_path / "photo.exr", img)
    with pytest.raises(InputError, match=r"photo.exr: image is 28x40 but 30x40 is expected.*capture.json"):
        read_image(p, rows=(5, 10), size=(40, 30))
    assert np.isfinite(read_image(p, rows=(5, 10))).all()
    with pytest.raises(InputError, match=r"NaN/Inf.*x=3, y=2"):
        read_image(p, rows=(1, 10))
    m = write_image(tmp_path / "m.png", np.ones((40, 28, 3), np.float32), bits=8)
    with pytest.raises(InputError, match=r"m.png: mask is 28x40 but its photo is 30x40"):
        read_mask(m, (40, 30), rows=(0, 4))
