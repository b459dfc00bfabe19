"""One root exception for the whole project, one subclass per domain.

Every message says what went wrong *and what to do about it*. Catch
:class:`MetricSlamError` at service and CLI boundaries; never let one kill a loop.
"""

from __future__ import annotations


class MetricSlamError(Exception):
    """Root of every error metricslam raises on purpose."""


class ConfigError(MetricSlamError):
    """An algorithm config or service setting is invalid."""


class GeometryError(MetricSlamError):
    """Invalid input to a geometry helper (wrong shape, not a rotation, ...)."""


class AlignmentError(GeometryError):
    """Trajectory alignment is degenerate (too few or collinear points)."""


class CameraError(MetricSlamError):
    """Invalid camera intrinsics or calibration."""


class DatasetError(MetricSlamError):
    """A dataset file is missing or malformed.

    Args:
        message: what was expected.
        path: the offending file, if any.
        line: 1-based line number in that file, if known.
    """

    def __init__(self, message: str, path: object = None, line: int | None = None) -> None:
        self.path = None if path is None else str(path)
        self.line = line
        where = ""
        if self.path is not None:
            where = f"{self.path}"
            if line is not None:
                where += f":{line}"
            where += ": "
        super().__init__(f"{where}{message}")


class CalibrationError(DatasetError):
    """A calibration file is missing or malformed."""


class TrajectoryError(DatasetError):
    """A trajectory file is missing or malformed, or two trajectories do not match."""


class EvaluationError(MetricSlamError):
    """The evaluator cannot compute a metric for the given trajectories."""


class DepthModelError(MetricSlamError):
    """The depth model file is missing, or its metadata does not match the code."""


class DepthSourceError(MetricSlamError):
    """A depth source (in-process model or HTTP service) failed to answer."""


class ImageError(MetricSlamError):
    """An image could not be decoded or has an unsupported shape/dtype."""


class GraphError(MetricSlamError):
    """The global pose graph rejected an input or failed to solve."""


class ScaleError(MetricSlamError):
    """A run asked for learned metric scale and never got it (its trajectory is not metric)."""


class CodecError(MetricSlamError):
    """A wire message could not be encoded or decoded."""


class SynthError(MetricSlamError):
    """The synthetic world generator got invalid parameters."""


class ServiceError(MetricSlamError):
    """A service could not start or a child process failed."""


class TrainingError(MetricSlamError):
    """Training configuration or data is invalid."""


class MapError(MetricSlamError):
    """A saved map (docs/maps.md) is missing, corrupt, of another schema version, or does not
    fit this session (another camera, another depth model); or it cannot be written."""


def validation_problems(exc: Exception, env_prefix: str | None = None,
                        from_flags: object = ()) -> str:
    """One line naming each problem of a pydantic ``ValidationError`` (or any error with an
    ``errors()`` method): ``field: message (got 'value')``, joined with ``; ``.

    pydantic's own ``str(exc)`` spans several lines and ends each with a documentation URL;
    this is what goes into a :class:`MetricSlamError` message instead, so the CLI prints one
    line. Duck-typed: this module imports no pydantic.

    Args:
        exc: the validation error.
        env_prefix: settings read from the environment (``"SLAM_"``, ``"DEPTH_"``): each field
            also names its variable, e.g. ``max_cameras (env SLAM_MAX_CAMERAS)``.
        from_flags: field names whose value came from the command line, not the environment
            (named ``(command line)`` instead).
    """
    errors = getattr(exc, "errors", None)
    if errors is None:
        return str(exc)
    try:
        details = errors(include_url=False)
    except TypeError:
        details = errors()
    problems = []
    for err in details:
        loc = [str(p) for p in err.get("loc", ())]
        msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
        if not loc:
            problems.append(msg)
            continue
        where = ".".join(loc)
        if loc[0] in set(from_flags):
            where += " (command line)"
        elif env_prefix:
            where += f" (env {env_prefix}{'__'.join(loc).upper()})"
        got = err.get("input")
        shown = "" if err.get("type") == "missing" or isinstance(got, dict) else f" (got {got!r})"
        problems.append(f"{where}: {msg}{shown}")
    return "; ".join(problems) or str(exc).splitlines()[0]
