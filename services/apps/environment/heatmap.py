"""A grid layer as a PNG heat map for people (Pillow).

North is up: the image's top row is the grid's last row (largest y), as on a map. Values run
from the layer's smallest (dark blue) to its largest (dark red) through cyan, green and yellow;
cells without a value are transparent. Each cell is drawn as a square of whole pixels, as many as
keep the image's long side within :data:`MIN_SIDE` pixels, so that a small grid is still big
enough to see; a grid longer than that is drawn one pixel a cell.
"""

from __future__ import annotations

import io

import numpy as np
import numpy.typing as npt
from PIL import Image

__all__ = ["MIN_SIDE", "heat_map_png"]

#: A small grid's image is scaled up by whole pixels a cell toward this many on its long side.
MIN_SIDE = 320

# Colour stops of the ramp, low to high: blue, cyan, green, yellow, red.
_STOPS = np.array(
    [[48, 18, 160], [30, 150, 220], [60, 190, 90], [245, 210, 40], [200, 30, 30]], dtype=np.float64
)


def _colours(values: npt.NDArray[np.float32], low: float, high: float) -> npt.NDArray[np.uint8]:
    finite = np.isfinite(values)
    span = high - low
    scaled = np.zeros(values.shape, dtype=np.float64)
    if span > 0:
        scaled[finite] = (values[finite] - low) / span
    else:
        scaled[finite] = 0.5
    position = np.clip(scaled, 0.0, 1.0) * (len(_STOPS) - 1)
    lower = np.minimum(position.astype(np.int64), len(_STOPS) - 2)
    frac = (position - lower)[..., None]
    rgb = _STOPS[lower] * (1.0 - frac) + _STOPS[lower + 1] * frac
    rgba = np.zeros((*values.shape, 4), dtype=np.uint8)
    rgba[..., :3] = np.round(rgb).astype(np.uint8)
    rgba[..., 3] = np.where(finite, 255, 0).astype(np.uint8)
    return rgba


def heat_map_png(values: npt.NDArray[np.float32]) -> bytes:
    """A PNG of the 2-D array ``values`` (row 0 at the bottom), NaN cells transparent."""
    if values.ndim != 2 or values.size == 0:
        raise ValueError(f"a heat map needs a non-empty 2-D array, got shape {values.shape}")
    finite = values[np.isfinite(values)]
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    rgba = _colours(np.flipud(values), low, high)
    rows, cols = values.shape
    scale = max(1, MIN_SIDE // max(rows, cols))
    image = Image.fromarray(rgba)
    if scale > 1:
        image = image.resize((cols * scale, rows * scale), Image.Resampling.NEAREST)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=False)
    return out.getvalue()
