"""SO(3) / SE(3) / Sim(3) helpers and Umeyama alignment: identities, round trips, properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from metricslam.errors import AlignmentError, GeometryError
from metricslam.geometry import align, se3, sim3, so3

#: per-test settings (no global profile: other modules keep their own)
SETTINGS = settings(max_examples=40, deadline=None)

finite = st.floats(-1.0, 1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
seeds = st.integers(0, 2**32 - 1)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return so3.from_quat_xyzw(q)


def hat6(xi: np.ndarray) -> np.ndarray:
    """4x4 Lie algebra element of se(3) with tangent order [ω, v]."""
    A = np.zeros((4, 4))
    A[:3, :3] = so3.hat(xi[:3])
    A[:3, 3] = xi[3:]
    return A


def hat7(z: np.ndarray) -> np.ndarray:
    """4x4 Lie algebra element of sim(3) with tangent order [ω, u, λ]."""
    A = hat6(z[:6])
    A[:3, :3] += z[6] * np.eye(3)
    return A


# ---------------------------------------------------------------- SO(3)

@SETTINGS
@given(vec3, vec3)
def test_hat_is_cross_product_and_vee_inverts_it(a, b):
    assert np.allclose(so3.hat(a) @ b, np.cross(a, b))
    assert np.allclose(so3.vee(so3.hat(a)), a)


@SETTINGS
@given(vec3.map(lambda v: v * 3.0))
def test_so3_exp_matches_matrix_exponential(omega):
    assert np.allclose(so3.exp(omega), expm(so3.hat(omega)), atol=1e-12)


@pytest.mark.parametrize("theta", [0.0, 1e-12, 1e-8, 1e-4, 0.5, 2.0, np.pi - 1e-3, np.pi - 1e-7])
def test_so3_log_exp_round_trip_near_zero_and_pi(theta):
    rng = np.random.default_rng(7)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    omega = theta * axis
    R = so3.exp(omega)
    back = so3.log(R)
    assert np.allclose(so3.exp(back), R, atol=1e-10)
    if theta < np.pi - 1e-6:  # at π the sign of the axis is ambiguous
        assert np.allclose(back, omega, atol=1e-9)
    assert so3.angle(R) == pytest.approx(theta, abs=2e-7 if theta < 1e-6 else 1e-8)


def test_so3_log_at_exactly_pi_gives_angle_pi():
    R = so3.exp(np.array([0.0, 0.0, np.pi]))
    w = so3.log(R)
    assert np.linalg.norm(w) == pytest.approx(np.pi)
    assert np.allclose(so3.exp(w), R, atol=1e-12)


@SETTINGS
@given(seeds)
def test_quaternion_round_trip_xyzw(seed):
    R = random_rotation(np.random.default_rng(seed))
    q = so3.to_quat_xyzw(R)
    assert q[3] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
    assert np.allclose(so3.from_quat_xyzw(q), R, atol=1e-12)
    assert np.allclose(so3.from_quat_xyzw(-q), R, atol=1e-12)


def test_quaternion_order_is_xyzw():
    # 90° about z: q = [0, 0, sin 45°, cos 45°]
    R = so3.from_quat_xyzw(np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]))
    assert np.allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_so3_rejects_non_rotations_and_zero_quaternion():
    with pytest.raises(GeometryError):
        so3.check_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(GeometryError):
        so3.check_rotation(2 * np.eye(3))
    with pytest.raises(GeometryError):
        so3.from_quat_xyzw(np.zeros(4))
    with pytest.raises(GeometryError):
        so3.exp(np.zeros(4))


@SETTINGS
@given(seeds)
def test_project_to_so3_returns_nearest_rotation(seed):
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    noisy = R + 1e-3 * rng.normal(size=(3, 3))
    P = so3.project_to_so3(noisy)
    so3.check_rotation(P, tol=1e-10)
    assert np.abs(P - R).max() < 1e-2


# ---------------------------------------------------------------- SE(3)

@SETTINGS
@given(vec3.map(lambda v: v * 3.0), vec3.map(lambda v: v * 10.0))
def test_se3_exp_matches_matrix_exponential_and_log_inverts(omega, v):
    xi = np.concatenate([omega, v])
    T = se3.exp(xi)
    assert np.allclose(T, expm(hat6(xi)), atol=1e-9)
    if np.linalg.norm(omega) < np.pi - 1e-3:
        assert np.allclose(se3.log(T), xi, atol=1e-8)


@pytest.mark.parametrize("theta", [0.0, 1e-10, 1e-5, np.pi - 1e-4])
def test_se3_round_trip_near_zero_and_pi(theta):
    xi = np.array([0.0, theta, 0.0, 1.0, -2.0, 0.5])
    T = se3.exp(xi)
    assert np.allclose(T, expm(hat6(xi)), atol=1e-10)
    assert np.allclose(se3.exp(se3.log(T)), T, atol=1e-10)
    assert np.allclose(se3.log(T), xi, atol=1e-6)


@SETTINGS
@given(seeds)
def test_se3_group_identities(seed):
    rng = np.random.default_rng(seed)
    A = se3.exp(rng.normal(size=6))
    B = se3.exp(rng.normal(size=6))
    C = se3.exp(rng.normal(size=6))
    assert np.allclose(se3.inverse(A) @ A, np.eye(4), atol=1e-12)
    assert np.allclose(se3.inverse(A), np.linalg.inv(A), atol=1e-12)
    assert np.allclose(se3.compose(A, B, C), (A @ B) @ C)
    assert np.allclose(se3.compose(A, B, C), A @ (B @ C))
    assert np.allclose(se3.inverse(A @ B), se3.inverse(B) @ se3.inverse(A), atol=1e-12)
    xi = rng.normal(size=6) * 0.3
    assert np.allclose(se3.retract(A, xi), A @ se3.exp(xi))
    assert np.allclose(se3.local(A, se3.retract(A, xi)), xi, atol=1e-9)


@SETTINGS
@given(seeds)
def test_se3_adjoint_moves_a_right_perturbation_to_the_left(seed):
    rng = np.random.default_rng(seed)
    T = se3.exp(rng.normal(size=6))
    xi = rng.normal(size=6) * 0.5
    assert np.allclose(T @ se3.exp(xi) @ se3.inverse(T), se3.exp(se3.adjoint(T) @ xi), atol=1e-9)
    assert np.allclose(se3.adjoint(se3.inverse(T)), np.linalg.inv(se3.adjoint(T)), atol=1e-9)


def test_se3_transform_points_and_kitti_rows():
    T = se3.from_rt(so3.exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    p = np.array([[0.5, -1.0, 4.0], [0.0, 0.0, 0.0]])
    hom = np.hstack([p, np.ones((2, 1))]) @ T.T
    assert np.allclose(se3.transform_points(T, p), hom[:, :3])
    assert np.allclose(se3.from_3x4_rows(T[:3].reshape(-1)), T)


def test_se3_check_rejects_bad_shapes_and_rows():
    with pytest.raises(GeometryError):
        se3.check(np.eye(3))
    bad = np.eye(4)
    bad[3, 0] = 1.0
    with pytest.raises(GeometryError):
        se3.check(bad)
    assert se3.check(np.eye(4)[:3]).shape == (4, 4)


# ---------------------------------------------------------------- Sim(3)

@SETTINGS
@given(vec3.map(lambda v: v * 3.0), vec3.map(lambda v: v * 10.0), st.floats(-2.0, 2.0))
def test_sim3_exp_matches_matrix_exponential_and_log_inverts(omega, u, lam):
    z = np.concatenate([omega, u, [lam]])
    S = sim3.exp(z)
    assert np.allclose(S, expm(hat7(z)), atol=1e-8, rtol=1e-9)
    assert sim3.scale(S) == pytest.approx(np.exp(lam))
    if np.linalg.norm(omega) < np.pi - 1e-3:
        assert np.allclose(sim3.log(S), z, atol=1e-7)


@pytest.mark.parametrize("lam", [0.0, 1e-12, -1e-7, 1.5])
@pytest.mark.parametrize("theta", [0.0, 1e-9, 1.0, np.pi - 1e-4])
def test_sim3_round_trip_near_zero_scale_and_angle(theta, lam):
    z = np.array([theta, 0.0, 0.0, 0.3, 0.2, -1.0, lam])
    S = sim3.exp(z)
    assert np.allclose(S, expm(hat7(z)), atol=1e-10)
    assert np.allclose(sim3.exp(sim3.log(S)), S, atol=1e-10)


def test_sim3_with_zero_scale_log_equals_se3():
    xi = np.array([0.2, -0.1, 0.4, 1.0, 2.0, 3.0])
    assert np.allclose(sim3.exp(np.append(xi, 0.0)), se3.exp(xi), atol=1e-12)


@SETTINGS
@given(seeds)
def test_sim3_group_identities(seed):
    rng = np.random.default_rng(seed)
    A = sim3.exp(rng.normal(size=7) * 0.7)
    B = sim3.exp(rng.normal(size=7) * 0.7)
    assert np.allclose(sim3.inverse(A) @ A, np.eye(4), atol=1e-10)
    assert np.allclose(sim3.inverse(A), np.linalg.inv(A), atol=1e-10)
    assert sim3.scale(A @ B) == pytest.approx(sim3.scale(A) * sim3.scale(B))
    z = rng.normal(size=7) * 0.3
    assert np.allclose(sim3.local(A, sim3.retract(A, z)), z, atol=1e-8)
    p = rng.normal(size=(5, 3))
    R, t, s = sim3.split(A)
    assert np.allclose(sim3.transform_points(A, p), s * p @ R.T + t)


def test_sim3_rejects_bad_scale():
    with pytest.raises(GeometryError):
        sim3.from_rts(np.eye(3), np.zeros(3), 0.0)
    with pytest.raises(GeometryError):
        sim3.from_rts(np.eye(3), np.zeros(3), float("nan"))
    with pytest.raises(GeometryError):
        sim3.split(np.eye(3))


def test_sim3_gtsam_convention():
    """gtsam's Similarity3(R, t_g, s) maps p -> s·(R·p + t_g), our S uses t = s·t_g."""
    gtsam = pytest.importorskip("gtsam")
    R = so3.exp(np.array([0.1, 0.2, -0.3]))
    t_g, s = np.array([1.0, -2.0, 0.5]), 1.7
    g = gtsam.Similarity3(gtsam.Rot3(R), t_g, s)
    S = sim3.from_rts(R, s * t_g, s)
    p = np.array([0.3, 0.4, 5.0])
    assert np.allclose(g.transformFrom(p), sim3.transform_points(S, p))
    M = g.matrix()  # gtsam's projective form [[R, t_g], [0, 1/s]]
    assert np.allclose(M / M[3, 3], S)


@SETTINGS
@given(seeds)
def test_exp_and_log_match_gtsam_tangent_order(seed):
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(seed)
    z = rng.normal(size=7) * 0.8
    M = gtsam.Similarity3.Expmap(z).matrix()
    assert np.allclose(M / M[3, 3], sim3.exp(z), atol=1e-9)
    assert np.allclose(gtsam.Pose3.Expmap(z[:6]).matrix(), se3.exp(z[:6]), atol=1e-9)
    if np.linalg.norm(z[:3]) < np.pi - 1e-3:
        assert np.allclose(gtsam.Similarity3.Logmap(gtsam.Similarity3.Expmap(z)), sim3.log(sim3.exp(z)), atol=1e-8)
        assert np.allclose(gtsam.Pose3.Logmap(gtsam.Pose3(se3.exp(z[:6]))), se3.log(se3.exp(z[:6])), atol=1e-8)


# ---------------------------------------------------------------- Umeyama

def _random_sim3(rng: np.random.Generator, with_scale: bool) -> np.ndarray:
    s = float(np.exp(rng.uniform(-1.5, 1.5))) if with_scale else 1.0
    return sim3.from_rts(random_rotation(rng), rng.normal(size=3) * 10, s)


@SETTINGS
@given(seeds, st.booleans())
def test_umeyama_recovers_a_random_similarity_exactly(seed, with_scale):
    rng = np.random.default_rng(seed)
    S_true = _random_sim3(rng, with_scale)
    p_est = rng.normal(size=(30, 3)) * 5
    p_gt = sim3.transform_points(S_true, p_est)
    S = align.umeyama(p_est, p_gt, with_scale=with_scale)
    assert np.allclose(S, S_true, atol=1e-8)


@SETTINGS
@given(seeds)
def test_umeyama_with_noise_is_close_and_se3_keeps_unit_scale(seed):
    rng = np.random.default_rng(seed)
    S_true = _random_sim3(rng, True)
    p_est = rng.normal(size=(200, 3)) * 5
    p_gt = sim3.transform_points(S_true, p_est) + rng.normal(size=(200, 3)) * 1e-3
    S = align.umeyama(p_est, p_gt)
    assert sim3.scale(S) == pytest.approx(sim3.scale(S_true), rel=1e-3)
    assert sim3.scale(align.umeyama(p_est, p_gt, with_scale=False)) == pytest.approx(1.0)


@SETTINGS
@given(seeds)
def test_align_trajectory_recovers_poses(seed):
    rng = np.random.default_rng(seed)
    S_true = _random_sim3(rng, True)
    T_gt = np.stack([se3.exp(rng.normal(size=6) * 2) for _ in range(12)])
    # an estimate in another frame and at another scale: T_est = S_true⁻¹ applied to T_gt
    T_est = align.apply_to_poses(sim3.inverse(S_true), T_gt)
    S, T_aligned = align.align_trajectory(T_est, T_gt)
    assert np.allclose(S, S_true, atol=1e-8)
    assert np.allclose(T_aligned, T_gt, atol=1e-8)


def test_umeyama_with_reflection_in_data_still_returns_a_rotation():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(20, 3))
    q = p * np.array([1.0, 1.0, -1.0])  # a mirror image: best proper rotation, det = +1
    S = align.umeyama(p, q)
    R, _, _ = sim3.split(S)
    assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((5, 3)),                                             # coincident
        np.outer(np.linspace(0, 10, 8), [1.0, 2.0, 3.0]),             # collinear
        np.zeros((2, 3)),                                             # too few
        np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 0, 0], [0, 1, 0]]),  # non-finite
    ],
)
def test_degenerate_alignment_raises(points):
    with pytest.raises(AlignmentError):
        align.umeyama(points, points + 1.0)


def test_alignment_rejects_mismatched_shapes():
    with pytest.raises(AlignmentError):
        align.umeyama(np.zeros((5, 3)), np.zeros((4, 3)))
