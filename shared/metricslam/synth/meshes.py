"""Triangle soup for the renderer: oriented boxes and ground-ribbon cells.

World frame: y points down (KITTI camera convention), so "up" is ``-y``. Every triangle stores
its three vertices (metres, world frame), per-vertex texture coordinates in metres on the
surface, a material id and three object parameters (see :mod:`metricslam.synth.materials`).
Triangles are wound so that ``(v1 - v0) x (v2 - v0)`` points out of the surface; the renderer
draws front faces only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

UP = np.array([0.0, -1.0, 0.0])


@dataclass(frozen=True)
class Mesh:
    """Arrays of a triangle soup.

    Attributes:
        vertices_m: (T, 3, 3) float64 world coordinates.
        uv_m: (T, 3, 2) float32 texture coordinates in metres.
        material: (T,) int32 material ids.
        params: (T, 3) float32 per-object parameters.
    """

    vertices_m: np.ndarray
    uv_m: np.ndarray
    material: np.ndarray
    params: np.ndarray

    def __len__(self) -> int:
        return int(self.material.size)


class MeshBuilder:
    """Accumulates triangles; :meth:`build` returns the :class:`Mesh`."""

    def __init__(self) -> None:
        self._v: list[np.ndarray] = []
        self._uv: list[np.ndarray] = []
        self._mat: list[np.ndarray] = []
        self._par: list[np.ndarray] = []

    def add_quads(self, corners: np.ndarray, uv: np.ndarray, material: int,
                  params: tuple[float, float, float], outward: np.ndarray | None = None) -> None:
        """Add quads as two triangles each.

        Args:
            corners: (Q, 4, 3) corners in order around the quad.
            uv: (Q, 4, 2) texture coordinates (metres) of the corners.
            material: material id for all of them.
            params: object parameters for all of them.
            outward: (Q, 3) direction the front face must point to; None keeps the given order
                (its right-hand normal is the front).
        """
        corners = np.asarray(corners, float).reshape(-1, 4, 3)
        uv = np.asarray(uv, np.float32).reshape(-1, 4, 2)
        tris = np.concatenate([corners[:, [0, 1, 2]], corners[:, [0, 2, 3]]])
        tuv = np.concatenate([uv[:, [0, 1, 2]], uv[:, [0, 2, 3]]])
        if outward is not None:
            out = np.concatenate([outward, outward]).reshape(-1, 3)
            normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
            flip = np.einsum("ij,ij->i", normal, out) < 0
            tris[flip] = tris[flip][:, [0, 2, 1]]
            tuv[flip] = tuv[flip][:, [0, 2, 1]]
        n = len(tris)
        self._v.append(tris)
        self._uv.append(tuv)
        self._mat.append(np.full(n, material, np.int32))
        self._par.append(np.tile(np.asarray(params, np.float32), (n, 1)))

    def add_box(self, base_center: np.ndarray, axis_a: np.ndarray, length_m: float, width_m: float,
                z0_m: float, z1_m: float, side_material: int, params: tuple[float, float, float],
                top_material: int | None = None, uv_offset: tuple[float, float] = (0.0, 0.0)) -> None:
        """An upright box (4 sides and a top).

        Args:
            base_center: (3,) ground point below the box centre (world, metres).
            axis_a: (3,) horizontal unit vector of the box's length direction.
            length_m, width_m: horizontal size along ``axis_a`` and across it.
            z0_m, z1_m: bottom and top heights above ``base_center`` (metres, up positive).
            side_material, top_material: material ids (top defaults to the side material).
            uv_offset: shift of the side texture coordinates (decorrelates identical objects).
        """
        a = np.asarray(axis_a, float)
        b = np.cross(UP, a)
        c = np.asarray(base_center, float)
        hl, hw = 0.5 * length_m, 0.5 * width_m
        foot = [c - hl * a - hw * b, c + hl * a - hw * b, c + hl * a + hw * b, c - hl * a + hw * b]
        lens = [length_m, width_m, length_m, width_m]
        quads, uvs, outs = [], [], []
        u0 = uv_offset[0]
        for k in range(4):
            p, q = foot[k], foot[(k + 1) % 4]
            quads.append([p + z0_m * UP, q + z0_m * UP, q + z1_m * UP, p + z1_m * UP])
            uvs.append([[u0, z0_m + uv_offset[1]], [u0 + lens[k], z0_m + uv_offset[1]],
                        [u0 + lens[k], z1_m + uv_offset[1]], [u0, z1_m + uv_offset[1]]])
            outs.append(0.5 * (p + q) - c)
            u0 += lens[k]
        self.add_quads(np.array(quads), np.array(uvs), side_material, params, np.array(outs))
        top = np.array([[f + z1_m * UP for f in foot]])
        top_uv = np.array([[[0, 0], [length_m, 0], [length_m, width_m], [0, width_m]]])
        self.add_quads(top, top_uv + np.asarray(uv_offset), side_material if top_material is None
                       else top_material, params, UP[None])

    def build(self) -> Mesh:
        if not self._v:
            return Mesh(np.zeros((0, 3, 3)), np.zeros((0, 3, 2), np.float32),
                        np.zeros(0, np.int32), np.zeros((0, 3), np.float32))
        return Mesh(np.concatenate(self._v), np.concatenate(self._uv).astype(np.float32),
                    np.concatenate(self._mat), np.concatenate(self._par))
