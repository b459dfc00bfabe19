"""Street world laid out along the camera path: road, kerbs, sidewalks, buildings, cars, trees.

The road centre line follows the camera path ``camera_height_m`` below the camera (world y is
down). Ground is a ribbon of cells along the path; where the path meets itself (loops,
crossings) the earlier road wins and later ribbon cells that would overlap it are dropped.
Objects are placed on both sides and rejected if they would stand on any road or sidewalk of
the whole path or overlap another object, so loops and crossings stay drivable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from metricslam.synth import materials as mt
from metricslam.synth.meshes import UP, Mesh, MeshBuilder
from metricslam.synth.traffic import add_bridges, add_traffic

_CELL_M = 2.0  # ground ribbon step along the path
_REVISIT_M = 40.0  # path parts further apart than this (in arc length) are "other parts"
_SINK_PER_M = 1e-5  # ribbon height offset per metre of arc length (see _ribbon)
_TERRAIN_CELL_M = 10.0
_TERRAIN_DROP_M = 0.3  # fallback ground lies this far below the ribbon


class WorldConfig(BaseModel):
    """Layout parameters of the street world (metres)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    camera_height_m: float = Field(1.65, gt=0.3)
    road_half_width_m: tuple[float, float] = (4.0, 5.5)
    sidewalk_width_m: tuple[float, float] = (2.0, 4.0)
    verge_width_m: float = Field(18.0, gt=0)
    margin_before_m: float = Field(40.0, ge=0)
    margin_after_m: float = Field(160.0, ge=0)
    building_probability: float = Field(0.8, ge=0, le=1)
    car_probability: float = Field(0.5, ge=0, le=1)
    #: vehicles standing on the road beside the path per 100 m (0 = empty road; see traffic.py)
    traffic_per_100m: float = Field(0.0, ge=0, le=50)
    #: overpasses across the path per km (0 = none)
    bridges_per_km: float = Field(0.0, ge=0, le=50)


@dataclass(frozen=True)
class World:
    """A built world: triangles plus lighting.

    Attributes:
        mesh: all triangles.
        sun_dir_world: (3,) unit vector towards the sun (world frame, y down).
        road_half_width_m, sidewalk_width_m: the cross-section used.
    """

    mesh: Mesh
    sun_dir_world: np.ndarray
    road_half_width_m: float
    sidewalk_width_m: float


def _centerline(T_world_cam: np.ndarray, cfg: WorldConfig) -> tuple[np.ndarray, np.ndarray]:
    """Road centre points (M, 3) every metre and their horizontal unit tangents (M, 3)."""
    p = T_world_cam[:, :3, 3] + cfg.camera_height_m * np.array([0.0, 1.0, 0.0])
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    keep = np.concatenate([[True], step > 1e-3])
    p = p[keep]
    fwd0 = T_world_cam[0, :3, 2]
    fwd1 = T_world_cam[-1, :3, 2]
    if len(p) >= 2:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        s_new = np.arange(0.0, s[-1] + 1e-9, 1.0)
        mid = np.stack([np.interp(s_new, s, p[:, k]) for k in range(3)], axis=1)
        fwd0 = mid[min(3, len(mid) - 1)] - mid[0] if len(mid) > 1 else fwd0
        fwd1 = mid[-1] - mid[max(0, len(mid) - 4)] if len(mid) > 1 else fwd1
    else:
        mid = p[:1]

    def horiz(v: np.ndarray) -> np.ndarray:
        v = np.array([v[0], 0.0, v[2]])
        n = np.linalg.norm(v)
        return v / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])

    fwd0, fwd1 = horiz(fwd0), horiz(fwd1)
    before = mid[0] - fwd0 * np.arange(cfg.margin_before_m, 0.0, -1.0)[:, None]
    after = mid[-1] + fwd1 * np.arange(1.0, cfg.margin_after_m + 1.0, 1.0)[:, None]
    pts = np.concatenate([before, mid, after])
    tangent = np.gradient(pts, axis=0)
    kernel = np.ones(7) / 7.0
    tangent = np.stack([np.convolve(np.pad(tangent[:, k], 3, mode="edge"), kernel, "valid")
                        for k in range(3)], axis=1)
    tangent[:, 1] = 0.0
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    return pts, tangent


class _Layout:
    """Placement bookkeeping: path clearance and object-object overlap."""

    def __init__(self, centers: np.ndarray) -> None:
        self.tree = cKDTree(centers[:, [0, 2]])
        self.occupied: set[tuple[int, int]] = set()

    @staticmethod
    def _footprint(center: np.ndarray, a: np.ndarray, length: float, width: float,
                   step: float) -> np.ndarray:
        b = np.cross(UP, a)
        la = np.linspace(-length / 2, length / 2, max(2, int(np.ceil(length / step)) + 1))
        wb = np.linspace(-width / 2, width / 2, max(2, int(np.ceil(width / step)) + 1))
        g = center[None, None, [0, 2]] + la[:, None, None] * a[[0, 2]] + wb[None, :, None] * b[[0, 2]]
        return g.reshape(-1, 2)

    def try_place(self, center: np.ndarray, a: np.ndarray, length: float, width: float,
                  clearance_m: float) -> bool:
        """Reserve a footprint if it keeps ``clearance_m`` from the path and overlaps nothing."""
        pts = self._footprint(center, a, length, width, 0.5)
        dist, _ = self.tree.query(pts)
        if dist.min() < clearance_m:
            return False
        inner = self._footprint(center, a, max(length - 1.0, 0.1), max(width - 1.0, 0.1), 0.5)
        cells = {(int(np.floor(x)), int(np.floor(z))) for x, z in inner}
        if cells & self.occupied:
            return False
        self.occupied |= cells
        return True


def _free_of_other_parts(tree: cKDTree, pts: np.ndarray, s_all: np.ndarray, centre: np.ndarray,
                         s_cell: np.ndarray, w: float, outer_lat: float) -> np.ndarray:
    """Mask of off-road cells that neither touch another path part's road nor lie inside an
    earlier part's ribbon (which already covers that ground)."""
    keep = np.ones(len(centre), bool)
    for i, near in enumerate(tree.query_ball_point(centre[:, [0, 2]], max(outer_lat + 1.0, w + 2.0))):
        if not near:
            continue
        near = np.asarray(near)
        ds = s_all[near] - s_cell[i]
        dist = np.linalg.norm(pts[near][:, [0, 2]] - centre[i, [0, 2]], axis=1)
        other = (np.abs(ds) > _REVISIT_M) & (np.abs(pts[near, 1] - centre[i, 1]) < 4.0)
        keep[i] = not ((other & (dist < w + 2.0)).any() or (other & (ds < 0) & (dist < outer_lat + 1.0)).any())
    return keep


def _terrain(mb: MeshBuilder, pts: np.ndarray, cfg: WorldConfig) -> None:
    """Coarse fallback ground under everything within ``verge_width_m + 90`` m of the path, so
    no gap between ribbons (at crossings) ever shows the void."""
    reach = cfg.verge_width_m + 90.0
    lo = pts[:, [0, 2]].min(axis=0) - reach
    hi = pts[:, [0, 2]].max(axis=0) + reach
    gx = np.arange(lo[0], hi[0] + _TERRAIN_CELL_M, _TERRAIN_CELL_M)
    gz = np.arange(lo[1], hi[1] + _TERRAIN_CELL_M, _TERRAIN_CELL_M)
    tree = cKDTree(pts[:, [0, 2]])
    X, Z = np.meshgrid(gx, gz, indexing="ij")
    dist, nearest = tree.query(np.stack([X.ravel(), Z.ravel()], 1))
    Y = (pts[nearest, 1] + _TERRAIN_DROP_M).reshape(X.shape)
    used = (dist < reach + _TERRAIN_CELL_M).reshape(X.shape)
    i, j = np.nonzero(used[:-1, :-1] & used[1:, :-1] & used[:-1, 1:] & used[1:, 1:])

    def v(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.stack([X[a, b], Y[a, b], Z[a, b]], 1)

    corners = np.stack([v(i, j), v(i + 1, j), v(i + 1, j + 1), v(i, j + 1)], 1)
    uv = corners[:, :, [0, 2]]
    mb.add_quads(corners, uv, mt.VERGE, (0.8, 0.0, 0.0), np.tile(UP, (len(corners), 1)))


def _ribbon(mb: MeshBuilder, pts: np.ndarray, tangent: np.ndarray, w: float, sw: float,
            cfg: WorldConfig) -> None:
    """Road, kerbs, sidewalks and verges along the path, minus cells owned by other parts."""
    idx = np.arange(0, len(pts), int(_CELL_M))
    c, t = pts[idx], tangent[idx]
    right = np.cross(np.array([0.0, 1.0, 0.0]), t)
    s = idx.astype(float)
    tree = cKDTree(pts[:, [0, 2]])
    s_all = np.arange(len(pts), dtype=float)
    kerb_h, verge_out = 0.15, w + sw + cfg.verge_width_m
    # (inner lateral, outer lateral, height, material)
    bands = [(-w, w, 0.0, mt.ROAD)]
    for sign in (1.0, -1.0):
        bands += [(sign * w, sign * (w + sw), kerb_h, mt.SIDEWALK),
                  (sign * (w + sw), sign * verge_out, kerb_h - 0.02, mt.VERGE)]

    def point(k: np.ndarray, lat: float, h: float) -> np.ndarray:
        # 10 µm lower per metre of path: where the path meets itself (loops, crossings) the
        # earlier surface lies a fraction of a millimetre above the later one, so the z-buffer
        # resolves the overlap the same way in every frame and both cameras (no z-fighting)
        return c[k] + right[k] * lat + UP * (h - _SINK_PER_M * s[k])[:, None]

    k0 = np.arange(len(idx) - 1)
    k1 = k0 + 1
    for lat_in, lat_out, h, mat in bands:
        lo, hi = sorted((lat_in, lat_out))
        centre = 0.5 * (point(k0, 0.5 * (lo + hi), h) + point(k1, 0.5 * (lo + hi), h))
        s_cell = 0.5 * (s[k0] + s[k1])
        if mat == mt.ROAD:  # roads always stay; overlaps are resolved by the height offset
            keep = np.ones(len(k0), bool)
        else:
            keep = _free_of_other_parts(tree, pts, s_all, centre, s_cell, w, max(abs(lo), abs(hi)))
        corners = np.stack([point(k0, lo, h), point(k0, hi, h), point(k1, hi, h),
                            point(k1, lo, h)], axis=1)[keep]
        uv = np.stack([np.stack([s[k0], np.full(len(k0), lo)], 1), np.stack([s[k0], np.full(len(k0), hi)], 1),
                       np.stack([s[k1], np.full(len(k0), hi)], 1), np.stack([s[k1], np.full(len(k0), lo)], 1)],
                      axis=1)[keep]
        # lo < hi makes every cell face up; cells folded over on the inside of tight turns face
        # down and are culled by the renderer instead of z-fighting with their neighbours
        mb.add_quads(corners, uv, mat, (1.0, w, 0.0))
        if mat == mt.SIDEWALK:
            lat = lat_in
            kc = np.stack([point(k0, lat, 0.0), point(k1, lat, 0.0), point(k1, lat, kerb_h),
                           point(k0, lat, kerb_h)], axis=1)[keep]
            kuv = np.stack([np.stack([s[k0], np.zeros(len(k0))], 1), np.stack([s[k1], np.zeros(len(k0))], 1),
                            np.stack([s[k1], np.full(len(k0), kerb_h)], 1),
                            np.stack([s[k0], np.full(len(k0), kerb_h)], 1)], axis=1)[keep]
            inward = -np.sign(lat) * right[k0][keep]
            mb.add_quads(kc, kuv, mt.KERB, (1.0, 0.0, 0.0), inward)


def _objects(mb: MeshBuilder, pts: np.ndarray, tangent: np.ndarray, w: float, sw: float,
             rng: np.random.Generator, cfg: WorldConfig) -> None:
    """Buildings, parked cars, poles, trees and clutter on both sides of the path."""
    layout = _Layout(pts)
    n = len(pts)
    right_all = np.cross(np.array([0.0, 1.0, 0.0]), tangent)

    def frame(s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = int(np.clip(round(s), 0, n - 1))
        return pts[k], tangent[k], right_all[k]

    kerb_h = 0.15
    for sign in (1.0, -1.0):
        # buildings
        s = 0.0
        while s < n:
            width = float(rng.uniform(8.0, 24.0))
            depth = float(rng.uniform(8.0, 18.0))
            setback = float(rng.uniform(0.3, 7.0))
            height = float(rng.choice([rng.uniform(5, 12), rng.uniform(10, 22), rng.uniform(20, 32)],
                                      p=[0.45, 0.4, 0.15]))
            p, t, r = frame(s + width / 2)
            lat = sign * (w + sw + setback + depth / 2)
            centre = p + r * lat
            if rng.random() < cfg.building_probability and layout.try_place(
                    centre, t, width, depth, w + sw - 0.05):
                brick = rng.random() < 0.55
                params = (float(rng.uniform(0.75, 1.25)), float(rng.uniform(1.8, 3.4)),
                          float(rng.uniform(0.08, 0.35)))
                mb.add_box(centre + UP * kerb_h, t, width, depth, -8.0, height,
                           mt.FACADE_BRICK if brick else mt.FACADE_PLASTER, params,
                           top_material=mt.ROOF, uv_offset=(float(rng.uniform(0, 50)), 0.0))
            s += width + (float(rng.uniform(2.0, 10.0)) if rng.random() < 0.25
                          else float(rng.uniform(0.0, 1.0)))
        # parked cars
        s = float(rng.uniform(0, 10))
        while s < n:
            p, t, r = frame(s)
            if rng.random() < cfg.car_probability:
                yaw = float(rng.normal(0.0, 0.03))
                a = np.cos(yaw) * t + np.sin(yaw) * r
                centre = p + r * sign * (w - 1.15)
                if layout.try_place(centre, a, 4.4, 1.8, 1.95):
                    gain = float(rng.choice([rng.uniform(0.3, 0.6), rng.uniform(0.9, 1.9)]))
                    off = (float(rng.uniform(0, 30)), 0.0)
                    mb.add_box(centre, a, 3.6, 1.6, 0.0, 0.4, mt.TYRE, (1.0, 0.0, 0.0))
                    mb.add_box(centre, a, 4.3, 1.78, 0.3, 1.05, mt.CAR_BODY, (gain, 0.0, 0.0),
                               uv_offset=off)
                    mb.add_box(centre - 0.25 * a, a, 2.3, 1.6, 1.05, 1.5, mt.CAR_GLASS,
                               (1.0, float(rng.uniform(0.8, 1.3)), float(rng.uniform(0.1, 0.3))),
                               top_material=mt.CAR_BODY, uv_offset=off)
            s += float(rng.uniform(5.5, 20.0))
        # poles with lamp heads
        s = float(rng.uniform(0, 20))
        while s < n:
            p, t, r = frame(s)
            base = p + r * sign * (w + 0.5) + UP * kerb_h
            if layout.try_place(base, t, 0.3, 0.3, w + 0.3):
                mb.add_box(base, t, 0.16, 0.16, 0.0, 6.5, mt.POLE, (1.0, 0.0, 0.0))
                mb.add_box(base - r * sign * 0.5, t, 0.35, 1.0, 6.3, 6.55, mt.POLE, (0.8, 0.0, 0.0))
            s += float(rng.uniform(20.0, 40.0))
        # trees
        s = float(rng.uniform(0, 10))
        while s < n:
            p, t, r = frame(s)
            if rng.random() < 0.6:
                base = p + r * sign * (w + sw - 0.9) + UP * kerb_h
                size = float(rng.uniform(2.2, 3.6))
                if layout.try_place(base, t, size, size, w + 0.3):
                    mb.add_box(base, t, 0.35, 0.35, 0.0, 3.0, mt.TRUNK, (1.0, 0.0, 0.0))
                    h0 = float(rng.uniform(2.4, 3.0))
                    h1 = h0 + float(rng.uniform(2.0, 3.5))
                    g = float(rng.uniform(0.7, 1.3))
                    mb.add_box(base, t, size, size, h0, h1, mt.CANOPY, (g, 0.0, 0.0),
                               uv_offset=(float(rng.uniform(0, 9)), 0.0))
                    diag = (t + r) / np.sqrt(2.0)
                    mb.add_box(base, diag, size * 0.8, size * 0.8, h0 + 0.4, h1 + 0.6, mt.CANOPY,
                               (g * 0.9, 0.0, 0.0), uv_offset=(float(rng.uniform(0, 9)), 0.3))
            s += float(rng.uniform(8.0, 20.0))
        # clutter: bins, boxes, signs
        s = float(rng.uniform(0, 15))
        while s < n:
            p, t, r = frame(s)
            lx, ly, lz = (float(v) for v in rng.uniform([0.4, 0.4, 0.5], [1.2, 1.0, 1.4]))
            base = p + r * sign * (w + sw * float(rng.uniform(0.35, 0.85))) + UP * kerb_h
            if layout.try_place(base, t, lx, ly, w + 0.3):
                mb.add_box(base, t, lx, ly, 0.0, lz, mt.CLUTTER, (float(rng.uniform(0.5, 1.5)), 0, 0),
                           uv_offset=(float(rng.uniform(0, 9)), 0.0))
            s += float(rng.uniform(10.0, 30.0))


def build_world(T_world_cam: np.ndarray, seed: int, cfg: WorldConfig | None = None) -> World:
    """Lay a street world out along the camera path ``T_world_cam`` (N, 4, 4); deterministic."""
    cfg = cfg or WorldConfig()
    rng = np.random.default_rng([seed, 5001])
    w = float(rng.uniform(*cfg.road_half_width_m))
    sw = float(rng.uniform(*cfg.sidewalk_width_m))
    pts, tangent = _centerline(np.asarray(T_world_cam, float), cfg)
    mb = MeshBuilder()
    _ribbon(mb, pts, tangent, w, sw, cfg)
    _terrain(mb, pts, cfg)
    _objects(mb, pts, tangent, w, sw, rng, cfg)
    # own generator: worlds without traffic stay exactly what they were
    rng_traffic = np.random.default_rng([seed, 5002])
    add_traffic(mb, pts, tangent, w, cKDTree(pts[:, [0, 2]]), cfg.traffic_per_100m, rng_traffic)
    add_bridges(mb, pts, tangent, w + sw, cfg.bridges_per_km, rng_traffic)
    az = float(rng.uniform(0, 2 * np.pi))
    el = float(rng.uniform(np.radians(30), np.radians(60)))
    sun = np.array([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)])
    return World(mb.build(), sun, w, sw)
