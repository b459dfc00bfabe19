"""The road-height estimator (metricslam.slam.ground) on rendered streets with a known mounting height."""

from __future__ import annotations

import numpy as np
import pytest

from metricslam.slam.ground.height import RoadHeightEstimator, plane_warp
from metricslam.slam.ground.plane import nominal_down, plane_homography, road_rays, tilt_normal, warp_to_prev

pytest.importorskip("numba")  # the renderer (synth extra)

from metricslam.synth import SynthConfig, SynthScene  # noqa: E402


def _street(h_mount_m: float, seed: int) -> tuple[SynthScene, list]:
    cfg = SynthConfig(world={"camera_height_m": h_mount_m})
    scene = SynthScene.procedural(7, seed, "straight", cfg)
    return scene, [scene.frame(i) for i in (0, 3, 6)]


def _pitched(T_world_cam: np.ndarray, pitch_rad: float) -> np.ndarray:
    R = np.eye(4)
    c, s = np.cos(pitch_rad), np.sin(pitch_rad)
    R[1:3, 1:3] = [[c, -s], [s, c]]
    return T_world_cam @ R


@pytest.mark.parametrize("h_mount_m,seed", [(1.65, 3), (1.2, 4)])
def test_rendered_street_recovers_the_mounting_height_within_1_percent(h_mount_m, seed):
    scene, frames = _street(h_mount_m, seed)
    est = RoadHeightEstimator()
    for a, b in ((0, 1), (1, 2)):
        T_prev_cur = np.linalg.inv(frames[a].T_world_cam) @ frames[b].T_world_cam
        res = est.estimate(frames[a].left, frames[b].left, scene.camera.K, T_prev_cur)
        assert res.accepted, res.reason
        assert abs(res.height / h_mount_m - 1) < 0.01
        assert np.degrees(res.normal_angle_rad) < 1.0


def test_height_is_in_the_units_of_the_relative_pose():
    scene, frames = _street(1.65, 3)
    T_prev_cur = np.linalg.inv(frames[0].T_world_cam) @ frames[1].T_world_cam
    T_vo = T_prev_cur.copy()
    T_vo[:3, 3] *= 0.37  # a monocular VO's arbitrary units
    res = RoadHeightEstimator().estimate(frames[0].left, frames[1].left, scene.camera.K, T_vo)
    assert res.accepted
    assert abs(res.height / (0.37 * 1.65) - 1) < 0.01


def test_no_road_in_view_is_rejected_with_a_reason():
    scene, frames = _street(1.65, 3)
    Ts = [_pitched(frames[i].T_world_cam, -1.2) for i in (0, 1)]  # looking up at facades and sky
    imgs = [np.clip(scene.renderer.render(T)[0] * 255, 0, 255).astype(np.uint8) for T in Ts]
    res = RoadHeightEstimator().estimate(imgs[0], imgs[1], scene.camera.K, np.linalg.inv(Ts[0]) @ Ts[1])
    assert not res.accepted and res.reason


def test_blank_images_and_no_motion_are_rejected():
    K = np.array([[700.0, 0, 600], [0, 700, 180], [0, 0, 1]])
    blank = np.full((370, 1220), 90, np.uint8)
    T = np.eye(4)
    T[2, 3] = 1.0
    assert not RoadHeightEstimator().estimate(blank, blank, K, T).accepted
    noise = np.random.default_rng(0).integers(0, 255, (370, 1220)).astype(np.uint8)
    res = RoadHeightEstimator().estimate(noise, noise, K, np.eye(4))
    assert not res.accepted and "motion" in res.reason


def test_plane_warp_matches_the_plane_homography():
    rng = np.random.default_rng(1)
    K = np.array([[718.0, 0, 607], [0, 718, 185], [0, 0, 1]])
    uv, rays = road_rays(K, 1241, 376, nominal_down(0.02), 1.2, (3.0, 12.0))
    assert len(uv) > 1000
    T = np.eye(4)
    T[:3, 3] = rng.normal(size=3) * [0.1, 0.05, 1.0]
    n = nominal_down(0.05)
    uv_prev, z = warp_to_prev(rays, K, T, n, 1.5)
    H = plane_homography(K, T, n, 1.5)
    p = np.hstack([uv, np.ones((len(uv), 1))]) @ H.T
    np.testing.assert_allclose(uv_prev, p[:, :2] / p[:, 2:], rtol=1e-9, atol=1e-7)
    assert np.all(z > 0)


def test_warp_jacobian_matches_central_differences():
    K = np.array([[718.0, 0, 607], [0, 718, 185], [0, 0, 1]])
    n0 = nominal_down(0.01)
    _, rays = road_rays(K, 1241, 376, n0, 1.2, (3.0, 12.0))
    rays = rays[::50]
    T = np.eye(4)
    T[:3, 3] = [0.05, -0.02, 1.1]
    p = np.array([np.log(1.6), 0.02, -0.01])
    uv, _, duv = plane_warp(rays, K, T, n0, p)
    eps = 1e-6
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = eps
        up = warp_to_prev(rays, K, T, tilt_normal(n0, (p + dp)[1:]), float(np.exp((p + dp)[0])))[0]
        um = warp_to_prev(rays, K, T, tilt_normal(n0, (p - dp)[1:]), float(np.exp((p - dp)[0])))[0]
        np.testing.assert_allclose(duv[:, :, k], (up - um) / (2 * eps), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(uv, warp_to_prev(rays, K, T, tilt_normal(n0, p[1:]), 1.6)[0], atol=1e-9)


def test_road_patch_warp_is_the_plane_warp_factored():
    from metricslam.slam.ground.road_image import RoadPatch, road_region

    K = np.array([[718.0, 0, 607], [0, 718, 185], [0, 0, 1]])
    n0 = nominal_down(0.01)
    region = road_region(K, (376, 1241), n0, 1.2, (3.0, 12.0))
    img = np.random.default_rng(2).uniform(0, 255, (376, 1241, 3)).astype(np.float32)
    T = np.eye(4)
    T[:3, 3] = [0.05, -0.02, 1.1]
    patch = RoadPatch(img, img, K, region, T, n0, min_gradient=0.0, max_pixels=500)
    p = np.array([np.log(1.6), 0.02, -0.01])
    u, v, Az, dc = patch.warp(p)
    uv_ref, Az_ref, duv_ref = plane_warp(patch.rays.T, K, T, n0, p)
    np.testing.assert_allclose(np.stack([u, v], axis=1), uv_ref, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(Az, Az_ref, rtol=1e-12)
    Kt = K @ T[:3, 3]
    duv = np.stack([dc * (Kt[0] - u * Kt[2]) / Az, dc * (Kt[1] - v * Kt[2]) / Az], axis=1)  # (3, 2, N)
    np.testing.assert_allclose(duv.transpose(2, 1, 0), duv_ref, rtol=1e-9, atol=1e-9)


def test_prepared_images_give_the_same_height_as_raw_ones():
    scene, frames = _street(1.65, 3)
    est = RoadHeightEstimator()
    T_prev_cur = np.linalg.inv(frames[0].T_world_cam) @ frames[1].T_world_cam
    raw = est.estimate(frames[0].left, frames[1].left, scene.camera.K, T_prev_cur)
    prepared = est.estimate_prepared(est.prepare(frames[0].left), est.prepare(frames[1].left),
                                     scene.camera.K, T_prev_cur)
    assert raw.accepted and prepared.height == raw.height and prepared.sigma_log == raw.sigma_log


def _keyframes(scene, Ts, images, vo_units_per_m: float):
    from metricslam.slam.types import MarginalizedKeyframe

    out = []
    for k, (T, img) in enumerate(zip(Ts, images)):
        T_prev = None
        if k:
            T_prev = np.linalg.inv(Ts[k - 1]) @ T
            T_prev[:3, 3] *= vo_units_per_m
        out.append(MarginalizedKeyframe(kf_id=k, frame_index=3 * k, t_ns=k, segment_id=0, T_vo_kf=T,
                                        T_prevkf_kf=T_prev, landmarks_uv_px=np.zeros((0, 2)),
                                        landmarks_inv_depth=np.zeros(0), image=img, camera=scene.camera))
    return out


def test_meter_turns_the_road_into_metres_per_vo_unit():
    from metricslam.slam.ground.config import ScaleConfig
    from metricslam.slam.ground.meter import GroundScaleMeter

    scene, frames = _street(1.65, 3)
    meter = GroundScaleMeter(ScaleConfig(sources=("ground",), mount_height_m=1.65))
    kfs = _keyframes(scene, [f.T_world_cam for f in frames], [f.left for f in frames], 2.5)
    events = [meter.measure(kf) for kf in kfs]
    assert not events[0].accepted and "first keyframe" in events[0].reason
    for ev in events[1:]:
        assert ev.accepted and ev.source == "ground"
        assert ev.scale == pytest.approx(1 / 2.5, rel=0.01)  # metres per VO unit
    assert meter.counts == {"ground_measured": 3, "ground_accepted": 2}


def test_rendered_drive_without_road_gets_no_ground_factors_and_says_so():
    from metricslam.slam.ground.config import ScaleConfig
    from metricslam.slam.ground.meter import GroundScaleMeter

    scene, frames = _street(1.65, 3)
    Ts = [_pitched(f.T_world_cam, -1.2) for f in frames]  # facades and sky only
    images = [np.clip(scene.renderer.render(T)[0] * 255, 0, 255).astype(np.uint8) for T in Ts]
    meter = GroundScaleMeter(ScaleConfig(sources=("ground",), mount_height_m=1.65))
    events = [meter.measure(kf) for kf in _keyframes(scene, Ts, images, 1.0)]
    assert not any(ev.accepted for ev in events) and all(ev.reason for ev in events)
    assert meter.counts["ground_accepted"] == 0 and sum(meter.reasons.values()) == 3
