"""``Relocalizer``: puts a new session into a saved map (``docs/maps.md``), then into its frame.

Until the session has relocalized (:data:`EARLY_MATCHES` verified matches; optionally a few more
after, :data:`EARLY_AFTER_QUERIES`), every keyframe is also queried as soon as a newer keyframe
observed it (:class:`~metricslam.slam.events.KeyframeSettled`), long before it leaves the VO
window: with the depth source's answer for it (asked there, bounded wait; without one, its
landmarks alone carry the scale), its pose ``S_world_kf`` the window's of that moment, carried
through every later warp of the VO (:meth:`~metricslam.slam.vo.window.SlidingWindow.warp_since`)
until the back end has the keyframe. Every keyframe the session marginalizes is a query (in scale
mode once its depth answer arrived): ORB retrieval descriptors → bag-of-words with the *map's*
vocabulary → cosine scores against the map's rows → the best ``n_candidates`` verified as a loop
is (:func:`metricslam.slam.loop.corners.verify_corners`: essential-matrix check, PnP of the
keyframe's pixels against the map keyframe's metric 3-D corners, scale from the network depth of
the keyframe's own corners, its VO units; without depth answers its VO landmarks alone,
:func:`metricslam.slam.loop.verification.verify`).
A verified match gives ``S_mapkf_kf`` (metres per session-keyframe VO unit), hence

    S_map_world = T_map_mapkf · S_mapkf_kf · S_world_kf⁻¹

with ``S_world_kf`` the session's global-graph estimate of that keyframe. Because the map is
metric, this carries metric scale into the session even before its own learned scale engaged.
:meth:`Relocalizer.S_map_world` combines every verified match against the *final* graph (a
robust mean around the medoid; matches that disagree are counted as rejected). The session
counts as relocalized from the frame being processed when :data:`MIN_AGREEING_MATCHES` matches
first agreed (``first_frame``); frames before it are reported as not localized, never given a pose.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import cv2
import numpy as np

from metricslam.camera import PinholeCamera
from metricslam.depth.model import to_gray_u8
from metricslam.geometry import sim3, so3
from metricslam.depth.sample import sample_map
from metricslam.slam.events import KeyframeMarginalized, KeyframeSettled, ScaleMeasured
from metricslam.slam.graph.config import LoopConfig
from metricslam.slam.initial_scale import ask_depth
from metricslam.slam.loop import corners as corner_mod
from metricslam.slam.loop.detector import retrieval_descriptors, retrieval_orb
from metricslam.slam.loop.verification import LandmarkFeatures, match_descriptors, landmark_features, verify
from metricslam.slam.loop.vocabulary import BinaryVocabulary
from metricslam.slam.map.format import SavedMap

log = logging.getLogger(__name__)

#: two matches agree (:func:`close`) within these: metres (where they place the session's
#: keyframes in the map), radians, |log scale|
GATE_M, GATE_RAD, GATE_LOG_SCALE = 2.0, 0.1, 0.1
#: |log scale| gate while the session's world is not metric yet: each match's scale is then one
#: keyframe's network depth (±20-40 % from one view), so only a factor of two is refused; where
#: the matches place the session's keyframes (``GATE_M``) still has to agree
GATE_LOG_SCALE_PREMETRIC = float(np.log(2.0))
#: a verified match is refined on the corners of the loop-database rows this close to its map
#: keyframe's, on the correspondences within each of these reprojection gates in turn (px), when
#: at least this many stay (:meth:`Relocalizer._refined`)
LOCAL_MAP_ROWS, LOCAL_MAP_GATES_PX, LOCAL_MAP_MIN_POINTS = 2, (8.0, 4.0, 3.0), 12
#: verified matches (of different session keyframes) that must agree before the session counts as
#: relocalized: one match alone was off by ~9 m in position on the rendered revisit (a far view of
#: the map's first keyframe), two agreed with the final estimate within ~2 m
MIN_AGREEING_MATCHES = 2
#: early queries (keyframes still in the VO window) stop once this many matches verified, or once
#: the session is relocalized; each asks the depth source for the keyframe (waiting at most this
#: long, on the tracking thread)
EARLY_MATCHES, EARLY_DEPTH_TIMEOUT_S = 6, 1.0
#: with ``early_after_relocalized`` they go on after it (the live alignment needs matches spread
#: along the path before the keyframes reach the graph) until this many marginalized keyframes'
#: matches were recorded since, at most this many more queries (none after a depth request failed)
EARLY_AFTER_MATCHES, EARLY_AFTER_QUERIES = 3, 12


@dataclass(frozen=True)
class RelocMatch:
    """One verified match of session keyframe ``kf_frame`` to map keyframe ``map_kf_id``."""

    map_kf_id: int
    kf_frame: int
    frame_now: int
    S_mapkf_kf: np.ndarray
    n_inliers: int
    score: float
    #: early match (keyframe not yet in the back end): its pose (4, 4 Sim(3)) in the VO world after
    #: ``warp_generation`` warps, the VO units ``S_mapkf_kf`` is expressed in
    S_world_kf_vo: np.ndarray | None = None
    warp_generation: int = 0


class Relocalizer:
    """Matches a session's keyframes against a :class:`SavedMap` (module docstring).

    Args:
        saved: the loaded map.
        camera: the session's camera (checked against the map's by the caller).
        config: loop parameters (retrieval ORB, verification thresholds, ``n_candidates``).
        seed: RANSAC seed (deterministic given the same keyframes).
        early_after_relocalized: early queries go on after relocalization (:data:`EARLY_AFTER_QUERIES`).
    """

    def __init__(self, saved: SavedMap, camera: PinholeCamera, config: LoopConfig | None = None,
                 seed: int = 0, early_after_relocalized: bool = False) -> None:
        self.config = config or LoopConfig()
        self.camera = camera
        kf, db = saved.arrays["keyframes"], saved.arrays["loop_db"]
        self._T_map_kf = {int(k): T for k, T in zip(kf["kf_id"], kf["T_map_kf"])}
        self._metric_map = bool(saved.metric)
        self._vocab = BinaryVocabulary(db["vocabulary_words"], db["vocabulary_idf"])
        self._ids = db["bow_kf_id"]
        self._rows = db["bow_rows"]
        o = db["feature_offsets"]
        self._features = [corner_mod.CornerFeatures(db["feature_uv_px"][a:b].astype(float),
                                                    db["feature_descriptors"][a:b],
                                                    db["feature_points_kf_m"][a:b].astype(float))
                          for a, b in zip(o[:-1], o[1:])]
        self._exact = [db["feature_exact"][a:b] for a, b in zip(o[:-1], o[1:])]
        # the map side is metric: PnP on it measures the pose, the query's network depth the scale
        self._corner_config = self.config.model_copy(update={"measurement": "network"})
        self._orb = retrieval_orb(self.config)
        self._orb_landmarks = cv2.ORB_create(nlevels=1)
        self._orb_corners = cv2.ORB_create(nfeatures=self.config.n_corner_features, nlevels=4,
                                           fastThreshold=12)
        self._waiting: dict[int, tuple] = {}  # kf_id -> (keyframe, frame_now) until its depth
        self._rng = np.random.default_rng(seed)
        self._prev_bow: dict[bool, np.ndarray] = {}  # early?: the previous query's row (score ratio)
        self._window = None  # the session VO's sliding window (its warps), once attached
        self._backend = None  # the session's back end (its latest solve), once attached
        self.matches: list[RelocMatch] = []
        self.version = 0  # bumped whenever ``matches`` changes (a new list each time)
        self._early_left = EARLY_AFTER_QUERIES if early_after_relocalized else 0  # after relocalization
        self._late_matches = 0  # marginalized keyframes' matches recorded after relocalization
        #: keyframe frame index -> its bag-of-words row (K,) in the MAP's vocabulary (a merged map
        #: indexes the session's keyframes with them, :mod:`metricslam.slam.map.merge`)
        self.bow_by_frame: dict[int, np.ndarray] = {}
        self.first_frame: int | None = None
        self.n_queries = 0
        self.query_ms: list[float] = []  # wall time of each query (retrieval + verification)

    def attach(self, session) -> None:
        """Query every keyframe ``session`` (a pipeline with a back end) marginalizes, and its
        window keyframes early until relocalized."""
        self.bind(session)
        session.backend.events.subscribe(self.on_event, KeyframeMarginalized, ScaleMeasured, KeyframeSettled)

    def bind(self, session) -> None:
        """Use ``session``'s depth source, VO window and back end; events come through
        :meth:`on_event` (:meth:`attach` subscribes it)."""
        self._depth_source = getattr(session.backend, "depth_source", None)
        self._with_depth = self._depth_source is not None
        self._window = session.vo.window
        self._backend = session.backend

    def on_event(self, ev) -> None:
        """Query the keyframe of a ``KeyframeSettled`` / ``KeyframeMarginalized`` event (or of the
        ``ScaleMeasured`` its query waited for)."""
        if isinstance(ev, KeyframeSettled):
            after = self.first_frame is not None and self._early_left > 0 and self._late_matches < EARLY_AFTER_MATCHES
            if after or (self.first_frame is None and len(self.matches) < EARLY_MATCHES):
                self._early_left -= after
                kf = ev.keyframe
                inv_depth, why = ((None, "") if self._depth_source is None else
                                  ask_depth(self._depth_source, kf.image, kf.camera, EARLY_DEPTH_TIMEOUT_S))
                self._early_left = 0 if after and why else self._early_left  # depth slow or failing: no more waits
                m = self.query(kf, ev.frame_index_now, inv_depth, early=True)
                if m is not None:
                    self._record(replace(m, S_world_kf_vo=sim3.from_se3(ev.keyframe.T_vo_kf),
                                         warp_generation=ev.warp_generation))
            return
        if isinstance(ev, KeyframeMarginalized):
            self._settle(ev.keyframe)
            if self._with_depth:
                self._waiting[int(ev.keyframe.kf_id)] = (ev.keyframe, ev.frame_index_now)
                return
            match = self.query(ev.keyframe, ev.frame_index_now)
        else:
            got = self._waiting.pop(int(ev.kf_id), None)
            if got is None:
                return
            match = self.query(got[0], got[1], ev.inv_depth_map_per_m)
        if match is not None:
            self._late_matches += self.first_frame is not None
            self._record(match)

    def _record(self, match: RelocMatch) -> None:
        """Add ``match``; one per session keyframe (a later query of the same keyframe replaces
        an early one, so two matches that agree are two keyframes)."""
        same = [k for k, m in enumerate(self.matches) if m.kf_frame == match.kf_frame]
        self.matches = ([*self.matches[:same[0]], match, *self.matches[same[0] + 1:]] if same
                        else [*self.matches, match])  # a new list: readers on other threads
        self.version += 1
        if self.first_frame is None and (agree := self._agreeing()) >= MIN_AGREEING_MATCHES:
            self.first_frame = match.frame_now
            log.info("relocalized into the map at frame %d: keyframe %d matches map keyframe %d (%d inliers; "
                     "%d matches agree)", match.frame_now, match.kf_frame, match.map_kf_id, match.n_inliers, agree)

    def _agreeing(self) -> int:
        """How many matches agree with their medoid against the back end's latest solve."""
        poses = {} if self._backend is None else self._backend.optimized_keyframe_poses()
        metric = self._metric_map and bool(getattr(self._backend, "scale_established", False))
        return self.S_map_world(poses, metric_world=metric)[1]

    def _settle(self, kf) -> None:
        """``kf`` leaves the VO window: its early match in the VO units the back end gets it in."""
        for k, m in enumerate(self.matches):
            if m.kf_frame == int(kf.frame_index) and m.S_world_kf_vo is not None:
                W = self._window.warp_since(m.warp_generation)
                down = sim3.from_rts(np.eye(3), np.zeros(3), 1.0 / sim3.scale(W))
                self.matches = [*self.matches[:k], replace(
                    m, S_mapkf_kf=m.S_mapkf_kf @ down, S_world_kf_vo=sim3.from_se3(kf.T_vo_kf),
                    warp_generation=len(self._window.warps)), *self.matches[k + 1:]]
                self.version += 1

    def query(self, kf, frame_now: int, inv_depth_map: np.ndarray | None = None,
              early: bool = False) -> RelocMatch | None:
        """Verify keyframe ``kf`` (a MarginalizedKeyframe; ``inv_depth_map`` (h, w) 1/m its network
        depth, None: landmarks only) against its best map candidates (``early``: a window snapshot)."""
        t0 = time.perf_counter()
        try:
            return self._query(kf, frame_now, inv_depth_map, early)
        finally:
            self.query_ms.append(1e3 * (time.perf_counter() - t0))

    def _query(self, kf, frame_now: int, inv_depth_map: np.ndarray | None, early: bool) -> RelocMatch | None:
        self.n_queries += 1
        cfg = self.config
        gray = to_gray_u8(kf.image)
        v = self._vocab.bow(retrieval_descriptors(self._orb, gray, cfg.image_scale))
        self.bow_by_frame[int(kf.frame_index)] = np.asarray(v, np.float32)
        prev = self._prev_bow.get(early)
        ref = None if prev is None else float(prev @ v)
        self._prev_bow[early] = v
        if not len(self._ids) or not np.any(v):
            return None
        scores = self._rows @ v
        order = np.argsort(-scores, kind="stable")[: cfg.n_candidates]
        lm = landmark_features(self._orb_landmarks, gray, kf.camera, kf.landmarks_uv_px,
                               kf.landmarks_inv_depth)
        new = (self._corners(gray, kf, lm, inv_depth_map) if inv_depth_map is not None or early
               else None)
        for i in order:
            if scores[i] <= 0 or (ref is not None and ref > 0 and scores[i] < cfg.min_score_ratio * ref):
                break
            if new is not None:
                res = corner_mod.verify_corners(new, self._features[i], kf.camera, self._corner_config, self._rng)
            else:
                f, ex = self._features[i], self._exact[i]
                res = verify(lm, LandmarkFeatures(f.uv_px[ex], f.points[ex], f.descriptors[ex]),
                             kf.camera, cfg, self._rng)
            if res is not None:
                S = res.S_old_new if new is None else self._refined(new, int(i), res.S_old_new, kf.camera)
                return RelocMatch(int(self._ids[i]), int(kf.frame_index), int(frame_now),
                                  S, res.n_inliers, float(scores[i]))
        return None

    def _refined(self, new: corner_mod.CornerFeatures, i: int, S_mapkf_kf: np.ndarray,
                 camera: PinholeCamera) -> np.ndarray:
        """``S_mapkf_kf`` (4, 4) of a match verified against loop-database row ``i``, its pose
        refined on the corners of rows ``i ± LOCAL_MAP_ROWS`` brought into row ``i``'s keyframe
        frame (several map keyframes' network depths average one view's depth error out, as
        ORB-SLAM tracks its local map after relocalizing); unchanged when fewer than
        ``LOCAL_MAP_MIN_POINTS`` correspondences stay within the last gate
        (``docs/history/rule_reloc_local_map_session18.md``)."""
        T_kf_map = np.linalg.inv(self._T_map_kf[int(self._ids[i])])
        uv, pts = [np.zeros((0, 2))], [np.zeros((0, 3))]
        for j in range(max(0, i - LOCAL_MAP_ROWS), min(len(self._ids), i + LOCAL_MAP_ROWS + 1)):
            f = self._features[j]
            ok = np.isfinite(f.points).all(axis=1)
            pairs = match_descriptors(new.descriptors, f.descriptors[ok], self.config.hamming_ratio)
            T = T_kf_map @ self._T_map_kf[int(self._ids[j])]
            uv.append(new.uv_px[pairs[:, 0]])
            pts.append(f.points[ok][pairs[:, 1]] @ T[:3, :3].T + T[:3, 3])
        uv, pts = np.vstack(uv), np.vstack(pts)
        R, t, s = sim3.split(S_mapkf_kf)
        rvec, tvec = cv2.Rodrigues(R.T)[0], (-R.T @ t).reshape(3, 1)  # the query camera's pose
        for gate_px in LOCAL_MAP_GATES_PX:
            q = pts @ cv2.Rodrigues(rvec)[0].T + tvec.ravel()
            err = np.full(len(q), np.inf)
            front = q[:, 2] > 0
            err[front] = np.linalg.norm(camera.project(q[front]) - uv[front], axis=1)
            keep = err < gate_px
            if keep.sum() < LOCAL_MAP_MIN_POINTS:
                return S_mapkf_kf
            rvec, tvec = cv2.solvePnPRefineLM(pts[keep], uv[keep], camera.K, None, rvec, tvec)
        R_kf_new = cv2.Rodrigues(rvec)[0].T
        return sim3.from_rts(R_kf_new, -R_kf_new @ tvec.ravel(), s)

    def _corners(self, gray, kf, lm: LandmarkFeatures, inv_depth_map) -> corner_mod.CornerFeatures | None:
        """The keyframe's ORB corners with network depth plus its landmark features, 3-D in its
        VO units (the loop detector's corner features), or None without a usable depth map.
        ``inv_depth_map`` None (an early query): the corners without depth (NaN) — PnP against the
        map's metric corners needs only their pixels, the scale then rests on the landmarks."""
        if inv_depth_map is None:
            uv, desc = corner_mod.detect_corners(self._orb_corners, gray)
            return corner_mod.CornerFeatures(np.vstack([uv, lm.uv_px]), np.vstack([desc, lm.descriptors]),
                                             np.vstack([np.full((len(uv), 3), np.nan), lm.points]))
        size = (int(gray.shape[1]), int(gray.shape[0]))
        lm_uv = np.asarray(kf.landmarks_uv_px, float).reshape(-1, 2)
        m_per_unit = corner_mod.metres_per_unit(kf.landmarks_inv_depth, sample_map(inv_depth_map, lm_uv, size))
        if m_per_unit is None:
            return None
        uv, desc = corner_mod.detect_corners(self._orb_corners, gray)
        pts = corner_mod.network_points(uv, sample_map(inv_depth_map, uv, size), m_per_unit, kf.camera)
        return corner_mod.CornerFeatures(np.vstack([uv, lm.uv_px]), np.vstack([desc, lm.descriptors]),
                                         np.vstack([pts, lm.points]))

    def S_map_world(self, S_world_kf_by_frame: dict[int, np.ndarray],
                    metric_world: bool = False) -> tuple[np.ndarray | None, int, int]:
        """``(S_map_world (4, 4) or None, matches used, matches rejected)`` from every match
        whose session keyframe is in ``S_world_kf_by_frame`` (the back end's
        ``optimized_keyframe_poses()``): the medoid's Sim(3), refined by the tangent mean of
        the matches within the gates of it.

        ``metric_world``: the session's world is metric already (learned scale established).
        Each match's scale then comes from the session's graph (``S_world_kf``'s, which fuses
        every scale factor) instead of its one keyframe's network depth (±20 % from one view,
        measured on the rendered revisit), so ``S_map_world`` is rigid: the map is metric, so
        is the session. Otherwise the network-depth scale carries the map's metres into the
        session (its first relocalized frame inherits metric scale)."""
        cands = [(S, S_world_kf[:3, 3]) for _, S, S_world_kf in self._candidates(S_world_kf_by_frame, metric_world)]
        if not cands:
            return None, 0, len(self.matches)

        def agree(a, b) -> bool:  # where both place the two matched keyframes, and how
            return agree_at(a[0], b[0], np.stack([a[1], b[1]]), metric_world)

        support = [sum(agree(a, b) for b in cands) for a in cands]
        medoid = cands[int(np.argmax(support))]
        kept = [c[0] for c in cands if agree(medoid, c)]
        mean = np.mean([sim3.local(medoid[0], c) for c in kept], axis=0)
        return sim3.retract(medoid[0], mean), len(kept), len(self.matches) - len(kept)

    def agreeing(self, S_map_world: np.ndarray, S_world_kf_by_frame: dict[int, np.ndarray],
                 metric_world: bool) -> list[tuple[RelocMatch, np.ndarray]]:
        """``(match, its keyframe's world position (3,))`` of the matches that agree with
        ``S_map_world`` (4, 4) where they place their keyframe (:func:`agree_at`)."""
        return [(m, S_world_kf[:3, 3]) for m, S, S_world_kf in self._candidates(S_world_kf_by_frame, metric_world)
                if agree_at(S_map_world, S, S_world_kf[None, :3, 3], metric_world)]

    def map_position_m(self, m: RelocMatch) -> np.ndarray:
        """Where match ``m`` puts its session keyframe's camera in the map (3,)."""
        return (self._T_map_kf[m.map_kf_id] @ np.append(m.S_mapkf_kf[:3, 3], 1.0))[:3]

    def measured_S_mapkf_kf(self, m: RelocMatch, S_world_kf: np.ndarray, metric_world: bool) -> np.ndarray:
        """The match's ``S_mapkf_kf`` (4, 4), its scale the session graph's when ``metric_world``
        (:meth:`S_map_world`)."""
        if not metric_world:
            return m.S_mapkf_kf
        R, t, _ = sim3.split(m.S_mapkf_kf)
        return sim3.from_rts(R, t, sim3.scale(S_world_kf))

    def candidates(self, S_world_kf_by_frame: dict[int, np.ndarray],
                   metric_world: bool = False) -> list[tuple[RelocMatch, np.ndarray]]:
        """``(match, S_map_world it implies)`` for every match whose keyframe is in the graph."""
        return [(m, S) for m, S, _ in self._candidates(S_world_kf_by_frame, metric_world)]

    def _candidates(self, S_world_kf_by_frame: dict[int, np.ndarray],
                    metric_world: bool) -> list[tuple[RelocMatch, np.ndarray, np.ndarray]]:
        """:meth:`candidates` with each match's ``S_world_kf`` (4, 4)."""
        out = []
        for m in self.matches:
            S_world_kf = S_world_kf_by_frame.get(m.kf_frame)
            if S_world_kf is None and m.S_world_kf_vo is not None and self._window is not None:
                S_world_kf = self._window.warp_since(m.warp_generation) @ m.S_world_kf_vo
            if S_world_kf is not None:
                T = sim3.from_se3(self._T_map_kf[m.map_kf_id])
                out.append((m, T @ self.measured_S_mapkf_kf(m, S_world_kf, metric_world) @ sim3.inverse(S_world_kf),
                            S_world_kf))
        return out


def close(a: np.ndarray, b: np.ndarray, gate_m: float = GATE_M, gate_rad: float = GATE_RAD,
          gate_log_scale: float = GATE_LOG_SCALE, at_world: np.ndarray | None = None) -> bool:
    """Two Sim(3) ``S_map_world`` (4, 4) within ``gate_rad`` and ``gate_log_scale`` of each other
    that place each point of ``at_world`` (N, 3, world units; None: the world origin) within
    ``gate_m`` metres of each other in the map."""
    Ra, _, sa = sim3.split(a)
    Rb, _, sb = sim3.split(b)
    p = np.zeros((1, 3)) if at_world is None else np.asarray(at_world, float).reshape(-1, 3)
    gap_m = np.linalg.norm(sim3.transform_points(a, p) - sim3.transform_points(b, p), axis=1).max()
    return (gap_m < gate_m and np.linalg.norm(so3.log(Ra.T @ Rb)) < gate_rad
            and abs(np.log(sa / sb)) < gate_log_scale)


def agree_at(a: np.ndarray, b: np.ndarray, p_world: np.ndarray, metric_world: bool) -> bool:
    """Two ``S_map_world`` agree: :func:`close` at the session keyframe positions ``p_world``
    (N, 3), with the scale gate of a metric world or, before learned scale, a factor of two."""
    return close(a, b, GATE_M, GATE_RAD, GATE_LOG_SCALE if metric_world else GATE_LOG_SCALE_PREMETRIC, at_world=p_world)


def to_map_frame(S_map_world: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """Rigid ``T_map_cam`` (4, 4): rotation ``R_map_world·R_world_cam``, position
    ``S_map_world · t_world_cam`` (a metric pose in the map frame)."""
    R, t, s = sim3.split(np.asarray(S_map_world, float))
    out = np.eye(4)
    out[:3, :3] = R @ T_world_cam[:3, :3]
    out[:3, 3] = s * R @ T_world_cam[:3, 3] + t
    return out
