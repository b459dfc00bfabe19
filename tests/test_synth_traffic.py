"""Traffic and overpasses in the synthetic world (training data for close-range depth)."""

from __future__ import annotations

import numpy as np

from metricslam.synth import SynthConfig, SynthScene
from metricslam.synth import trajectory as trj
from metricslam.synth.photometric import PhotometricConfig
from metricslam.synth.world import WorldConfig, build_world


def _config(world: WorldConfig, w: int = 160, h: int = 48) -> SynthConfig:
    return SynthConfig(width_px=w, height_px=h, world=world,
                       photometric=PhotometricConfig(noise_sigma=0.0, vignetting=0.0))


def test_traffic_off_leaves_the_world_unchanged() -> None:
    """Traffic has its own random stream: the default world's triangles come first, unchanged."""
    T = trj.procedural("turns", 80, seed=5)
    plain = build_world(T, 5).mesh
    busy = build_world(T, 5, WorldConfig(traffic_per_100m=15, bridges_per_km=20)).mesh
    assert len(busy) > len(plain) + 100
    np.testing.assert_array_equal(busy.vertices_m[:len(plain)], plain.vertices_m)
    np.testing.assert_array_equal(build_world(T, 5, WorldConfig()).mesh.vertices_m, plain.vertices_m)


def test_camera_path_stays_clear_and_traffic_is_close() -> None:
    """Dense poses along the path never see anything nearer than the clearance (no vehicle is
    driven through), and traffic brings content much closer than the empty street."""
    T = trj.procedural("straight", 120, seed=9)
    dense = T[::2]
    busy = SynthScene(T, seed=9, config=_config(WorldConfig(traffic_per_100m=25, bridges_per_km=30)))
    empty = SynthScene(T, seed=9, config=_config(WorldConfig()))
    near_busy, near_empty = [], []
    for pose in dense:
        _, depth_b = busy.renderer.render(pose)
        _, depth_e = empty.renderer.render(pose)
        centre = (slice(12, 36), slice(40, 120))
        hit_b = depth_b[depth_b > 0]
        assert hit_b.size and hit_b.min() > 0.3, "the camera passed through an object"
        near_busy.append(np.median(np.where(depth_b[centre] > 0, depth_b[centre], 250.0)))
        near_empty.append(np.median(np.where(depth_e[centre] > 0, depth_e[centre], 250.0)))
    assert np.median(near_busy) < 0.75 * np.median(near_empty)
