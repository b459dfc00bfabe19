"""Early relocalization queries (keyframes still in the VO window, ``KeyframeSettled``).

An early match is expressed in the VO units of the moment it verified; the VO is warped later
(the back end's metric corrections scale it by s), and the keyframe reaches the back end in the
new units. Whatever happens in between, the ``S_map_world`` the match implies must not move: it
is one fact about the world. Checked with a real :class:`SlidingWindow` (its warp log) and the
relocalizer's own bookkeeping; the end-to-end effect (0013 relocalized at frame 3 instead of 32)
is in ``bench/maps.py``.
"""

from __future__ import annotations

import numpy as np
from metricslam.camera import PinholeCamera
from metricslam.geometry import se3, sim3, so3
from metricslam.slam.events import EventBus, KeyframeMarginalized, KeyframeSettled, ScaleMeasured
from metricslam.slam.map.relocalizer import EARLY_AFTER_MATCHES, EARLY_AFTER_QUERIES, RelocMatch, Relocalizer
from metricslam.slam.types import MarginalizedKeyframe
from metricslam.slam.vo.config import VOConfig
from metricslam.slam.vo.window import SlidingWindow

CAMERA = PinholeCamera(fx_px=700.0, fy_px=700.0, cx_px=320.0, cy_px=180.0, width_px=640, height_px=360)


def _bare_relocalizer(window: SlidingWindow, T_map_mapkf: np.ndarray, early_after: bool = False) -> Relocalizer:
    r = Relocalizer.__new__(Relocalizer)  # no saved map needed for the bookkeeping under test
    r._T_map_kf = {7: T_map_mapkf}
    r._window, r._backend = window, None
    r.matches, r.version, r.first_frame, r._metric_map = [], 0, None, True
    r._depth_source, r._with_depth, r._waiting = None, False, {}
    r._early_left, r._late_matches = (EARLY_AFTER_QUERIES if early_after else 0), 0
    return r


def _kf(frame: int, T_vo_kf: np.ndarray) -> MarginalizedKeyframe:
    return MarginalizedKeyframe(kf_id=frame, frame_index=frame, t_ns=0, segment_id=0, T_vo_kf=T_vo_kf,
                                T_prevkf_kf=None, landmarks_uv_px=np.zeros((0, 2)),
                                landmarks_inv_depth=np.zeros(0), image=np.zeros((360, 640), np.uint8),
                                camera=CAMERA)


def _warp(W: np.ndarray, T: np.ndarray) -> np.ndarray:
    R, t, s = sim3.split(W)
    return se3.from_rt(R @ T[:3, :3], s * R @ T[:3, 3] + t)


def test_an_early_match_implies_the_same_map_frame_before_and_after_warps_and_marginalization():
    window = SlidingWindow(VOConfig(), CAMERA, counters={"keyframes": 0}, timings_ms={})
    T_map_mapkf = se3.from_rt(so3.exp(np.array([0.0, 0.3, 0.0])), np.array([5.0, 0.0, 20.0]))
    r = _bare_relocalizer(window, T_map_mapkf)
    T_vo_kf = se3.from_rt(so3.exp(np.array([0.0, -0.1, 0.02])), np.array([1.0, 0.1, 3.0]))
    S_mapkf_kf = sim3.from_rts(so3.exp(np.array([0.01, 0.05, 0.0])), np.array([0.5, 0.0, -2.0]), 7.5)
    r._record(RelocMatch(7, 12, 14, S_mapkf_kf, 80, 0.4, sim3.from_se3(T_vo_kf), len(window.warps)))
    before, = [S for _, S in r.candidates({})]

    # the back end warps the VO twice (scale 3, then 0.8) before the keyframe leaves the window
    for W in (sim3.from_rts(so3.exp(np.array([0.0, 0.02, 0.0])), np.array([1.0, 0.0, 0.5]), 3.0),
              sim3.from_rts(np.eye(3), np.array([0.0, 0.2, 0.0]), 0.8)):
        window.apply_similarity(W, segment_id=0)
        T_vo_kf = _warp(W, T_vo_kf)
    S_after_warps = sim3.inverse(window.warp_since(0))
    pending, = [S for _, S in r.candidates({})]
    np.testing.assert_allclose(pending, before @ S_after_warps, atol=1e-9)  # map ← today's world

    r._settle(_kf(12, T_vo_kf))  # marginalized: handed to the back end in today's units
    settled, = [S for _, S in r.candidates({})]
    in_graph, = [S for _, S in r.candidates({12: sim3.from_se3(T_vo_kf)})]
    np.testing.assert_allclose(settled, pending, atol=1e-9)
    np.testing.assert_allclose(in_graph, pending, atol=1e-9)
    assert np.isclose(sim3.scale(r.matches[0].S_mapkf_kf), 7.5 / (3.0 * 0.8))


def test_a_later_query_of_the_same_keyframe_replaces_its_early_match_and_two_keyframes_must_agree():
    window = SlidingWindow(VOConfig(), CAMERA, counters={"keyframes": 0}, timings_ms={})
    r = _bare_relocalizer(window, np.eye(4))
    T_vo_12, T_vo_15 = se3.from_rt(np.eye(3), np.array([0.0, 0.0, 1.0])), se3.from_rt(np.eye(3), np.array([0.0, 0.0, 2.5]))
    S_map_world = sim3.from_rts(so3.exp(np.array([0.0, 0.2, 0.0])), np.array([3.0, 0.0, 30.0]), 1.0)
    # each match: S_mapkf_kf = T_map_mapkf⁻¹ · S_map_world · S_world_kf (map keyframe 7 at the origin)
    early = RelocMatch(7, 12, 14, S_map_world @ sim3.from_se3(T_vo_12), 40, 0.3, sim3.from_se3(T_vo_12), 0)
    later = RelocMatch(7, 12, 30, S_map_world @ sim3.from_se3(T_vo_12), 200, 0.3, sim3.from_se3(T_vo_12), 0)
    far_off = RelocMatch(7, 13, 31, sim3.from_rts(np.eye(3), np.array([9.0, 0.0, 0.0]), 1.0) @ S_map_world
                         @ sim3.from_se3(T_vo_15), 30, 0.3, sim3.from_se3(T_vo_15), 0)
    agrees = RelocMatch(7, 15, 33, S_map_world @ sim3.from_se3(T_vo_15), 90, 0.3, sim3.from_se3(T_vo_15), 0)
    r._record(early)
    r._record(later)  # the same keyframe: replaces, still one keyframe
    assert [m.n_inliers for m in r.matches] == [200] and r.first_frame is None
    r._record(far_off)  # 9 m off: two keyframes, but they do not agree
    assert r.first_frame is None
    r._record(agrees)
    assert r.first_frame == 33 and r.version == 4  # relocalized once two keyframes agree


def test_settled_events_are_built_only_for_subscribers():
    bus = EventBus()
    assert not bus.wants(KeyframeSettled)
    bus.subscribe(lambda ev: None, ScaleMeasured)
    assert not bus.wants(KeyframeSettled)
    bus.subscribe(lambda ev: None, KeyframeSettled)
    assert bus.wants(KeyframeSettled)


def test_before_metric_scale_two_matches_agree_on_where_they_place_the_keyframes_not_the_origin():
    """Pre-metric, each match's scale is one view's network depth: two matches of keyframes near
    each other that place both within the gate agree although their scales differ by 40 % (the
    former rule, origins and a 10 % scale gate, refused them); a match that places the keyframes
    metres apart does not agree."""
    window = SlidingWindow(VOConfig(), CAMERA, counters={"keyframes": 0}, timings_ms={})
    r = _bare_relocalizer(window, np.eye(4))
    kf_a, kf_b = se3.from_rt(np.eye(3), np.array([0.0, 0.0, 1.0])), se3.from_rt(np.eye(3), np.array([0.0, 0.0, 1.5]))
    far = np.array([0.0, 0.0, 30.0])  # the session's origin is 30 units behind its keyframes

    def match(frame, T_vo_kf, s, shift=0.0):  # S_map_world = translate(far) · scale(s)
        S_map_world = sim3.from_rts(np.eye(3), far + np.array([shift, 0.0, 0.0]), s)
        return RelocMatch(7, frame, frame, S_map_world @ sim3.from_se3(T_vo_kf), 50, 1.0,
                          S_world_kf_vo=sim3.from_se3(T_vo_kf), warp_generation=0)

    r.matches = [match(3, kf_a, 2.0), match(5, kf_b, 2.8)]
    assert r.S_map_world({}, metric_world=False)[1] == 2  # 0.8 m apart at kf_a, 1.2 m at kf_b
    r.matches = [match(3, kf_a, 2.0), match(5, kf_b, 2.0, shift=2.5)]
    assert r.S_map_world({}, metric_world=False)[1] == 1  # 2.5 m apart wherever they are applied



class _FailingDepth:
    def inv_depth_map(self, image, camera):
        raise RuntimeError("depth service unreachable")


def _early_queries(early_after: bool, matching: bool, depth_source: object = None) -> list[int]:
    """Keyframe k settles at frame 2k and is marginalized 10 keyframes later; the second early
    match relocalizes; after relocalization queries verify only when ``matching``. Returns the
    keyframes queried early."""
    window = SlidingWindow(VOConfig(), CAMERA, counters={"keyframes": 0}, timings_ms={})
    r = _bare_relocalizer(window, np.eye(4), early_after)
    r._depth_source = depth_source
    asked: list[tuple[int, bool]] = []

    def query(kf, frame_now, inv_depth_map=None, early=False):
        asked.append((int(kf.frame_index), early))
        if early and r.first_frame is None and len(asked) == 2:
            r.first_frame = frame_now
        ok = matching or r.first_frame is None
        return RelocMatch(7, int(kf.frame_index), frame_now, np.eye(4), 50, 1.0) if ok else None

    r.query, r._record = query, lambda m: None
    for k in range(40):
        r.on_event(KeyframeSettled(_kf(k, np.eye(4)), 2 * k, 0))
        if k >= 10:
            r.on_event(KeyframeMarginalized(_kf(k - 10, np.eye(4)), 2 * k))
    return [f for f, early in asked if early]


def test_after_relocalization_early_queries_go_on_until_marginalized_keyframes_match_or_their_budget_ends():
    """The live alignment needs matches spread along the path before the session's keyframes reach
    the graph (~20 frames on KITTI): with ``early_after_relocalized`` window keyframes are still
    queried after relocalization, until :data:`EARLY_AFTER_MATCHES` marginalized keyframes matched
    since, at most :data:`EARLY_AFTER_QUERIES` queries (a session that left the map stops paying).
    Without it (a tracking segment's relocalizer) they stop at relocalization, as before."""
    # keyframe EARLY_AFTER_MATCHES - 1 is the last marginalized match needed: it leaves the window
    # right after keyframe 10 + EARLY_AFTER_MATCHES - 1 settled, the last one queried early
    assert _early_queries(True, True) == list(range(min(10 + EARLY_AFTER_MATCHES, 2 + EARLY_AFTER_QUERIES)))
    assert _early_queries(True, False) == list(range(2 + EARLY_AFTER_QUERIES))
    assert _early_queries(False, True) == [0, 1]
    # a depth source that fails (or does not answer within EARLY_DEPTH_TIMEOUT_S): the tracking
    # thread stops waiting on it after relocalization — the query that found out is the last
    assert _early_queries(True, True, _FailingDepth()) == [0, 1, 2]
