"""Encoding and decoding of recorded images (``recording-format.md``, Encodings).

Images are handed around as numpy arrays in RGB order: ``(H, W)`` for one channel,
``(H, W, 3)`` RGB for colour, ``uint8`` or (``mono16`` and 16-bit PNG) ``uint16``.

Encodings
---------
``png``, ``jpeg``
    Compressed (``foxglove.CompressedImage``); decoded with OpenCV. PNG carries
    ``uint8`` grey/RGB and ``uint16`` grey exactly; JPEG is lossy and ``uint8`` only.
    A PNG with an alpha channel decodes to its RGB part.
``mono8``, ``rgb8``, ``bgr8``, ``mono16``
    Raw (``foxglove.RawImage``): rows of ``step`` bytes (``step >= width * bytes per
    pixel``; padding at the end of rows is honoured and dropped). ``mono16`` is
    little-endian, as the Foxglove schema specifies. robo3d writes these four.

Read as well (``READ_RAW_ENCODINGS``): what camera drivers in real cells publish as
``sensor_msgs/msg/Image`` (ROS ``image_encodings``), so that such a recording is read as
it is, not converted first:

- ``rgba8``, ``bgra8``, ``rgb16``, ``bgr16``, ``rgba16``, ``bgra16``: the alpha channel
  is dropped, 16-bit colour stays ``uint16``;
- ``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``, ``bayer_grbg8`` and their ``16``
  forms: the sensor's colour mosaic, demosaiced with OpenCV's edge-aware interpolation
  (``COLOR_Bayer*2RGB_EA``: it interpolates along edges, not across them, so a laser
  stripe or an outline is not smeared across the mosaic's colours; the pattern names
  map to OpenCV's as ``cv_bridge`` maps them: ``rggb`` is OpenCV's ``BayerBG``);
- ``yuv422`` (UYVY, as ``cv_bridge`` reads it) and ``yuv422_yuy2`` (YUYV): a USB
  camera's native format, 8-bit RGB after conversion (even widths only);
- the aliases ``8UC1``, ``8UC3`` (BGR), ``8UC4`` (BGRA), ``16UC1``, ``16UC3`` (BGR) and
  ``16UC4`` (BGRA).

The decoders take any object with the fields of :class:`EncodedImage` (the reader's
:class:`~.model.ImageMessage` has them), so this module does not import the model:
``model`` imports ``images``, never the other way round.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

from ..camera import CameraModel
from ..errors import ImageDecodeError

__all__ = [
    "COMPRESSED_ENCODINGS",
    "RAW_ENCODINGS",
    "READ_RAW_ENCODINGS",
    "normalize_encoding",
    "encode_image",
    "decode_image",
    "decode_checked",
    "chroma_subsampled",
    "EncodedImage",
]

#: Compressed encodings robo3d writes (``foxglove.CompressedImage.format``).
COMPRESSED_ENCODINGS = ("png", "jpeg")
#: Raw encodings robo3d reads and writes (``foxglove.RawImage.encoding``).
RAW_ENCODINGS = ("mono8", "rgb8", "bgr8", "mono16")
#: OpenCV's demosaicing of each ROS Bayer pattern (``cv_bridge``'s mapping: OpenCV names
#: the pattern by the second row's second and third pixels).
_BAYER = {"rggb": cv2.COLOR_BayerBG2RGB_EA, "bggr": cv2.COLOR_BayerRG2RGB_EA,
          "gbrg": cv2.COLOR_BayerGR2RGB_EA, "grbg": cv2.COLOR_BayerGB2RGB_EA}
_YUV422 = {"yuv422": cv2.COLOR_YUV2RGB_UYVY, "yuv422_yuy2": cv2.COLOR_YUV2RGB_YUY2}
#: Raw encodings read: (channels in the buffer, bytes per channel) of each.
_RAW_LAYOUT = {"mono8": (1, 1), "rgb8": (3, 1), "bgr8": (3, 1), "mono16": (1, 2),
               "rgba8": (4, 1), "bgra8": (4, 1), "rgb16": (3, 2), "bgr16": (3, 2),
               "rgba16": (4, 2), "bgra16": (4, 2), "yuv422": (2, 1), "yuv422_yuy2": (2, 1),
               **{f"bayer_{p}{b}": (1, b // 8) for p in _BAYER for b in (8, 16)}}
#: Raw encodings robo3d reads (the written ones and what camera drivers publish).
READ_RAW_ENCODINGS = tuple(_RAW_LAYOUT)



class EncodedImage(Protocol):
    """What the decoders read of a recorded image (:class:`~.model.ImageMessage`).

    ``topic``, ``timestamp_ns``, ``frame_id`` and ``path`` name the image in errors;
    ``encoding`` and ``data`` are the recorded encoding and bytes; ``width``, ``height``
    and ``step`` describe a raw buffer (0 for compressed images).
    """

    topic: str
    timestamp_ns: int
    frame_id: str
    encoding: str
    data: bytes
    width: int
    height: int
    step: int
    path: str


_RAW_ALIASES = {"8uc1": "mono8", "8uc3": "bgr8", "8uc4": "bgra8", "16uc1": "mono16",
                "16uc3": "bgr16", "16uc4": "bgra16"}


def normalize_encoding(encoding: str) -> str:
    """Canonical name of an image encoding or compressed format string.

    ``"png"``, ``"image/png"``, ``"PNG"`` give ``"png"``; ``"jpeg"``, ``"jpg"``,
    ``"image/jpeg"`` give ``"jpeg"``; raw names and their aliases give the raw name
    (``"8UC1"`` -> ``"mono8"``). ROS-style compressed formats such as
    ``"rgb8; jpeg compressed bgr8"`` give the compression. Anything else is returned
    lower-cased and stripped (and fails to decode later if OpenCV cannot read it).

    Parameters
    ----------
    encoding : str
        The ``format`` of a compressed image or the ``encoding`` of a raw one.

    Returns
    -------
    str
    """
    e = str(encoding).strip().lower()
    if e.startswith("image/"):
        e = e[len("image/"):]
    if e in _RAW_ALIASES:
        return _RAW_ALIASES[e]
    if e in _RAW_LAYOUT:
        return e
    if e in ("jpg", "jpeg"):
        return "jpeg"
    if e == "png":
        return "png"
    # ROS image_transport style: "<raw>; <codec> compressed <raw>"
    if "compressed" in e:
        if "png" in e:
            return "png"
        if "jpeg" in e or "jpg" in e:
            return "jpeg"
    return e


def _check_image(image: np.ndarray, encoding: str) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
    shape, dtype = image.shape, image.dtype
    desc = f"{shape} {dtype}"
    if encoding in ("mono8", "mono16"):
        want = np.uint8 if encoding == "mono8" else np.uint16
        if image.ndim != 2 or dtype != want:
            raise ValueError(f"{encoding} image must be (H, W) {np.dtype(want)}, got {desc}")
    elif encoding in ("rgb8", "bgr8"):
        if image.ndim != 3 or shape[2] != 3 or dtype != np.uint8:
            raise ValueError(f"{encoding} image must be (H, W, 3) uint8 RGB, got {desc}")
    elif encoding == "png":
        ok = (image.ndim == 2 and dtype in (np.uint8, np.uint16)) or (
            image.ndim == 3 and shape[2] == 3 and dtype in (np.uint8, np.uint16))
        if not ok:
            raise ValueError(f"png image must be (H, W) or (H, W, 3) uint8/uint16, got {desc}")
    elif encoding == "jpeg":
        ok = (image.ndim == 2 or (image.ndim == 3 and shape[2] == 3)) and dtype == np.uint8
        if not ok:
            raise ValueError(f"jpeg image must be (H, W) or (H, W, 3) uint8, got {desc}")
    else:
        raise ValueError(f"image encoding must be one of "
                         f"{', '.join(COMPRESSED_ENCODINGS + RAW_ENCODINGS)}, got {encoding!r}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"image must not be empty, got {desc}")
    return np.ascontiguousarray(image)


def encode_image(image: np.ndarray, encoding: str, jpeg_quality: int = 95) -> bytes:
    """Encode an image for a recording.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 / uint16
        Grey or RGB pixels (see the module docstring for which dtype each encoding takes).
    encoding : str
        ``png``, ``jpeg`` (compressed bytes) or ``mono8``, ``rgb8``, ``bgr8``, ``mono16``
        (the raw row-major buffer, ``step = width * bytes per pixel``, no padding).
    jpeg_quality : int
        JPEG quality, 1..100.

    Returns
    -------
    bytes

    Raises
    ------
    ValueError
        Wrong shape/dtype for the encoding, unknown encoding, bad quality.
    """
    enc = normalize_encoding(encoding)
    image = _check_image(image, enc)
    if enc == "mono8" or enc == "rgb8":
        return image.tobytes()
    if enc == "bgr8":
        return np.ascontiguousarray(image[..., ::-1]).tobytes()
    if enc == "mono16":
        return image.astype("<u2", copy=False).tobytes()
    bgr = image[..., ::-1] if image.ndim == 3 else image
    if enc == "png":
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(bgr))
    else:
        q = int(jpeg_quality)
        if not 1 <= q <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(bgr), [cv2.IMWRITE_JPEG_QUALITY, q])
    if not ok:  # pragma: no cover - OpenCV fails only on invalid input, checked above
        raise ValueError(f"OpenCV could not encode a {image.shape} {image.dtype} image as {enc}")
    return buf.tobytes()


def _fail(msg: EncodedImage, what: str) -> ImageDecodeError:
    return ImageDecodeError(f"image ({msg.encoding}, frame_id {msg.frame_id!r}) {what}",
                            path=msg.path or None, topic=msg.topic, time_ns=msg.timestamp_ns)


def raw_bytes_per_channel(encoding: str) -> int:
    """Bytes per channel of a raw encoding read (1 or 2; 0 when it is not one): what a
    big-endian buffer is byte-swapped by."""
    lay = _RAW_LAYOUT.get(normalize_encoding(encoding))
    return lay[1] if lay else 0


def _decode_raw(msg: EncodedImage, enc: str) -> np.ndarray:
    nch, bpc = _RAW_LAYOUT[enc]
    bpp = nch * bpc
    w, h = int(msg.width), int(msg.height)
    if w <= 0 or h <= 0:
        raise _fail(msg, f"has an invalid size {w}x{h}")
    if enc in _YUV422 and w % 2:
        raise _fail(msg, f"has an odd width {w}: {enc} stores two pixels per 4 bytes")
    step = int(msg.step) if msg.step else w * bpp
    if step < w * bpp:
        raise _fail(msg, f"has step {step} bytes, less than width {w} x {bpp} bytes per pixel")
    need = step * (h - 1) + w * bpp
    if len(msg.data) < need:
        raise _fail(msg, f"has {len(msg.data)} bytes of data, {w}x{h} with step {step} "
                         f"needs {need}")
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if len(buf) < step * h:  # last row unpadded: pad to a whole number of rows
        buf = np.concatenate([buf, np.zeros(step * h - len(buf), np.uint8)])
    rows = buf[: step * h].reshape(h, step)[:, : w * bpp]
    if bpc == 2:
        px = np.ascontiguousarray(rows).view("<u2").astype(np.uint16)
    else:
        px = np.ascontiguousarray(rows)
    if nch == 1:
        px = px.reshape(h, w)
        if enc.startswith("bayer_"):
            if h < 2 or w < 2:
                raise _fail(msg, f"is {w}x{h}: a Bayer mosaic needs at least 2x2 pixels")
            return cv2.cvtColor(px, _BAYER[enc[6:10]])
        return px
    px = px.reshape(h, w, nch)
    if enc in _YUV422:
        return cv2.cvtColor(px, _YUV422[enc])
    if enc.startswith("bgr"):
        return np.ascontiguousarray(px[..., 2::-1])
    return np.ascontiguousarray(px[..., :3])


def chroma_subsampled(data: bytes) -> bool:
    """Whether a JPEG stores its colour (Cb, Cr) at a lower resolution than its luma.

    Read from the frame header (SOF marker): a component's sampling factors below the
    luma's mean its plane was stored at half (4:2:2, 4:2:0) or a quarter the resolution.
    Cheap (the header is near the start) and False for anything that is not a colour
    JPEG (PNG, raw buffers, grey JPEG, or a header that does not parse).
    """
    b = bytes(data[:65536])
    if len(b) < 4 or b[0] != 0xFF or b[1] != 0xD8:
        return False
    i = 2
    while i + 4 <= len(b):
        if b[i] != 0xFF:
            return False
        marker = b[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        seg = int.from_bytes(b[i + 2:i + 4], "big")
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC9, 0xCA, 0xCB):  # start of frame
            n = b[i + 9] if i + 9 < len(b) else 0
            comps = b[i + 10:i + 10 + 3 * n]
            if n < 3 or len(comps) < 9:
                return False
            factors = [(comps[3 * j + 1] >> 4, comps[3 * j + 1] & 15) for j in range(n)]
            (h0, v0), rest = factors[0], factors[1:3]
            return any(h < h0 or v < v0 for h, v in rest)
        if marker == 0xDA:  # start of scan before any frame header: malformed
            return False
        i += 2 + seg
    return False


def decode_image(msg: EncodedImage) -> np.ndarray:
    """Decode a recorded image.

    Parameters
    ----------
    msg : EncodedImage
        An :class:`~.model.ImageMessage`: a compressed (``png``/``jpeg``, or any format
        OpenCV sniffs from the bytes) or raw (``READ_RAW_ENCODINGS``: ``mono8``,
        ``rgb8``, ``bgr8``, ``mono16``, colour with alpha or 16 bits, Bayer, YUV 4:2:2)
        image.

    Returns
    -------
    (H, W) or (H, W, 3) uint8 or uint16
        Grey or RGB pixels.

    Raises
    ------
    ImageDecodeError
        Bytes that do not decode, or a raw buffer inconsistent with its size; the
        message names the file, topic and time.
    """
    enc = normalize_encoding(msg.encoding)
    if enc in _RAW_LAYOUT:
        return _decode_raw(msg, enc)
    if len(msg.data) == 0:
        raise _fail(msg, "has no data")
    try:
        img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise _fail(msg, f"does not decode: {exc}") from None
    if img is None:
        raise _fail(msg, f"does not decode ({len(msg.data)} bytes, first bytes "
                         f"{bytes(msg.data[:8])!r})")
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[..., 0]
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.dtype not in (np.uint8, np.uint16):
        raise _fail(msg, f"decodes to unsupported pixel type {img.dtype}")
    return np.ascontiguousarray(img)


def decode_checked(msg: EncodedImage, camera: CameraModel) -> np.ndarray:
    """Decode an image and check that its size matches its camera's calibration.

    Parameters
    ----------
    msg : EncodedImage
        An :class:`~.model.ImageMessage`.
    camera : CameraModel
        The calibration of ``msg.frame_id``.

    Returns
    -------
    (H, W) or (H, W, 3) uint8 or uint16
        With ``H == camera.height`` and ``W == camera.width``.

    Raises
    ------
    ImageDecodeError
        The image does not decode, or its size differs from the calibration.
    """
    img = decode_image(msg)
    h, w = img.shape[:2]
    if (h, w) != (camera.height, camera.width):
        raise _fail(msg, f"is {w}x{h} pixels but its calibration ({camera.frame_id!r}) is "
                         f"{camera.width}x{camera.height}")
    return img
