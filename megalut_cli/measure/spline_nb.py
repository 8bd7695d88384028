"""Compiled kernels (numba): a periodic quintic B-spline of complex coefficients evaluated at
scattered points or on the outer product of two sets of coordinates.

:class:`PeriodicQuintic` is ``scipy.ndimage.map_coordinates(c, (rows, cols), order=5,
mode="grid-wrap", prefilter=False)`` for complex coefficients ``c``, both parts in one pass
(to 1e-13 of SciPy's sums): the cell engine reads the PSF's transform at the moving
fixnoise's frequencies with it (:mod:`.cell_metacal`). The coefficients are stored with five
wrapped lines and columns appended, real and imaginary parts interleaved, so that a point's
six-by-six nodes are one contiguous block of each of six lines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from megalut_cli.jit import njit

#: Lines and columns appended (wrapped) to the coefficients: a point's last node is five on.
WRAP = 5


@njit(cache=True, inline="always")
def _weights(t: float, w: np.ndarray) -> None:
    """The uniform quintic B-spline's weights of the six nodes ``floor - 2 .. floor + 3`` at
    the fractional offset ``t`` (in [0, 1)) from ``floor``."""
    s = 1.0 - t
    t2 = t * t
    t4 = t2 * t2
    t5 = t4 * t
    s2 = s * s
    w[0] = s2 * s2 * s / 120.0
    w[1] = (26.0 - 50.0 * t + 20.0 * t2 + 20.0 * t2 * t - 20.0 * t4 + 5.0 * t5) / 120.0
    w[2] = (66.0 - 60.0 * t2 + 30.0 * t4 - 10.0 * t5) / 120.0
    w[3] = (26.0 + 50.0 * t + 20.0 * t2 - 20.0 * t2 * t - 20.0 * t4 + 10.0 * t5) / 120.0
    w[4] = (1.0 + 5.0 * t + 10.0 * t2 + 10.0 * t2 * t + 5.0 * t4 - 5.0 * t5) / 120.0
    w[5] = t5 / 120.0


@njit(cache=True, fastmath=True, error_model="numpy", nogil=True)
def _at_points(
    block: np.ndarray, ny: int, nx: int, rows: np.ndarray, cols: np.ndarray, out: np.ndarray
) -> None:
    """The spline of the wrapped, interleaved coefficients ``block`` (``ny`` by ``nx``
    nodes) at ``(rows[k], cols[k])`` (grid units, any real value) into ``out[k]``."""
    wy = np.empty(6)
    wx = np.empty(6)
    for k in range(rows.shape[0]):
        fr = math.floor(rows[k])
        fc = math.floor(cols[k])
        _weights(rows[k] - fr, wy)
        _weights(cols[k] - fc, wx)
        r0 = (int(fr) - 2) % ny
        c0 = 2 * ((int(fc) - 2) % nx)
        re = 0.0
        im = 0.0
        for a in range(6):
            part_re = 0.0
            part_im = 0.0
            for b in range(6):
                part_re += wx[b] * block[r0 + a, c0 + 2 * b]
                part_im += wx[b] * block[r0 + a, c0 + 2 * b + 1]
            re += wy[a] * part_re
            im += wy[a] * part_im
        out[k] = complex(re, im)


@njit(cache=True, fastmath=True, error_model="numpy", nogil=True)
def _on_outer(
    block: np.ndarray, ny: int, nx: int, rows: np.ndarray, cols: np.ndarray, out: np.ndarray
) -> None:
    """The spline of :func:`_at_points` at every ``(rows[a], cols[b])`` into ``out[a, b]``:
    the rows' six nodes contracted first (whole lines), then the columns' (12 products per
    point where :func:`_at_points` makes 36)."""
    w = np.empty(6)
    line = np.empty(block.shape[1])
    wx = np.empty((cols.shape[0], 6))
    cx = np.empty(cols.shape[0], dtype=np.int64)
    for b in range(cols.shape[0]):
        fc = math.floor(cols[b])
        _weights(cols[b] - fc, wx[b])
        cx[b] = 2 * ((int(fc) - 2) % nx)
    for a in range(rows.shape[0]):
        fr = math.floor(rows[a])
        _weights(rows[a] - fr, w)
        r0 = (int(fr) - 2) % ny
        line[:] = 0.0
        for j in range(6):
            wj = w[j]
            source = block[r0 + j]
            for c in range(line.shape[0]):
                line[c] += wj * source[c]
        for b in range(cols.shape[0]):
            re = 0.0
            im = 0.0
            c0 = cx[b]
            for j in range(6):
                re += wx[b, j] * line[c0 + 2 * j]
                im += wx[b, j] * line[c0 + 2 * j + 1]
            out[a, b] = complex(re, im)


@dataclass(frozen=True)
class PeriodicQuintic:
    """The periodic quintic spline of complex coefficients (e.g. SciPy's
    ``spline_filter(..., mode="grid-wrap")`` of samples): ``block`` holds them wrapped by
    :data:`WRAP` lines and columns, parts interleaved; ``shape`` the nodes."""

    block: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def from_coefficients(cls, coefficients: np.ndarray) -> PeriodicQuintic:
        """The spline of ``coefficients`` (ny, nx), complex."""
        ny, nx = coefficients.shape
        wrapped = np.empty((ny + WRAP, nx + WRAP), dtype=np.complex128)
        wrapped[:ny, :nx] = coefficients
        wrapped[:ny, nx:] = coefficients[:, :WRAP]
        wrapped[ny:] = wrapped[:WRAP]
        return cls(wrapped.view(np.float64), (ny, nx))

    def at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The spline at the points ``(rows[k], cols[k])`` (grid units, any real value)."""
        rows = np.ascontiguousarray(rows, dtype=np.float64)
        out = np.empty(rows.shape[0], dtype=np.complex128)
        _at_points(self.block, *self.shape, rows, np.ascontiguousarray(cols, np.float64), out)
        return out

    def outer(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The spline at every ``(rows[a], cols[b])``: (len(rows), len(cols))."""
        rows = np.ascontiguousarray(rows, dtype=np.float64)
        cols = np.ascontiguousarray(cols, dtype=np.float64)
        out = np.empty((rows.shape[0], cols.shape[0]), dtype=np.complex128)
        _on_outer(self.block, *self.shape, rows, cols, out)
        return out
