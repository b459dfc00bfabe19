"""``HttpDepthSource``: the depth service over HTTP, as a :class:`metricslam.slam.depth_source.DepthSource`.

``inv_depth_map(image, camera)`` sends the keyframe's gray pixels as a binary PGM (no compression:
the service copies them instead of inflating a PNG, and this side skips a ~5 ms PNG encode per
keyframe; a depth service too old to know PGM answers 415 once and gets PNG from then on). For a
contract-version-1 model (the whole image resized to the network input, learnt from ``GET
/v1/model`` once per served model) it first resizes the image to that input itself, with the
service's own ``INTER_AREA`` and the intrinsics scaled to match: the network sees the very same
input (``d_frac`` bit-identical) while the upload shrinks ~3.5x and the service skips its resize.
It ``POST``s it to
``{url}/v1/disparity?fx=<fx_px>&fy=<fy_px>&cx=<cx_px>&cy=<cy_px>`` (``Accept: application/x-npy``)
and returns the service's metric inverse depth (h, w) float32 (1/m) for that camera, covering the
whole image; NaN in cells outside a canonical-camera (contract version 2) model's field of view. Connection failures, timeouts and 5xx/429 are
retried a bounded number of times with a short backoff, then :class:`DepthSourceError` is raised —
the global back end treats that as "no scale factor for this keyframe" and tracking goes on. So is
an answer the service flags ``valid: false`` (``X-Valid: 0``: a flat image, no depth to read;
counted in ``requests_invalid``): its plausible-looking map never becomes a scale factor.
``reachable`` (None until first use), ``last_error`` and ``outages`` (times it went from not
known-bad to unreachable) say whether the service answers; the SLAM service probes once at start
(:meth:`probe`, ``GET /readyz``), reports them on ``…/status`` and probes periodically so the
status recovers as soon as the depth service is back. A change of state is logged once (an
error when it is lost: no learned scale until it answers), never once per request.
"""

from __future__ import annotations

import io
import logging
import threading
import time

import cv2
import httpx
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.depth.contract import PGM_MEDIA_TYPE, ModelContract
from metricslam.depth.model import to_gray_u8
from metricslam.errors import DepthSourceError

log = logging.getLogger(__name__)
_RETRY_STATUS = {429, 502, 503, 504}


class HttpDepthSource:
    """Client of the depth service. Thread-safe (one pooled ``httpx.Client``).

    Args:
        url: base URL, e.g. ``http://127.0.0.1:8100``.
        timeout_s: read timeout of one request (s).
        connect_timeout_s: connect timeout (s); short, so a dead service is noticed fast.
        retries: extra attempts after the first for connection errors, timeouts, 429/5xx.
        backoff_s: sleep before retry k is ``backoff_s * 2**k``.
        down_timeout_s: while the service is known to be unreachable (the last request or probe
            failed), a keyframe gets ONE attempt with this read timeout instead of ``retries + 1``
            attempts of ``timeout_s``: a frozen service (SIGSTOP: it still accepts connections) cost
            ~15.6 s per keyframe before, and the back end's keyframe-ordered work queued behind it
            (bench/results/stack_faults_depth_stop.md). The periodic probe marks it reachable again.
    """

    def __init__(self, url: str, timeout_s: float = 5.0, connect_timeout_s: float = 0.5,
                 retries: int = 2, backoff_s: float = 0.2, down_timeout_s: float = 0.5) -> None:
        self.url = url.rstrip("/")
        self.down_timeout_s = float(down_timeout_s)
        self._connect_timeout_s = float(connect_timeout_s)
        self.retries = int(retries)
        self.backoff_s = float(backoff_s)
        self._client = httpx.Client(base_url=self.url, timeout=httpx.Timeout(
            timeout_s, connect=connect_timeout_s))
        self._media = PGM_MEDIA_TYPE
        self._input_size: tuple[int, int] | None = None  # (w, h) a v1 model resizes every image to
        self._input_model_id: str | None = None
        self._lock = threading.Lock()
        self._reachable: bool | None = None
        self._last_error: str | None = None
        self.requests_ok = 0
        self.requests_failed = 0
        self.requests_invalid = 0  # answered, but flagged ``valid: false`` (X-Valid: 0)
        self.outages = 0

    # -- state -------------------------------------------------------------------------------
    @property
    def reachable(self) -> bool | None:
        """True after a successful request/probe, False after a failed one, None before any."""
        return self._reachable

    @property
    def last_error(self) -> str | None:
        return self._last_error

    @property
    def upload_size_px(self) -> tuple[int, int] | None:
        """(width, height) larger keyframes are resized to before upload (a version-1 model's
        input), or None while they go as they are (version 2, or the contract not known yet)."""
        return self._input_size if self._input_size and self._input_size != (0, 0) else None

    def _mark(self, ok: bool, error: str | None = None) -> None:
        with self._lock:
            if ok and self._reachable is False:
                log.warning("depth service at %s is reachable again: learned scale factors resume",
                            self.url)
            if not ok and self._reachable is not False:
                self.outages += 1
                log.error("depth service at %s is NOT reachable (%s): keyframes get NO learned "
                          "scale factors until it answers; start it (`metricslam depth-service`) "
                          "or point SLAM_DEPTH_URL / --depth-url at it", self.url, error)
            self._reachable = ok
            self._last_error = None if ok else error

    # -- API ---------------------------------------------------------------------------------
    def probe(self, timeout_s: float = 1.0) -> bool:
        """``GET /readyz``; updates and returns :attr:`reachable`."""
        try:
            ok = self._client.get("/readyz", timeout=timeout_s).status_code == 200
            self._mark(ok, None if ok else "/readyz is not 200 (model not loaded yet?)")
        except httpx.HTTPError as exc:
            self._mark(False, f"{type(exc).__name__}: {exc}")
        return bool(self._reachable)

    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        """Metric inverse depth (h, w) float32 in 1/m for ``image`` taken with ``camera``.

        Raises:
            DepthSourceError: the service could not be reached or answered garbage after retries.
        """
        media = self._media
        image, camera = self._as_uploaded(image, camera)
        body = encode_pgm(image) if media == PGM_MEDIA_TYPE else encode_png(image)
        params = {"fx": f"{camera.fx_px!r}", "fy": f"{camera.fy_px!r}",
                  "cx": f"{camera.cx_px!r}", "cy": f"{camera.cy_px!r}"}
        headers = {"Content-Type": media, "Accept": "application/x-npy"}
        error = "no attempt"
        down = self._reachable is False
        attempts = 1 if down else self.retries + 1
        timeout = httpx.Timeout(self.down_timeout_s, connect=self._connect_timeout_s) if down else httpx.USE_CLIENT_DEFAULT
        for attempt in range(attempts):
            if attempt:
                time.sleep(self.backoff_s * 2 ** (attempt - 1))
            try:
                response = self._client.post("/v1/disparity", params=params, content=body,
                                             headers=headers, timeout=timeout)
            except httpx.HTTPError as exc:
                error = f"{type(exc).__name__}: {exc}"
                continue
            if response.status_code in _RETRY_STATUS:
                error = f"HTTP {response.status_code}"
                continue
            if response.status_code == 415 and media == PGM_MEDIA_TYPE:
                log.warning("depth service at %s does not take PGM (an older version?): sending PNG "
                            "from now on (~5 ms more per keyframe on each side)", self.url)
                self._media = "image/png"
                return self.inv_depth_map(image, camera)
            if response.status_code != 200:
                self.requests_failed += 1
                self._mark(True)  # it answered: reachable, but refused this request
                raise DepthSourceError(f"depth service rejected the keyframe: HTTP "
                                       f"{response.status_code} {response.text[:200]}")
            inv_depth = _parse(response)
            self._mark(True)  # it answered
            if response.headers.get("x-valid", "1") == "0":
                self.requests_invalid += 1
                raise DepthSourceError("no learned scale from this keyframe: the depth service flagged "
                                       "its image invalid (flat: blank, dark or covered lens)")
            if response.headers.get("x-model-id") != self._input_model_id:
                self._input_size = None  # another model serves now: ask for its contract again
            self.requests_ok += 1
            return inv_depth
        self.requests_failed += 1
        self._mark(False, error)
        raise DepthSourceError(f"depth service at {self.url} failed after {attempts} "
                               f"attempt(s){' (known down: one short attempt)' if down else ''}: {error}; start it (`metricslam depth-service`) or "
                               "run with --no-scale")

    def close(self) -> None:
        self._client.close()

    def _as_uploaded(self, image: np.ndarray, camera: PinholeCamera) -> tuple[np.ndarray, PinholeCamera]:
        """``image`` resized to a version-1 model's input (intrinsics scaled with it), when the
        service serves one and the image is larger; else both unchanged (also until the service
        has answered once: the contract is asked for only from a service known to be up)."""
        if self._input_size is None and self._reachable:  # never an extra wait on a dead service
            self._learn_input_size()
        if not self._input_size or self._input_size == (0, 0):
            return image, camera
        width_in, height_in = self._input_size
        height_px, width_px = image.shape[:2]
        if width_px <= width_in or height_px <= height_in or (camera.width_px, camera.height_px) != (width_px, height_px):
            return image, camera
        small = camera.resized(width_in, height_in)
        # a principal point on the image's border may land half a pixel off it; a v1 model uses fx only
        small = small.model_copy(update={"cx_px": min(max(small.cx_px, 0.0), float(width_in)),
                                         "cy_px": min(max(small.cy_px, 0.0), float(height_in))})
        return cv2.resize(image, (width_in, height_in), interpolation=cv2.INTER_AREA), small

    def _learn_input_size(self) -> None:
        """``GET /v1/model``: remember a version-1 model's input size ((0, 0): send full images —
        a version-2 model warps to its canonical camera itself; None again after a failure)."""
        try:
            response = self._client.get("/v1/model", timeout=self._connect_timeout_s + 1.0)
            contract = ModelContract.model_validate(response.json()) if response.status_code == 200 else None
        except (httpx.HTTPError, ValueError):
            return
        if contract is None:
            return
        self._input_model_id = contract.model_id
        self._input_size = (0, 0) if contract.uses_canonical_camera else (contract.input_width, contract.input_height)


def encode_pgm(image: np.ndarray) -> bytes:
    """(H, W) uint8 gray or (H, W, 3) uint8 RGB -> binary (P5) PGM bytes of its gray pixels (the
    network's input kind; RGB is converted as :func:`metricslam.depth.model.to_gray_u8` does)."""
    gray = np.ascontiguousarray(to_gray_u8(image))
    height, width = gray.shape
    return b"P5\n%d %d\n255\n" % (width, height) + gray.tobytes()


def encode_png(image: np.ndarray) -> bytes:
    """The same gray pixels as :func:`encode_pgm`, PNG-encoded (fast compression level)."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(to_gray_u8(image)), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise DepthSourceError("OpenCV could not PNG-encode the keyframe image")
    return buf.tobytes()


def _parse(response: httpx.Response) -> np.ndarray:
    """``.npy`` (2, h, w) [d_frac, inv_depth_per_m] or JSON ``{"inv_depth_per_m": ...}`` -> (h, w).

    NaN (JSON ``null``) marks cells outside the network's field of view and is kept (samples
    there are dropped downstream); infinities, or a map with no finite cell, are refused."""
    try:
        if response.content[:6] == b"\x93NUMPY":
            array = np.load(io.BytesIO(response.content), allow_pickle=False)
            if array.ndim != 3 or array.shape[0] != 2:
                raise ValueError(f"expected a (2, h, w) stack, got {array.shape}")
            array = array[1]
        else:
            rows = response.json()["inv_depth_per_m"]
            array = np.asarray([[np.nan if v is None else v for v in row] for row in rows], dtype=np.float32)
    except (ValueError, KeyError, TypeError) as exc:
        raise DepthSourceError(f"depth service answered an unreadable body: {exc}") from None
    if array.ndim != 2 or array.size == 0 or np.isinf(array).any() or not np.isfinite(array).any():
        raise DepthSourceError(f"depth service answered a bad inverse-depth map, shape {array.shape} "
                               "(infinite values, or no cell in the network's field of view)")
    return array.astype(np.float32, copy=False)
