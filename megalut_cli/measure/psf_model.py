"""PSF models of an exposure, evaluated at object positions: PSFEx ``.psf`` files and Piff models.

:func:`load_psf_model` recognises the file (FITS read with fitsio, no extra import) and
returns a :class:`PsfModel` whose :meth:`PsfModel.draw` gives the pixelised PSF image at
1-based FITS positions ``(x, y)`` of the exposure the model was fit on, as a stack
``(n, size, size)`` of float64 stamps normalised to unit sum. Each PSF is centred on its
stamp's true centre, as GalSim draws a profile by default and as megalut's stamps are cut
(:mod:`.stamps`: the centre of an even stamp lies between pixels), so that the stamps serve
as ``measure``'s per-row PSF stamps (``psf_adamom_*``) and as the PSF that ``--metacal``
deconvolves.

* PSFEx (GalSim's :class:`galsim.des.DES_PSFEx`): the model is a polynomial in the image
  position of basis images sampled every ``PSF_SAMP`` image pixels; it includes the pixel,
  so it is drawn without one (``method='no_pixel'``). The drawing is linear in the basis,
  and every PSF is drawn at its stamp's centre, so the basis images are resampled once per
  stamp size with GalSim's own Lanczos(3) kernel (as ``DES_PSFEx.getPSF`` interpolates:
  one separable matrix product) and each position costs one polynomial combination of
  those (vectorised over all positions). On an odd stamp it agrees with
  ``DES_PSFEx.getPSF(pos).drawImage(method='no_pixel')`` to ~1e-7 of the peak
  (``tests/test_psf_model.py``; GalSim combines the basis in float32); on an even one it is
  that drawing on a pixel fewer moved half a pixel by lanczos15 (GalSim's there is 1 %
  too narrow: docs/catalogs.md, PSF models). The model is in image pixels: it has no
  arcsecond scale of its own.
* Piff (``pip install 'megalut-cli[piff]'``; ``piff.read``): a single-chip model, drawn by
  Piff itself (``PSF.draw``, which chooses the drawing method of the model: with the pixel
  for a ``GSObjectModel``, without for a ``PixelGrid``), one position at a time, on the
  local WCS of the exposure at that position, or at ``pixel_scale`` arcsec per pixel (sky
  coordinates) when given.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli.errors import InputError
from megalut_cli.measure.metacal_defaults import INTERPOLANT
from megalut_cli.provenance import recorded_path, sha256_file

#: The model types, as :attr:`PsfModel.kind` names them.
PSFEX, PIFF = "psfex", "piff"
#: What to install for Piff models.
PIFF_HINT = "pip install 'megalut-cli[piff]'"
#: Header cards that record the model in a catalog measured with it.
CARD_FILE, CARD_SHA, CARD_TYPE = "PSFMODEL", "PSFMSHA", "PSFMTYPE"


@dataclass
class PsfModel:
    """A PSF model file: ``path``, ``kind`` (:data:`PSFEX` or :data:`PIFF`), the file's
    ``sha256``, and the area ``bounds`` ``(xmin, xmax, ymin, ymax)`` (1-based image pixels)
    of the stars it was fit to, where the file says (outside it, the model extrapolates)."""

    path: str
    kind: str
    sha256: str
    bounds: tuple[float, float, float, float] | None = None

    def draw(self, x: Any, y: Any, size: int, pixel_scale: float | None = None) -> np.ndarray:
        """The PSF at the 1-based image positions ``(x, y)`` (scalars or arrays of the same
        length ``n``) as ``(n, size, size)`` float64 stamps of unit sum, centred on each
        stamp's true centre; in the exposure's pixels, or at ``pixel_scale`` arcsec per
        pixel. A PSF without positive flux (far outside the model's area) is all NaN."""
        x, y = _positions(x, y)
        if not (isinstance(size, (int, np.integer)) and size >= 3):
            raise ValueError(f"size must be an integer of at least 3, got {size!r}")
        if pixel_scale is not None and not (np.isfinite(pixel_scale) and pixel_scale > 0):
            raise ValueError(f"pixel_scale must be a positive number, got {pixel_scale!r}")
        return _unit_sum(self._draw(x, y, int(size), pixel_scale))

    def _draw(
        self, x: np.ndarray, y: np.ndarray, size: int, pixel_scale: float | None
    ) -> np.ndarray:
        raise NotImplementedError

    def native_scale(self, x: float, y: float) -> float | None:
        """The exposure's pixel scale (arcsec, the root of the local pixel area) at ``(x, y)``,
        where the model knows it (Piff); None for a model in pixels only (PSFEx)."""
        return None

    def outside(self, x: Any, y: Any) -> np.ndarray:
        """Mask of the positions outside :attr:`bounds` (all False where unknown)."""
        x, y = _positions(x, y)
        if self.bounds is None:
            return np.zeros(len(x), dtype=bool)
        x0, x1, y0, y1 = self.bounds
        return (x < x0) | (x > x1) | (y < y0) | (y > y1)

    def provenance(self) -> dict[str, str]:
        """The model for provenance: file (as :func:`megalut_cli.provenance.recorded_path`
        names it), sha256 and type."""
        return {"file": recorded_path(self.path), "sha256": self.sha256, "type": self.kind}

    def header_cards(self) -> dict[str, tuple[str, str]]:
        """FITS cards recording the model (:data:`CARD_FILE`, :data:`CARD_SHA`,
        :data:`CARD_TYPE`)."""
        return {
            CARD_FILE: (os.path.basename(self.path)[:68], "PSF model file (measure --psf-model)"),
            CARD_SHA: (self.sha256, "sha256 of the PSF model file"),
            CARD_TYPE: (self.kind, "PSF model type"),
        }


def _positions(x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y, dtype=np.float64))
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(
            f"x and y must be scalars or 1-d arrays of one length, got shapes {x.shape}, {y.shape}"
        )
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("x and y must be finite")
    return x, y


def _unit_sum(stamps: np.ndarray) -> np.ndarray:
    """Each stamp divided by its sum, in place; NaN where the sum is not positive."""
    sums = stamps.sum(axis=(1, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        stamps /= np.where(sums > 0, sums, np.nan)[:, None, None]
    return stamps


def _kernel_matrix(kernel: Any, positions: np.ndarray, n_in: int) -> np.ndarray:
    """``(len(positions), n_in)``: the weight of input pixel ``j`` at each output position (in
    input pixels) under the GalSim interpolant ``kernel``."""
    offsets = positions[:, None] - np.arange(n_in)[None, :]
    return np.asarray(kernel.xval(offsets.ravel())).reshape(offsets.shape)


@dataclass
class PsfexModel(PsfModel):
    """A PSFEx model (:class:`galsim.des.DES_PSFEx`): a polynomial of ``fit_order`` in
    ``((x - x_zero) / x_scale, (y - y_zero) / y_scale)`` whose coefficients are the basis
    images, sampled every ``sample_scale`` image pixels."""

    basis: np.ndarray = field(default_factory=lambda: np.zeros((1, 1, 1)))
    fit_order: int = 0
    zero: tuple[float, float] = (0.0, 0.0)
    scale: tuple[float, float] = (1.0, 1.0)
    sample_scale: float = 1.0
    _resampled: dict[int, np.ndarray] = field(default_factory=dict, repr=False)

    def terms(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The polynomial's terms ``(n, k)`` at the positions, in the basis's order (GalSim's
        ``getPSFArray``: ``x^i y^j`` for ``j = 0..order``, ``i = 0..order - j``)."""
        u = (x - self.zero[0]) / self.scale[0]
        v = (y - self.zero[1]) / self.scale[1]
        order = self.fit_order
        return np.stack(
            [u**i * v**j for j in range(order + 1) for i in range(order + 1 - j)], axis=1
        )

    def resampled_basis(self, size: int) -> np.ndarray:
        """The basis images ``(k, size, size)`` drawn as ``DES_PSFEx.getPSF`` draws a PSF
        (``InterpolatedImage`` with a Lanczos(3) kernel, no pixel) centred on the stamp's true
        centre, in image pixels; for an even ``size``, drawn so on ``size - 1`` pixels and
        moved half a pixel to the even stamp's centre by GalSim's ``lanczos15`` (as
        ``measurer.same_parity_psfs`` redraws a PSF image; docs/catalogs.md, PSF models):
        Lanczos(3) read half a pixel off a basis sampled every image pixel narrows the PSF
        by about 1 %. Cached per size."""
        if size not in self._resampled:
            import galsim

            kernel = galsim.Lanczos(3)  # DES_PSFEx.getPSF's x_interpolant (with conserve_dc)
            odd = size - 1 + size % 2

            def weights(n_in: int) -> np.ndarray:
                # output pixel i at (i - (odd-1)/2) image pixels from the centre, i.e. at
                # that / sample_scale basis pixels from the basis's true centre (n_in-1)/2
                u = (np.arange(odd) - (odd - 1) / 2.0) / self.sample_scale + (n_in - 1) / 2.0
                w = _kernel_matrix(kernel, u, n_in)
                if odd == size:
                    return w
                # the even stamp's pixel i lies at i - 1/2 on the odd one's
                shift = galsim.Interpolant.from_name(INTERPOLANT)
                return _kernel_matrix(shift, np.arange(size) - 0.5, odd) @ w

            wy, wx = weights(self.basis.shape[1]), weights(self.basis.shape[2])
            self._resampled[size] = np.ascontiguousarray(
                np.einsum("ij,kjl,ml->kim", wy, self.basis, wx)
            )
        return self._resampled[size]

    def _draw(
        self, x: np.ndarray, y: np.ndarray, size: int, pixel_scale: float | None
    ) -> np.ndarray:
        if pixel_scale is not None:
            raise InputError(
                f"{self.path}: a PSFEx model is in its exposure's pixels and has no arcsecond "
                "scale: draw it in those pixels (without pixel_scale)"
            )
        drawn = self.resampled_basis(size)
        terms = self.terms(x, y)
        out = np.empty((len(x), size, size))
        # term by term, in blocks of positions that stay in the CPU cache: each stamp is the
        # same sum in the same order whatever the number of positions (bit-for-bit)
        block = max(1, (1 << 18) // (size * size))
        for a in range(0, len(x), block):
            b = min(a + block, len(x))
            part = out[a:b]
            np.multiply(terms[a:b, 0, None, None], drawn[0], out=part)
            for k in range(1, len(drawn)):
                part += terms[a:b, k, None, None] * drawn[k]
        return out


@dataclass
class PiffModel(PsfModel):
    """A single-chip Piff model (``piff.PSF``) and its chip number."""

    psf: Any = None
    chipnum: Any = None

    def native_scale(self, x: float, y: float) -> float | None:
        import galsim

        return float(
            np.sqrt(abs(self.psf.wcs[self.chipnum].local(galsim.PositionD(x, y)).pixelArea()))
        )

    def _draw(
        self, x: np.ndarray, y: np.ndarray, size: int, pixel_scale: float | None
    ) -> np.ndarray:
        import galsim

        wcs = self.psf.wcs[self.chipnum]
        out = np.empty((len(x), size, size))
        for i, (xi, yi) in enumerate(zip(x, y)):
            local = (
                galsim.PixelScale(pixel_scale)
                if pixel_scale is not None
                else wcs.local(galsim.PositionD(xi, yi))
            )
            image = galsim.ImageD(size, size, wcs=local)
            self.psf.draw(float(xi), float(yi), chipnum=self.chipnum, image=image, center=True)
            out[i] = image.array
        return out


def file_kind(path: str | os.PathLike) -> str | None:
    """:data:`PSFEX` for a FITS file with a ``PSF_DATA`` table (or ``POLNAXIS`` cards),
    :data:`PIFF` for one written by Piff (a ``PIFF_VERSION`` card, or a ``psf`` table with a
    ``type`` column), else None. Raises :class:`InputError` for a missing or non-FITS file."""
    import fitsio

    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file")
    try:
        with fitsio.FITS(str(path)) as f:
            primary = f[0].read_header()
            if "PIFF_VERSION" in primary:
                return PIFF
            for hdu in f:
                name = hdu.get_extname()
                header = hdu.read_header()
                if name.upper() == "PSF_DATA" or "POLNAXIS" in header:
                    return PSFEX
                if (
                    name == "psf"
                    and hdu.get_exttype() == "BINARY_TBL"
                    and "type" in hdu.get_colnames()
                ):
                    return PIFF
    except (OSError, ValueError, IndexError):
        raise InputError(
            f"{path}: not a PSF model (not a readable FITS file); expected a PSFEx .psf file "
            "or a Piff model"
        ) from None
    return None


def load_psf_model(path: str | os.PathLike) -> PsfModel:
    """The PSF model of the file ``path``: a PSFEx ``.psf`` file or a Piff model (which
    needs the optional ``piff`` package). Anything else, or a model megalut cannot
    evaluate, raises :class:`InputError` (one line naming the file)."""
    path = str(path)
    kind = file_kind(path)
    if kind is None:
        raise InputError(
            f"{path}: not a PSF model: neither a PSFEx .psf file (a PSF_DATA table) "
            "nor a Piff model (a psf table)"
        )
    sha = sha256_file(path)
    return _load_psfex(path, sha) if kind == PSFEX else _load_piff(path, sha)


def _load_psfex(path: str, sha: str) -> PsfexModel:
    import galsim.des

    try:
        psfex = galsim.des.DES_PSFEx(path)
    except KeyError as err:
        raise InputError(
            f"{path}: a PSFEx file GalSim cannot read (a card is missing: {err.args[0]})"
        ) from None
    except (OSError, ValueError, IndexError) as err:
        text = str(err).strip()
        why = (
            "its POL*/PSF* cards do not describe its basis"
            if "not as expected" in text
            else text.splitlines()[0]
            if text
            else type(err).__name__
        )
        raise InputError(f"{path}: a PSFEx file GalSim cannot read ({why})") from None
    basis = np.asarray(psfex.basis, dtype=np.float64)
    if not np.isfinite(basis).all():
        raise InputError(f"{path}: the PSFEx basis holds NaN or infinite values")
    zero, scale = (
        (float(psfex.x_zero), float(psfex.y_zero)),
        (float(psfex.x_scale), float(psfex.y_scale)),
    )
    bounds = (
        zero[0] - scale[0] / 2,
        zero[0] + scale[0] / 2,
        zero[1] - scale[1] / 2,
        zero[1] + scale[1] / 2,
    )
    return PsfexModel(
        path,
        PSFEX,
        sha,
        bounds,
        basis=basis,
        fit_order=int(psfex.fit_order),
        zero=zero,
        scale=scale,
        sample_scale=float(psfex.sample_scale),
    )


def _load_piff(path: str, sha: str) -> PiffModel:
    try:
        import piff
    except ImportError:
        raise InputError(f"{path} is a Piff model: {PIFF_HINT}") from None
    try:
        psf = piff.read(path)
    except Exception as err:  # Piff raises many kinds on a damaged file
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f"{path}: a Piff model Piff cannot read ({first})") from None
    chips = list(psf.wcs or {})
    if len(chips) != 1:
        raise InputError(
            f"{path}: a Piff model of {len(chips)} chips; megalut measures one exposure chip: "
            "fit (or split) a single-chip model"
        )
    extra = [p for p in getattr(psf, "interp_property_names", ()) if p not in ("x", "y", "u", "v")]
    if extra:
        raise InputError(
            f"{path}: the Piff model interpolates in {', '.join(extra)} besides the position, "
            "which megalut cannot give"
        )
    stars = getattr(psf, "stars", None) or []
    bounds = None
    if stars:
        xs = np.array([s.image_pos.x for s in stars])
        ys = np.array([s.image_pos.y for s in stars])
        bounds = (float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max()))
    return PiffModel(path, PIFF, sha, bounds, psf=psf, chipnum=chips[0])


@functools.lru_cache(maxsize=4)
def _cached(path: str, mtime_ns: int, size: int) -> PsfModel:
    return load_psf_model(path)


def cached_psf_model(path: str | os.PathLike) -> PsfModel:
    """:func:`load_psf_model`, loaded once per process (and file version): what a work unit
    calls in a worker, given the model's path (no GalSim or Piff object crosses processes)."""
    path = os.path.abspath(path)
    try:
        st = os.stat(path)
    except OSError:
        raise InputError(f"{path}: no such file") from None
    return _cached(path, st.st_mtime_ns, st.st_size)
