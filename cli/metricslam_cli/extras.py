"""Which optional extra (pyproject.toml) each component needs, checked before a command imports it.

A bare ``pip install metricslam`` is the core and ``metricslam run``; the services, the renderer
and the plots are extras. A command that needs one checks for it first, so a missing extra is a
one-line error naming it instead of a ``ModuleNotFoundError`` traceback::

    require("slam-service", command="replay")
"""

from __future__ import annotations

import importlib.util

from metricslam.errors import ConfigError

#: extra -> the modules it provides (import names, not distribution names)
EXTRAS: dict[str, tuple[str, ...]] = {
    "depth-service": ("fastapi", "uvicorn", "python_multipart", "prometheus_client", "pydantic_settings"),
    "slam-service": ("zenoh", "httpx", "pydantic_settings"),
    "synth": ("numba", "skimage"),
    "plots": ("matplotlib",),
}


def require(*extras: str, command: str) -> None:
    """Raise :class:`~metricslam.errors.ConfigError` naming every extra whose modules are missing.

    Args:
        extras: keys of :data:`EXTRAS`.
        command: the subcommand, for the message (``metricslam <command> needs ...``).
    """
    missing = {extra: [m for m in EXTRAS[extra] if not _installed(m)] for extra in extras}
    missing = {extra: mods for extra, mods in missing.items() if mods}
    if missing:
        names = ",".join(missing)
        what = "; ".join(f"{extra}: {', '.join(mods)}" for extra, mods in missing.items())
        raise ConfigError(f"metricslam {command} needs the {names} extra ({what} not installed): "
                          f"pip install 'metricslam[{names}]' (or pip install -e '.[{names}]' in a checkout)")


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a broken or half-installed package counts as missing
        return False
