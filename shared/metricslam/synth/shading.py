"""Per-pixel shading of visible surfaces and the sky (numba).

Textures are sampled trilinearly from mip levels chosen by the pixel footprint on the surface,
and procedural patterns (lane markings, windows, car glass) are box-filtered analytically over
the footprint, so the left and right images of a pair show the same surface the same way.
The sky depends only on the ray direction in the world frame (zero disparity, as it should).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from metricslam.synth.materials import PATTERN_CAR_GLASS, PATTERN_LANES, PATTERN_WINDOWS

_TILE_TEXELS = 256.0


@nb.njit(inline="always")
def _mirror(i, size):
    # sizes are powers of two: mirror repeat with period 2·size via a bit mask
    i = i & (2 * size - 1)
    return i if i < size else 2 * size - 1 - i


@nb.njit(inline="always")
def _bilinear(data, off, size, x, y):
    fx = np.floor(x)
    fy = np.floor(y)
    ax = x - fx
    ay = y - fy
    ix = int(fx)
    iy = int(fy)
    x0 = _mirror(ix, size)
    x1 = _mirror(ix + 1, size)
    y0 = _mirror(iy, size)
    y1 = _mirror(iy + 1, size)
    top = data[off + y0 * size + x0] * (1 - ax) + data[off + y0 * size + x1] * ax
    bot = data[off + y1 * size + x0] * (1 - ax) + data[off + y1 * size + x1] * ax
    return top * (1 - ay) + bot * ay


@nb.njit(inline="always")
def _texture_fast(data, offset, sizes, tex, s_m, t_m, metres_per_tile, footprint_m):
    """Bilinear sample at the nearest mip level (for low-amplitude detail layers)."""
    texels_per_m = _TILE_TEXELS / metres_per_tile
    lod = np.log2(max(footprint_m * texels_per_m, 1.0))
    lev = min(int(lod + 0.5), offset.shape[1] - 1)
    sz = sizes[tex, lev]
    return _bilinear(data, offset[tex, lev], sz, s_m * texels_per_m * sz / _TILE_TEXELS - 0.5,
                     t_m * texels_per_m * sz / _TILE_TEXELS - 0.5)


@nb.njit(inline="always")
def _texture(data, offset, sizes, tex, s_m, t_m, metres_per_tile, footprint_m):
    """Trilinear sample of texture ``tex`` at surface coordinates (metres)."""
    texels_per_m = _TILE_TEXELS / metres_per_tile
    lod = np.log2(max(footprint_m * texels_per_m, 1.0))
    n_lev = offset.shape[1]
    lod = min(lod, n_lev - 1.0)
    l0 = int(lod)
    l1 = min(l0 + 1, n_lev - 1)
    a = lod - l0
    s0 = sizes[tex, l0]
    s1 = sizes[tex, l1]
    c0 = _bilinear(data, offset[tex, l0], s0, s_m * texels_per_m * s0 / _TILE_TEXELS - 0.5,
                   t_m * texels_per_m * s0 / _TILE_TEXELS - 0.5)
    if a <= 0.0:
        return c0
    c1 = _bilinear(data, offset[tex, l1], s1, s_m * texels_per_m * s1 / _TILE_TEXELS - 0.5,
                   t_m * texels_per_m * s1 / _TILE_TEXELS - 0.5)
    return c0 * (1 - a) + c1 * a


@nb.njit(inline="always")
def _box(dist_to_edge, footprint_m):
    """Coverage in [0, 1] of a pixel of width ``footprint_m`` by a region whose signed inside
    distance at the pixel centre is ``dist_to_edge`` (box filter of a step)."""
    return min(1.0, max(0.0, dist_to_edge / footprint_m + 0.5))


@nb.njit(inline="always")
def _hash01(i, j, salt):
    h = (i * 374761393 + j * 668265263 + salt * 982451653) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    return ((h ^ (h >> 16)) & 0xFFFFFF) / 16777216.0


@nb.njit(inline="always")
def _lanes(s_m, lat_m, half_width_m, fp):
    line_hw = 0.075
    cover = _box(line_hw - abs(lat_m), fp) * _box(1.5 - abs((s_m % 9.0) - 1.5), fp)
    edge = half_width_m - 0.3
    cover = max(cover, _box(line_hw - abs(abs(lat_m) - edge), fp))
    return cover


@nb.njit(inline="always")
def _windows(u_m, v_m, spacing_m, fp):
    """(coverage of glass, coverage of frame, window index hash) of a facade point."""
    if v_m < 0.4:
        return 0.0, 0.0, 0.0
    floor_h = 3.2
    ground = v_m < floor_h
    fl = np.floor(v_m / floor_h)
    fy = v_m - fl * floor_h
    col = np.floor(u_m / spacing_m)
    fx = u_m - col * spacing_m
    hx = 0.38 * spacing_m if ground else 0.25 * spacing_m
    y0, y1 = (0.4, 2.6) if ground else (0.9, 2.5)
    cx = 0.5 * spacing_m
    cy = 0.5 * (y0 + y1)
    hy = 0.5 * (y1 - y0)
    dx = hx - abs(fx - cx)
    dy = hy - abs(fy - cy)
    outer = _box(dx + 0.09, fp) * _box(dy + 0.09, fp)
    glass = _box(dx, fp) * _box(dy, fp)
    fade = min(1.0, max(0.0, 2.0 - 4.0 * fp / spacing_m))
    return glass * fade, (outer - glass) * fade, _hash01(int(col), int(fl), 17)


_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}  # no nnan/ninf: depth uses inf


@nb.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def shade(depth, tri_id, bary, uv, mat, par, normal_w, materials, tex_data, tex_off, tex_size,
          sun_w, R_wc, fx, fy, cx, cy, out):
    """Fill ``out`` (H, W) float32 with radiance for every pixel (see module docstring)."""
    height, width = depth.shape
    for v in nb.prange(height):
        y = (v - cy) / fy
        for u in range(width):
            x = (u - cx) / fx
            k = tri_id[v, u]
            if k < 0:
                dwx = R_wc[0, 0] * x + R_wc[0, 1] * y + R_wc[0, 2]
                dwy = R_wc[1, 0] * x + R_wc[1, 1] * y + R_wc[1, 2]
                dwz = R_wc[2, 0] * x + R_wc[2, 1] * y + R_wc[2, 2]
                nrm = np.sqrt(dwx * dwx + dwy * dwy + dwz * dwz)
                elev = -dwy / nrm
                if elev <= 0.0:
                    out[v, u] = 0.62
                    continue
                # clouds: noise on the plane 1 km up, seen along the ray; fades to haze
                q = 0.15 / (elev + 0.05)
                cloud = _texture_fast(tex_data, tex_off, tex_size, 5, dwx / nrm * q * 40.0,
                                 dwz / nrm * q * 40.0, 60.0, q * 40.0 / fx / max(elev, 0.02))
                out[v, u] = 0.70 + 0.18 * min(1.0, elev * 3.0) + 0.25 * (cloud - 0.5) * min(1.0, elev * 4.0)
                continue
            z = depth[v, u]
            b1 = bary[v, u, 0]
            b2 = bary[v, u, 1]
            b0 = 1.0 - b1 - b2
            s_m = b0 * uv[k, 0, 0] + b1 * uv[k, 1, 0] + b2 * uv[k, 2, 0]
            t_m = b0 * uv[k, 0, 1] + b1 * uv[k, 1, 1] + b2 * uv[k, 2, 1]
            # normal in the camera frame for the foreshortening of the pixel footprint
            ncx = R_wc[0, 0] * normal_w[k, 0] + R_wc[1, 0] * normal_w[k, 1] + R_wc[2, 0] * normal_w[k, 2]
            ncy = R_wc[0, 1] * normal_w[k, 0] + R_wc[1, 1] * normal_w[k, 1] + R_wc[2, 1] * normal_w[k, 2]
            ncz = R_wc[0, 2] * normal_w[k, 0] + R_wc[1, 2] * normal_w[k, 1] + R_wc[2, 2] * normal_w[k, 2]
            dlen = np.sqrt(x * x + y * y + 1.0)
            cosang = abs(ncx * x + ncy * y + ncz) / dlen
            fp = z * dlen / fx / np.sqrt(max(cosang, 0.03))
            m = mat[k]
            tex = int(materials[m, 0])
            mpt = materials[m, 1]
            base = materials[m, 2]
            contrast = materials[m, 3]
            pattern = int(materials[m, 4])
            c = base + contrast * (_texture(tex_data, tex_off, tex_size, tex, s_m, t_m, mpt, fp) - 0.5)
            gain = par[k, 0]
            if pattern == PATTERN_LANES:
                cover = _lanes(s_m, t_m, par[k, 1], fp)
                c = c * (1.0 - cover) + 0.85 * cover
            elif pattern == PATTERN_WINDOWS:
                glass, frame, h = _windows(s_m, t_m, par[k, 1], fp)
                tone = par[k, 2] + 0.25 * (h - 0.5) + 0.1 * ((t_m % 3.2) / 3.2)
                c = c * (1.0 - glass - frame) + glass * tone / max(gain, 0.3) + frame * 0.8 / max(gain, 0.3)
            elif pattern == PATTERN_CAR_GLASS:
                pf = s_m % par[k, 1]
                pillar = _box(0.08 - abs(pf - 0.08), fp)
                c = c * (1.0 - pillar) + pillar * 0.5
            light = 0.6 + 0.5 * max(0.0, normal_w[k, 0] * sun_w[0] + normal_w[k, 1] * sun_w[1]
                                    + normal_w[k, 2] * sun_w[2])
            out[v, u] = c * gain * light
