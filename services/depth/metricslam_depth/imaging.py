"""Decode uploaded PNG/JPEG/PGM bytes into uint8 arrays, refusing anything odd with a clear reason.

The image size, channels and bit depth are read from the file header (PNG IHDR, JPEG SOF,
binary PGM ``P5``) *before* decoding, so a tiny file that claims to be 100000x100000 pixels, or
4096x4096 16-bit RGBA (a decompression bomb), is refused without allocating or touching its pixels.

Returned images are ``(H, W)`` uint8 gray, the network's input kind: OpenCV converts colour
to gray with the right channel weights, drops alpha and scales
16-bit to 8-bit. A JPEG much larger than the network input is decoded at 1/2 or 1/4 size in the
DCT (:func:`decode_gray`): the network sees it resized to its input anyway.

Binary PGM (``image/x-portable-graymap``, ``P5``) is the fast path for a client that already
holds gray pixels (the SLAM service's keyframes): its raster is the pixels themselves, so
"decoding" is a copy (~0.05 ms for a KITTI frame against ~3.4 ms of PNG inflate, and the client
saves the ~5 ms PNG encode).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

from .errors import RequestProblem
from .schemas import PGM_MEDIA_TYPE

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8\xff"
PGM_SIGNATURE = b"P5"
_MEDIA_ALIASES = {"image/png": "image/png", "image/jpeg": "image/jpeg", "image/jpg": "image/jpeg",
                  PGM_MEDIA_TYPE: PGM_MEDIA_TYPE, "image/x-pgm": PGM_MEDIA_TYPE}
# JPEG start-of-frame markers carry the size; C4 (DHT), C8 (JPG), CC (DAC) are not frames.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def normalise_media_type(content_type: str | None) -> str:
    """``"image/PNG; foo=bar"`` -> ``"image/png"``.

    Raises:
        RequestProblem: 415 when the type is missing or not PNG/JPEG/PGM.
    """
    media = (content_type or "").split(";", 1)[0].strip().lower()
    if media not in _MEDIA_ALIASES:
        shown = media or "no Content-Type"
        raise RequestProblem(
            415, "unsupported-media-type", "Unsupported media type",
            f"got {shown}; send the encoded image as the body with Content-Type image/png, "
            f"image/jpeg or {PGM_MEDIA_TYPE} (binary P5; other formats: convert to PNG first).",
        )
    return _MEDIA_ALIASES[media]


def _undecodable(detail: str) -> RequestProblem:
    return RequestProblem(400, "undecodable-image", "Image could not be decoded", detail)


@dataclass(frozen=True)
class ImageHeader:
    """What a PNG/JPEG/PGM header declares, read without decoding a pixel.

    Attributes:
        width_px / height_px: image size.
        channels: samples per pixel the decoder produces (gray 1, gray+alpha 2, RGB and
            palette 3, RGBA / CMYK 4).
        bytes_per_sample: 1 for up to 8 bits per sample, 2 above (16-bit PNG, 12-bit JPEG,
            PGM with maxval > 255).
        raster_offset: PGM only: where the pixels start in the file, bytes (0 otherwise).
        max_value: PGM only: the file's maxval (white), 1..65535 (0 otherwise).
    """

    width_px: int
    height_px: int
    channels: int
    bytes_per_sample: int
    raster_offset: int = 0
    max_value: int = 0

    @property
    def pixels(self) -> int:
        return self.width_px * self.height_px

    @property
    def decoded_bytes(self) -> int:
        """Size of the full decoded raster (what the decoder allocates and touches), bytes."""
        return self.pixels * self.channels * self.bytes_per_sample


# PNG colour type -> samples per pixel (palette images are expanded to RGB by the decoder)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}


def _png_header(data: bytes) -> ImageHeader:
    # IHDR is always the first chunk: length(4) 'IHDR'(4) width(4) height(4) depth(1) colour(1)
    if len(data) < 26 or data[12:16] != b"IHDR":
        raise _undecodable("the PNG has no IHDR header; the file is truncated or corrupt.")
    width, height, bit_depth, colour_type = struct.unpack(">IIBB", data[16:26])
    if colour_type not in _PNG_CHANNELS or bit_depth not in (1, 2, 4, 8, 16):
        raise _undecodable(
            f"the PNG header declares colour type {colour_type} with bit depth {bit_depth}, which "
            "is not valid PNG; re-encode the image."
        )
    return ImageHeader(width, height, _PNG_CHANNELS[colour_type], 2 if bit_depth > 8 else 1)


def _jpeg_header(data: bytes) -> ImageHeader:
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
            # length(2) precision(1) height(2) width(2) components(1)
            if pos + 10 > len(data):
                break
            precision, height, width, components = struct.unpack(">BHHB", data[pos + 4 : pos + 10])
            if components == 0:
                break
            return ImageHeader(width, height, components, 2 if precision > 8 else 1)
        if seg_len < 2:
            break
        pos += 2 + seg_len
    raise _undecodable("no JPEG frame header found; the file is truncated or corrupt.")


#: longest PGM header accepted (magic, size, maxval and comments), bytes
_PGM_MAX_HEADER_BYTES = 1024


def _pgm_header(data: bytes) -> ImageHeader:
    """``P5 <width> <height> <maxval>`` + one whitespace byte, with ``#`` comments allowed
    between the fields (netpbm's definition); the raster follows."""
    fields: list[int] = []
    pos = 2
    end = min(len(data), _PGM_MAX_HEADER_BYTES)
    while len(fields) < 3 and pos < end:
        byte = data[pos : pos + 1]
        if byte.isspace():
            pos += 1
        elif byte == b"#":
            newline = data.find(b"\n", pos, end)
            pos = end if newline < 0 else newline + 1
        elif byte.isdigit():
            start = pos
            while pos < end and data[pos : pos + 1].isdigit():
                pos += 1
            fields.append(int(data[start:pos]))
        else:
            break
    if len(fields) < 3 or pos >= len(data) or not data[pos : pos + 1].isspace():
        raise _undecodable("the PGM header is not 'P5 <width> <height> <maxval>' followed by one "
                           "whitespace byte; the file is truncated or corrupt.")
    width, height, max_value = fields
    if not 0 < max_value < 65536:
        raise _undecodable(f"the PGM header declares maxval {max_value}; PGM allows 1 to 65535.")
    return ImageHeader(width, height, 1, 1 if max_value < 256 else 2, raster_offset=pos + 1,
                       max_value=max_value)


def read_header(data: bytes, media_type: str) -> ImageHeader:
    """The :class:`ImageHeader` of PNG/JPEG/PGM ``data`` (IHDR / SOF / P5), without decoding pixels.

    Raises:
        RequestProblem: 400 when ``data`` is not a file of the declared ``media_type``.
    """
    if media_type == "image/png":
        if not data.startswith(PNG_SIGNATURE):
            raise _undecodable(
                "the body does not start with the PNG signature although Content-Type is "
                "image/png; send the PNG file's bytes unchanged (or fix the Content-Type)."
            )
        return _png_header(data)
    if media_type == PGM_MEDIA_TYPE:
        if not data.startswith(PGM_SIGNATURE):
            raise _undecodable(
                f"the body does not start with 'P5' although Content-Type is {PGM_MEDIA_TYPE}; "
                "send a binary (P5) PGM, not an ASCII (P2) one (or fix the Content-Type)."
            )
        return _pgm_header(data)
    if not data.startswith(JPEG_SIGNATURE):
        raise _undecodable(
            "the body does not start with a JPEG SOI marker although Content-Type is "
            "image/jpeg; send the JPEG file's bytes unchanged (or fix the Content-Type)."
        )
    return _jpeg_header(data)


def image_size(data: bytes, media_type: str) -> tuple[int, int]:
    """(width_px, height_px) from the header of PNG/JPEG/PGM ``data`` (see :func:`read_header`)."""
    header = read_header(data, media_type)
    return header.width_px, header.height_px


def check_header(data: bytes, media_type: str, max_pixels: int, max_decoded_bytes: int | None) -> ImageHeader:
    """Refuse, from the header alone, an image that is empty or would decode too large.

    This is the decompression-bomb guard: a 130 kB PNG declaring 4096x4096 16-bit RGBA would
    decode to 128 MiB; it is refused here in microseconds, before any decoder runs.

    Args:
        data: the encoded file.
        media_type: ``"image/png"``, ``"image/jpeg"`` or :data:`PGM_MEDIA_TYPE`.
        max_pixels: largest accepted ``width * height``.
        max_decoded_bytes: largest accepted ``width*height*channels*bytes_per_sample``
            (``None``: no byte limit).

    Raises:
        RequestProblem: 400 for empty or non-image data; 413 (``image-too-large``) over a limit.
    """
    if not data:
        raise _undecodable("the request body is empty; send the encoded image as the body.")
    h = read_header(data, media_type)
    if h.width_px == 0 or h.height_px == 0:
        raise _undecodable(f"the image header says {h.width_px}x{h.height_px} pixels; send a non-empty image.")
    if h.pixels > max_pixels:
        raise RequestProblem(
            413, "image-too-large", "Image has too many pixels",
            f"the image is {h.width_px}x{h.height_px} = {h.pixels} pixels, more than the limit of "
            f"{max_pixels}; downscale it (the network runs at a few hundred pixels wide anyway).",
        )
    if max_decoded_bytes is not None and h.decoded_bytes > max_decoded_bytes:
        raise RequestProblem(
            413, "image-too-large", "Image has too many pixels",
            f"the image header declares {h.width_px}x{h.height_px} pixels x {h.channels} channels x "
            f"{8 * h.bytes_per_sample} bits = {h.decoded_bytes} bytes decoded, more than the limit "
            f"of {max_decoded_bytes} bytes; send it as 8-bit gray (the network's input) or "
            "downscale it.",
        )
    return h


#: JPEG scale-down factor -> OpenCV flag (libjpeg scales in the DCT: it never touches the
#: full-resolution pixels, so a 1/2 decode costs about a third of a full one)
_JPEG_REDUCED = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4}


def jpeg_reduction(header: ImageHeader, min_size_px: tuple[int, int]) -> int:
    """1, 2 or 4: the largest JPEG decode scale-down that keeps the image at least
    ``min_size_px`` = (width, height) (the network's input) in both directions; 8-bit only."""
    if header.bytes_per_sample != 1:
        return 1
    for factor in (4, 2):
        if header.width_px >= factor * min_size_px[0] and header.height_px >= factor * min_size_px[1]:
            return factor
    return 1


def _pgm_pixels(data: bytes, header: ImageHeader) -> np.ndarray:
    """The (H, W) uint8 raster of a checked PGM (maxval other than 255 rescaled to 0..255)."""
    n = header.pixels * header.bytes_per_sample
    raster = memoryview(data)[header.raster_offset : header.raster_offset + n]
    if len(raster) < n:
        raise _undecodable(
            f"the PGM raster has {len(raster)} bytes where its header ({header.width_px}x"
            f"{header.height_px}, maxval {header.max_value}) needs {n}; send the complete file."
        )
    dtype = np.uint8 if header.bytes_per_sample == 1 else np.dtype(">u2")
    pixels = np.frombuffer(raster, dtype=dtype).reshape(header.height_px, header.width_px)
    if header.max_value == 255:
        return pixels.copy()  # own the pixels: the upload's buffer is freed after decoding
    scaled = (pixels.astype(np.uint32) * 255 + header.max_value // 2) // header.max_value
    return np.minimum(scaled, 255).astype(np.uint8)


def decode_gray(
    data: bytes, media_type: str, max_pixels: int, max_decoded_bytes: int | None = None,
    min_size_px: tuple[int, int] | None = None,
) -> tuple[np.ndarray, tuple[int, int]]:
    """Decode PNG/JPEG/PGM ``data`` straight to ``(H, W)`` uint8 gray; also return the uploaded
    image's (width, height) upright (the decoder applies the JPEG EXIF orientation).

    Args:
        data: the encoded file.
        media_type: ``"image/png"``, ``"image/jpeg"`` or :data:`PGM_MEDIA_TYPE` (see
            :func:`normalise_media_type`).
        max_pixels: largest accepted ``width * height``.
        max_decoded_bytes: largest decoded raster, bytes (see :func:`check_header`).
        min_size_px: (width, height) the image is going to be resized to (the network input).
            A JPEG at least 2x / 4x that size is decoded at 1/2 / 1/4 resolution
            (:func:`jpeg_reduction`); the size returned is still the uploaded one. PNG has no
            such shortcut and is always decoded in full.

    Raises:
        RequestProblem: 400 for empty, garbage, truncated or mismatched data; 413 when the
            header announces more than ``max_pixels`` pixels or ``max_decoded_bytes`` bytes.
    """
    header = check_header(data, media_type, max_pixels, max_decoded_bytes)
    if media_type == PGM_MEDIA_TYPE:
        image = _pgm_pixels(data, header)
        if image.shape[0] < 2 or image.shape[1] < 2:
            raise _undecodable(f"the image is {image.shape[1]}x{image.shape[0]} pixels; send at least 2x2.")
        return image, (header.width_px, header.height_px)
    factor = jpeg_reduction(header, min_size_px) if media_type == "image/jpeg" and min_size_px else 1
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), _JPEG_REDUCED[factor])
    if image is None or image.size == 0:
        raise _undecodable(
            f"the {media_type} body could not be decoded (truncated or corrupt); "
            "re-encode the image and send the complete file."
        )
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise _undecodable(f"the image is {image.shape[1]}x{image.shape[0]} pixels; send at least 2x2.")
    height_px, width_px = image.shape
    if factor > 1:  # the uploaded size, oriented like the decoded image
        width_px, height_px = header.width_px, header.height_px
        if image.shape != (-(-height_px // factor), -(-width_px // factor)):
            width_px, height_px = height_px, width_px
    return image, (int(width_px), int(height_px))


def decode_image(
    data: bytes, media_type: str, max_pixels: int, max_decoded_bytes: int | None = None
) -> np.ndarray:
    """Decode PNG/JPEG/PGM ``data`` into a full-resolution ``(H, W)`` uint8 gray array (see
    :func:`decode_gray` for the arguments and errors)."""
    return decode_gray(data, media_type, max_pixels, max_decoded_bytes)[0]
