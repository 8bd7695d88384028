"""``profile = "real"``: HST galaxies of a GalSim ``RealGalaxyCatalog`` (``galsim.RealGalaxy``),
deconvolved from their HST PSF, scaled to the requested flux, dilated to simulation pixels,
rotated and lensed; their own HST noise is symmetrized or whitened by the drawing
(:mod:`megalut_cli.sim.draw`), and each may be replaced by its Sérsic twin
(:mod:`megalut_cli.sim.twins`). Size and shape come from the images: ``tru_rad`` and the
ellipticity are NaN."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError
from megalut_cli.expr import check_expression, columns_used, evaluate_rows
from megalut_cli.schema import OneOf, Option, Required, resolve_beside
from megalut_cli.sim.distributions import Distribution, Grid, parse_distribution
from megalut_cli.sim.profiles.base import GalaxyProfile, GalaxySpec, ProfileTruth
from megalut_cli.sim.profiles.common import (
    ANGLE,
    FLUX,
    FLUX_KEYS,
    MAG,
    SB,
    flux_mode,
    position_angle,
    with_help,
)

log = logging.getLogger(__name__)

#: What to do with the HST noise of real galaxies (see docs/config.md).
HST_NOISE_MODES = ("symmetrize", "whiten", "keep")
#: What to draw in place of each real galaxy: itself, or its Sérsic twin (docs/realgal.md).
TWIN_MODES = ("none", "sersic")
#: How real galaxies are assigned to SNC groups: drawn at random, or each in turn.
REAL_ORDERS = ("random", "each")

OPTIONS = (
    Option(
        "real_catalog",
        "path",
        None,
        "the GalSim RealGalaxyCatalog FITS file (e.g. "
        "`examples/data/cosmos/real_galaxy_catalog_26_extension_example.fits`)",
        default_text="required",
    ),
    Option(
        "real_dir",
        "path",
        None,
        "the folder of its image files",
        default_text="the catalog's folder",
    ),
    Option(
        "pixel_scale",
        "float",
        None,
        "arcsec per simulation pixel (the HST images are dilated to it)",
        default_text="required",
        allowed_text="> 0",
    ),
    Option(
        "index",
        "dist",
        "random",
        'the catalog rows drawn (0-based), or `"random"`: any row',
        allowed_text='*dist* of integers, or "random"',
    ),
    Option(
        "real_select",
        "expr",
        None,
        "instead of `index`: the rows where this expression over the catalog's "
        'columns holds (e.g. `"MAG < 24"`)',
        default_text="none",
    ),
    Option(
        "real_order",
        "choice",
        "random",
        '`"random"`: each SNC group draws a galaxy from `index`/`real_select`; `"each"`: SNC '
        "group g of every case shows galaxy g (mod N) of that list (with `per_realization = "
        '["galaxy"]`; else case c shows galaxy c), so that with `n_realizations` = 2N and `snc = '
        '"pairs"` every galaxy is seen under every shear in a 90° pair',
        choices=REAL_ORDERS,
    ),
    Option(
        "hst_noise",
        "choice",
        "symmetrize",
        "what becomes of the images' own HST noise: symmetrized (order 4) or whitened, then "
        "topped up with Gaussian noise to the requested sigma; or kept as it is (below)",
        choices=HST_NOISE_MODES,
    ),
    Option(
        "twin",
        "choice",
        "none",
        '`"sersic"`: draw each galaxy\'s Sérsic twin (its PSF-convolved Sérsic fit, from '
        "`twin_catalog`) in its place, with every draw of the real set unchanged: same shear, "
        "rotation, offset, flux and noise seeds (`docs/realgal.md`)",
        choices=TWIN_MODES,
    ),
    Option(
        "twin_catalog",
        "path",
        None,
        "FITS table of Sérsic twins (`megalut.sersic-twins`, e.g. "
        "`examples/data/cosmos/real_galaxy_catalog_26_extension_sersic_twins.fits`); required by "
        '`twin = "sersic"`; when given, both sets get the truth columns `tru_twin_rad` (fitted '
        "half-light radius, pixels), `tru_twin_sersicn`, `tru_twin_g1`, `tru_twin_g2`, "
        "`tru_twin` (1 for twins)",
        default_text="—",
    ),
    FLUX,
    with_help(
        SB,
        "surface brightness S: F = S·π·R² with R the galaxy's fitted half-light radius "
        "(`tru_twin_rad`), so that real galaxies follow the size–flux coupling of a Sérsic "
        "training population; needs `twin_catalog`",
    ),
    MAG,
    ANGLE,
)
#: Why it refuses these keys of other profiles.
FROM_THE_IMAGES = "size, shape and profile come from the HST images"


def real_rows(select: Any, cat: Path) -> list[int]:
    """Rows of the RealGalaxyCatalog ``cat`` where the expression ``select`` holds."""
    from megalut_cli.catalog import catalog_info, read_catalog  # fitsio: not needed for --help

    if not isinstance(select, str) or not select.strip():
        raise ConfigError('galaxy.real_select: expected an expression string, e.g. "MAG < 24"')
    _, names, _ = catalog_info(cat)
    try:
        check_expression(select, names)
    except ConfigError as err:
        raise ConfigError(f"galaxy.real_select: {err}") from None
    used = columns_used(select)
    table = read_catalog(cat, columns=used)
    mask = np.asarray(
        evaluate_rows(select, {c: np.asarray(table[c]) for c in used}, len(table)), dtype=bool
    )
    if not mask.any():
        raise ConfigError(f"galaxy.real_select: no galaxy of {cat.name} passes {select!r}")
    log.info("galaxy.real_select: %d of %d galaxies of %s", int(mask.sum()), len(mask), cat.name)
    return [int(i) for i in np.flatnonzero(mask)]


def parse_twin(
    given: Mapping[str, Any], twin: str, config_path: str, index: Distribution
) -> dict[str, Any]:
    """``galaxy.twin`` and ``galaxy.twin_catalog``: draw each real galaxy's Sérsic twin."""
    if "twin_catalog" not in given:
        if twin != "none":
            raise ConfigError(
                "galaxy.twin_catalog: missing (required by galaxy.twin = 'sersic': the Sérsic-twin "
                "FITS table)"
            )
        return {"twin": twin}
    path = str(resolve_beside(given["twin_catalog"], "galaxy.twin_catalog", config_path))
    if twin != "none":
        from megalut_cli.sim.twins import load_twins  # GalSim: not needed for --help

        twins = load_twins(path)
        lo, hi = index.bounds()
        values = getattr(index, "values", None)
        rows = [int(v) for v in values] if values is not None else list(range(int(lo), int(hi) + 1))
        absent = [r for r in rows if r not in twins]
        if absent:
            raise ConfigError(
                f"galaxy.twin_catalog: {path}: no twin for real-catalog row(s) {absent[:5]}"
            )
    return {"twin": twin, "twin_catalog": path}


def parse(
    given: Mapping[str, Any],
    values: Mapping[str, Any],
    instrument: Mapping[str, float],
    config_path: str,
) -> GalaxySpec:
    """Galaxies of a GalSim RealGalaxyCatalog (HST images)."""
    from megalut_cli.sim.galaxies import real_galaxy_catalog  # GalSim: not needed for --help

    cat = resolve_beside(given["real_catalog"], "galaxy.real_catalog", config_path)
    if "real_dir" in given:
        real_dir = str(
            resolve_beside(given["real_dir"], "galaxy.real_dir", config_path, folder=True)
        )
    else:
        real_dir = str(cat.parent)
    scale = float(values["pixel_scale"])
    if scale <= 0:
        raise ConfigError(f"galaxy.pixel_scale: must be > 0, got {scale}")
    n_obj = real_galaxy_catalog(str(cat), real_dir).nobjects
    mode = flux_mode(given, instrument)
    if mode == "sb" and "twin_catalog" not in given:
        raise ConfigError(
            "galaxy.sb: profile 'real' takes its size from galaxy.twin_catalog (the fitted "
            "half-light radius); give galaxy.twin_catalog, or galaxy.flux"
        )
    index = values["index"]
    if "real_select" in given:
        if "index" in given:
            raise ConfigError("galaxy.real_select: give either galaxy.index or galaxy.real_select")
        index = {"type": "grid", "values": real_rows(given["real_select"], cat)}
    elif index == "random":
        index = {"type": "grid", "values": list(range(n_obj))}
    params = {
        "index": parse_distribution(index, "galaxy.index"),
        mode: parse_distribution(given[mode], f"galaxy.{mode}"),
    }
    lo, hi = params["index"].bounds()
    if lo < 0 or hi > n_obj - 1 or any(float(v) != int(v) for v in (lo, hi)):
        raise ConfigError(
            f"galaxy.index: must be integers in [0, {n_obj - 1}] (the rows of {cat.name}), "
            f"got [{lo:g}, {hi:g}]"
        )
    angle = position_angle(values)
    real = {
        "catalog": str(cat),
        "dir": real_dir,
        "pixel_scale": scale,
        "n_objects": int(n_obj),
        "hst_noise": values["hst_noise"],
    }
    real.update(parse_twin(given, values["twin"], config_path, params["index"]))
    real["order"] = values["real_order"]
    if real["order"] == "each":
        if not isinstance(params["index"], Grid):
            raise ConfigError(
                "galaxy.real_order: 'each' needs galaxy.real_select or a grid of galaxy.index "
                "values"
            )
        real["rows"] = tuple(int(v) for v in params["index"].values)
    return GalaxySpec("real", params, angle, mode, 0.0, real)


def truth(spec: GalaxySpec, drawn: dict[str, np.ndarray], sequence: np.ndarray) -> ProfileTruth:
    """The catalog row of each realization's galaxy; with ``real_order = "each"``, galaxy
    ``sequence`` (mod N) of the list. Size and shape: NaN."""
    real = spec.real or {}
    index = np.round(drawn["index"]).astype(np.int64)
    if real.get("order") == "each":
        rows = np.asarray(real["rows"], dtype=np.int64)
        index = rows[sequence % len(rows)]
    rad = np.full(len(index), np.nan)
    flux_rad = rad
    if spec.flux_mode == "sb":  # F = S * pi * R^2, R the fitted (twin) half-light radius
        from megalut_cli.sim.twins import twin_truth  # GalSim: not needed for --help

        flux_rad = twin_truth(real, index)["tru_twin_rad"]
    return ProfileTruth(
        {"tru_real_index": index, "tru_rad": rad}, np.full(len(index), np.nan), flux_rad
    )


def build(
    spec: GalaxySpec, truth: Mapping[str, np.ndarray], k: int, gsparams: Any, pad_pixels: float
) -> Any:
    from megalut_cli.sim.galaxies import real_profile  # GalSim: not needed to read a config

    return real_profile(
        spec.real or {}, int(truth["tru_real_index"][k]), truth["tru_flux"][k], gsparams, pad_pixels
    )


def summary(table: Mapping[str, Any]) -> str:
    g = f"real galaxies of {Path(str(table.get('real_catalog', '?'))).name}"
    return f"Sersic twins of {g}" if table.get("twin", "none") != "none" else g


PROFILE = GalaxyProfile(
    "real",
    "HST galaxies of a GalSim RealGalaxyCatalog, with their own (symmetrized) noise; see "
    "`docs/great3.md` and below",
    OPTIONS,
    (
        Required("real_catalog", "required by profile 'real': the RealGalaxyCatalog FITS file"),
        Required("pixel_scale", "required by profile 'real': arcsec per simulation pixel"),
        OneOf(
            FLUX_KEYS,
            "profile 'real' needs exactly one of galaxy.flux, galaxy.sb or galaxy.mag (got {got})",
        ),
    ),
    parse,
    truth,
    build,
    truth_columns=(
        "tru_real_index",
        "tru_hst_noise_var",
        "tru_twin",
        "tru_twin_rad",
        "tru_twin_sersicn",
        "tru_twin_g1",
        "tru_twin_g2",
    ),
    refuses={k: FROM_THE_IMAGES for k in ("rad", "sersicn", "sersicn_step", "ellipticity")},
    only_own_keys=True,
    summary=summary,
)
