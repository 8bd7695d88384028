"""The metacal operation on a whole cell (metadetection) on the cell's own FFT grid.

Version ``v`` of shear matrix ``A`` (:func:`~.metacal_fft.shear_matrix`) is, about the
cell's true centre, ``J(x) = H(A^-1 x)`` where ``H`` has the transform
``T(A^-1 q) I(q) / P(q)`` on the grid of the zero-padded cell: the target ``T`` at the
unsheared frequencies (analytic), the cell ``I`` and the PSF ``P`` where they were sampled,
zero beyond the PSF's ``maxk`` (as GalSim's ``Deconvolve``). The change of coordinates
``A^-1`` is made by 1-D Fourier shifts of rows and columns (three shears, four for a
diagonal matrix): exact for a band-limited image. The fixnoise that moves with the image
(:mod:`.cell_fixnoise`; white, or coloured by a noise correlation) enters ``H`` with its own
filter, so a version costs one inverse FFT and the shifts. GalSim's operation
(:mod:`.metacal`) stays the reference (``measure --engine galsim``); docs/metadetect.md
compares the two.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.ndimage

from megalut_cli.measure.metacal_defaults import SHEARS, TYPES
from megalut_cli.measure.metacal_fft import psf_params, shear_matrix
from megalut_cli.measure.metacal_targets import MetacalTarget, metacal_target
from megalut_cli.measure.noise_correlation import spectrum_on_grid
from megalut_cli.measure.spline_nb import PeriodicQuintic

#: Pixels of zero padding each side of the cell beyond the largest shift of the passes:
#: room for the tails of the deconvolution and fixnoise kernels.
HALO = 24
#: The 90-degree rotation of the fixnoise (``np.rot90(a, -1)``) acting on ``(x, y)``.
ROTATION = np.array([[0.0, -1.0], [1.0, 0.0]])


@dataclass(frozen=True)
class Pass:
    """One 1-D Fourier shift: along ``axis`` (1: rows shifted along x, 0: columns along y),
    the transform multiplied by ``phase``."""

    axis: int
    phase: np.ndarray


@dataclass(frozen=True, eq=False)
class CellGeometry:
    """What a cell of ``size`` pixels needs for one step, whatever its PSF: the grid side,
    the cell's offset in it, each version's inverse shear matrix and its shifts (hashed by
    identity: one per size and step, :func:`cell_geometry`)."""

    size: int
    grid: int
    offset: int
    inverses: tuple[np.ndarray, ...]
    passes: tuple[tuple[Pass, ...], ...]


@dataclass(frozen=True)
class CellFilters:
    """Per version, the filters (``rfft2`` layout) of the cell's transform and of the moving
    fixnoise field's, under one PSF, step and target (``None``: a version not made)."""

    image: tuple[np.ndarray | None, ...]
    noise: tuple[np.ndarray | None, ...]
    target_sigma: float


def shear_passes(matrix: np.ndarray) -> list[tuple[int, float]]:
    """``matrix`` (determinant 1, acting on ``(x, y)``) as 1-D shears ``(axis, s)`` to apply
    in order: axis 1 maps ``F(x, y) -> F(x + s y, y)``, axis 0 ``F(x, y) -> F(x, y + s x)``;
    applying them to ``H`` gives ``H(matrix @ (x, y))``. Identity: none; else the first is
    along axis 1 (it is merged with the inverse FFT)."""
    (a, b), (c, d) = matrix
    if abs(b) < 1e-15 and abs(c) < 1e-15 and abs(a - 1) < 1e-15 and abs(d - 1) < 1e-15:
        return []
    last: list[tuple[int, float]] = []
    if abs(c) < 1e-12:  # diagonal-like: matrix @ Y(-u), then Y(u) last (u balances the rest)
        u = math.sqrt(max(abs(a - 1.0), abs(d - 1.0), abs(b), 1e-12))
        last = [(0, u)]
        a, c = a - u * b, c - u * d
    return [(1, (a - 1.0) / c), (0, c), (1, (d - 1.0) / c), *last]


def _margin(size: int, steps: list[list[tuple[int, float]]]) -> int:
    """The padding each side: the largest shift of any pass at the cell's corners, plus
    :data:`HALO`."""
    largest = max((abs(s) for passes in steps for _, s in passes), default=0.0)
    return int(math.ceil(largest * size / math.sqrt(2.0))) + HALO


@functools.lru_cache(maxsize=8)
def _grid_k(grid: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``rfft2`` frequencies (radians per pixel): ``qx`` (1, grid//2+1), ``qy`` (grid, 1)
    (cached, read-only)."""
    qx = 2.0 * math.pi * np.fft.rfftfreq(grid)[None, :]
    qy = 2.0 * math.pi * np.fft.fftfreq(grid)[:, None]
    qx.flags.writeable = qy.flags.writeable = False
    return qx, qy


def _apply(matrix: np.ndarray, qx: np.ndarray, qy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``matrix @ (qx, qy)``, broadcast."""
    return matrix[0, 0] * qx + matrix[0, 1] * qy, matrix[1, 0] * qx + matrix[1, 1] * qy


def _within(matrix: np.ndarray, grid: int, maxk: float) -> np.ndarray:
    """Where ``|matrix @ q| <= maxk`` on the grid's frequencies ``q`` (``rfft2`` layout), from
    the quadratic form of ``matrix``."""
    qx, qy = _grid_k(grid)
    (a, b), (_, d) = matrix.T @ matrix
    return a * (qx * qx) + (2.0 * b * qx) * qy + d * (qy * qy) <= maxk * maxk


def _pass(axis: int, s: float, grid: int, centre: float) -> Pass:
    """The phase of one shear pass: a line at ``(coordinate - centre)`` shifted by ``s`` times
    it, ``exp(i k s (c - centre))``."""
    k = 2.0 * math.pi * np.fft.rfftfreq(grid)
    c = np.arange(grid) - centre
    phase = np.exp(1j * s * np.multiply.outer(c, k)).astype(np.complex64)  # (line, k)
    return Pass(axis, phase if axis == 1 else np.ascontiguousarray(phase.T))


def _quintic_dual(grid: int) -> np.ndarray:
    """The transform of the quintic B-spline's samples (1, 26, 66, 26, 1) / 120 at each of
    the grid's indices: what the periodic prefilter divides by, axis by axis."""
    t = 2.0 * math.pi * np.arange(grid) / grid
    return (66.0 + 52.0 * np.cos(t) + 2.0 * np.cos(2.0 * t)) / 120.0


@dataclass(frozen=True)
class PsfTransform:
    """A PSF image's DFT on a grid, its true centre the origin: ``half`` its values on the
    grid (``rfft2`` layout); ``spline`` the periodic quintic spline of the DFT of the image
    rolled by whole pixels to the origin, the x frequency its first axis (``None`` when not
    asked), ``shift`` the half pixel left (0 for an odd size, 0.5 for an even one): at any
    ``u`` the DFT is ``exp(i shift (u_x + u_y))`` times the spline's value at
    ``(u_x, u_y)``."""

    half: np.ndarray
    spline: PeriodicQuintic | None
    shift: float


def _rfft2_of_support(image: np.ndarray, at: np.ndarray, grid: int) -> np.ndarray:
    """``scipy.fft.rfft2`` of a ``grid``-sided zero image holding ``image`` at rows and
    columns ``at``: its rows' transforms only where the image is, then the columns'."""
    rows = np.zeros((image.shape[0], grid))
    rows[:, at] = image
    half = np.zeros((grid, grid // 2 + 1), dtype=np.complex128)
    half[at] = scipy.fft.rfft(rows, axis=1)
    return scipy.fft.fft(half, axis=0, overwrite_x=True)


def psf_transform(psf: np.ndarray, grid: int, spline: bool) -> PsfTransform:
    """The :class:`PsfTransform` of ``psf`` on a ``grid``-sided grid, its spline when asked:
    SciPy's ``spline_filter(mode="grid-wrap")`` of the rolled image's DFT, made as a
    division of its dual (the rolled image) by the spline's transform. The spline's axes are
    swapped (x first) because the moving fixnoise reads it at a nearly anti-diagonal map of
    the grid's frequencies (:data:`ROTATION`): ``u_y`` then changes along a grid row, and
    :meth:`~.spline_nb.PeriodicQuintic.on_grid` contracts whole lines of coefficients."""
    p = psf.shape[0]
    whole = (p - 1) // 2
    shift = 0.5 * (p - 1) - whole
    at = (np.arange(p) - whole) % grid
    half = _rfft2_of_support(psf, at, grid)
    if shift:
        qx, qy = _grid_k(grid)
        half *= np.exp(1j * shift * qy) * np.exp(1j * shift * qx)
    if not spline:
        return PsfTransform(half, None, shift)
    beta = 1.0 / _quintic_dual(grid)[at]
    dual = _rfft2_of_support(psf.T * np.multiply.outer(beta, beta), at, grid)
    return PsfTransform(half, PeriodicQuintic.from_half_spectrum(dual, grid), shift)


def _spline_on_grid(
    spline: PeriodicQuintic,
    matrix: np.ndarray,
    keep: np.ndarray,
    shift: float = 0.0,
    x_first: bool = False,
) -> np.ndarray:
    """A transform sampled on the grid (a PSF's DFT, :func:`psf_transform`, or a noise
    spectrum), read from its periodic quintic ``spline`` (axes ``(u_y, u_x)``, or
    ``(u_x, u_y)`` when ``x_first``) at ``u = matrix @ q`` for the grid's frequencies ``q``
    where ``keep`` (``rfft2`` layout, values in ``keep``'s order), times
    ``exp(i shift (u_x + u_y))``: fine where the grid samples it finely (the PSF: the grid
    is several times its image, 1e-9 of the exact sum where it exceeds 1e-3). The phase is
    one factor per axis: ``u_x + u_y = (a + c) q_x + (b + d) q_y``."""
    scale = keep.shape[0] / (2.0 * math.pi)
    qx, qy = (k.ravel() for k in _grid_k(keep.shape[0]))
    (a, b), (c, d) = matrix
    phase_x = np.exp(1j * shift * (a + c) * qx) if shift else None
    phase_y = np.exp(1j * shift * (b + d) * qy) if shift else None
    to_nodes = matrix[::-1] if x_first else matrix
    return spline.on_grid(to_nodes, qx * scale, qy * scale, keep, phase_x, phase_y)


@functools.lru_cache(maxsize=8)
def cell_geometry(size: int, step: float) -> CellGeometry:
    """The grid and shifts of a ``size``-pixel cell for the shear ``step`` (cached)."""
    matrices = [shear_matrix(s1 * step, s2 * step) for s1, s2 in (SHEARS[k] for k in TYPES)]
    inverses = tuple(np.linalg.inv(m) for m in matrices)
    steps = [shear_passes(inv) for inv in inverses]
    grid = scipy.fft.next_fast_len(size + 2 * _margin(size, steps), real=True)
    offset = (grid - size) // 2
    centre = offset + 0.5 * (size - 1)
    passes = tuple(tuple(_pass(axis, s, grid, centre) for axis, s in st) for st in steps)
    return CellGeometry(size, grid, offset, inverses, passes)


@functools.lru_cache(maxsize=16)
def cell_filters(
    psf_bytes: bytes,
    psf_size: int,
    target: MetacalTarget,
    geometry: CellGeometry,
    moving: bool = True,
    correlation_bytes: bytes | None = None,
    kinds: tuple[str, ...] = TYPES,
) -> CellFilters:
    """The filters of one PSF image (its bytes and side) and target on ``geometry``
    (cached), for the versions ``kinds`` (``None`` for the others); without ``moving``, none
    for the moving fixnoise (``noise`` empty). With ``correlation_bytes`` (a noise
    correlation, :func:`~.noise_correlation.noise_correlation`, as float64 bytes) the
    fixnoise filters colour a unit white field to that noise."""
    psf, maxk, _ = psf_params(psf_bytes, psf_size)
    grid = geometry.grid
    qx, qy = np.broadcast_arrays(*_grid_k(grid))
    within = _within(np.eye(2), grid, maxk)
    q_within = qx[within], qy[within]
    psf_k = psf_transform(psf, grid, moving)
    reciprocal = 1.0 / psf_k.half[within]
    wanted = [kind in kinds for kind in TYPES]
    image: list[np.ndarray | None] = []
    for inv, want in zip(geometry.inverses, wanted):
        if not want:
            image.append(None)
            continue
        filt = np.zeros(within.shape, dtype=np.complex64)
        filt[within] = target.kvalue(*_apply(inv, *q_within)) * reciprocal
        image.append(filt)
    if psf_k.spline is None:
        return CellFilters(tuple(image), (), float(target.sigma))
    colour = None
    if correlation_bytes is not None:
        correlation = np.frombuffer(correlation_bytes)
        side = math.isqrt(correlation.size)
        spectrum = spectrum_on_grid(correlation.reshape(side, side), grid)
        colour = PeriodicQuintic.from_coefficients(
            scipy.ndimage.spline_filter(spectrum, order=5, mode="grid-wrap") + 0j
        )
    noise: list[np.ndarray | None] = []
    for inv, want in zip(geometry.inverses, wanted):
        if not want:
            noise.append(None)
            continue
        # the fixnoise: the white field sheared like the image, convolved with the rotated
        # response of the operation: T(R A^-1 q) / P(R A^-2 q), zero beyond maxk there;
        # a noise correlation of spectrum S adds sqrt(S(A^-2 q)): metacal's rotated field
        # is that noise sheared the other way
        psf_at = ROTATION @ inv @ inv
        keep = _within(psf_at, grid, maxk)
        filt = np.zeros(keep.shape, dtype=np.complex64)
        values = target.kvalue(*_apply(ROTATION @ inv, qx[keep], qy[keep])) / _spline_on_grid(
            psf_k.spline, psf_at, keep, psf_k.shift, x_first=True
        )
        if colour is not None:
            values *= np.sqrt(np.maximum(_spline_on_grid(colour, inv @ inv, keep).real, 0.0))
        filt[keep] = values
        noise.append(filt)
    return CellFilters(tuple(image), tuple(noise), float(target.sigma))


def _shifted(image: np.ndarray, passes: tuple[Pass, ...]) -> np.ndarray:
    """``image`` (grid, grid) through the 1-D Fourier shifts ``passes``, in order."""
    n = image.shape[0]
    for p in passes:
        spec = scipy.fft.rfft(image, axis=p.axis)
        spec *= p.phase
        image = scipy.fft.irfft(spec, n=n, axis=p.axis)
    return image


def _version(spec: np.ndarray, passes: tuple[Pass, ...], geometry: CellGeometry) -> np.ndarray:
    """One version's cell from its transform ``spec`` (``rfft2`` layout, overwritten)."""
    o, g, size = geometry.offset, geometry.grid, geometry.size
    if passes:  # the first shift (axis 1) between the inverse FFT's two axes
        mixed = scipy.fft.ifft(spec, axis=0, overwrite_x=True)
        mixed *= passes[0].phase
        h = _shifted(scipy.fft.irfft(mixed, n=g, axis=1), passes[1:])
    else:
        h = scipy.fft.irfft2(spec, s=(g, g))
    return h[o : o + size, o : o + size].astype(np.float64)


def cell_versions(
    image: np.ndarray,
    psf_image: np.ndarray,
    step: float,
    target: str,
    moving_field: np.ndarray | None = None,
    rotated_field: np.ndarray | None = None,
    kinds: tuple[str, ...] = TYPES,
    moving_correlation: np.ndarray | None = None,
) -> tuple[dict[str, np.ndarray], float]:
    """The metacal versions ``kinds`` (default all five), ``{type: (S, S)}``, of a cell
    ``image`` (S, S) under ``psf_image`` (pixel included, centred on its true centre), and
    the target's sigma. Fixnoise: ``moving_field`` (S, S), white noise, moves with the image
    (:mod:`.cell_fixnoise`), coloured by ``moving_correlation`` when given (a noise's
    correlation, :func:`~.noise_correlation.noise_correlation`; the field then unit white
    noise); ``rotated_field`` (S, S), e.g. a noise image with the data's correlations, is
    metacal's: rotated by 90 degrees, through the operation, rotated back."""
    image = np.asarray(image, dtype=np.float64)
    size = image.shape[0]
    if image.shape != (size, size):
        raise ValueError(f"a cell must be square, got shape {image.shape}")
    psf = np.ascontiguousarray(psf_image, dtype=np.float64)
    geometry = cell_geometry(size, float(step))
    filters = cell_filters(
        psf.tobytes(),
        psf.shape[0],
        metacal_target(target, psf, step),
        geometry,
        moving_field is not None,
        None
        if moving_correlation is None
        else np.ascontiguousarray(moving_correlation, dtype=np.float64).tobytes(),
        tuple(kind for kind in TYPES if kind in kinds),
    )
    o, g = geometry.offset, geometry.grid
    padded = np.zeros((g, g), dtype=np.float32)

    def transform(cell: np.ndarray) -> np.ndarray:
        padded[o : o + size, o : o + size] = cell
        return scipy.fft.rfft2(padded)

    image_k = transform(image)
    moving_k = None if moving_field is None else transform(moving_field)
    rotated_k = None if rotated_field is None else transform(np.rot90(rotated_field, 1))
    out = {}
    for v, kind in enumerate(TYPES):
        if kind not in kinds:
            continue
        spec = image_k * filters.image[v]
        if moving_k is not None:
            spec += moving_k * filters.noise[v]
        out[kind] = _version(spec, geometry.passes[v], geometry)
        if rotated_k is not None:
            spec = rotated_k * filters.image[v]
            out[kind] += np.rot90(_version(spec, geometry.passes[v], geometry), -1)
    return out, filters.target_sigma
