"""Compiled kernels (numba): a periodic quintic B-spline of complex coefficients evaluated at
scattered points or at a linear map of a grid's frequencies.

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


@njit(cache=True, inline="always")
def _point_at(
    block: np.ndarray, ny: int, nx: int, row: float, col: float, wy: np.ndarray, wx: np.ndarray
) -> tuple[float, float]:
    """The spline of the wrapped, interleaved coefficients ``block`` (``ny`` by ``nx`` nodes)
    at ``(row, col)``: its real and imaginary parts (``wy``, ``wx`` the weights' work
    arrays)."""
    fr = math.floor(row)
    fc = math.floor(col)
    _weights(row - fr, wy)
    _weights(col - fc, wx)
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
    return re, im


@njit(cache=True, fastmath=True, error_model="numpy", nogil=True)
def _at_points(
    block: np.ndarray, ny: int, nx: int, rows: np.ndarray, cols: np.ndarray, out: np.ndarray
) -> None:
    """The spline of the wrapped, interleaved coefficients ``block`` (``ny`` by ``nx``
    nodes) at ``(rows[k], cols[k])`` (grid units, any real value) into ``out[k]``."""
    wy = np.empty(6)
    wx = np.empty(6)
    for k in range(rows.shape[0]):
        re, im = _point_at(block, ny, nx, rows[k], cols[k], wy, wx)
        out[k] = complex(re, im)


@njit(cache=True, inline="always")
def _line_at(line: np.ndarray, u: float, n: int, w: np.ndarray) -> tuple[float, float]:
    """The spline of one interleaved, wrapped line of coefficients (``n`` nodes) at ``u``:
    its real and imaginary parts (``w`` the weights' work array)."""
    f = math.floor(u)
    _weights(u - f, w)
    first = 2 * ((int(f) - 2) % n)
    re = 0.0
    im = 0.0
    for j in range(6):
        re += w[j] * line[first + 2 * j]
        im += w[j] * line[first + 2 * j + 1]
    return re, im


@njit(cache=True, fastmath=True, error_model="numpy", nogil=True)
def _on_grid(
    block: np.ndarray,
    ny: int,
    nx: int,
    matrix: np.ndarray,
    kx: np.ndarray,
    ky: np.ndarray,
    keep: np.ndarray,
    phase_x: np.ndarray,
    phase_y: np.ndarray,
    out: np.ndarray,
) -> None:
    """The spline of :func:`_at_points` at ``(u_y, u_x)``, ``(u_x, u_y) = matrix @
    (kx[ix], ky[iy])``, for every grid point where ``keep[iy, ix]``, in C order, times
    ``phase_y[iy] * phase_x[ix]``, into ``out``. Where ``u_y`` is constant along a grid row
    (``matrix[1, 0] == 0``) the six lines are contracted once per row (and where ``u_x`` is
    a column's alone, its weights made once per column), where ``u_x`` is
    (``matrix[0, 0] == 0``) the six columns: 12 products per point then, not 36."""
    (m00, m01), (m10, m11) = (matrix[0, 0], matrix[0, 1]), (matrix[1, 0], matrix[1, 1])
    height, width = block.shape
    wa = np.empty(6)
    wb = np.empty(6)
    line = np.empty(max(width, 2 * height))
    # u_x a function of the column alone: its weights and first node once per column
    by_column = m10 == 0.0 and m01 == 0.0
    column_weights = np.empty((keep.shape[1] if by_column else 0, 6))
    column_first = np.empty(keep.shape[1] if by_column else 0, dtype=np.int64)
    for ix in range(column_first.shape[0]):
        ux = m00 * kx[ix]
        fc = math.floor(ux)
        _weights(ux - fc, column_weights[ix])
        column_first[ix] = 2 * ((int(fc) - 2) % nx)
    n = 0
    for iy in range(keep.shape[0]):
        first = -1
        for ix in range(keep.shape[1]):
            if keep[iy, ix]:
                first = ix
                break
        if first < 0:
            continue
        mode = 0  # 1: a fixed u_y along the row, 2: a fixed u_x, 0: neither
        if m10 == 0.0:
            mode = 1
            uy = m11 * ky[iy]
            fr = math.floor(uy)
            _weights(uy - fr, wa)
            r0 = (int(fr) - 2) % ny
            line[:width] = 0.0
            for j in range(6):
                wj = wa[j]
                source = block[r0 + j]
                for c in range(width):
                    line[c] += wj * source[c]
        elif m00 == 0.0:
            mode = 2
            ux = m01 * ky[iy]
            fc = math.floor(ux)
            _weights(ux - fc, wb)
            c0 = 2 * ((int(fc) - 2) % nx)
            for r in range(height):
                re = 0.0
                im = 0.0
                for j in range(6):
                    re += wb[j] * block[r, c0 + 2 * j]
                    im += wb[j] * block[r, c0 + 2 * j + 1]
                line[2 * r] = re
                line[2 * r + 1] = im
        for ix in range(first, keep.shape[1]):
            if not keep[iy, ix]:
                continue
            re = 0.0
            im = 0.0
            if by_column:
                c0 = column_first[ix]
                for j in range(6):
                    re += column_weights[ix, j] * line[c0 + 2 * j]
                    im += column_weights[ix, j] * line[c0 + 2 * j + 1]
            elif mode == 1:
                re, im = _line_at(line, m00 * kx[ix] + m01 * ky[iy], nx, wb)
            elif mode == 2:
                re, im = _line_at(line, m10 * kx[ix] + m11 * ky[iy], ny, wa)
            else:
                uy = m10 * kx[ix] + m11 * ky[iy]
                re, im = _point_at(block, ny, nx, uy, m00 * kx[ix] + m01 * ky[iy], wa, wb)
            out[n] = complex(re, im) * (phase_y[iy] * phase_x[ix])
            n += 1


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

    @classmethod
    def from_half_spectrum(cls, half: np.ndarray, nx: int) -> PeriodicQuintic:
        """The spline of the whole DFT of a real image ``nx`` wide, given as its ``rfft2``
        ``half`` (ny, nx // 2 + 1): the other columns by Hermitian symmetry, written in
        place."""
        ny, nh = half.shape
        wrapped = np.empty((ny + WRAP, nx + WRAP), dtype=np.complex128)
        wrapped[:ny, :nh] = half
        # column nx - j of row (-r) mod ny is the conjugate of column j of row r
        np.conjugate(half[0, nx - nh : 0 : -1], out=wrapped[0, nh:nx])
        np.conjugate(half[ny - 1 : 0 : -1, nx - nh : 0 : -1], out=wrapped[1:ny, nh:nx])
        wrapped[:ny, nx:] = wrapped[:ny, :WRAP]
        wrapped[ny:] = wrapped[:WRAP]
        return cls(wrapped.view(np.float64), (ny, nx))

    def at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The spline at the points ``(rows[k], cols[k])`` (grid units, any real value)."""
        rows = np.ascontiguousarray(rows, dtype=np.float64)
        cols = np.ascontiguousarray(cols, dtype=np.float64)
        if rows.ndim != 1 or cols.shape != rows.shape:  # the kernel does not check indices
            raise ValueError(f"at: rows and cols of one length, got {rows.shape}, {cols.shape}")
        out = np.empty(rows.shape[0], dtype=np.complex128)
        _at_points(self.block, *self.shape, rows, cols, out)
        return out

    def on_grid(
        self,
        matrix: np.ndarray,
        kx: np.ndarray,
        ky: np.ndarray,
        keep: np.ndarray,
        phase_x: np.ndarray | None = None,
        phase_y: np.ndarray | None = None,
    ) -> np.ndarray:
        """The spline at ``(u_y, u_x)`` (its rows, its columns), ``(u_x, u_y) = matrix @
        (kx[ix], ky[iy])`` (grid units), for every ``(iy, ix)`` where ``keep`` (2-D
        boolean), in ``keep``'s C order (as ``values[keep]``), times
        ``phase_y[iy] * phase_x[ix]`` when given (complex)."""
        keep = np.ascontiguousarray(keep, dtype=np.bool_)
        ny, nx = keep.shape
        matrix = np.ascontiguousarray(matrix, dtype=np.float64)
        kx = np.ascontiguousarray(kx, dtype=np.float64)
        ky = np.ascontiguousarray(ky, dtype=np.float64)
        phase_x = np.ones(nx, np.complex128) if phase_x is None else np.asarray(phase_x)
        phase_y = np.ones(ny, np.complex128) if phase_y is None else np.asarray(phase_y)
        # the kernel does not check its indices
        if matrix.shape != (2, 2) or kx.shape != (nx,) or phase_x.shape != (nx,):
            raise ValueError(f"on_grid: a 2x2 matrix and {nx} x frequencies and phases")
        if ky.shape != (ny,) or phase_y.shape != (ny,):
            raise ValueError(f"on_grid: {ny} y frequencies and phases")
        out = np.empty(int(np.count_nonzero(keep)), dtype=np.complex128)
        _on_grid(
            self.block,
            *self.shape,
            matrix,
            kx,
            ky,
            keep,
            np.ascontiguousarray(phase_x, np.complex128),
            np.ascontiguousarray(phase_y, np.complex128),
            out,
        )
        return out
