"""``GroundScaleMeter``: per keyframe, the road-plane scale measurement ``s = h_mount_m / h_vo``.

It keeps the previous marginalized keyframe of each tracking segment — its image already
prepared for the aligner (:class:`~.road_image.RoadImage`: each image is prepared once, as the
current image of one measurement and the previous one of the next) — and runs the dense
road-height estimator (:mod:`.height`) between it and the new one, using the VO's relative pose
``T_prevkf_kf`` (keyframe VO units). The answer is a
:class:`~metricslam.slam.events.GroundScaleMeasured` event; accepted ones become unary
log-scale factors in the global graph (:mod:`metricslam.slam.graph.ground_factor`).
Single-threaded: the back end calls it in keyframe order from one thread.
"""

from __future__ import annotations

import re
import time

import numpy as np

from metricslam.slam.events import GroundScaleMeasured
from metricslam.slam.ground.config import ScaleConfig
from metricslam.slam.ground.consistency import HeightConsistency, ScaleOf
from metricslam.slam.ground.height import RoadHeightEstimator
from metricslam.slam.ground.road_image import RoadImage
from metricslam.slam.timing import TimingSummary
from metricslam.slam.types import MarginalizedKeyframe


class GroundScaleMeter:
    """Road-plane scale per keyframe (module docstring).

    Args:
        config: the scale configuration; ``mount_height_m`` must be set.
    """

    def __init__(self, config: ScaleConfig) -> None:
        if config.mount_height_m is None:
            raise ValueError("GroundScaleMeter needs ScaleConfig.mount_height_m")
        self.config = config
        self.h_mount_m = float(config.mount_height_m)
        self._estimator = RoadHeightEstimator(config.ground)
        self._consistency = HeightConsistency(config.consistency)
        #: (segment, frame_index, prepared image) of the newest segment's previous keyframe: only
        #: the newest segment's (a prepared image is ~16x the raw one; segments never resume)
        self._prev: tuple[int, int, RoadImage] | None = None
        #: wall and thread-CPU ms of one :meth:`measure` (image preparation and alignment)
        self.wall_ms, self.cpu_ms = TimingSummary(), TimingSummary()
        #: measurements made and accepted, and why the others were not (run statistics)
        self.counts: dict[str, int] = {"ground_measured": 0, "ground_accepted": 0}
        self.reasons: dict[str, int] = {}

    def measure(self, kf: MarginalizedKeyframe, scale_of: ScaleOf | None = None) -> GroundScaleMeasured:
        """The keyframe's road-plane scale measurement (``accepted`` False with a reason when
        the road gave none: a segment's first keyframe, no road, too little motion, a height far
        from the recent ones, …). ``scale_of``: the graph's scale of a keyframe now (m per its VO
        unit), for the consistency gate (:mod:`.consistency`; None: heights compared as given)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            return self._measure(kf, scale_of)
        finally:
            self.wall_ms.append(1e3 * (time.perf_counter() - t0))
            self.cpu_ms.append(1e3 * (time.thread_time() - c0))

    def _measure(self, kf: MarginalizedKeyframe, scale_of: ScaleOf | None) -> GroundScaleMeasured:
        seg = int(kf.segment_id)
        prev = self._prev[1:] if self._prev is not None and self._prev[0] == seg else None
        image = self._estimator.prepare(np.asarray(kf.image))
        self._prev = (seg, int(kf.frame_index), image)
        self.counts["ground_measured"] += 1
        base = dict(kf_id=int(kf.kf_id), frame_index=int(kf.frame_index), t_ns=int(kf.t_ns))
        if prev is None or kf.T_prevkf_kf is None:
            return self._rejected(base, "first keyframe of a tracking segment")
        T_prev_cur = np.asarray(kf.T_prevkf_kf, dtype=float)
        base.update(prev_frame_index=prev[0], step_vo=float(np.linalg.norm(T_prev_cur[:3, 3])))
        if prev[1].shape != image.shape:
            return self._rejected(base, "the previous keyframe image has another size")
        res = self._estimator.estimate_prepared(prev[1], image, kf.camera.K, T_prev_cur)
        base.update(height_vo=float(res.height), inlier_fraction=float(res.inlier_fraction),
                    normal_angle_rad=float(res.normal_angle_rad))
        if not res.accepted:
            return self._rejected(base, res.reason)
        inconsistent = self._consistency.check(int(kf.kf_id), float(res.height), scale_of)
        if inconsistent:
            return self._rejected(base, inconsistent)
        self.counts["ground_accepted"] += 1
        return GroundScaleMeasured(**base, scale=self.h_mount_m / float(res.height),
                                   sigma_log=float(self.config.ground_sigma_log), accepted=True)

    def _rejected(self, base: dict, reason: str) -> GroundScaleMeasured:
        key = " ".join(re.sub(r"\s*\(.*\)|[-\d.]+ ?%?", "", reason).split())  # without its numbers
        self.reasons[key] = self.reasons.get(key, 0) + 1
        base.setdefault("height_vo", float("nan"))
        return GroundScaleMeasured(**base, scale=float("nan"), sigma_log=float("inf"), accepted=False,
                                   reason=reason)
