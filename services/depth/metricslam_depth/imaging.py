"""Decode uploaded PNG/JPEG bytes into uint8 arrays, refusing anything odd with a clear reason.

The image size is read from the file header *before* decoding, so a tiny file that claims to
be 100000x100000 pixels (a decompression bomb) is refused without allocating it.

Returned images are ``(H, W)`` uint8 gray, the network's input kind: OpenCV converts colour
to gray with the right channel weights, drops alpha and scales
16-bit to 8-bit.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

from .errors import RequestProblem

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8\xff"
_MEDIA_ALIASES = {"image/png": "image/png", "image/jpeg": "image/jpeg", "image/jpg": "image/jpeg"}
# JPEG start-of-frame markers carry the size; C4 (DHT), C8 (JPG), CC (DAC) are not frames.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def normalise_media_type(content_type: str | None) -> str:
    """``"image/PNG; foo=bar"`` -> ``"image/png"``.

    Raises:
        RequestProblem: 415 when the type is missing or not PNG/JPEG.
    """
    media = (content_type or "").split(";", 1)[0].strip().lower()
    if media not in _MEDIA_ALIASES:
        shown = media or "no Content-Type"
        raise RequestProblem(
            415, "unsupported-media-type", "Unsupported media type",
            f"got {shown}; send the encoded image as the body with Content-Type image/png or "
            "image/jpeg (other formats: convert to PNG first).",
        )
    return _MEDIA_ALIASES[media]


def _undecodable(detail: str) -> RequestProblem:
    return RequestProblem(400, "undecodable-image", "Image could not be decoded", detail)


def _png_size(data: bytes) -> tuple[int, int]:
    # IHDR is always the first chunk: length(4) 'IHDR'(4) width(4) height(4)
    if len(data) < 24 or data[12:16] != b"IHDR":
        raise _undecodable("the PNG has no IHDR header; the file is truncated or corrupt.")
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _jpeg_size(data: bytes) -> tuple[int, int]:
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            break
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
            pos += 2
            continue
        (seg_len,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        if marker in _SOF_MARKERS:
            if pos + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[pos + 5 : pos + 9])
            return width, height
        if seg_len < 2:
            break
        pos += 2 + seg_len
    raise _undecodable("no JPEG frame header found; the file is truncated or corrupt.")


def image_size(data: bytes, media_type: str) -> tuple[int, int]:
    """(width_px, height_px) from the header of PNG/JPEG ``data`` without decoding pixels.

    Raises:
        RequestProblem: 400 when ``data`` is not a file of the declared ``media_type``.
    """
    if media_type == "image/png":
        if not data.startswith(PNG_SIGNATURE):
            raise _undecodable(
                "the body does not start with the PNG signature although Content-Type is "
                "image/png; send the PNG file's bytes unchanged (or fix the Content-Type)."
            )
        return _png_size(data)
    if not data.startswith(JPEG_SIGNATURE):
        raise _undecodable(
            "the body does not start with a JPEG SOI marker although Content-Type is "
            "image/jpeg; send the JPEG file's bytes unchanged (or fix the Content-Type)."
        )
    return _jpeg_size(data)


def decode_image(data: bytes, media_type: str, max_pixels: int) -> np.ndarray:
    """Decode PNG/JPEG ``data`` into a ``(H, W)`` uint8 gray array.

    Args:
        data: the encoded file.
        media_type: ``"image/png"`` or ``"image/jpeg"`` (see :func:`normalise_media_type`).
        max_pixels: largest accepted ``width * height``.

    Raises:
        RequestProblem: 400 for empty, garbage, truncated or mismatched data; 413 when the
            header announces more than ``max_pixels`` pixels.
    """
    if not data:
        raise _undecodable("the request body is empty; send the encoded image as the body.")
    width, height = image_size(data, media_type)
    if width == 0 or height == 0:
        raise _undecodable(f"the image header says {width}x{height} pixels; send a non-empty image.")
    if width * height > max_pixels:
        raise RequestProblem(
            413, "image-too-large", "Image has too many pixels",
            f"the image is {width}x{height} = {width * height} pixels, more than the limit of "
            f"{max_pixels}; downscale it (the network runs at a few hundred pixels wide anyway).",
        )
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise _undecodable(
            f"the {media_type} body could not be decoded (truncated or corrupt); "
            "re-encode the image and send the complete file."
        )
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise _undecodable(f"the image is {image.shape[1]}x{image.shape[0]} pixels; send at least 2x2.")
    return image
