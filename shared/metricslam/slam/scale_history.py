"""The system's own scale estimate over time (for ``metricslam run --json`` and the plots).

Three scale quantities, all *world units per VO unit* (world units are metres when learned scale
factors are on; with ``--no-scale`` or ``--vo-only`` they are the first keyframe's VO units, so
the values show the VO's arbitrary scale — nothing here uses ground truth):

* **live** — ``P = Π s_k``, the running product of the scales of every warp ``S_new_vo`` the
  pipeline applied to the local VO so far (paper §III-D). One unit of the VO's *initial* frame
  (``VO₀``, the monocular initialization's arbitrary unit) is ``P`` units of its current frame;
  as the warp makes the current frame metric, ``P`` is the system's live estimate of metres
  per ``VO₀`` unit at that moment.
* **optimized (per keyframe)** — the scale ``s`` of the keyframe's final ``S_world_kf`` from the
  global graph: world units per unit of the VO frame the keyframe was marginalized in. Times
  the keyframe's ``P`` it is in world units per ``VO₀`` unit, comparable with the live value.
* **measured (per keyframe)** — the median of the keyframe's learned scale measurements
  ``ξ_j / z_j`` (eq. 12: VO inverse depth over the network's metric inverse depth, metres per
  keyframe VO unit), as the back end computes them (same sampling and filters). Recorded only
  when the back end's depth source is wrapped in :class:`RecordingDepthSource`.

Units conventions: ``docs/conventions.md``.
"""

from __future__ import annotations

import collections
import logging
import threading
import weakref

import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.geometry import sim3
from metricslam.slam.depth_source import DepthSource
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.types import MarginalizedKeyframe

log = logging.getLogger(__name__)

#: pending keyframes beyond the back end's depth queue (requests in flight); older pending
#: entries belong to dropped requests and are forgotten
_PENDING_MARGIN = 8


class ScaleHistory:
    """Thread-safe recorder of the scale estimate (see the module docstring).

    Args:
        graph_config: the back end's parameters (filters of the scale measurements); the
            default :class:`GraphConfig` when None.
    """

    def __init__(self, graph_config: GraphConfig | None = None) -> None:
        self.graph_config = graph_config or GraphConfig()
        self.records_measurements = False  # set by RecordingDepthSource
        self._lock = threading.Lock()
        self._scale_live = 1.0
        self._keyframes: list[dict] = []
        self._by_frame: dict[int, dict] = {}
        self._corrections: list[dict] = []
        # id(image) -> (weakref to image, keyframe record, uv (M, 2) px, ξ (M,) 1/VO-units)
        self._pending: collections.OrderedDict = collections.OrderedDict()

    @property
    def scale_live(self) -> float:
        """Current running product of the applied warp scales (world units per ``VO₀`` unit)."""
        return self._scale_live

    def on_correction(self, frame_index: int, t_ns: int, s: float) -> None:
        """A warp with scale ``s`` was applied to the VO after frame ``frame_index``."""
        with self._lock:
            self._scale_live *= float(s)
            self._corrections.append({"frame_index": int(frame_index), "t_ns": int(t_ns),
                                      "s": float(s), "scale_live": self._scale_live})

    def on_keyframe(self, kf: MarginalizedKeyframe) -> None:
        """A keyframe was marginalized (before the back end sees it): remember its live scale,
        its VO step from the previous keyframe, and its landmarks for the depth measurement."""
        step = None if kf.T_prevkf_kf is None else float(np.linalg.norm(kf.T_prevkf_kf[:3, 3]))
        with self._lock:
            rec = {"frame_index": int(kf.frame_index), "t_ns": int(kf.t_ns), "kf_id": int(kf.kf_id),
                   "segment_id": int(kf.segment_id), "scale_live": self._scale_live,
                   "step_vo": step, "scale_factors": None, "scale_measured_median": None}
            self._keyframes.append(rec)
            self._by_frame[rec["frame_index"]] = rec
            if self.records_measurements and kf.image is not None:
                uv = np.asarray(kf.landmarks_uv_px, dtype=float).reshape(-1, 2)
                xi = np.asarray(kf.landmarks_inv_depth, dtype=float).reshape(-1)
                self._pending[id(kf.image)] = (weakref.ref(kf.image), rec, uv, xi)
                while len(self._pending) > self.graph_config.depth_queue_size + _PENDING_MARGIN:
                    self._pending.popitem(last=False)

    def on_depth(self, image: np.ndarray, inv_depth_map_per_m: np.ndarray) -> None:
        """The depth source answered for ``image``: record that keyframe's measurements."""
        from metricslam.depth.sample import sample_map
        from metricslam.slam.graph.scale_factor import scale_measurements

        with self._lock:
            entry = self._pending.pop(id(image), None)
        if entry is None or entry[0]() is not image:
            return
        _, rec, uv, xi = entry
        z = sample_map(inv_depth_map_per_m, uv, (int(image.shape[1]), int(image.shape[0])))
        s = scale_measurements(xi, z, self.graph_config)
        s = s[np.isfinite(s) & (s > 0)]
        with self._lock:
            rec["scale_factors"] = int(s.size)
            rec["scale_measured_median"] = float(np.median(s)) if s.size else None

    def keyframes(self, S_world_kf_by_frame: dict[int, np.ndarray] | None = None) -> list[dict]:
        """One dict per marginalized keyframe, in marginalization order.

        Args:
            S_world_kf_by_frame: the back end's ``optimized_keyframe_poses()`` (frame index ->
                (4, 4) Sim(3)), or None without a back end.

        Returns:
            dicts with ``frame_index``, ``t_ns``, ``kf_id``, ``segment_id``; ``scale_live``
            (world units per ``VO₀`` unit when the keyframe was marginalized); ``step_vo``
            (VO translation from the previous keyframe of its segment, in the keyframe's VO
            units; None for a segment's first); ``scale_kf_optimized`` (scale of the final
            ``S_world_kf``: world units per keyframe VO unit) and ``scale_optimized``
            (``scale_kf_optimized · scale_live``: world units per ``VO₀`` unit), None when the
            keyframe is not in the graph; ``scale_factors`` (learned scale measurements of the
            keyframe; 0 when its depth request was dropped or failed, None when not recorded)
            and ``scale_measured_median`` (median ``ξ/z``, metres per keyframe VO unit).
        """
        poses = S_world_kf_by_frame or {}
        out = []
        with self._lock:
            for rec in self._keyframes:
                r = dict(rec)
                if self.records_measurements and r["scale_factors"] is None:
                    r["scale_factors"] = 0
                S = poses.get(r["frame_index"])
                if S is None:
                    r["scale_kf_optimized"] = r["scale_optimized"] = None
                else:
                    s = sim3.scale(S)
                    r["scale_kf_optimized"] = s
                    r["scale_optimized"] = s * r["scale_live"]
                out.append(r)
        return out

    def corrections(self) -> list[dict]:
        """Every applied warp: ``frame_index``, ``t_ns``, its scale ``s`` and the running
        product ``scale_live`` after it (world units per ``VO₀`` unit)."""
        with self._lock:
            return [dict(c) for c in self._corrections]


class RecordingDepthSource:
    """A :class:`DepthSource` that passes every answer on to a :class:`ScaleHistory`.

    Wrap the back end's source with it (``make_backend(..., depth_source=...)``) to record each
    keyframe's learned scale measurements; answers and errors are passed through unchanged.
    """

    def __init__(self, inner: DepthSource, history: ScaleHistory) -> None:
        self.inner = inner
        self.history = history
        history.records_measurements = True

    def inv_depth_map(self, image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
        inv_map = self.inner.inv_depth_map(image, camera)
        try:
            self.history.on_depth(image, inv_map)
        except Exception:  # recording must never cost a keyframe its scale
            log.exception("scale history: recording a depth answer failed")
        return inv_map
