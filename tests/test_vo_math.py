"""VO numerics: analytic Jacobians vs central differences, normal-equation assembly, the 7-D
gauge freedom of the window, exact Schur marginalization, and BA on a seeded synthetic scene."""

from __future__ import annotations

import numpy as np
import pytest

from metricslam.geometry import se3, sim3
from metricslam.slam.vo.ba import bundle_adjust
from metricslam.slam.vo.linear_system import (
    Prior,
    WindowProblem,
    dense_hessian,
    linearize,
    total_cost,
)
from metricslam.slam.vo.marginalization import marginalize_pose, rescale_prior
from metricslam.slam.vo.motion_only import estimate_pose
from metricslam.slam.vo.reprojection import project, triangulate_inverse_depth
from vo_scene import make_window

EPS = 1e-6


def _perturbed(T: np.ndarray, rng: np.random.Generator, rot: float, trans: float) -> np.ndarray:
    return np.array([se3.retract(Ti, np.r_[rng.normal(0, rot, 3), rng.normal(0, trans, 3)])
                     for Ti in T])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reprojection_jacobians_match_central_differences(seed: int) -> None:
    P = make_window(seed).problem
    rng = np.random.default_rng(seed)
    T = _perturbed(P.T_world_kf, rng, 0.05, 0.3)
    lm = P.obs_lm
    Th, Tt = T[P.lm_host[lm]], T[P.obs_kf]
    f, rho, uv = P.lm_bearing[lm], P.lm_rho[lm] * rng.uniform(0.5, 2.0, len(lm)), P.obs_uv_px
    pr = project(Th, Tt, f, rho, uv, P.K)
    assert pr.valid.all()
    for k in range(6):
        d = np.zeros(6)
        d[k] = EPS
        for which, J in (("host", pr.J_host), ("target", pr.J_target)):
            def res(delta, which=which):
                if which == "host":
                    return project(Th @ se3.exp(delta), Tt, f, rho, uv, P.K, False).residual_px
                return project(Th, Tt @ se3.exp(delta), f, rho, uv, P.K, False).residual_px
            num = (res(d) - res(-d)) / (2 * EPS)
            np.testing.assert_allclose(J[:, :, k], num, rtol=1e-5, atol=1e-4)
    num_rho = (project(Th, Tt, f, rho + EPS, uv, P.K, False).residual_px
               - project(Th, Tt, f, rho - EPS, uv, P.K, False).residual_px) / (2 * EPS)
    np.testing.assert_allclose(pr.J_rho, num_rho, rtol=1e-5, atol=1e-4)


def test_normal_equations_are_the_gradient_of_the_cost() -> None:
    """b = ½ ∇E for residuals inside the Huber core (checks the sparse assembly)."""
    P = make_window(3).problem
    rng = np.random.default_rng(3)
    T = _perturbed(P.T_world_kf, rng, 1e-4, 1e-4)
    T[0] = P.T_world_kf[0]
    Q = P.with_values(T, P.lm_rho * rng.uniform(0.999, 1.001, P.n_landmarks))
    huber = 1e3  # quadratic everywhere
    lin = linearize(Q, huber)
    for i in range(Q.n_poses):
        for k in range(6):
            d = np.zeros(6)
            d[k] = EPS
            Tp, Tm = Q.T_world_kf.copy(), Q.T_world_kf.copy()
            Tp[i] = Tp[i] @ se3.exp(d)
            Tm[i] = Tm[i] @ se3.exp(-d)
            g = (total_cost(Q.with_values(Tp, Q.lm_rho), huber)
                 - total_cost(Q.with_values(Tm, Q.lm_rho), huber)) / (2 * EPS)
            assert lin.bp[6 * i + k] == pytest.approx(0.5 * g, rel=1e-4, abs=1e-4)
    for j in rng.choice(Q.n_landmarks, 10, replace=False):
        rp, rm = Q.lm_rho.copy(), Q.lm_rho.copy()
        rp[j] += EPS
        rm[j] -= EPS
        g = (total_cost(Q.with_values(Q.T_world_kf, rp), huber)
             - total_cost(Q.with_values(Q.T_world_kf, rm), huber)) / (2 * EPS)
        assert lin.bl[j] == pytest.approx(0.5 * g, rel=1e-4, abs=1e-4)


@pytest.mark.parametrize("seed", [0, 4])
def test_window_gauge_freedom_is_7d(seed: int) -> None:
    """Without a prior the BA Hessian has exactly a 7-D null space (pose + scale)."""
    P = make_window(seed, n_kf=5, n_per_kf=30).problem
    H, _ = dense_hessian(linearize(P, 1e3))
    ev = np.linalg.eigvalsh(H)
    rel = ev / ev.max()
    assert int(np.sum(rel < 1e-10)) == 7
    assert rel[7] > 1e-8  # the 8th direction is genuinely constrained


def _without_obs_in(P: WindowProblem, kf: int) -> WindowProblem:
    keep = P.obs_kf != kf
    return WindowProblem(P.T_world_kf, P.lm_host, P.lm_bearing, P.lm_rho, P.obs_lm[keep],
                         P.obs_kf[keep], P.obs_uv_px[keep], P.K, P.prior)


def _subset(P: WindowProblem, lm_mask: np.ndarray, poses: np.ndarray, prior: Prior | None) -> WindowProblem:
    new_lm = -np.ones(P.n_landmarks, dtype=int)
    new_lm[lm_mask] = np.arange(lm_mask.sum())
    new_pose = -np.ones(P.n_poses, dtype=int)
    new_pose[poses] = np.arange(len(poses))
    keep = lm_mask[P.obs_lm] & (new_pose[P.obs_kf] >= 0)
    return WindowProblem(P.T_world_kf[poses], new_pose[P.lm_host[lm_mask]], P.lm_bearing[lm_mask],
                         P.lm_rho[lm_mask], new_lm[P.obs_lm[keep]], new_pose[P.obs_kf[keep]],
                         P.obs_uv_px[keep], P.K, prior)


@pytest.mark.parametrize("seed", [0, 5])
def test_marginalization_is_exact(seed: int) -> None:
    """Covariance of the reduced graph == marginal covariance of the full graph."""
    w = make_window(seed, n_kf=5, n_per_kf=30, noise_px=0.5)
    P = _without_obs_in(w.problem, 0)  # dropped before marginalizing, as LocalVO does
    n = P.n_poses
    P = _subset(P, np.bincount(P.obs_lm, minlength=P.n_landmarks) > 0, np.arange(n), None)
    # a gauge prior on poses 1 and 2 (7-D gauge needs more than one pose) plus an old prior
    H0 = np.zeros((6 * n, 6 * n))
    H0[6:18, 6:18] = np.eye(12) * 50.0
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(6 * n, 6 * n))
    H0 += 0.1 * A @ A.T
    prior = Prior(H0, rng.normal(size=6 * n), P.T_world_kf.copy())
    full = WindowProblem(P.T_world_kf, P.lm_host, P.lm_bearing, P.lm_rho, P.obs_lm, P.obs_kf,
                         P.obs_uv_px, P.K, prior)
    H_full, _ = dense_hessian(linearize(full, 1.5))
    cov_full = np.linalg.inv(H_full)

    children = P.lm_host == 0
    new_prior = marginalize_pose(_subset(full, children, np.arange(n), prior), 0, 1.5)
    reduced = _subset(full, ~children, np.arange(1, n), new_prior)
    H_red, _ = dense_hessian(linearize(reduced, 1.5))
    cov_red = np.linalg.inv(H_red)

    keep = np.r_[np.arange(6, 6 * n), 6 * n + np.flatnonzero(~children)]
    np.testing.assert_allclose(cov_red, cov_full[np.ix_(keep, keep)], rtol=1e-6, atol=1e-10)


def test_rescaled_prior_gives_the_same_cost() -> None:
    rng = np.random.default_rng(7)
    T_lin = _perturbed(np.repeat(np.eye(4)[None], 3, 0), rng, 0.3, 2.0)
    A = rng.normal(size=(18, 18))
    prior = Prior(A @ A.T, rng.normal(size=18), T_lin)
    T = _perturbed(T_lin, rng, 0.01, 0.05)
    S = sim3.from_rts(se3.exp(np.r_[rng.normal(0, 1, 3), 0, 0, 0])[:3, :3], rng.normal(size=3), 3.7)
    warped = prior and rescale_prior(prior, S)

    def warp(Ti):
        out = np.eye(4)
        out[:3, :3] = S[:3, :3] / 3.7 @ Ti[:3, :3]
        out[:3, 3] = S[:3, :3] @ Ti[:3, 3] + S[:3, 3]
        return out

    T_new = np.array([warp(Ti) for Ti in T])
    assert warped.cost(T_new) == pytest.approx(prior.cost(T), rel=1e-8)


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_bundle_adjustment_recovers_synthetic_scene(noise_px: float) -> None:
    w = make_window(11, n_kf=6, n_per_kf=50, noise_px=noise_px)
    rng = np.random.default_rng(11)
    T0 = _perturbed(w.T_world_kf_true, rng, 0.01, 0.05)
    T0[0] = w.T_world_kf_true[0]  # gauge: first pose fixed
    Q = w.problem.with_values(T0, w.rho_true * rng.uniform(0.7, 1.3, len(w.rho_true)))
    res = bundle_adjust(Q, huber_px=2.0, iterations=30)
    assert res.final_cost < res.initial_cost
    # pose 0 was held at the truth, so only the scale is free
    t_est = res.T_world_kf[:, :3, 3] - res.T_world_kf[0, :3, 3]
    t_true = w.T_world_kf_true[:, :3, 3] - w.T_world_kf_true[0, :3, 3]
    s = float(np.sum(t_est * t_true) / np.sum(t_est * t_est))  # t_true ≈ s · t_est
    pos_tol, rot_tol_deg, rho_tol = (1e-6, 1e-5, 1e-6) if noise_px == 0 else (0.02, 0.05, 0.02)
    assert np.abs(s * t_est - t_true).max() < pos_tol
    for Te, Tt in zip(res.T_world_kf, w.T_world_kf_true):
        assert np.degrees(np.linalg.norm(se3.local(Tt, Te)[:3])) < rot_tol_deg
    rel = np.abs(res.lm_rho - w.rho_true * s) / (w.rho_true * s)  # depth_true = s · depth_est
    assert np.median(rel) < rho_tol


def test_motion_only_pose_recovers_camera() -> None:
    w = make_window(2)
    P = w.problem
    T_true = w.T_world_kf_true[2]
    rng = np.random.default_rng(2)
    p_world = rng.uniform([-10, -3, 5], [10, 3, 40], size=(80, 3))
    p_cam = se3.transform_points(se3.inverse(T_true), p_world)
    uv = (p_cam[:, :2] / p_cam[:, 2:]) * np.diag(P.K)[:2] + P.K[:2, 2]
    uv[:8] += 40.0  # outliers
    T_init = se3.retract(T_true, np.r_[0.02, -0.01, 0.01, 0.3, -0.2, 0.5])
    T, inl = estimate_pose(T_init, p_world, uv, P.K, huber_px=1.5, iterations=15)
    assert np.abs(se3.local(T_true, T)).max() < 1e-6
    assert not inl[:8].any() and inl[8:].all()


def test_inverse_depth_triangulation_is_exact_without_noise() -> None:
    w = make_window(4)
    P = w.problem
    lm = P.obs_lm
    Th, Tt = P.T_world_kf[P.lm_host[lm]], P.T_world_kf[P.obs_kf]
    xy = (P.obs_uv_px - P.K[:2, 2]) / np.diag(P.K)[:2]
    rho, parallax = triangulate_inverse_depth(Th, Tt, P.lm_bearing[lm], xy)
    good = parallax > np.radians(0.5)
    np.testing.assert_allclose(rho[good], P.lm_rho[lm][good], rtol=1e-6)


def test_batched_lie_matches_geometry_helpers() -> None:
    from metricslam.slam.vo import lie
    rng = np.random.default_rng(9)
    xi = np.concatenate([rng.normal(0, 1.0, (20, 3)), rng.normal(0, 5.0, (20, 3))], axis=1)
    xi[:3, :3] *= 1e-7  # the small-angle series
    T = lie.exp(xi)
    for k in range(20):
        np.testing.assert_allclose(T[k], se3.exp(xi[k]), atol=1e-10)
        np.testing.assert_allclose(lie.log(T[k:k + 1])[0], se3.log(T[k]), atol=1e-8)
    np.testing.assert_allclose(lie.local(T[:10], T[10:]),
                               np.array([se3.local(a, b) for a, b in zip(T[:10], T[10:])]), atol=1e-8)


def test_gauge_basis_spans_the_hessian_null_space_and_is_projected_out() -> None:
    from metricslam.slam.vo.marginalization import gauge_basis, project_out_gauge
    P = make_window(6, n_kf=4, n_per_kf=30).problem
    lin = linearize(P, 1e3)
    from metricslam.slam.vo.marginalization import eliminate_landmarks
    S, _ = eliminate_landmarks(lin)
    N = gauge_basis(P.T_world_kf)
    assert np.linalg.norm(S @ N) < 1e-6 * np.linalg.norm(S) * np.linalg.norm(N)
    rng = np.random.default_rng(6)
    A = rng.normal(size=(24, 24))
    prior = project_out_gauge(Prior(A @ A.T, rng.normal(size=24), P.T_world_kf))
    assert np.abs(prior.H @ N).max() < 1e-9 * np.abs(prior.H).max()
    assert np.abs(N.T @ prior.b).max() < 1e-9
    assert np.linalg.matrix_rank(prior.H) == 24 - 7


def test_pnp_relocalization_recovers_a_pose_far_from_any_prediction() -> None:
    from metricslam.slam.vo.motion_only import relocalize_pnp
    w = make_window(8)
    K = w.problem.K
    T_true = se3.retract(w.T_world_kf_true[3], np.r_[0.3, -0.2, 0.1, 1.0, 0.5, 2.0])
    rng = np.random.default_rng(8)
    p_cam = rng.uniform([-8, -3, 4], [8, 3, 40], size=(60, 3))
    p_world = se3.transform_points(T_true, p_cam)
    uv = (p_cam[:, :2] / p_cam[:, 2:]) * np.diag(K)[:2] + K[:2, 2]
    uv[:6] = rng.uniform(0, 600, (6, 2))  # gross outliers
    T, inl = relocalize_pnp(p_world, uv, K, huber_px=1.5, iterations=10)
    assert np.abs(se3.local(T_true, T)).max() < 1e-6
    assert inl[6:].all() and not inl[:6].any()
