"""Whether an image can carry a depth map at all: one check shared by the depth service (its
``valid`` flag) and the SLAM side's depth sources (no scale factor from a flat image).

The network answers something plausible-looking for any input; an image without contrast
(blank, black, a lens cap, a uniform wall) holds no depth to read, so its map must not be
trusted.
"""

from __future__ import annotations

import numpy as np

#: an image whose gray levels (0-255) have a standard deviation below this is flat: no contrast to
#: read depth from (sensor noise on a uniform scene is ~1-2 levels; any real view has tens)
FLAT_STD_LEVELS = 2.0


def flat_image_reason(gray: np.ndarray) -> str | None:
    """Why the ``(H, W)`` uint8 gray image is too flat for a depth map, or None.

    Example::

        >>> flat_image_reason(np.full((8, 8), 128, np.uint8))
        'flat image: gray-level standard deviation 0.00 < 2 (blank, covered or uniform view)'
    """
    std = float(np.std(gray, dtype=np.float64))
    if std < FLAT_STD_LEVELS:
        return (f"flat image: gray-level standard deviation {std:.2f} < {FLAT_STD_LEVELS:g} "
                "(blank, covered or uniform view)")
    return None
