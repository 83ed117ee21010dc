"""Grid layers, sans-IO: a square-celled raster of the plane with numpy arrays per layer.

A :class:`GridSpec` fixes the raster: ``origin`` (x0, y0) is the corner of cell (0, 0) in the
world frame, ``cell`` its side in metres, ``shape`` (rows, cols). Row ``r``, column ``c``
covers ``x0 + c·cell <= x < x0 + (c+1)·cell`` and ``y0 + r·cell <= y < y0 + (r+1)·cell``: row
0 is the southern edge (smallest y). A point outside is not recorded (and counted as such).

* :class:`MeanLayer` (``temperature``): a running mean per cell, from ``sum`` and ``count``.
* :class:`HitLayer` (``occupancy``): hit counts, how many sightings fell in each cell.

``values()`` is float32 (NaN where a mean layer has no reading yet); :func:`to_npy` writes it
as ``numpy.save`` does, so any numpy reads it with ``numpy.load``.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["MAX_CELLS", "MAX_SIDE", "GridSpec", "HitLayer", "Layer", "MeanLayer", "to_npy"]

#: Most cells of a grid: 1,000,000 float32 cells are 3.8 MiB, so a Get of a whole layer still
#: fits one gRPC message (4 MiB by default).
MAX_CELLS = 1_000_000
#: Longest side of a grid in cells.
MAX_SIDE = 4096

Float32Array = npt.NDArray[np.float32]


@dataclass(frozen=True, slots=True)
class GridSpec:
    """Where the raster lies: origin (x0 y0) of cell (0, 0), cell side (m), shape (rows cols)."""

    origin: tuple[float, float] = (-10.0, -10.0)
    cell: float = 0.5
    shape: tuple[int, int] = (40, 40)

    def __post_init__(self) -> None:
        if len(self.origin) != 2 or not all(math.isfinite(v) for v in self.origin):
            raise ValueError(f"grid origin must be 2 finite numbers (x0 y0), got {self.origin}")
        if not (math.isfinite(self.cell) and self.cell > 0):
            raise ValueError(f"grid cell must be a positive number of metres, got {self.cell}")
        rows, cols = self.shape
        if not (1 <= rows <= MAX_SIDE and 1 <= cols <= MAX_SIDE):
            raise ValueError(f"grid shape must be 1 to {MAX_SIDE} rows and columns, got {self.shape}")
        if rows * cols > MAX_CELLS:
            raise ValueError(f"grid shape {rows}×{cols} has {rows * cols} cells, the limit is {MAX_CELLS}")

    @classmethod
    def from_options(cls, origin: Sequence[float], cell: float, shape: Sequence[int]) -> GridSpec:
        """A spec from config values; ValueError saying what is wrong."""
        try:
            x0, y0 = (float(v) for v in origin)
        except (TypeError, ValueError):
            raise ValueError(f"grid origin must be 2 numbers (x0 y0), got {origin!r}") from None
        try:
            rows, cols = shape
        except (TypeError, ValueError):
            raise ValueError(f"grid shape must be 2 integers (rows cols), got {shape!r}") from None
        if not all(isinstance(n, int) and not isinstance(n, bool) for n in (rows, cols)):
            raise ValueError(f"grid shape must be 2 integers (rows cols), got {shape!r}")
        if isinstance(cell, bool) or not isinstance(cell, int | float):
            raise ValueError(f"grid cell must be a number of metres, got {cell!r}")
        return cls((x0, y0), float(cell), (rows, cols))

    def index(self, x: float, y: float) -> tuple[int, int] | None:
        """(row, col) of the cell holding (x, y), or None outside the grid."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return None
        col = math.floor((x - self.origin[0]) / self.cell)
        row = math.floor((y - self.origin[1]) / self.cell)
        if 0 <= row < self.shape[0] and 0 <= col < self.shape[1]:
            return row, col
        return None

    def centre(self, row: int, col: int) -> tuple[float, float]:
        """The world position of a cell's centre."""
        return (self.origin[0] + (col + 0.5) * self.cell, self.origin[1] + (row + 0.5) * self.cell)


class Layer:
    """One grid layer; the subclasses say what a cell holds."""

    kind = ""
    unit = ""

    def __init__(self, name: str, spec: GridSpec) -> None:
        self.name = name
        self.spec = spec
        self.counts = np.zeros(spec.shape, dtype=np.int64)
        #: Points given that fell outside the grid.
        self.outside = 0

    def values(self) -> Float32Array:
        raise NotImplementedError

    def clear(self) -> None:
        self.counts[:] = 0
        self.outside = 0

    @property
    def filled(self) -> int:
        """Cells with at least one value."""
        return int(np.count_nonzero(self.counts))

    @property
    def total(self) -> int:
        """Values recorded in all."""
        return int(self.counts.sum())

    def info(self) -> list[Any]:
        """What ``grid.<layer>.info`` says, as a list of (key value) pairs for the value grammar."""
        values = self.values()
        seen = values[np.isfinite(values)] if self.filled else values[:0]
        # float32 values, shown to the precision they hold (7 significant digits), not as float64 noise.
        low: Any = float(f"{seen.min():.7g}") if seen.size else []
        high: Any = float(f"{seen.max():.7g}") if seen.size else []
        return [
            ["kind", self.kind],
            ["origin", list(self.spec.origin)],
            ["cell", self.spec.cell],
            ["shape", list(self.spec.shape)],
            ["min", low],
            ["max", high],
            ["filled", self.filled],
            ["total", self.total],
            ["outside", self.outside],
            ["unit", self.unit or "-"],
        ]


class MeanLayer(Layer):
    """A running mean per cell (sum and count); cells without a value read NaN."""

    kind = "mean"

    def __init__(self, name: str, spec: GridSpec, unit: str = "") -> None:
        super().__init__(name, spec)
        self.unit = unit
        self.sums = np.zeros(spec.shape, dtype=np.float64)

    def add(self, x: float, y: float, value: float) -> bool:
        """Record ``value`` read at (x, y); False when outside the grid or not a finite number."""
        where = self.spec.index(x, y)
        if where is None or not math.isfinite(value):
            self.outside += 1
            return False
        self.sums[where] += value
        self.counts[where] += 1
        return True

    def values(self) -> Float32Array:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(self.counts > 0, self.sums / np.maximum(self.counts, 1), np.nan)
        return mean.astype(np.float32)

    def clear(self) -> None:
        super().clear()
        self.sums[:] = 0.0


class HitLayer(Layer):
    """Hit counts: how many sightings fell in each cell (0 where none did)."""

    kind = "hits"

    def add(self, x: float, y: float) -> bool:
        where = self.spec.index(x, y)
        if where is None:
            self.outside += 1
            return False
        self.counts[where] += 1
        return True

    def values(self) -> Float32Array:
        return self.counts.astype(np.float32)


def to_npy(array: npt.NDArray[Any]) -> bytes:
    """``array`` in the ``.npy`` format (``numpy.save``; ``numpy.load`` reads it back)."""
    out = io.BytesIO()
    np.save(out, array, allow_pickle=False)
    return out.getvalue()
