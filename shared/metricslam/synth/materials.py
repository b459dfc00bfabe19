"""Material table for the synthetic street world (gray-level appearance of each surface kind).

A material is one row of :data:`MATERIALS` (float32): texture id, metres per texture tile, base
gray level, texture contrast, procedural pattern id, and a reserved column (detail noise is
baked into the textures, see :mod:`metricslam.synth.textures`). Objects add
three per-triangle parameters (``params``): a brightness gain and two pattern parameters whose
meaning is given per pattern below.
"""

from __future__ import annotations

import numpy as np

from metricslam.synth import textures as tx

#: pattern ids understood by the shader
PATTERN_NONE, PATTERN_LANES, PATTERN_WINDOWS, PATTERN_CAR_GLASS = range(4)

# material ids
(ROAD, KERB, SIDEWALK, VERGE, FACADE_BRICK, FACADE_PLASTER, ROOF, CAR_BODY, CAR_GLASS,
 TYRE, POLE, TRUNK, CANOPY, CLUTTER) = range(14)

# tex, m/tile, base, contrast, pattern, noise
_ROWS = {
    # params: (gain, road half width m, unused)
    ROAD: (tx.TEX_ASPHALT, 4.0, 0.34, 0.55, PATTERN_LANES, 0.04),
    KERB: (tx.TEX_CONCRETE, 1.5, 0.66, 0.55, PATTERN_NONE, 0.04),
    SIDEWALK: (tx.TEX_PAVING, 2.2, 0.52, 0.65, PATTERN_NONE, 0.04),
    VERGE: (tx.TEX_FOLIAGE, 5.0, 0.33, 0.9, PATTERN_NONE, 0.06),
    # params: (gain, window spacing m, glass gray level)
    FACADE_BRICK: (tx.TEX_BRICK, 2.4, 0.50, 0.8, PATTERN_WINDOWS, 0.03),
    FACADE_PLASTER: (tx.TEX_CONCRETE, 7.0, 0.62, 0.45, PATTERN_WINDOWS, 0.05),
    ROOF: (tx.TEX_CONCRETE, 8.0, 0.45, 0.5, PATTERN_NONE, 0.05),
    CAR_BODY: (tx.TEX_NOISE, 4.0, 0.45, 0.25, PATTERN_NONE, 0.02),
    # params: (gain, pillar spacing m, glass gray level)
    CAR_GLASS: (tx.TEX_NOISE, 3.0, 0.18, 0.3, PATTERN_CAR_GLASS, 0.02),
    TYRE: (tx.TEX_NOISE, 1.0, 0.08, 0.3, PATTERN_NONE, 0.02),
    POLE: (tx.TEX_CONCRETE, 1.0, 0.58, 0.4, PATTERN_NONE, 0.03),
    TRUNK: (tx.TEX_BRICK, 0.8, 0.25, 0.6, PATTERN_NONE, 0.05),
    CANOPY: (tx.TEX_FOLIAGE, 3.0, 0.28, 1.2, PATTERN_NONE, 0.10),
    CLUTTER: (tx.TEX_PAVING, 1.0, 0.50, 0.8, PATTERN_NONE, 0.05),
}

#: (n_materials, 6) float32 table indexed by material id
MATERIALS = np.array([_ROWS[k] for k in range(len(_ROWS))], dtype=np.float32)
