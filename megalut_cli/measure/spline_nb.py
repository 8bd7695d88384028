"""Compiled kernel (numba): a periodic quintic B-spline evaluated at scattered points.

:func:`quintic_wrap` is ``scipy.ndimage.map_coordinates(c, (rows, cols), order=5,
mode="grid-wrap", prefilter=False)`` for complex coefficients ``c``, both parts in one pass
(to 1e-13 of SciPy's sums): the cell engine reads the PSF's transform at the moving
fixnoise's frequencies with it (:mod:`.cell_metacal`).
"""

from __future__ import annotations

import math

import numpy as np

from megalut_cli.jit import njit


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


@njit(cache=True, inline="always")
def _nodes(first: int, n: int, index: np.ndarray) -> None:
    """The six node indices from ``first``, wrapped into ``[0, n)``."""
    for j in range(6):
        index[j] = (first + j) % n


@njit(cache=True, error_model="numpy", nogil=True)
def quintic_wrap(
    coefficients: np.ndarray, rows: np.ndarray, cols: np.ndarray, out: np.ndarray
) -> None:
    """The spline of the complex ``coefficients`` (ny, nx), periodic, at the points
    ``(rows[k], cols[k])`` (grid units, any real value) into ``out[k]``."""
    ny, nx = coefficients.shape
    wy = np.empty(6)
    wx = np.empty(6)
    iy = np.empty(6, dtype=np.int64)
    ix = np.empty(6, dtype=np.int64)
    for k in range(rows.shape[0]):
        fr = math.floor(rows[k])
        fc = math.floor(cols[k])
        _weights(rows[k] - fr, wy)
        _weights(cols[k] - fc, wx)
        r0 = int(fr) - 2
        c0 = int(fc) - 2
        _nodes(r0, ny, iy)
        inside = 0 <= c0 and c0 + 6 <= nx
        if not inside:
            _nodes(c0, nx, ix)
        acc = 0j
        for a in range(6):
            line = coefficients[iy[a]]
            part = 0j
            if inside:  # contiguous nodes: no index array
                for b in range(6):
                    part += wx[b] * line[c0 + b]
            else:
                for b in range(6):
                    part += wx[b] * line[ix[b]]
            acc += wy[a] * part
        out[k] = acc
