"""Run the depth service under uvicorn (used by ``metricslam depth-service`` and ``python -m``)."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import resource

from metricslam.errors import ConfigError

from .settings import DepthServiceSettings

log = logging.getLogger(__name__)


def serve(settings: DepthServiceSettings) -> None:
    """Serve until interrupted (SIGINT/SIGTERM shut down gracefully).

    Raises:
        ConfigError: the model file given in the settings does not exist.
    """
    import uvicorn

    from .app import create_app

    if settings.model_path is not None and not settings.model_path.is_file():
        raise ConfigError(
            f"depth model {settings.model_path} does not exist: pass --model PATH (or "
            "DEPTH_MODEL_PATH) pointing at an ONNX file exported by metricslam, or leave it unset "
            "for the shipped int8 model"
        )
    from .connections import ConnectionLimits, GuardedHttpProtocol, IdleConnections

    _raise_open_files_limit(settings.max_connections)
    _return_large_buffers_to_os()
    limits = ConnectionLimits(
        max_connections=settings.max_connections,
        header_timeout_s=settings.header_timeout_s,
        max_header_bytes=settings.max_header_bytes,
        retry_after_s=settings.retry_after_s,
    )
    config = uvicorn.Config(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        access_log=settings.access_log,
        # connections and requests are capped by GuardedHttpProtocol and InflightLimit instead:
        # uvicorn's limit_concurrency counts idle connections, so idle sockets could starve it
        http=functools.partial(GuardedHttpProtocol, limits=limits, idle=IdleConnections()),  # type: ignore[arg-type]
        limit_concurrency=None,
        timeout_keep_alive=settings.keep_alive_timeout_s,  # type: ignore[arg-type]
        timeout_graceful_shutdown=10,
    )
    log.info("depth service listening on http://%s:%d", settings.host, settings.port)
    uvicorn.Server(config).run()


def _raise_open_files_limit(max_connections: int) -> None:
    """Raise the soft open-files limit so ``max_connections`` sockets (plus room for a few
    more being accepted and closed, model and log files) fit; the hard limit is left alone."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    wanted = 2 * max_connections + 256
    if soft != resource.RLIM_INFINITY and soft < wanted:
        new = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))
        if new < wanted:
            log.warning("open-files limit %d is below the %d that max_connections=%d wants; "
                        "lower DEPTH_MAX_CONNECTIONS or raise `ulimit -n`", new, wanted, max_connections)


# glibc mallopt parameter; the value is the one in <malloc.h>
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD_BYTES = 256 * 1024


def _return_large_buffers_to_os() -> None:
    """Serve every allocation over 256 KiB (bodies, image parts, decoded images) from its own
    mmap, returned to the OS when freed.

    glibc otherwise raises its mmap threshold to the size of the largest buffer freed (up to
    32 MiB), after which 8 MiB image buffers come from the heap, fragment it and stay resident:
    the upload memory budget would bound what requests hold but not what the process keeps.
    A no-op where the C library is not glibc.
    """
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        if libc is None or not libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_BYTES):
            log.info("mallopt unavailable; large buffers follow the C library's default policy")
    except (OSError, AttributeError):
        log.info("mallopt unavailable; large buffers follow the C library's default policy")
