"""Parse the batch endpoint's ``multipart/form-data`` body into image uploads.

Every part named ``images`` is an image, with or without a ``filename`` (generated clients
often omit it); its own ``Content-Type`` says PNG or JPEG. Other parts are ignored. Parsing
is done in memory on an already size-limited body with python-multipart's streaming parser.
"""

from __future__ import annotations

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from .errors import RequestProblem
from .imaging import normalise_media_type
from .pipeline import Upload

IMAGES_FIELD = "images"
MAX_OTHER_PARTS = 32


def _bad(detail: str) -> RequestProblem:
    return RequestProblem(
        400, "bad-multipart", "Malformed multipart body",
        f"{detail}; send multipart/form-data with one part per image, each named 'images' "
        "(e.g. curl -F images=@a.png -F images=@b.png).",
    )


class _Part:
    __slots__ = ("headers", "chunks")

    def __init__(self) -> None:
        self.headers: dict[str, str] = {}
        self.chunks: list[bytes] = []


def parse_batch(content_type: str, body: bytes, max_images: int) -> list[Upload]:
    """Image uploads of a multipart body, in order.

    Args:
        content_type: the request's ``Content-Type`` (must carry a boundary).
        body: the whole (already size-limited) body.
        max_images: most ``images`` parts accepted.

    Raises:
        RequestProblem: 400 malformed, 413 too many images, 415 a part is not PNG/JPEG,
            422 no ``images`` part.
    """
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise _bad("the Content-Type has no boundary parameter")
    parts: list[_Part] = []
    header_name: list[bytes] = []
    header_value: list[bytes] = []

    def on_part_begin() -> None:
        if len(parts) >= max_images + MAX_OTHER_PARTS:
            raise RequestProblem(
                413, "too-many-images", "Too many images in one batch",
                f"the body has more than {max_images + MAX_OTHER_PARTS} parts; a batch holds at "
                f"most {max_images} images, split the request.",
            )
        parts.append(_Part())

    def on_header_field(data: bytes, start: int, end: int) -> None:
        header_name.append(data[start:end])

    def on_header_value(data: bytes, start: int, end: int) -> None:
        header_value.append(data[start:end])

    def on_header_end() -> None:
        name = b"".join(header_name).decode("latin-1").strip().lower()
        parts[-1].headers[name] = b"".join(header_value).decode("latin-1").strip()
        header_name.clear()
        header_value.clear()

    def on_part_data(data: bytes, start: int, end: int) -> None:
        parts[-1].chunks.append(data[start:end])

    parser = MultipartParser(
        boundary,
        {
            "on_part_begin": on_part_begin,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_part_data": on_part_data,
        },
    )
    try:
        parser.write(body)
        parser.finalize()
    except MultipartParseError as exc:
        raise _bad(f"the multipart body is malformed ({exc})") from exc
    return _images(parts, max_images)


def _images(parts: list[_Part], max_images: int) -> list[Upload]:
    uploads: list[Upload] = []
    for part in parts:
        _, disposition = parse_options_header(part.headers.get("content-disposition", ""))
        if disposition.get(b"name", b"").decode("latin-1") != IMAGES_FIELD:
            continue
        index = len(uploads)
        if index >= max_images:
            raise RequestProblem(
                413, "too-many-images", "Too many images in one batch",
                f"a batch holds at most {max_images} images; split the request.",
            )
        try:
            media_type = normalise_media_type(part.headers.get("content-type"))
        except RequestProblem as exc:
            exc.detail = f"images[{index}]: {exc.detail} (set it on the part, e.g. curl -F 'images=@a.png;type=image/png')"
            raise
        uploads.append(Upload(b"".join(part.chunks), media_type))
    if not uploads:
        raise RequestProblem(
            422, "invalid-parameter", "Invalid request parameter",
            "the batch has no parts named 'images' (or the body ended before the first part); "
            "add one part per image named 'images'.",
        )
    return uploads
