"""Fixnoise of metacal on a whole cell (metadetection): a noise field that moves with the image,
drawn by GalSim for the reference engine (``--engine galsim``; the cell engine,
:mod:`.cell_metacal`, puts the same field in its own transforms).

Metacal's fixnoise (:mod:`.metacal`) adds to every version the operation's image of a noise
field rotated by 90 degrees and rotated back, so that the noise the operation shears is
matched by noise sheared the other way. On a stamp centred on its object that is all; on a
cell the shear is applied about the cell's centre, so the image moves by ``step * r`` at a
distance ``r`` from it, and the rotated field moves the other way: under an object 100 px
from the centre, the fixnoise of its 1p and 1m versions are 4 px apart, two independent
noise realizations, and its response ``R = (g_1p - g_1m) / (2 step)`` scatters by about 1.4
where the noise's own shear leaves 0.06 (examples/metadetect/README.md).

Here version ``v`` gets the same noise field ``W`` sheared like the image (it moves with the
objects) and convolved with ``K_v``: the operation's response to one pixel, rotated by 90
degrees (what the rotated field's pixels become: the noise deconvolved by the PSF rotated
by 90 degrees and sheared the other way), drawn on :data:`KERNEL_SIZE` pixels. Each
version's fixnoise then has the power spectrum of the rotated field's (the shear of the
pixel positions keeps white noise white; the kernels are drawn by the same operation, with
its band limit), so the correction is metacal's, while under each object it is one field.

Correlated noise of spectrum ``S`` (a noise image's correlation,
:mod:`.noise_correlation`): ``W`` is unit white noise and ``K_v`` is also convolved with
the kernel of transform ``sqrt(S(A^-1 k))``, the noise's colour sheared the other way, as
metacal's rotated field carries it (docs/metadetect.md, "A noise image").
"""

from __future__ import annotations

import functools

import galsim
import numpy as np

from megalut_cli.measure.metacal_defaults import INTERPOLANT, SHEARS
from megalut_cli.measure.metacal_fft import shear_matrix
from megalut_cli.measure.noise_correlation import spectrum_at

#: Side (pixels) of the drawn response of the operation to one pixel (its tails come from the
#: band limit of the target: for the Gaussian PSF of examples/scenes/isolated.toml, its power
#: changes by less than 0.3 % from 129 to 385 px).
KERNEL_SIZE = 129


@functools.lru_cache(maxsize=16)
def _kernels(
    psf_bytes: bytes, psf_size: int, step: float, target: str, size: int
) -> dict[str, np.ndarray]:
    """The operation's response to one pixel in each version, rotated by 90 degrees."""
    from megalut_cli.measure.metacal import metacal_versions

    psf = np.frombuffer(psf_bytes).reshape(psf_size, psf_size)
    impulse = np.zeros((1, size, size))
    impulse[0, size // 2, size // 2] = 1.0
    versions, _ = metacal_versions(impulse, psf, step, engine="galsim", target=target)
    return {k: np.ascontiguousarray(np.rot90(v[0], -1)) for k, v in versions.items()}


def kernel_size(cell_size: int) -> int:
    """The side of the drawn kernels for a cell: :data:`KERNEL_SIZE`, at most the cell's
    (odd: the pixel on the central one)."""
    return min(KERNEL_SIZE, cell_size - 1 + cell_size % 2)


def coloured(kernel: np.ndarray, correlation: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``kernel`` (odd square) convolved with the kernel of transform ``sqrt(S(M^-1 k))``
    (``S`` the spectrum of ``correlation``, ``M`` = ``matrix``), on a grid padded by the
    correlation's lags and cut back to the kernel's side."""
    n, pad = kernel.shape[0], correlation.shape[0]
    grid = n + 2 * pad
    padded = np.zeros((grid, grid))
    padded[pad : pad + n, pad : pad + n] = kernel
    k = 2.0 * np.pi * np.fft.fftfreq(grid)
    kx, ky = np.meshgrid(k, k)
    inv = np.linalg.inv(matrix)
    ux, uy = inv[0, 0] * kx + inv[0, 1] * ky, inv[1, 0] * kx + inv[1, 1] * ky
    spectrum = spectrum_at(correlation, ux, uy)
    # the colour's kernel centred on pixel 0: its phases cancel, as a real even transform's
    out = np.fft.ifft2(np.fft.fft2(padded) * np.sqrt(np.maximum(spectrum, 0.0))).real
    return out[pad : pad + n, pad : pad + n]


def moving_fixnoise(
    field: np.ndarray,
    psf_image: np.ndarray,
    step: float,
    target: str,
    correlation: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The fixnoise of each metacal version (``{type: (S, S)}``) of a cell, from its noise
    ``field`` (S, S) (e.g. :func:`~.metacal.noise_field`): ``field`` sheared like the image
    by that version's shear, about the cell's centre, convolved with the rotated response
    of the operation (``psf_image``, ``step``, ``target``: as the cell's operation), and
    with ``correlation`` (a noise's, :func:`~.noise_correlation.noise_correlation`; the
    field then unit white noise) the noise's colour sheared the other way."""
    field = np.asarray(field, dtype=np.float64)
    ny, nx = field.shape
    psf = np.ascontiguousarray(psf_image, dtype=np.float64)
    kernels = _kernels(psf.tobytes(), psf.shape[0], float(step), target, kernel_size(min(ny, nx)))
    noise = galsim.InterpolatedImage(galsim.ImageD(field, scale=1.0), x_interpolant=INTERPOLANT)
    out = {}
    for kind, kernel in kernels.items():
        s1, s2 = SHEARS[kind]
        if correlation is not None:
            kernel = coloured(kernel, correlation, shear_matrix(s1 * step, s2 * step))
        moved = noise.shear(g1=s1 * step, g2=s2 * step) if kind != "noshear" else noise
        k_obj = galsim.InterpolatedImage(
            galsim.ImageD(kernel, scale=1.0), x_interpolant=INTERPOLANT
        )
        drawn = galsim.Convolve(moved, k_obj).drawImage(
            nx=nx, ny=ny, scale=1.0, method="no_pixel", dtype=np.float64
        )
        out[kind] = drawn.array
    return out
