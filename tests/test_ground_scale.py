"""Ground-plane scale: configuration and mounting-height checks, the graph factor, the back end
with ground factors, and the scale-health warning (issue #33)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from graph_chain import FAST_DRIFT
from metricslam.calibration import load_calibration
from metricslam.errors import CalibrationError, ConfigError, GraphError
from metricslam.geometry import sim3
from metricslam.slam.config_file import load_system_config
from metricslam.slam.events import GroundScaleMeasured
from metricslam.slam.graph.backend import GlobalBackend
from metricslam.slam.graph.config import GraphConfig
from metricslam.slam.graph.ground_factor import make_ground_scale_factor
from metricslam.slam.graph.gtsam_sim3 import key
from metricslam.slam.graph.synthetic import SimulatedVO, SyntheticDepthSource, circle_path
from metricslam.slam.ground.config import ScaleConfig, check_mount_height, parse_scale_sources
from metricslam.slam.system_config import SystemConfig

BAD_HEIGHTS = [0.0, -1.65, 10.5, float("nan"), float("inf")]


# -- configuration ----------------------------------------------------------------------------
def test_default_is_learned_only_without_a_ground_meter():
    config = SystemConfig()
    assert config.scale.sources == ("learned",) and not config.use_ground and config.use_scale
    assert config.mode == "metric"


@pytest.mark.parametrize("h", BAD_HEIGHTS)
def test_bad_mounting_heights_are_refused(h):
    with pytest.raises(ConfigError, match="height above the road"):
        check_mount_height(h, "--mount-height")
    with pytest.raises(ConfigError, match="mount_height_m"):
        load_system_config(env={}, overrides={"scale": {"mount_height_m": h}})


def test_ground_needs_a_mounting_height_and_sources_parse():
    with pytest.raises(ConfigError, match="needs the camera's mounting height"):
        load_system_config(env={}, overrides={"scale": {"sources": ["ground"]}})
    cfg = load_system_config(env={"METRICSLAM_SCALE__SOURCES": "[ground]",
                                  "METRICSLAM_SCALE__MOUNT_HEIGHT_M": "1.2"})
    assert cfg.scale.sources == ("ground",) and cfg.use_ground and not cfg.use_scale
    assert cfg.mode == "metric"
    assert parse_scale_sources("learned, ground") == ("learned", "ground")
    for bad in ("", "lidar", "ground,ground"):
        with pytest.raises(ConfigError):
            parse_scale_sources(bad)
    assert ScaleConfig(sources="learned,ground", mount_height_m=1.65).ground_on


def _calib_file(tmp_path, extra: str):
    p = tmp_path / "cam.yaml"
    p.write_text(f"width: 640\nheight: 480\nfx: 500\nfy: 500\ncx: 319.5\ncy: 239.5\n{extra}")
    return p


def test_calibration_file_carries_the_mounting_height(tmp_path):
    calib = load_calibration(_calib_file(tmp_path, "mount_height_m: 0.72\n"))
    assert calib.mount_height_m == 0.72
    again = tmp_path / "again.yaml"
    again.write_text(calib.to_yaml())
    assert load_calibration(again).mount_height_m == 0.72
    assert load_calibration(_calib_file(tmp_path, "")).mount_height_m is None


@pytest.mark.parametrize("text", ["0", "-1.65", "12", ".nan", "high"])
def test_calibration_file_refuses_a_bad_mounting_height(tmp_path, text):
    with pytest.raises(CalibrationError, match="mount_height_m"):
        load_calibration(_calib_file(tmp_path, f"mount_height_m: {text}\n"))


# -- the factor ---------------------------------------------------------------------------------
def test_ground_factor_talks_only_about_scale_and_is_robust():
    S = gtsam.Similarity3.Expmap(np.array([0.1, -0.2, 0.3, 1.0, 2.0, -1.0, 0.4]))
    v = gtsam.Values()
    v.insert(key(0), S)
    near = make_ground_scale_factor(key(0), S, S.scale() * 1.02, 0.05, 1.345)
    A, b = near.linearize(v).jacobian()
    assert np.abs(A[6, :6]).max() < 1e-12 and A[6, 6] == pytest.approx(1 / 0.05, rel=1e-6)
    assert -b[6] * 0.05 == pytest.approx(np.log(1 / 1.02), rel=1e-6)
    far = make_ground_scale_factor(key(0), S, S.scale() * 2.0, 0.05, 1.345)
    A_far, _ = far.linearize(v).jacobian()
    assert A_far[6, 6] < 0.4 * A[6, 6]  # a "road" that was a car roof: down-weighted (Huber)
    with pytest.raises(GraphError):
        make_ground_scale_factor(key(0), S, float("nan"), 0.05, 1.345)


# -- the back end -------------------------------------------------------------------------------
class _TruthGroundMeter:
    """Ground measurements from the simulated VO's true scale, with noise and a few outliers."""

    def __init__(self, vo: SimulatedVO, noise_log: float = 0.02, seed: int = 0, every: int = 1) -> None:
        self.config = ScaleConfig(sources=("learned", "ground"), mount_height_m=1.65)
        self.vo, self.every = vo, every
        self.rng = np.random.default_rng(seed)
        self.noise = noise_log
        self.counts = {"ground_measured": 0, "ground_accepted": 0}
        self.reasons: dict[str, int] = {}

    def measure(self, kf, scale_of=None):
        self.counts["ground_measured"] += 1
        k = int(kf.kf_id)
        if k == 0 or k % self.every:
            return GroundScaleMeasured(k, k, kf.t_ns, float("nan"), float("nan"), float("inf"), False, "no road")
        s = self.vo.sigma_at_kf[k] * float(np.exp(self.noise * self.rng.normal()))
        if k % 17 == 0:
            s *= 1.6  # a car bonnet taken for the road
        self.counts["ground_accepted"] += 1
        return GroundScaleMeasured(k, k, kf.t_ns, 1.65 / s, s, self.config.ground_sigma_log, True)


def _run(vo, backend, n):
    for _ in range(n):
        backend.on_keyframe_marginalized(vo.next_keyframe())
        S = backend.take_correction()
        if S is not None:
            vo.apply_similarity(S)
    backend.close()
    est = backend.optimized_keyframe_poses()
    return np.array([sim3.scale(est[k]) for k in range(n)]) / np.array(vo.sigma_at_kf) - 1


@pytest.mark.parametrize("inline", [True, False])
def test_ground_factors_alone_make_the_graph_metric(inline):
    n = 60
    vo = SimulatedVO(circle_path(n, 40.0, turns=0.5), drift_per_kf=0.01, sigma0=3.0, seed=2)
    meter = _TruthGroundMeter(vo)
    backend = GlobalBackend(GraphConfig(inline=inline, **FAST_DRIFT), ground_meter=meter)
    s_err = _run(vo, backend, n)
    assert not backend.estimator.graph.anchor_scale
    assert np.median(np.abs(s_err)) < 0.03 and np.abs(s_err).max() < 0.08
    stats = backend.stats()
    assert stats["ground_factors"] == stats["ground_accepted"] == n - 1
    assert backend.scale_established and stats["scale_factors"] == 0


def _health_run(bias: float):
    n = 40
    vo = SimulatedVO(circle_path(n, 40.0, turns=0.4), drift_per_kf=0.0, sigma0=1.0, seed=4)
    meter = _TruthGroundMeter(vo, noise_log=0.01)
    # the default sigmas: a learned keyframe factor 0.2 (per-image network error), ground 0.05
    backend = GlobalBackend(GraphConfig(inline=True, depth_queue_size=n),
                            depth_source=SyntheticDepthSource(n, bias=bias), ground_meter=meter)
    s_err = _run(vo, backend, n)
    return backend, s_err


def test_health_warns_when_the_depth_source_is_scaled_1_3():
    backend, s_err = _health_run(bias=1.3)  # inverse depth x1.3: the learned scale reads 1/1.3
    health = backend.stats()["scale_health"]
    assert health["warning"] and health["warnings_issued"] == 1
    assert health["disagreement_log_median"] == pytest.approx(np.log(1 / 1.3), abs=0.05)
    assert np.median(np.abs(s_err)) < 0.05  # the fused graph follows the tighter ground factors


def test_health_is_quiet_when_the_sources_agree():
    backend, _ = _health_run(bias=1.0)
    health = backend.stats()["scale_health"]
    assert not health["warning"] and health["warnings_issued"] == 0
    assert abs(health["disagreement_log_median"]) < 0.05
    assert all(k["learned"] and k["ground"] for k in health["keyframes"][1:])
