"""Gray texture atlas with mip levels: real photos from scikit-image plus procedural noise.

Textures are float32 in [0, 1], square, tiled with mirror repeat (seamless without editing the
photos). Each texture carries a mip pyramid (2x2 box filter) so distant surfaces are sampled at
about one texel per pixel: no aliasing shimmer that would differ between the left and right
images. Everything is flattened into one array for the numba shader.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Texture ids used by :mod:`metricslam.synth.world` materials.
TEX_ASPHALT, TEX_BRICK, TEX_FOLIAGE, TEX_PAVING, TEX_CONCRETE, TEX_NOISE = range(6)
TEXTURE_NAMES = ("asphalt", "brick", "foliage", "paving", "concrete", "noise")

_SIZE = 256  # texels per side at level 0; 256 keeps the atlas small and cache friendly


@dataclass(frozen=True)
class TextureAtlas:
    """All textures and their mip levels in one flat array.

    Attributes:
        data: (N,) float32, every level of every texture, row-major, values in [0, 1].
        offset: (n_tex, n_levels) int64, start of level ``l`` of texture ``k`` in ``data``.
        size: (n_tex, n_levels) int64, side length in texels of that level.
    """

    data: np.ndarray
    offset: np.ndarray
    size: np.ndarray


def _normalize(img: np.ndarray) -> np.ndarray:
    """Zero-mean, unit-contrast version of an image mapped to [0, 1] around 0.5."""
    x = img.astype(np.float32)
    x = (x - x.mean()) / (x.std() + 1e-6)
    return np.clip(0.5 + 0.18 * x, 0.0, 1.0).astype(np.float32)


def _resize(img: np.ndarray, size: int) -> np.ndarray:
    import cv2

    return cv2.resize(img.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)


def _fractal_noise(rng: np.random.Generator, size: int, octaves: int = 6) -> np.ndarray:
    """Tileable multi-octave value noise (wraps at ``size``), (size, size) float32."""
    import cv2

    out = np.zeros((size, size), np.float32)
    amp = 1.0
    for k in range(octaves):
        cells = 4 * 2**k
        if cells > size:
            break
        grid = rng.standard_normal((cells, cells)).astype(np.float32)
        tiled = np.tile(grid, (3, 3))  # wrap so the upsampled noise tiles seamlessly
        up = cv2.resize(tiled, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
        out += amp * up[size:2 * size, size:2 * size]
        amp *= 0.6
    return out


def _mips(img: np.ndarray) -> list[np.ndarray]:
    levels = [img.astype(np.float32)]
    while levels[-1].shape[0] > 2:
        a = levels[-1]
        levels.append(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]))
    return levels


def build_atlas(seed: int = 0) -> TextureAtlas:
    """Build the atlas: asphalt, brick, foliage, paving, concrete, noise (ids ``TEX_*``).

    Photos come from ``skimage.data`` (bundled with scikit-image, no download); the procedural
    noise depends on ``seed`` only.
    """
    from skimage import data as skdata

    rng = np.random.default_rng([seed, 7001])
    noise = _fractal_noise(rng, _SIZE)
    gravel = _resize(skdata.gravel(), _SIZE)
    brick = _resize(skdata.brick(), _SIZE)
    grass = _resize(skdata.grass(), _SIZE)
    moon = _resize(skdata.moon(), _SIZE)
    # fine detail baked into every texture at 3x the tile frequency: corners at more scales
    # without a second texture lookup per pixel
    detail = _normalize(_resize(np.tile(_fractal_noise(rng, _SIZE), (3, 3)), _SIZE))
    textures = [
        _normalize(0.7 * _normalize(gravel) + 0.3 * _normalize(noise)),  # asphalt
        _normalize(brick),
        _normalize(grass),
        _normalize(0.6 * _normalize(gravel[::-1].T) + 0.4 * _normalize(brick.T)),  # paving
        _normalize(0.5 * _normalize(moon) + 0.5 * _normalize(noise[::-1])),  # concrete
        _normalize(noise),
    ]
    textures = [_normalize(t + 0.12 * (detail - 0.5) / 0.18) if k != TEX_NOISE else t
                for k, t in enumerate(textures)]
    pyramids = [_mips(t) for t in textures]
    n_levels = len(pyramids[0])
    offset = np.zeros((len(textures), n_levels), np.int64)
    size = np.zeros((len(textures), n_levels), np.int64)
    chunks = []
    pos = 0
    for k, pyr in enumerate(pyramids):
        for lev, img in enumerate(pyr):
            offset[k, lev] = pos
            size[k, lev] = img.shape[0]
            chunks.append(img.ravel())
            pos += img.size
    return TextureAtlas(np.concatenate(chunks).astype(np.float32), offset, size)
