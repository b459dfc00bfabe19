"""Parse the batch endpoint's ``multipart/form-data`` body, as it streams in, into image uploads.

Every part named ``images`` is an image, with or without a ``filename`` (generated clients
often omit it); its own ``Content-Type`` says PNG or JPEG. Other parts are ignored and their
bytes dropped as they arrive. Each image part is judged while it streams: more than
``max_part_bytes`` is refused (413) at the byte that crosses the limit, a wrong type (415) as
soon as its headers end, a header declaring too many pixels or decoded bytes (413) as soon as the
part ends — never after the whole batch has been buffered.
"""

from __future__ import annotations

import contextlib
import logging

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from .bodies import too_large
from .errors import RequestProblem
from .imaging import check_header, normalise_media_type
from .pipeline import Upload

log = logging.getLogger(__name__)

IMAGES_FIELD = "images"
MAX_OTHER_PARTS = 32


def _bad(detail: str) -> RequestProblem:
    return RequestProblem(
        400, "bad-multipart", "Malformed multipart body",
        f"{detail}; send multipart/form-data with one part per image, each named 'images' "
        "(e.g. curl -F images=@a.png -F images=@b.png).",
    )


def _too_many(max_images: int) -> RequestProblem:
    return RequestProblem(
        413, "too-many-images", "Too many images in one batch",
        f"a batch holds at most {max_images} images; split the request.",
    )


def boundary_of(content_type: str) -> bytes:
    """The ``boundary`` parameter of a multipart ``Content-Type``.

    Raises:
        RequestProblem: 400 when there is none.
    """
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise _bad("the Content-Type has no boundary parameter")
    return boundary


class _Part:
    __slots__ = ("headers", "data", "media_type", "index")

    def __init__(self) -> None:
        self.headers: dict[str, str] = {}
        self.data = bytearray()
        self.media_type: str | None = None  # set once the headers say it is an image
        self.index = -1


class BatchParser:
    """Feed body chunks with :meth:`write`, then :meth:`finish` for the uploads in order.

    Args:
        content_type: the request's ``Content-Type`` (must carry a boundary).
        max_images: most ``images`` parts accepted.
        max_part_bytes: largest image part (the single-image endpoint's body limit).
        max_pixels / max_decoded_bytes: image header limits (see
            :func:`metricslam_depth.imaging.check_header`).

    Raises (from :meth:`write` and :meth:`finish`):
        RequestProblem: 400 malformed, 413 too many images / part too large / image too large,
            415 a part is not PNG/JPEG, 422 no ``images`` part.
    """

    def __init__(
        self, content_type: str, max_images: int, max_part_bytes: int, max_pixels: int,
        max_decoded_bytes: int,
    ) -> None:
        self._max_images = max_images
        self._max_part_bytes = max_part_bytes
        self._max_pixels = max_pixels
        self._max_decoded_bytes = max_decoded_bytes
        self._parts = 0
        self._part: _Part | None = None
        self._uploads: list[Upload] = []
        self._header_name: list[bytes] = []
        self._header_value: list[bytes] = []
        self._parser = MultipartParser(
            boundary_of(content_type),
            {
                "on_part_begin": self._on_part_begin,
                "on_header_field": lambda d, s, e: self._header_name.append(d[s:e]),
                "on_header_value": lambda d, s, e: self._header_value.append(d[s:e]),
                "on_header_end": self._on_header_end,
                "on_headers_finished": self._on_headers_finished,
                "on_part_data": self._on_part_data,
                "on_part_end": self._on_part_end,
            },
        )

    def write(self, chunk: bytes) -> None:
        """Parse the next chunk of the body."""
        try:
            self._parser.write(chunk)
        except MultipartParseError as exc:
            log.info("malformed multipart body: %s", exc)
            raise _bad("the multipart body is malformed") from None

    def finish(self) -> list[Upload]:
        """The image uploads, in body order (call once the whole body was written)."""
        try:
            self._parser.finalize()
        except MultipartParseError as exc:
            log.info("malformed multipart body: %s", exc)
            raise _bad("the multipart body is malformed") from None
        if not self._uploads:
            raise RequestProblem(
                422, "invalid-parameter", "Invalid request parameter",
                "the batch has no parts named 'images' (or the body ended before the first part); "
                "add one part per image named 'images'.",
            )
        return self._uploads

    def discard(self) -> None:
        """Free the bytes of every part now (the request is over, whatever still references it)."""
        buffers = [u.data for u in self._uploads] + ([self._part.data] if self._part else [])
        for data in buffers:
            if isinstance(data, bytearray):
                with contextlib.suppress(BufferError):  # still exported to a decoder: GC frees it
                    data.clear()

    # ----- parser callbacks -----

    def _on_part_begin(self) -> None:
        self._parts += 1
        if self._parts > self._max_images + MAX_OTHER_PARTS:
            raise RequestProblem(
                413, "too-many-images", "Too many images in one batch",
                f"the body has more than {self._max_images + MAX_OTHER_PARTS} parts; a batch holds "
                f"at most {self._max_images} images, split the request.",
            )
        self._part = _Part()

    def _on_header_end(self) -> None:
        assert self._part is not None
        name = b"".join(self._header_name).decode("latin-1").strip().lower()
        self._part.headers[name] = b"".join(self._header_value).decode("latin-1").strip()
        self._header_name.clear()
        self._header_value.clear()

    def _on_headers_finished(self) -> None:
        part = self._part
        assert part is not None
        _, disposition = parse_options_header(part.headers.get("content-disposition", ""))
        if disposition.get(b"name", b"").decode("latin-1") != IMAGES_FIELD:
            return
        part.index = len(self._uploads)
        if part.index >= self._max_images:
            raise _too_many(self._max_images)
        try:
            part.media_type = normalise_media_type(part.headers.get("content-type"))
        except RequestProblem as exc:
            exc.detail = (
                f"images[{part.index}]: {exc.detail} (set it on the part, e.g. curl -F "
                "'images=@a.png;type=image/png')"
            )
            raise

    def _on_part_data(self, data: bytes, start: int, end: int) -> None:
        part = self._part
        if part is None or part.media_type is None:
            return  # not an image: dropped as it arrives
        if len(part.data) + (end - start) > self._max_part_bytes:
            raise too_large(self._max_part_bytes, f"image part images[{part.index}]")
        part.data += data[start:end]

    def _on_part_end(self) -> None:
        part, self._part = self._part, None
        if part is None or part.media_type is None:
            return
        try:
            check_header(part.data, part.media_type, self._max_pixels, self._max_decoded_bytes)
        except RequestProblem as exc:
            exc.detail = f"image {part.index}: {exc.detail}"
            raise
        self._uploads.append(Upload(part.data, part.media_type))
