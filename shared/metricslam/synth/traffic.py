"""Traffic and overpasses: vehicles standing on the road beside the camera path, and bridges.

KITTI's urban scenes are full of things *close* to the camera — the car ahead in a queue, a truck
in the next lane, an overpass — while parked cars and facades stay metres to the side. A depth
network trained only on the latter learns "up in the image = far". This module adds, on demand
(``WorldConfig.traffic_per_100m`` / ``bridges_per_km``), what the former look like:

* vehicles (cars, vans, trucks, buses) standing in the lanes with their sides at least
  ``_PATH_CLEARANCE_M`` from the camera path, so the camera passes them at close range and sees
  them nearly straight ahead when they are in its lane offset;
* overpasses: a deck 5–7.5 m above the road across road and sidewalks, with pillars beyond the
  sidewalks.

The camera path is a point track, so nothing here can be "driven into": every footprint is
checked against all path points (loops and crossings included) and against the other vehicles.
"""

from __future__ import annotations

import numpy as np

from metricslam.synth import materials as mt
from metricslam.synth.meshes import UP, MeshBuilder

_PATH_CLEARANCE_M = 0.45  # vehicle side to camera path, metres

#: (probability, length range m, width range m, body height range m)
_VEHICLES = (
    (0.55, (3.8, 4.8), (1.7, 1.9), (1.3, 1.55)),   # car
    (0.20, (4.8, 6.0), (1.9, 2.1), (1.9, 2.6)),    # van
    (0.17, (7.0, 12.0), (2.4, 2.55), (3.0, 3.9)),  # truck
    (0.08, (10.0, 13.0), (2.5, 2.55), (2.9, 3.3)),  # bus
)


def _add_vehicle(mb: MeshBuilder, centre: np.ndarray, a: np.ndarray, length: float, width: float,
                 height: float, kind: int, rng: np.random.Generator) -> None:
    """Boxes of one vehicle standing on the road at ``centre`` (ground point), length along a."""
    gain = float(rng.choice([rng.uniform(0.3, 0.6), rng.uniform(0.8, 1.9)]))
    off = (float(rng.uniform(0, 30)), 0.0)
    mb.add_box(centre, a, length * 0.82, width * 0.9, 0.0, 0.45, mt.TYRE, (1.0, 0.0, 0.0))
    if kind == 0:  # car: body plus glass cabin
        mb.add_box(centre, a, length, width, 0.3, height * 0.68, mt.CAR_BODY, (gain, 0.0, 0.0),
                   uv_offset=off)
        mb.add_box(centre - 0.1 * length * a, a, length * 0.55, width * 0.9, height * 0.68, height,
                   mt.CAR_GLASS, (1.0, float(rng.uniform(0.8, 1.3)), float(rng.uniform(0.1, 0.3))),
                   top_material=mt.CAR_BODY, uv_offset=off)
        return
    cab_len = min(2.2, 0.3 * length) if kind == 2 else 0.0
    body_len = length - cab_len
    body_c = centre - 0.5 * cab_len * a
    material = mt.CAR_BODY if kind != 3 else mt.CAR_GLASS
    params = (gain, 0.0, 0.0) if kind != 3 else (1.0, float(rng.uniform(1.0, 1.6)), 0.2)
    mb.add_box(body_c, a, body_len, width, 0.35, height, material, params,
               top_material=mt.CAR_BODY, uv_offset=off)
    if cab_len > 0:  # truck cab, lower, at the front
        cab_c = centre + 0.5 * body_len * a
        mb.add_box(cab_c, a, cab_len, width, 0.4, height * 0.8, mt.CAR_GLASS,
                   (1.0, float(rng.uniform(0.8, 1.2)), float(rng.uniform(0.1, 0.3))),
                   top_material=mt.CAR_BODY, uv_offset=off)


def add_traffic(mb: MeshBuilder, pts: np.ndarray, tangent: np.ndarray, road_half_width_m: float,
                path_tree, per_100m: float, rng: np.random.Generator) -> int:
    """Vehicles on the road along ``pts`` (M, 3) road-centre points every metre.

    Args:
        pts, tangent: road centre points (M, 3) and horizontal unit tangents (M, 3).
        road_half_width_m: half the road width; vehicles stay on the road.
        path_tree: ``cKDTree`` over the (x, z) of all road-centre points (clearance checks).
        per_100m: mean number of vehicles per 100 m of path.

    Returns:
        the number of vehicles placed.
    """
    n = len(pts)
    if per_100m <= 0 or n < 2:
        return 0
    right_all = np.cross(np.array([0.0, 1.0, 0.0]), tangent)
    probs = np.array([v[0] for v in _VEHICLES])
    placed: list[tuple[np.ndarray, float]] = []  # (centre xz, radius) of placed vehicles
    count = 0
    s = float(rng.exponential(100.0 / per_100m))
    while s < n:
        k = int(min(round(s), n - 1))
        kind = int(rng.choice(len(_VEHICLES), p=probs / probs.sum()))
        _, lr, wr, hr = _VEHICLES[kind]
        length, width, height = (float(rng.uniform(*r)) for r in (lr, wr, hr))
        side = float(rng.choice([-1.0, 1.0]))
        lat_min = _PATH_CLEARANCE_M + width / 2
        lat_max = road_half_width_m - width / 2 - 0.2
        s += float(rng.exponential(100.0 / per_100m))
        if lat_max <= lat_min:
            continue
        lat = side * float(rng.uniform(lat_min, lat_max))
        yaw = float(rng.normal(0.0, 0.04))
        a = np.cos(yaw) * tangent[k] + np.sin(yaw) * right_all[k]
        a = a * float(rng.choice([-1.0, 1.0]))  # either driving direction
        centre = pts[k] + right_all[k] * lat
        b = np.cross(UP, a)
        corners = [centre + i * 0.5 * length * a + j * 0.5 * width * b
                   for i in np.linspace(-1, 1, 7) for j in (-1.0, 0.0, 1.0)]
        dist, _ = path_tree.query(np.array(corners)[:, [0, 2]])
        if dist.min() < _PATH_CLEARANCE_M:
            continue
        radius = 0.5 * np.hypot(length, width)
        if any(np.linalg.norm(c - centre[[0, 2]]) < r + radius for c, r in placed):
            continue
        placed.append((centre[[0, 2]], radius))
        _add_vehicle(mb, centre, a, length, width, height, kind, rng)
        count += 1
    return count


def add_bridges(mb: MeshBuilder, pts: np.ndarray, tangent: np.ndarray, half_span_m: float,
                per_km: float, rng: np.random.Generator) -> int:
    """Overpasses across the path: a deck over ``±half_span_m`` and two pillars beyond it.

    Returns the number of bridges placed.
    """
    n = len(pts)
    if per_km <= 0 or n < 40:
        return 0
    right_all = np.cross(np.array([0.0, 1.0, 0.0]), tangent)
    count = 0
    s = float(rng.uniform(20.0, 1000.0 / per_km))
    while s < n - 20:
        k = int(s)
        t, r = tangent[k], right_all[k]
        deck_w = float(rng.uniform(8.0, 16.0))  # along the path
        z0 = float(rng.uniform(5.0, 7.5))
        thick = float(rng.uniform(0.8, 1.6))
        span = 2 * (half_span_m + 6.0)
        gain = float(rng.uniform(0.7, 1.2))
        # the deck: an upright box (sides and top) plus its underside, seen from the road
        mb.add_box(pts[k], r, span, deck_w, z0, z0 + thick, mt.POLE, (gain, 0.0, 0.0),
                   top_material=mt.ROOF)
        hl, hw = 0.5 * span, 0.5 * deck_w
        c = pts[k] + z0 * UP
        under = np.array([[c - hl * r - hw * t, c - hl * r + hw * t, c + hl * r + hw * t,
                           c + hl * r - hw * t]])
        uv = np.array([[[0, 0], [0, deck_w], [span, deck_w], [span, 0]]], float)
        mb.add_quads(under, uv, mt.ROOF, (gain, 0.0, 0.0), -UP[None])
        for sign in (-1.0, 1.0):
            mb.add_box(pts[k] + r * sign * (half_span_m + 2.0), t, deck_w * 0.6, 1.2, 0.0, z0,
                       mt.POLE, (gain, 0.0, 0.0))
        count += 1
        s += float(rng.exponential(1000.0 / per_km)) + deck_w + 30.0
    return count
