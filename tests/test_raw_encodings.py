"""Raw image encodings that camera drivers publish, read as they are (``images.py``).

Each test writes the buffer itself from a known RGB image (numpy, not the decoder under
test): colour with alpha and 16-bit colour must come back exactly; a Bayer mosaic must
demosaic to the image it was sampled from (each of the four patterns, whose names differ
between ROS and OpenCV), and YUV 4:2:2 to within its chroma subsampling.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from robo3d.errors import ImageDecodeError
from robo3d.recording import ImageMessage
from robo3d.recording.images import READ_RAW_ENCODINGS, decode_image, normalize_encoding

H, W = 48, 64


def _smooth_rgb(dtype=np.uint8) -> np.ndarray:
    """A smooth colour image with a red, a green and a blue patch (values 8-bit)."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    img = np.stack([110 + 40 * np.sin(xx / 9), 120 + 35 * np.cos(yy / 7),
                    95 + 30 * np.sin((xx + yy) / 11)], axis=-1)
    img[8:20, 8:20] = (220, 30, 30)
    img[8:20, 26:38] = (30, 220, 30)
    img[8:20, 44:56] = (30, 30, 220)
    img = np.rint(img).astype(np.uint8)
    return img.astype(np.uint16) * 257 if dtype == np.uint16 else img


def _msg(enc: str, buf: np.ndarray, width: int = W, height: int = H, pad: int = 0
         ) -> ImageMessage:
    """A raw message of ``buf`` ((H, row bytes) uint8 view), rows padded by ``pad``."""
    rows = buf.reshape(height, -1)
    if pad:
        rows = np.hstack([rows, np.full((height, pad), 7, np.uint8)])
    return ImageMessage("/cam", 42, "camera", enc, rows.tobytes(), width, height,
                        rows.shape[1])


def _bytes(px: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(px.astype(px.dtype.newbyteorder("<"))).view(np.uint8)


@pytest.mark.parametrize("enc", ["rgba8", "bgra8", "8UC4", "rgb16", "bgr16", "rgba16",
                                 "bgra16", "16UC3", "16UC4"])
def test_colour_with_alpha_and_16_bit_colour_are_exact(enc: str) -> None:
    want = _smooth_rgb(np.uint16 if "16" in enc else np.uint8)
    name = normalize_encoding(enc)
    px = want[..., ::-1] if name.startswith("bgr") else want
    if name.endswith(("a8", "a16")):
        alpha = np.full((H, W, 1), 200, px.dtype)
        px = np.concatenate([px, alpha], axis=2)
    got = decode_image(_msg(enc, _bytes(np.ascontiguousarray(px)), pad=6))
    assert got.dtype == want.dtype and got.shape == (H, W, 3)
    np.testing.assert_array_equal(got, want)


def _mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The sensor's mosaic: each pixel keeps the channel its filter passes."""
    m = np.zeros(rgb.shape[:2], rgb.dtype)
    ch = {"r": 0, "g": 1, "b": 2}
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        m[dy::2, dx::2] = rgb[dy::2, dx::2, ch[pattern[k]]]
    return m


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_mosaics_demosaic_to_the_image(pattern: str, bits: int) -> None:
    want = _smooth_rgb(np.uint16 if bits == 16 else np.uint8)
    got = decode_image(_msg(f"bayer_{pattern}{bits}", _bytes(_mosaic(want, pattern))))
    assert got.dtype == want.dtype and got.shape == (H, W, 3)
    scale = 257.0 if bits == 16 else 1.0
    err = np.abs(got.astype(np.float64) - want) / scale
    # the smooth part comes back within a grey level; the patches' centres keep their colour
    assert np.median(err[24:-4, 4:-4]) < 1.0
    for k, x0 in enumerate((8, 26, 44)):
        patch = got[11:17, x0 + 3:x0 + 9].reshape(-1, 3).mean(axis=0) / scale
        assert patch.argmax() == k and patch[k] > 200 and np.delete(patch, k).max() < 50


@pytest.mark.parametrize(("enc", "code"), [("yuv422", "COLOR_RGB2YUV_UYVY"),
                                           ("yuv422_yuy2", "COLOR_RGB2YUV_YUY2")])
def test_yuv422(enc: str, code: str) -> None:
    if not hasattr(cv2, code):
        pytest.skip(f"this OpenCV has no {code} to write the test's image")
    want = _smooth_rgb()
    buf = cv2.cvtColor(want, getattr(cv2, code))
    got = decode_image(_msg(enc, np.ascontiguousarray(buf).view(np.uint8), pad=4))
    err = np.abs(got.astype(np.int64) - want)
    assert got.dtype == np.uint8 and got.shape == (H, W, 3)
    assert err[24:].max() <= 4 and err.mean() < 1.5


def test_every_encoding_read_is_listed_and_bad_buffers_are_named() -> None:
    assert {"bayer_rggb8", "bayer_grbg16", "rgba8", "bgr16", "yuv422"} <= set(READ_RAW_ENCODINGS)
    odd = ImageMessage("/cam", 42, "camera", "yuv422", bytes(2 * 5 * 4), 5, 4, 10)
    with pytest.raises(ImageDecodeError, match="odd width 5") as ei:
        decode_image(odd)
    assert ei.value.topic == "/cam"
    short = ImageMessage("/cam", 42, "camera", "bayer_rggb16", bytes(10), 4, 4, 8)
    with pytest.raises(ImageDecodeError, match="10 bytes of data"):
        decode_image(short)
    with pytest.raises(ImageDecodeError, match="at least 2x2"):
        decode_image(ImageMessage("/cam", 42, "camera", "bayer_rggb8", bytes(1), 1, 1, 1))
