"""PSFs of the simulations, in pixel units (the simulator draws with ``scale=1``).

A PSF is described by a spec: a TOML table of scalars with a ``type`` and its
parameters (see the "PSF" section of ``docs/config.md``):

``gaussian``
    ``sigma`` or ``fwhm`` (pixels), optional ``g1, g2`` (reduced shear, |g| < 1).
``moffat``
    ``beta`` and one of ``fwhm``/``half_light_radius`` (pixels), optional ``trunc``
    (pixels, 0 = none) and ``g1, g2``.
``field``
    The variable PSF of the paper's Sect. 6, at field position ``x, y`` in [0, 1]: an
    elliptical Gaussian with ``e1 = e1_min + (e1_max - e1_min) x`` (default -0.25 to
    0.25), ``e2 = e2_min + (e2_max - e2_min) y`` (default 0 to 0.25) and ``sigma =
    sigma_mean + sigma_slope (x + y - 1)`` (default 2 + 0.25 (x + y - 1)); (e1, e2) is
    applied as GalSim's reduced shear g, which preserves the area, so ``sigma`` stays the
    azimuthally averaged standard deviation.
``euclid``
    The Euclid-VIS-like PSF of Sect. 7.1.2: GalSim OpticalPSFs (``diam`` 1.2 m,
    ``obscuration`` 0.29, ``nstruts`` 6) at ``lam_min`` to ``lam_max`` (550-900 nm) in
    ``lam_step`` (50 nm) steps, drawn ``oversampling`` (5) times finer than the
    ``pixel_scale`` (0.1 arcsec) on ``size`` (64) pixels, stacked with photon-count
    weights of a stellar spectrum, and interpolated. The paper's Pickles G5V template is
    not available here: a blackbody of ``temperature`` (5800 K) in photon counts
    (``B_lambda * lambda / hc``) stands in for it; over 550-900 nm the two differ by
    a smooth tilt of a few per cent, a negligible change of the stacked PSF.
``stamp``
    A PSF read from a FITS image of a star (``path``, optional ``hdu``): a GalSim
    InterpolatedImage with flux 1. With ``stamp_size``, the image is a grid of star
    stamps (e.g. a GREAT3 ``starfield_image``, 3x3) and ``index`` (default 0) picks one,
    in grid order from the lower-left; ``index = "random"`` (or any distribution, e.g.
    ``{type = "grid", values = [0, 4, 8]}``) picks one per case (per realization with
    ``"psf"`` in ``structure.per_realization``), as the paper does for GREAT3 (Sect. 8.2).
    ``pixel_scale`` is the star image's pixel in simulation pixels (default 1).
    ``interpolant`` is GalSim's x interpolant (default quintic).

Truth values ``tru_psf_g1, tru_psf_g2, tru_psf_sigma`` (sigma in pixels) are analytic
for the Gaussian types; otherwise ``g1, g2`` are analytic (shear applied to a round
profile) and ``sigma`` is HSM's adaptive-moment sigma on a well-sampled image of the
profile without pixel response; the ``euclid`` and ``stamp`` truths are HSM measurements
on the 5x oversampled image and on the star image.

Star images already contain the pixel response: see :func:`psf_includes_pixel`.

GalSim is imported by the functions that build or measure profiles, not with this module:
reading a config, and the fast engine with a PSF in the disk cache
(:mod:`megalut_cli.sim.psf_store`), do not load it.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from megalut_cli.errors import ConfigError, InputError
from megalut_cli.measure.stamps import check_grid, image_info, read_rows
from megalut_cli.schema import OneOf, Option, Required, check_params

if TYPE_CHECKING:
    import galsim

#: Truth columns returned by :func:`make_psf`.
TRUTH_COLUMNS = ("tru_psf_g1", "tru_psf_g2", "tru_psf_sigma")

#: GalSim x interpolants of ``stamp`` PSFs.
INTERPOLANTS = ("quintic", "cubic", "linear", "lanczos3", "lanczos5", "lanczos7", "lanczos15")


@dataclass(frozen=True)
class PsfType:
    """One kind of PSF: its keys and defaults, its checks and how to build it.

    ``options`` declare its keys (kind, default, range, help: their values are checked by
    :func:`~megalut_cli.schema.check_params`, the docs table comes from them), ``required``
    the keys that must be given, ``one_of`` groups of keys of which exactly one must be
    given. ``check(spec, full, where)`` checks what the declarations cannot (keys together)
    on the spec with defaults filled in; ``build(spec, x, y)`` returns the profile and its
    truth at field position ``(x, y)``. ``help`` says what the model is.
    """

    name: str
    options: tuple[Option, ...]
    check: Callable[[Mapping[str, Any], Mapping[str, Any], str], None]
    build: Callable[[Mapping[str, Any], float, float], tuple[galsim.GSObject, dict[str, float]]]
    required: tuple[str, ...] = ()
    one_of: tuple[tuple[str, ...], ...] = ()
    #: Whether the PSF depends on the field position.
    varies: bool = False
    help: str = ""

    @property
    def keys(self) -> dict[str, Any]:
        """Its keys and their defaults (``None``: no default)."""
        return {o.name: o.default for o in self.options}

    def rules(self) -> tuple[Required | OneOf, ...]:
        """Its required keys, then its exactly-one groups, as :func:`check_params` takes them."""
        need = tuple(Required(k, f"required by PSF type {self.name!r}") for k in self.required)
        return need + tuple(
            OneOf(
                group,
                f"PSF type {self.name!r} needs exactly one of {' or '.join(group)}, got {{got}}",
            )
            for group in self.one_of
        )


#: Every PSF type by name, in the order of registration (``psf.type`` values).
PSF_REGISTRY: dict[str, PsfType] = {}


def register_psf_type(psf_type: PsfType) -> None:
    """Make ``psf_type`` available as ``psf.type = "<name>"`` (the one place a PSF type is
    added)."""
    if psf_type.name in PSF_REGISTRY:
        raise ValueError(f"PSF type {psf_type.name!r} is already registered")
    PSF_REGISTRY[psf_type.name] = psf_type


def _key(where: str, k: str) -> str:
    return f"{where}.{k}" if where else k


def _check_shear(g1: float, g2: float, where: str, what: str = "g1, g2") -> None:
    if math.hypot(g1, g2) >= 1.0:
        raise ConfigError(f"{where}: the PSF ellipticity |({what})| must be < 1, got ({g1}, {g2})")


def _full(spec: Mapping[str, Any]) -> dict[str, Any]:
    """The spec with defaults filled in (assumes a validated spec)."""
    t = spec["type"]
    out = PSF_REGISTRY[t].keys
    out.update({k: v for k, v in spec.items() if k != "type"})
    out["type"] = t
    return out


def validate_psf_config(spec: Mapping[str, Any], where: str = "psf") -> None:
    """Check a PSF spec; raise :class:`ConfigError` naming the bad key.

    ``where`` prefixes key names in messages (``psf.sigma``). For ``stamp``, a missing
    file is an :class:`InputError`.
    """
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: expected a table")
    t = spec.get("type")
    if t is None:
        raise ConfigError(f"{_key(where, 'type')}: missing")
    if t not in PSF_REGISTRY:
        raise ConfigError(
            f"{_key(where, 'type')}: unknown PSF type {t!r} (choose from {', '.join(PSF_REGISTRY)})"
        )
    kind = PSF_REGISTRY[t]
    allowed = ", ".join(sorted(kind.keys))
    check_params(
        {k: v for k, v in spec.items() if k != "type"},
        where,
        kind.options,
        kind.rules(),
        lambda key: f"unknown key for PSF type {t!r} (allowed: {allowed})",
    )
    kind.check(spec, _full(spec), where)


def _check_gaussian(spec: Mapping[str, Any], s: Mapping[str, Any], where: str) -> None:
    """``gaussian``: |g| < 1."""
    _check_shear(float(s["g1"]), float(s["g2"]), where)


def _check_moffat(spec: Mapping[str, Any], s: Mapping[str, Any], where: str) -> None:
    """``moffat``: |g| < 1, ``trunc`` >= 0, ``beta`` > 1.1 without it."""
    _check_shear(float(s["g1"]), float(s["g2"]), where)
    beta, trunc = float(s["beta"]), float(s["trunc"])
    if trunc < 0:
        raise ConfigError(f"{_key(where, 'trunc')}: must be >= 0, got {trunc}")
    if beta <= 1.1 and trunc == 0:
        raise ConfigError(f"{_key(where, 'beta')}: must be > 1.1 without trunc, got {beta}")


def _check_field(spec: Mapping[str, Any], s: Mapping[str, Any], where: str) -> None:
    """``field``: a valid PSF at the four corners of the field."""
    for x in (0.0, 1.0):
        for y in (0.0, 1.0):
            e1, e2, sigma = field_psf_params(s, x, y)
            _check_shear(e1, e2, where, "e1, e2")
            if sigma <= 0:
                raise ConfigError(
                    f"{_key(where, 'sigma_mean')}: the field PSF sigma must stay > 0 over "
                    f"the field, got {sigma} at x={x}, y={y}"
                )


def _check_euclid(spec: Mapping[str, Any], s: Mapping[str, Any], where: str) -> None:
    """``euclid``: an obscuration in [0, 1), ``lam_max`` >= ``lam_min``."""
    obsc = float(s["obscuration"])
    if not 0 <= obsc < 1:
        raise ConfigError(f"{_key(where, 'obscuration')}: must be in [0, 1), got {obsc}")
    if s["lam_max"] < s["lam_min"]:
        raise ConfigError(f"{_key(where, 'lam_max')}: must be >= lam_min")


def _check_stamp(spec: Mapping[str, Any], s: Mapping[str, Any], where: str) -> None:
    """``stamp``: an existing image, a star ``index`` within its grid."""
    path = s["path"]
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise ConfigError(f"{_key(where, 'path')}: expected a file path, got {path!r}")
    if not os.path.isfile(path):
        raise InputError(f"{_key(where, 'path')}: {path}: no such file")
    index = int(s["index"])
    n_stars = star_grid_size(path, s["hdu"], s["stamp_size"], where)
    if index >= n_stars:
        raise ConfigError(
            f"{_key(where, 'index')}: {index} is beyond the {n_stars} star(s) of {path} "
            "(0-based, in grid order from the lower-left)"
        )


@functools.lru_cache(maxsize=64)
def _star_grid(path: str, hdu: int | None, stamp_size: int | None) -> tuple[int, int]:
    info = image_info(path, hdu)
    if stamp_size is None:
        return 1, 1
    return check_grid(info, stamp_size)


def star_grid_size(
    path: str | os.PathLike, hdu: Any = None, stamp_size: Any = None, where: str = "psf"
) -> int:
    """Number of stars in a ``stamp`` PSF image: 1 without ``stamp_size``, else the grid's."""
    try:
        n_y, n_x = _star_grid(
            str(path),
            None if hdu is None else int(hdu),
            None if stamp_size is None else int(stamp_size),
        )
    except InputError as err:
        raise InputError(f"{_key(where, 'path')}: {err}") from None
    return n_y * n_x


def psf_varies(spec: Mapping[str, Any]) -> bool:
    """Whether the PSF depends on the field position (``field`` type)."""
    kind = PSF_REGISTRY.get(str(spec.get("type")))
    return kind is not None and kind.varies


def psf_includes_pixel(spec: Mapping[str, Any]) -> bool:
    """Whether the PSF profile already contains the pixel response.

    True for ``stamp`` PSFs sampled like the simulation (``pixel_scale`` 1, a star image
    is an effective PSF), unless ``includes_pixel`` says otherwise: such PSFs must be drawn
    with ``method="no_pixel"``. False for every other type (draw with ``method="auto"``).
    """
    if spec.get("type") != "stamp":
        return False
    flag = spec.get("includes_pixel")
    if flag is not None:
        return bool(flag)
    return float(spec.get("pixel_scale", 1.0)) == 1.0


def field_psf_params(
    spec: Mapping[str, Any], field_x: float, field_y: float
) -> tuple[float, float, float]:
    """``(e1, e2, sigma)`` of the Sect. 6 toy PSF at field position ``(x, y)``."""
    s = {**PSF_REGISTRY["field"].keys, **{k: v for k, v in spec.items() if k != "type"}}
    e1 = s["e1_min"] + (s["e1_max"] - s["e1_min"]) * field_x
    e2 = s["e2_min"] + (s["e2_max"] - s["e2_min"]) * field_y
    sigma = s["sigma_mean"] + s["sigma_slope"] * (field_x + field_y - 1.0)
    return float(e1), float(e2), float(sigma)


def _hashable(spec: Mapping[str, Any]) -> tuple[tuple[str, Any], ...]:
    return tuple(sorted((k, str(v) if isinstance(v, os.PathLike) else v) for k, v in spec.items()))


def _hsm_truth(image: galsim.Image, scale: float) -> tuple[float, float, float]:
    """``(g1, g2, sigma)`` from HSM on ``image``, sigma converted by ``scale`` to pixels."""
    import galsim

    res = galsim.hsm.FindAdaptiveMom(image, strict=False)
    if res.moments_status != 0:
        raise ConfigError(f"psf: HSM could not measure the PSF ({res.error_message.strip()})")
    return (
        float(res.observed_shape.g1),
        float(res.observed_shape.g2),
        float(res.moments_sigma * scale),
    )


@functools.lru_cache(maxsize=64)
def _moffat_sigma(beta: float, fwhm: float | None, hlr: float | None, trunc: float) -> float:
    """Adaptive-moment sigma (pixels) of a round Moffat, on a 10x oversampled image."""
    import galsim

    prof = galsim.Moffat(beta=beta, fwhm=fwhm, half_light_radius=hlr, trunc=trunc)
    scale = prof.calculateFWHM() / 10.0
    img = prof.drawImage(nx=256, ny=256, scale=scale, method="no_pixel")
    return _hsm_truth(img, scale)[2]


def _gaussian(spec: Mapping[str, Any]) -> tuple[galsim.GSObject, dict[str, float]]:
    import galsim

    s = _full(spec)
    prof = galsim.Gaussian(sigma=s["sigma"], fwhm=s["fwhm"])
    sigma = float(prof.sigma)
    g1, g2 = float(s["g1"]), float(s["g2"])
    if g1 or g2:
        prof = prof.shear(g1=g1, g2=g2)
    return prof, {"tru_psf_g1": g1, "tru_psf_g2": g2, "tru_psf_sigma": sigma}


def _moffat(spec: Mapping[str, Any]) -> tuple[galsim.GSObject, dict[str, float]]:
    import galsim

    s = _full(spec)
    beta, trunc = float(s["beta"]), float(s["trunc"])
    fwhm = None if s["fwhm"] is None else float(s["fwhm"])
    hlr = None if s["half_light_radius"] is None else float(s["half_light_radius"])
    prof = galsim.Moffat(beta=beta, fwhm=fwhm, half_light_radius=hlr, trunc=trunc)
    g1, g2 = float(s["g1"]), float(s["g2"])
    if g1 or g2:
        prof = prof.shear(g1=g1, g2=g2)
    sigma = _moffat_sigma(beta, fwhm, hlr, trunc)
    return prof, {"tru_psf_g1": g1, "tru_psf_g2": g2, "tru_psf_sigma": sigma}


def _field(spec: Mapping[str, Any], x: float, y: float) -> tuple[galsim.GSObject, dict[str, float]]:
    import galsim

    e1, e2, sigma = field_psf_params(spec, x, y)
    if sigma <= 0 or math.hypot(e1, e2) >= 1:
        raise ConfigError(
            f"psf: the field PSF is undefined at x={x}, y={y} (sigma={sigma}, e1={e1}, e2={e2})"
        )
    prof = galsim.Gaussian(sigma=sigma).shear(g1=e1, g2=e2)
    return prof, {"tru_psf_g1": e1, "tru_psf_g2": e2, "tru_psf_sigma": sigma}


def blackbody_photons(lam_nm: np.ndarray, temperature: float) -> np.ndarray:
    """Photon counts per unit wavelength of a blackbody (arbitrary normalisation)."""
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = np.asarray(lam_nm, dtype=np.float64) * 1e-9
    # B_lambda ~ lam^-5 / (exp(hc / lam k T) - 1); photons: times lam / (h c).
    return lam**-4 / np.expm1(h * c / (lam * k * temperature))


@functools.lru_cache(maxsize=8)
def _euclid_cached(
    key: tuple[tuple[str, Any], ...],
) -> tuple[galsim.GSObject, tuple[float, float, float]]:
    import galsim

    s = dict(key)
    over = int(s["oversampling"])
    fine = float(s["pixel_scale"]) / over  # arcsec per fine pixel
    n = int(s["size"]) * over
    lams = np.arange(float(s["lam_min"]), float(s["lam_max"]) + 1e-9, float(s["lam_step"]))
    weights = blackbody_photons(lams, float(s["temperature"]))
    weights /= weights.sum()
    stack = np.zeros((n, n))
    mono = galsim.ImageD(n, n, scale=fine)
    for lam, w in zip(lams, weights):
        psf = galsim.OpticalPSF(
            lam=float(lam),
            diam=float(s["diam"]),
            obscuration=float(s["obscuration"]),
            nstruts=int(s["nstruts"]),
            scale_unit=galsim.arcsec,
        )
        psf.drawImage(image=mono)  # sampled on the fine grid (fine-pixel response included)
        stack += w * mono.array
    stack /= stack.sum()
    image = galsim.ImageD(stack, scale=1.0 / over)  # in simulation pixels
    prof = galsim.InterpolatedImage(image, flux=1.0)
    g1, g2, sigma = _hsm_truth(galsim.ImageD(stack), 1.0 / over)
    return prof, (g1, g2, sigma)


def _euclid(spec: Mapping[str, Any]) -> tuple[galsim.GSObject, dict[str, float]]:
    prof, (g1, g2, sigma) = _euclid_cached(_hashable(_full(spec)))
    return prof, {"tru_psf_g1": g1, "tru_psf_g2": g2, "tru_psf_sigma": sigma}


@functools.lru_cache(maxsize=32)
def _stamp_cached(
    key: tuple[tuple[str, Any], ...],
) -> tuple[galsim.GSObject, tuple[float, float, float]]:
    import galsim

    s = dict(key)
    path = str(s["path"])
    info = image_info(path, None if s["hdu"] is None else int(s["hdu"]))
    ny, nx = info.shape
    if s["stamp_size"] is None:
        if int(s["index"]) != 0:
            raise ConfigError("psf.index: needs psf.stamp_size (the image is one star)")
        star = read_rows(info, 0, ny)
    else:
        size = int(s["stamp_size"])
        n_y, n_x = check_grid(info, size)
        k = int(s["index"])
        if k >= n_x * n_y:
            raise ConfigError(f"psf.index: {k} is beyond the {n_x}x{n_y} grid of stars in {path}")
        row, col = divmod(k, n_x)
        star = read_rows(info, row * size, (row + 1) * size)[:, col * size : (col + 1) * size]
    if not np.isfinite(star).all():
        raise InputError(f"{path}: the PSF star stamp has NaN or infinite pixels")
    if not star.sum() > 0:
        raise InputError(f"{path}: the PSF star stamp has no positive flux")
    scale = float(s["pixel_scale"])
    image = galsim.ImageD(np.ascontiguousarray(star), scale=scale)
    prof = galsim.InterpolatedImage(image, x_interpolant=str(s["interpolant"]), flux=1.0)
    g1, g2, sigma = _hsm_truth(galsim.ImageD(np.ascontiguousarray(star)), scale)
    return prof, (g1, g2, sigma)


def _stamp(spec: Mapping[str, Any]) -> tuple[galsim.GSObject, dict[str, float]]:
    prof, (g1, g2, sigma) = _stamp_cached(_hashable(_full(spec)))
    return prof, {"tru_psf_g1": g1, "tru_psf_g2": g2, "tru_psf_sigma": sigma}


def measured_psf_sigma(spec: Mapping[str, Any], stamp_size: int) -> float | None:
    """The adaptive-moment sigma (pixels) that ``megalut measure --psf`` finds on this PSF drawn
    with the pixel response on a ``stamp_size`` stamp; None for a PSF that varies (over the field,
    or with parameters drawn from distributions) or that cannot be built here (a star file
    that is not at hand)."""
    shape = measured_psf_shape(spec, stamp_size)
    return None if shape is None else shape[0]


def measured_psf_shape(
    spec: Mapping[str, Any], stamp_size: int
) -> tuple[float, float, float] | None:
    """``(sigma, g1, g2)``: the adaptive moments ``megalut measure --psf`` finds on this PSF
    (``psf_adamom_sigma, psf_adamom_g1, psf_adamom_g2``), as :func:`measured_psf_sigma`."""
    import galsim

    if psf_varies(spec) or any(isinstance(v, Mapping) for v in spec.values()):
        return None
    try:
        prof, _ = make_psf(spec, 0.5, 0.5)
    except (ConfigError, OSError, ValueError):
        return None
    method = "no_pixel" if psf_includes_pixel(spec) else "auto"
    image = prof.drawImage(nx=int(stamp_size), ny=int(stamp_size), scale=1.0, method=method)
    res = galsim.hsm.FindAdaptiveMom(image, strict=False)
    if res.moments_status != 0:
        return None
    shape = res.observed_shape
    return float(res.moments_sigma), float(shape.g1), float(shape.g2)


def make_psf(
    spec: Mapping[str, Any], field_x: float, field_y: float
) -> tuple[galsim.GSObject, dict[str, float]]:
    """The PSF profile (pixel units, flux 1) at field position ``(x, y)`` and its truth.

    Returns ``(profile, {"tru_psf_g1": ..., "tru_psf_g2": ..., "tru_psf_sigma": ...})``.
    Costly PSFs (``euclid``, ``stamp``) are built once per process and cached.
    """
    validate_psf_config(spec)
    return PSF_REGISTRY[spec["type"]].build(spec, float(field_x), float(field_y))


#: |g| < 1, as docs tables write it.
_SHEAR_RANGE = "\\|(g1, g2)\\| < 1"
_G1 = Option(
    "g1", "float", 0.0, "reduced shear g1 applied to the round profile", allowed_text=_SHEAR_RANGE
)
_G2 = Option(
    "g2", "float", 0.0, "reduced shear g2 applied to the round profile", allowed_text=_SHEAR_RANGE
)


def _size(name: str, what: str, other: str) -> Option:
    """A size of which the PSF type takes exactly one of two (``name`` or ``other``)."""
    return Option(
        name, "float", None, what, minimum=0.0, min_open=True, default_text=f"or `{other}`"
    )


def _positive(name: str, default: float, what: str, allowed: str | None = None) -> Option:
    return Option(name, "float", default, what, minimum=0.0, min_open=True, allowed_text=allowed)


register_psf_type(
    PsfType(
        "gaussian",
        (
            _size("sigma", "standard deviation, pixels", "fwhm"),
            _size("fwhm", "full width at half maximum, pixels", "sigma"),
            _G1,
            _G2,
        ),
        _check_gaussian,
        lambda spec, x, y: _gaussian(spec),
        one_of=(("sigma", "fwhm"),),
        help="Gaussian, sheared by (g1, g2)",
    )
)
register_psf_type(
    PsfType(
        "moffat",
        (
            Option(
                "beta",
                "float",
                None,
                "Moffat index β (> 1.1 without `trunc`)",
                minimum=0.0,
                min_open=True,
                default_text="required",
            ),
            _size("fwhm", "full width at half maximum, pixels", "half_light_radius"),
            _size("half_light_radius", "half-light radius, pixels", "fwhm"),
            Option(
                "trunc",
                "float",
                0.0,
                "truncation radius, pixels (0 = none; needed if β ≤ 1.1)",
                allowed_text=">= 0",
            ),
            _G1,
            _G2,
        ),
        _check_moffat,
        lambda spec, x, y: _moffat(spec),
        required=("beta",),
        one_of=(("fwhm", "half_light_radius"),),
        help="Moffat, sheared by (g1, g2)",
    )
)
register_psf_type(
    PsfType(
        "field",
        (
            Option("e1_min", "float", -0.25, "e1 at x = 0: e1 = e1_min + (e1_max − e1_min) x"),
            Option("e1_max", "float", 0.25, "e1 at x = 1"),
            Option("e2_min", "float", 0.0, "e2 at y = 0: e2 = e2_min + (e2_max − e2_min) y"),
            Option("e2_max", "float", 0.25, "e2 at y = 1"),
            Option(
                "sigma_mean",
                "float",
                2.0,
                "sigma at x + y = 1: sigma = sigma_mean + sigma_slope (x + y − 1), pixels",
                allowed_text="sigma > 0 over the field",
            ),
            Option("sigma_slope", "float", 0.25, "change of sigma with x + y, pixels"),
        ),
        _check_field,
        _field,
        varies=True,
        help="the variable PSF of the paper's Sect. 6, at the case's field position (x, y) in "
        "[0, 1] (below)",
    )
)
register_psf_type(
    PsfType(
        "euclid",
        (
            _positive("diam", 1.2, "telescope diameter, m"),
            Option("obscuration", "float", 0.29, "linear obscuration", allowed_text="[0, 1)"),
            Option("nstruts", "int", 6, "number of struts", minimum=0),
            _positive("lam_min", 550.0, "shortest wavelength, nm"),
            _positive("lam_max", 900.0, "longest wavelength, nm", allowed="> 0, >= lam_min"),
            _positive("lam_step", 50.0, "wavelength step, nm"),
            _positive("pixel_scale", 0.1, "the VIS pixel, arcsec"),
            Option(
                "oversampling",
                "int",
                5,
                "the PSF is drawn this many times finer than the pixel",
                minimum=1,
            ),
            Option("size", "int", 64, "size of the drawn PSF, pixels", minimum=8),
            _positive(
                "temperature",
                5800.0,
                "temperature of the blackbody spectrum that weights the wavelengths, K",
            ),
        ),
        _check_euclid,
        lambda spec, x, y: _euclid(spec),
        help="the Euclid-VIS-like polychromatic PSF of Sect. 7.1.2 (below)",
    )
)
register_psf_type(
    PsfType(
        "stamp",
        (
            Option(
                "path",
                "path",
                None,
                "FITS image of a star (relative: beside the config file)",
                default_text="required",
            ),
            Option(
                "hdu", "int", None, "HDU of the image", minimum=0, default_text="the first image"
            ),
            Option(
                "stamp_size",
                "int",
                None,
                "the stamp size of a grid of stars",
                minimum=3,
                default_text="none: one star",
            ),
            Option(
                "index",
                "int",
                0,
                "the star, in grid order from the lower-left (0-based); a *dist* "
                'or `"random"`: one star per case',
                minimum=0,
            ),
            _positive("pixel_scale", 1.0, "the star image's pixel in simulation pixels"),
            Option(
                "interpolant", "choice", "quintic", "GalSim's x interpolant", choices=INTERPOLANTS
            ),
            Option(
                "includes_pixel",
                "bool",
                None,
                'whether the image holds the pixel response (drawn with `method = "no_pixel"`)',
                default_text="true if `pixel_scale` = 1",
            ),
        ),
        _check_stamp,
        lambda spec, x, y: _stamp(spec),
        required=("path",),
        help="a star image from a FITS file (below)",
    )
)
#: The PSF types, in the order of registration.
PSF_TYPES = tuple(PSF_REGISTRY)
