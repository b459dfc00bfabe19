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
  keyframe VO unit), exactly the values the back end gives the graph: recorded from its
  :class:`~metricslam.slam.events.ScaleMeasured` events once :meth:`ScaleHistory.attach` has
  subscribed to them.

Units conventions: ``docs/conventions.md``.
"""

from __future__ import annotations

import threading

import numpy as np

from metricslam.geometry import sim3
from metricslam.slam.events import EventBus, ScaleMeasured
from metricslam.slam.types import MarginalizedKeyframe


class ScaleHistory:
    """Thread-safe recorder of the scale estimate (see the module docstring)."""

    def __init__(self) -> None:
        self.records_measurements = False  # set by attach()
        self._lock = threading.Lock()
        self._scale_live = 1.0
        self._keyframes: list[dict] = []
        self._by_frame: dict[int, dict] = {}
        self._corrections: list[dict] = []

    def attach(self, events: EventBus) -> None:
        """Record each keyframe's learned scale measurements from the back end's events."""
        self.records_measurements = True
        events.subscribe(self.on_scale_measured, ScaleMeasured)

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
        """A keyframe was marginalized (before the back end sees it): remember its live scale
        and its VO step from the previous keyframe."""
        step = None if kf.T_prevkf_kf is None else float(np.linalg.norm(kf.T_prevkf_kf[:3, 3]))
        with self._lock:
            rec = {"frame_index": int(kf.frame_index), "t_ns": int(kf.t_ns), "kf_id": int(kf.kf_id),
                   "segment_id": int(kf.segment_id), "scale_live": self._scale_live,
                   "step_vo": step, "scale_factors": None, "scale_measured_median": None}
            self._keyframes.append(rec)
            self._by_frame[rec["frame_index"]] = rec

    def on_scale_measured(self, ev: ScaleMeasured) -> None:
        """The back end turned a keyframe's depth answer into scale measurements (or failed)."""
        s = np.asarray(ev.scales, dtype=float)
        with self._lock:
            rec = self._by_frame.get(int(ev.frame_index))
            if rec is None:
                return
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
