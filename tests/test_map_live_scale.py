"""Which ``S_map_world`` the live map-frame poses use (``MapLocalization.S_map_world_live``;
``docs/history/rule_live_map_scale_session22.md``).

A session placed in the map before its learned scale is established carries the map's metres by
each match's network-depth scale. When the back end declares its scale established, its graph can
still be ~15 % short of metres for tens of frames (KITTI raw 0013), so turning the live alignment
rigid then put the live poses metres off: the live poses keep the network-depth estimate until it is
within ``LIVE_RIGID_LOG_SCALE`` of rigid, then go rigid for good. A session placed in an already
metric world is rigid at once; ``S_map_world`` itself (the finished trajectory) is rigid as before.
"""

from __future__ import annotations

import numpy as np

from metricslam.geometry import sim3
from metricslam.slam.map.localization import LIVE_RIGID_LOG_SCALE, LIVE_SPAN_MIN_M, MapLocalization
from metricslam.slam.map.relocalizer import agree_at
from tests.test_map_format import CAMERA, random_map

RIGID = sim3.from_rts(np.eye(3), np.array([1.0, 0.0, 2.0]), 1.0)


class _Relocalizer:
    """What ``refresh`` asks: a match version and the two estimates (rigid once metric)."""

    def __init__(self) -> None:
        self.version, self.pre_scale = 1, 1.19
        self.placed: list[tuple[np.ndarray, np.ndarray]] = []  # (world, map) position of each match's keyframe

    def S_map_world(self, poses, metric_world: bool = False):
        S = RIGID if metric_world else sim3.from_rts(np.eye(3), np.array([1.0, 0.0, 2.0]), self.pre_scale)
        return S, 2, 0

    def agreeing(self, S_map_world, poses, metric_world: bool = False):
        """Each match (standing for its map position) with its keyframe's world position, when the
        S_map_world it implies (its scale the one view's, pre_scale; S · p_world = p_map) agrees
        with ``S_map_world`` where it places the keyframe (the relocalizer's own test)."""
        return [(p_map, p_world) for p_world, p_map in self.placed
                if agree_at(S_map_world, sim3.from_rts(np.eye(3), p_map - self.pre_scale * p_world, self.pre_scale),
                            p_world[None], metric_world)]

    def map_position_m(self, m):
        return m


class _Backend:
    def __init__(self, established: bool) -> None:
        self.scale_established = established

    def optimized_keyframe_poses(self) -> dict:
        return {}


def _localization(established: bool) -> tuple[MapLocalization, _Relocalizer, _Backend]:
    loc = MapLocalization(random_map(0), CAMERA)
    loc.relocalizer, loc._backend = _Relocalizer(), _Backend(established)
    return loc, loc.relocalizer, loc._backend


def test_placed_before_its_scale_the_live_poses_go_rigid_only_once_the_scales_agree() -> None:
    loc, reloc, backend = _localization(established=False)
    loc.refresh()
    assert np.isclose(sim3.scale(loc.S_map_world_live), 1.19) and loc.S_map_world_live is loc.S_map_world
    backend.scale_established, reloc.pre_scale = True, 1.10  # declared, but the graph still converges
    loc.refresh(force=True)
    assert np.allclose(loc.S_map_world, RIGID) and np.isclose(sim3.scale(loc.S_map_world_live), 1.10)
    reloc.pre_scale = np.exp(0.5 * LIVE_RIGID_LOG_SCALE)  # within the gate: rigid from now on
    loc.refresh(force=True)
    assert np.allclose(loc.S_map_world_live, RIGID)
    reloc.pre_scale = 1.2
    loc.refresh(force=True)
    assert np.allclose(loc.S_map_world_live, RIGID) and np.allclose(loc.S_map_world, RIGID)


def test_placed_in_a_metric_world_the_live_poses_are_rigid_at_once() -> None:
    loc, _, _ = _localization(established=True)
    loc.refresh()
    assert np.allclose(loc.S_map_world_live, RIGID) and np.allclose(loc.S_map_world, RIGID)


def test_until_it_is_rigid_the_live_alignment_takes_its_scale_from_where_the_matches_place_the_keyframes():
    """Each match's scale is one view's network depth (here 1.19, the map's metres say 1.25), but
    matches spread along the path place their keyframes in the map 1.25 world units apart per unit:
    once 3 span LIVE_SPAN_MIN_M the live alignment's scale and translation are fitted to those
    positions (its rotation kept); over a shorter spread, or once rigid, it is left alone. The
    finished trajectory's S_map_world never is (rule_live_map_early_session24.md)."""
    loc, reloc, backend = _localization(established=False)
    origin = np.array([1.0, 0.0, 2.0])
    along = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.5], [0.3, 0.0, 3.0]])  # world units along the street
    reloc.placed = [(p, origin + 1.25 * p) for p in along]  # 1.9 m from their centroid: too close
    loc.refresh(force=True)
    assert np.isclose(sim3.scale(loc.S_map_world_live), 1.19)
    span = 1.2 * LIVE_SPAN_MIN_M / 1.25
    reloc.placed = [(p, origin + 1.25 * p) for p in along * span / 1.5]
    loc.refresh(force=True)
    S = loc.S_map_world_live
    assert np.isclose(sim3.scale(S), 1.25) and np.allclose(sim3.transform_points(S, along), origin + 1.25 * along)
    assert np.isclose(sim3.scale(loc.S_map_world), 1.19)  # the finished trajectory's: the matches' robust mean
    backend.scale_established, reloc.pre_scale = True, 1.0 + 0.5 * LIVE_RIGID_LOG_SCALE  # rigid now
    loc.refresh(force=True)
    assert np.allclose(loc.S_map_world_live, RIGID)
