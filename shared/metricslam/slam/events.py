"""What the global back end did, as typed events (``GlobalBackend.events``).

Observers (the scale history, the Rerun view, the status publisher, benchmarks) subscribe to an
:class:`EventBus` instead of wrapping the back end's depth source or reading its private state.
Events are frozen dataclasses; their arrays are the back end's own (do not modify them).

Threading: in threaded mode :class:`ScaleMeasured` is emitted on the depth worker's thread and
the others on the graph worker's (or the tracking thread for :class:`WarpApplied` and
:class:`InitialScaleApplied`, which the pipeline emits on the back end's bus); with
``GraphConfig.inline`` everything is emitted on the caller's thread, in a deterministic order.
A subscriber must be quick and thread-safe; an exception in one is logged and never reaches the
back end (observing must not change what the system estimates).

Example::

    session = build_session(camera, config)
    session.backend.events.subscribe(lambda ev: print(ev.frame_index, len(ev.scales)),
                                     ScaleMeasured)
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScaleMeasured:
    """A keyframe's depth request was answered (or failed) and turned into scale measurements.

    Attributes:
        kf_id, frame_index, t_ns: the keyframe.
        landmarks_uv_px: (M, 2) landmark pixels in the keyframe image.
        landmarks_inv_depth: (M,) VO inverse depths ξ_j (1 / keyframe VO units).
        net_inv_depth_per_m: (M,) the depth source's metric inverse depth z_j (1/m) sampled at
            the landmarks (NaN where it could not be sampled); empty when the request failed.
        scales: (K,) the measurements ``ξ_j / z_j`` the graph receives (metres per keyframe VO
            unit), after the filters of :func:`~metricslam.slam.graph.scale_factor.scale_measurements`.
        inv_depth_map_per_m: (h, w) the answer itself (1/m), or None when the request failed.
        image_size: (width, height) px of the keyframe image.
        error: why the request failed ("" when it did not).
    """

    kf_id: int
    frame_index: int
    t_ns: int
    landmarks_uv_px: np.ndarray
    landmarks_inv_depth: np.ndarray
    net_inv_depth_per_m: np.ndarray
    scales: np.ndarray
    inv_depth_map_per_m: np.ndarray | None
    image_size: tuple[int, int]
    error: str = ""


@dataclass(frozen=True)
class GroundScaleMeasured:
    """A keyframe's road-plane scale measurement (``scale.sources`` with ``ground``;
    :mod:`metricslam.slam.ground`), accepted or not.

    Attributes:
        kf_id, frame_index, t_ns: the keyframe.
        height_vo: camera height above the road in the keyframe's VO units (NaN: no estimate).
        scale: ``h_mount_m / height_vo`` (metres per keyframe VO unit; NaN when not accepted).
        sigma_log: the factor's log-scale sigma (inf when not accepted).
        accepted: the measurement became a ground factor; ``reason`` says why not otherwise.
        inlier_fraction, normal_angle_rad: the road fit's quality (see
            :class:`~metricslam.slam.ground.height.GroundHeight`).
        prev_frame_index: the previous keyframe the road was aligned with (-1: none).
        step_vo: distance between the two keyframes in VO units (NaN: none); with a true
            distance in metres, ``height_vo · true_m / step_vo`` is the height in metres.
        source: always ``"ground"`` (the learned source's event is :class:`ScaleMeasured`).
    """

    kf_id: int
    frame_index: int
    t_ns: int
    height_vo: float
    scale: float
    sigma_log: float
    accepted: bool
    reason: str = ""
    inlier_fraction: float = 0.0
    normal_angle_rad: float = 0.0
    prev_frame_index: int = -1
    step_vo: float = float("nan")
    source: str = "ground"


@dataclass(frozen=True)
class ScaleHealthUpdated:
    """A keyframe's scale measurements as the scale-health observer holds them, after one of them
    arrived (:class:`~metricslam.slam.ground.health.ScaleHealth`; emitted on the thread of the
    measurement that arrived, right after it). The recordings log it (``run --rerun/--mcap``).

    Attributes:
        kf_id, frame_index, t_ns: the keyframe.
        learned_scale: the learned source's robust estimate (metres per keyframe VO unit; NaN:
            none yet or none used).
        ground_scale: the accepted road-plane measurement (same units; NaN: none).
        disagreement_log: ``log(learned / ground)`` (NaN unless both are known).
        warning: the scale-health flag after this keyframe (the sources disagree).
        learned_spread_log: standard deviation of log learned scale over the last
            ``ScaleHealthConfig.window`` keyframes (NaN under 2).
    """

    kf_id: int
    frame_index: int
    t_ns: int
    learned_scale: float
    ground_scale: float
    disagreement_log: float
    warning: bool
    learned_spread_log: float = float("nan")


#: the numbers of one keyframe's scale record as the recordings name them (:func:`scale_record`)
SCALE_RECORD_VALUES = ("learned", "ground", "disagreement_log", "learned_spread_log", "sigma_log")


def scale_record(ev: ScaleHealthUpdated, backend: object = None) -> dict[str, float | None]:
    """One keyframe's scale record for a recording (keys :data:`SCALE_RECORD_VALUES`): the
    event's numbers — learned and ground scale (m per keyframe VO unit), ``log(learned /
    ground)``, the learned spread — and ``sigma_log``, the back end's σ of the newest solved
    keyframe's log scale as it stands now (``backend.scale_sigma_log()``; None when unknown)."""
    sigma_of = getattr(backend, "scale_sigma_log", None)
    return {"learned": ev.learned_scale, "ground": ev.ground_scale, "disagreement_log": ev.disagreement_log,
            "learned_spread_log": ev.learned_spread_log, "sigma_log": sigma_of() if callable(sigma_of) else None}


@dataclass(frozen=True)
class Solved:
    """One incremental solve of the global graph finished.

    Attributes:
        n_keyframes, n_scale_factors: the graph's size after the solve.
        newest_frame_index: frame index of the newest keyframe in the graph.
        loops_removed: loop factors the solve removed as inconsistent.
        solve_ms: wall time of the solve (ms).
        batch: the whole graph was re-solved in batch and ISAM2 replaced (a new loop, or a
            recovery); the old one's memory was freed.
    """

    n_keyframes: int
    n_scale_factors: int
    newest_frame_index: int
    loops_removed: int
    solve_ms: float
    batch: bool = False


@dataclass(frozen=True)
class LoopAccepted:
    """A verified loop passed the consistency gate and is in the graph."""

    kf_old: int
    kf_new: int
    frame_old: int
    frame_new: int
    n_inliers: int


@dataclass(frozen=True)
class WarpApplied:
    """The back end handed the VO its metric warp ``S_new_vo`` (4, 4) Sim(3) (paper §III-D);
    ``scale`` is its scale (new units per old VO unit), ``epoch`` the VO frame it starts."""

    S_new_vo: np.ndarray
    scale: float
    epoch: int


@dataclass(frozen=True)
class InitialScaleApplied:
    """The pipeline warped the freshly initialized VO to a provisional metric scale before any
    keyframe reached the graph (:mod:`metricslam.slam.initial_scale`; emitted on the tracking
    thread). ``scale``: metres per VO unit from ``n_landmarks`` measurements of keyframe
    ``kf_frame_index``, applied at frame ``frame_index`` after waiting ``wait_ms``."""

    kf_frame_index: int
    frame_index: int
    scale: float
    n_landmarks: int
    wait_ms: float


@dataclass(frozen=True)
class KeyframeMarginalized:
    """The pipeline is handing ``keyframe`` (a :class:`~metricslam.slam.types.MarginalizedKeyframe`)
    to the back end, while processing frame ``frame_index_now`` (emitted on the tracking thread,
    before the back end sees it; relocalization into a saved map listens here)."""

    keyframe: object
    frame_index_now: int


@dataclass(frozen=True)
class SegmentRelocalized:
    """Tracking segment ``segment_id`` (a new one after a tracking loss) was relocalized in the
    session's own map (:mod:`metricslam.slam.map.segments`) and moved there in the graph: its
    link to the previous segment replaced by ``n_loops`` loops; ``frame_index``: the frame being
    processed when it was placed."""

    segment_id: int
    frame_index: int
    n_loops: int


@dataclass(frozen=True)
class KeyframeSettled:
    """A keyframe still in the VO window that a newer keyframe has observed: ``keyframe`` is a
    :class:`~metricslam.slam.types.MarginalizedKeyframe` snapshot of it (``T_vo_kf`` and the
    landmarks' inverse depths in the VO units of that moment, ``T_prevkf_kf`` None), taken while
    processing frame ``frame_index_now`` after ``warp_generation`` warps had been applied to the VO
    (:meth:`~metricslam.slam.vo.window.SlidingWindow.warp_since`). Emitted once per keyframe on the
    tracking thread, only while someone subscribes (relocalization into a saved map queries it
    early, long before the keyframe is marginalized)."""

    keyframe: object
    frame_index_now: int
    warp_generation: int


Event = (ScaleMeasured | GroundScaleMeasured | ScaleHealthUpdated | Solved | LoopAccepted | WarpApplied
         | InitialScaleApplied | KeyframeMarginalized | KeyframeSettled | SegmentRelocalized)


class EventBus:
    """Synchronous publish/subscribe for back-end events (see the module docstring)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscribers: list[tuple[Callable[[Event], None], tuple[type, ...]]] = []

    def subscribe(self, callback: Callable[[Event], None], *types: type) -> None:
        """Call ``callback(event)`` for every event of the given types (all types when none)."""
        with self._lock:
            self._subscribers.append((callback, tuple(types)))

    def unsubscribe(self, callback: Callable[[Event], None]) -> None:
        with self._lock:
            self._subscribers = [s for s in self._subscribers if s[0] is not callback]

    def wants(self, event_type: type) -> bool:
        """Whether any subscriber receives events of ``event_type`` (skip building them if not)."""
        with self._lock:
            return any(not types or issubclass(event_type, types) for _, types in self._subscribers)

    def emit(self, event: Event) -> None:
        with self._lock:
            subscribers = list(self._subscribers)
        for callback, types in subscribers:
            if types and not isinstance(event, types):
                continue
            try:
                callback(event)
            except Exception:  # noqa: BLE001 -- observing must never change the estimate
                log.exception("event subscriber %r failed on %s", callback, type(event).__name__)
