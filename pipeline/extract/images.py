"""Camera images from ROS messages, decoded with OpenCV: ``sensor_msgs/CompressedImage`` (JPEG, PNG) and
``sensor_msgs/Image`` (raw pixel rows in a named encoding).

The one home of image decoding: the stereo VO reads its frames through :func:`gray8`, and
``extract.images=files`` writes raw images through :func:`png_bytes`. Raw images follow
``sensor_msgs/image_encodings.h``: rows are ``step`` bytes long (``step`` may exceed the pixel bytes of a
row: padding is skipped), 16-bit data is in the byte order ``is_bigendian`` states, Bayer mosaics are
demosaiced by OpenCV (bilinear, to colour, then grey) with the codes cv_bridge uses (OpenCV names a
pattern by its second row, so ROS's ``rggb`` is OpenCV's ``BG``), and 16-bit images become 8-bit as
cv_bridge does (the high byte).

Demosaicing to colour then grey rather than OpenCV's direct Bayer-to-grey conversion: on rendered
drives mosaiced in the test's way the VO's largest position error was 1.04 / 1.24 cm (4.8 m drives,
renderer seeds 3 and 21) against 1.56 / 1.48 cm direct and 0.88 / 0.56 cm for the grey images
themselves, for 0.11 ms instead of 0.07 ms per 320x240 image (VNG demosaicing came closest to grey,
0.92 / 0.73 cm, at 2.4 ms per image: too slow for megapixel pairs; measured 2026-11-23).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np


class ImageDecodeError(ValueError):
    """An image message whose pixels cannot be decoded (unknown encoding, too few bytes, bad data)."""


@dataclass(frozen=True)
class Encoding:
    """How to read one ``sensor_msgs/Image`` encoding: bytes per channel value, channels per pixel,
    the OpenCV conversion to grey (None: already grey), to a viewable colour image for PNG files (None:
    written as is) and, for a Bayer mosaic, the demosaicing to BGR that comes before grey."""

    depth: int
    channels: int
    to_gray: int | None
    to_bgr: int | None = None
    demosaic: int | None = None


def _bayer(cv_pattern: str, depth: int) -> Encoding:
    return Encoding(depth, 1, cv2.COLOR_BGR2GRAY, demosaic=getattr(cv2, f"COLOR_Bayer{cv_pattern}2BGR"))


ENCODINGS: dict[str, Encoding] = {
    "mono8": Encoding(1, 1, None),
    "8UC1": Encoding(1, 1, None),
    "mono16": Encoding(2, 1, None),
    "16UC1": Encoding(2, 1, None),
    "bgr8": Encoding(1, 3, cv2.COLOR_BGR2GRAY),
    "rgb8": Encoding(1, 3, cv2.COLOR_RGB2GRAY, cv2.COLOR_RGB2BGR),
    "bgra8": Encoding(1, 4, cv2.COLOR_BGRA2GRAY),
    "rgba8": Encoding(1, 4, cv2.COLOR_RGBA2GRAY, cv2.COLOR_RGBA2BGRA),
    "bgr16": Encoding(2, 3, cv2.COLOR_BGR2GRAY),
    "rgb16": Encoding(2, 3, cv2.COLOR_RGB2GRAY, cv2.COLOR_RGB2BGR),
    "bgra16": Encoding(2, 4, cv2.COLOR_BGRA2GRAY),
    "rgba16": Encoding(2, 4, cv2.COLOR_RGBA2GRAY, cv2.COLOR_RGBA2BGRA),
    # ROS pattern (first two rows) -> OpenCV pattern (named by the second row), as cv_bridge maps them
    **{
        f"bayer_{ros}{bits}": _bayer(cv, bits // 8)
        for ros, cv in (("rggb", "BG"), ("bggr", "RG"), ("gbrg", "GR"), ("grbg", "GB"))
        for bits in (8, 16)
    },
    "yuv422": Encoding(1, 2, cv2.COLOR_YUV2GRAY_UYVY),  # ROS's yuv422 is UYVY
    "uyvy": Encoding(1, 2, cv2.COLOR_YUV2GRAY_UYVY),
    "yuv422_yuy2": Encoding(1, 2, cv2.COLOR_YUV2GRAY_YUY2),
    "yuyv": Encoding(1, 2, cv2.COLOR_YUV2GRAY_YUY2),
}


def encoding_of(name: str) -> Encoding:
    """The :class:`Encoding` of an encoding name; ImageDecodeError listing the supported ones."""
    try:
        return ENCODINGS[name]
    except KeyError:
        raise ImageDecodeError(
            f"image encoding {name!r} is not supported (supported: {', '.join(sorted(ENCODINGS))})"
        ) from None


def raw_pixels(msg: Any) -> np.ndarray:
    """An Image message's pixels: ``(height, width)`` or ``(height, width, channels)``, ``uint8`` or
    native-order ``uint16``, row padding removed. Channel order as the encoding names it."""
    enc = encoding_of(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * enc.channels * enc.depth
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if step < row or data.size < h * step:
        raise ImageDecodeError(
            f"{msg.encoding} image {w}x{h}: {data.size} bytes with step {step} "
            f"(needs step >= {row} and {h * step} bytes)"
        )
    rows = data[: h * step].reshape(h, step)[:, :row]
    if enc.depth == 2:
        order = ">" if msg.is_bigendian else "<"
        pixels = np.ascontiguousarray(rows).view(f"{order}u2").astype(np.uint16)
    else:
        pixels = np.ascontiguousarray(rows)
    # packed YUV 4:2:2 too: OpenCV takes it as two 8-bit channels
    return pixels.reshape((h, w) if enc.channels == 1 else (h, w, enc.channels))


def _to8(img: np.ndarray) -> np.ndarray:
    # cv_bridge's 16 -> 8 bit conversion: scale by 255/65535, i.e. keep the high byte
    return img if img.dtype == np.uint8 else (img >> 8).astype(np.uint8)


def gray8(msg: Any) -> np.ndarray:
    """One image message -> an 8-bit grey image ``(height, width)``, the VO's input.

    A CompressedImage is decoded by ``cv2.imdecode``; an Image by its encoding (module docstring)."""
    if hasattr(msg, "format"):  # sensor_msgs/CompressedImage
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8).reshape(-1), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ImageDecodeError(f"undecodable {msg.format or 'compressed'} image ({len(msg.data)} bytes)")
        return img
    enc = encoding_of(msg.encoding)
    pixels = raw_pixels(msg)
    if enc.demosaic is not None:
        pixels = cv2.cvtColor(pixels, enc.demosaic)
    if enc.to_gray is not None:
        pixels = cv2.cvtColor(pixels, enc.to_gray)
    return _to8(pixels)


def png_bytes(msg: Any) -> bytes | None:
    """An Image message as lossless PNG bytes (8 or 16 bit; mono and Bayer mosaics as one channel,
    colour converted to OpenCV's BGR order so that the file views correctly), or None when its
    encoding has no lossless PNG form here (YUV, unknown encodings) or its data is malformed."""
    try:
        enc = encoding_of(msg.encoding)
        if enc.channels == 2:
            return None
        pixels = raw_pixels(msg)
    except ImageDecodeError:
        return None
    if enc.to_bgr is not None:
        pixels = cv2.cvtColor(pixels, enc.to_bgr)
    ok, buf = cv2.imencode(".png", pixels)
    return buf.tobytes() if ok else None
