"""A provisional metric scale at VO initialization, so a live stream is metric from its first pose.

Without it the monocular VO publishes poses in its arbitrary initialization unit until the global
graph has learned scale factors (on KITTI 06: 26 of 51 live poses, then a 20 m jump). Here, when
the VO first has a map, the initial keyframe's image goes to the back end's depth source once
(bounded wait); the robust median of ``ξ_j / z_j`` over the initialization's landmarks — the
same measurements and Huber M-estimate the graph's per-keyframe scale factors use
(:func:`~metricslam.slam.graph.scale_factor.scale_measurements`,
:func:`~metricslam.slam.graph.scale_factor.robust_log_scale`) — is the metres per VO unit that
the pipeline applies to the VO as a pure-scale warp before any keyframe reaches the graph. The
graph's scale factors then refine it as before. Docs: ``docs/global_graph.md``, "Metric from the
first pose".

The estimate is the pipeline's, not the estimator's: it is applied before the first keyframe is
marginalized, so the back end simply receives keyframes in (provisionally) metric units.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from metricslam.camera import PinholeCamera
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.scale_factor import robust_log_scale, scale_measurements


class InitialScaleConfig(BaseModel):
    """The initial scale step (:mod:`metricslam.slam.initial_scale`).

    Off by default, so offline runs (``metricslam run``, ``--deterministic`` golden trajectories)
    are unchanged; the live SLAM service turns it on (:data:`~metricslam.slam.system_config.LIVE_PROFILE`).

    Attributes:
        enabled: ask the depth source for the initial keyframe's depth when the VO first has a map.
        timeout_s: longest wait for that answer (the tracking thread waits; frames queue up).
        min_landmarks: fewer usable measurements than this give no initial scale.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = False
    timeout_s: float = Field(default=2.0, gt=0, le=60)
    min_landmarks: int = Field(default=8, ge=1)


@dataclass(frozen=True)
class InitialScale:
    """The outcome of one attempt.

    Attributes:
        frame_index: the keyframe whose image was measured (the VO's initialization reference).
        scale: metres per VO unit (the warp's scale), or None when there is no estimate.
        n_landmarks: usable measurements ``ξ_j / z_j``.
        wait_ms: time spent waiting for the depth source.
        error: why there is no estimate ("" when there is one).
    """

    frame_index: int
    scale: float | None
    n_landmarks: int
    wait_ms: float
    error: str = ""

    def as_dict(self) -> dict:
        """JSON-ready (``run --json``, the service's status)."""
        return {"frame_index": self.frame_index, "scale": self.scale, "n_landmarks": self.n_landmarks,
                "wait_ms": self.wait_ms, "error": self.error}


def measure_initial_scale(depth_source: object, image: np.ndarray, camera: PinholeCamera,
                          landmarks_uv_px: np.ndarray, landmarks_inv_depth: np.ndarray,
                          frame_index: int, config: InitialScaleConfig,
                          graph_config: GraphConfig) -> InitialScale:
    """Metres per VO unit from one keyframe: Huber M-estimate of ``ξ_j / z_j`` at its landmarks.

    Args:
        depth_source: a :class:`~metricslam.slam.depth_source.DepthSource`; one that reports
            ``reachable is False`` (the HTTP client after a failed probe) is not waited for.
        image: (H, W) uint8 keyframe image.
        camera: its intrinsics.
        landmarks_uv_px: (M, 2) landmark pixels in ``image``.
        landmarks_inv_depth: (M,) their VO inverse depths ξ_j (1 / VO units).
        frame_index: the keyframe's input frame (reported back).
        config: timeout and minimum landmark count.
        graph_config: the scale-factor filters and Huber parameters the graph uses.

    Never raises: a failure, a timeout or too few landmarks give ``scale=None`` and ``error``.
    """
    uv = np.asarray(landmarks_uv_px, dtype=float).reshape(-1, 2)
    xi = np.asarray(landmarks_inv_depth, dtype=float).reshape(-1)
    if depth_source is None:
        return InitialScale(frame_index, None, 0, 0.0, "no depth source")
    if getattr(depth_source, "reachable", None) is False:
        return InitialScale(frame_index, None, 0, 0.0, "depth source unreachable: "
                            f"{getattr(depth_source, 'last_error', None) or 'no answer'}")
    if len(xi) < config.min_landmarks:
        return InitialScale(frame_index, None, len(xi), 0.0,
                            f"{len(xi)} initial landmarks < min_landmarks {config.min_landmarks}")
    t0 = time.perf_counter()
    answer, error = ask_depth(depth_source, image, camera, config.timeout_s)
    wait_ms = 1e3 * (time.perf_counter() - t0)
    if answer is None:
        return InitialScale(frame_index, None, 0, wait_ms, error)
    from metricslam.depth.sample import sample_map  # the depth package loads onnxruntime

    size = (int(image.shape[1]), int(image.shape[0]))
    try:
        z = sample_map(answer, uv, size)
    except Exception as exc:  # noqa: BLE001 -- a foreign source's odd answer must not stop tracking
        return InitialScale(frame_index, None, 0, wait_ms, f"unusable depth map: {exc}")
    scales = scale_measurements(xi, z, graph_config)
    if scales.size < config.min_landmarks:
        return InitialScale(frame_index, None, int(scales.size), wait_ms,
                            f"{scales.size} usable measurements < min_landmarks {config.min_landmarks}")
    log_s, _ = robust_log_scale(scales, graph_config.scale_sigma_log, graph_config.scale_huber_k)
    return InitialScale(frame_index, float(np.exp(log_s)), int(scales.size), wait_ms)


def ask_depth(depth_source: object, image: np.ndarray, camera: PinholeCamera,
                      timeout_s: float) -> tuple[np.ndarray | None, str]:
    """``depth_source``'s answer for ``image``: ``(inverse-depth map (h, w) 1/m, "")`` or
    ``(None, why)``; gives up after ``timeout_s`` (the request then finishes on its own daemon
    thread and is discarded). Never raises: the caller is the tracking thread."""
    result: dict = {}

    def ask() -> None:
        try:
            result["map"] = np.asarray(depth_source.inv_depth_map(image, camera), dtype=np.float32)
        except Exception as exc:  # noqa: BLE001 -- reported, never raised into tracking
            result["error"] = f"{type(exc).__name__}: {exc}"

    worker = threading.Thread(target=ask, name="initial-scale", daemon=True)
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        return None, f"no depth answer within {timeout_s:g} s (initial_scale.timeout_s)"
    if "error" in result:
        return None, result["error"]
    return result["map"], ""
