"""Simulation configuration: loading and validation of a config file.

The reference of every key is ``docs/config.md``. This module holds the whole config
(:class:`SimConfig`), ``[structure]``, ``[instrument]``, ``[psf]``, ``[gsparams]``,
``[shear]``, ``[field]`` and the ranges; ``galaxy_config``, ``noise_config`` and
``catalog_config`` the other tables, ``megalut_cli.configfile`` TOML reading and
overrides. :func:`load_config` returns a
:class:`SimConfig` whose parts are plain, picklable data (distributions, numbers and the
input-catalog columns already read), so that work units can carry it to any worker.
Every problem is reported as one :class:`~megalut_cli.errors.ConfigError` naming the key.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from megalut_cli.configfile import (
    apply_overrides,
    config_source,
    parse_override,
    read_toml,
    where_written,
)
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.schema import (
    Option,
    Table,
    check_int,
    check_table,
    resolve_beside,
)
from megalut_cli.sim.catalog_config import load_catalog_columns
from megalut_cli.sim.distributions import (
    DIST_TYPES,
    Distribution,
    check_bounds,
    is_distribution_table,
    parse_distribution,
    parse_distributions,
)
from megalut_cli.sim.galaxy_config import GalaxySpec, check_galaxy_ranges, parse_galaxy
from megalut_cli.sim.noise_config import (
    CorrelationSource,
    NoiseSpec,
    is_measured,
    measured_value,
    parse_noise,
)
from megalut_cli.sim.profiles import GALAXY_PROFILES
from megalut_cli.sim.profiles.common import SERSIC_N_RANGE, round_sersicn
from megalut_cli.sim.profiles.cosmos_fit import COSMOS_FIT_COLUMNS
from megalut_cli.sim.scene_config import SceneSpec, parse_scene

#: Public names, with those of the table modules that stay importable from here (as before the
#: split).
__all__ = [
    "COSMOS_FIT_COLUMNS",
    "SERSIC_N_RANGE",
    "CorrelationSource",
    "GalaxySpec",
    "NoiseSpec",
    "SimConfig",
    "StructureSpec",
    "apply_overrides",
    "is_measured",
    "load_config",
    "measured_value",
    "parse_override",
    "read_toml",
    "round_sersicn",
    "validate_config",
]

log = logging.getLogger(__name__)

#: Parameter groups that can be redrawn for every realization (else once per case).
VARY_GROUPS = ("shear", "galaxy", "angle", "psf")
SNC_MODES = ("ring", "pairs", "none")

_TOP_KEYS = {
    "description",
    "structure",
    "shear",
    "galaxy",
    "psf",
    "noise",
    "instrument",
    "field",
    "catalog",
    "gsparams",
    "scene",
}
#: GalSim GSParams settable in ``[gsparams]`` (accuracy/speed of the rendering), declared once.
GSPARAMS_OPTIONS: tuple[Option, ...] = tuple(
    Option(
        name,
        "float",
        None,
        what,
        minimum=0.0,
        maximum=1.0,
        min_open=True,
        max_open=True,
        default_text="GalSim's",
    )
    for name, what in (
        (
            "folding_threshold",
            "fraction of the flux allowed to fold in the FFT (smaller: larger FFTs)",
        ),
        ("maxk_threshold", "largest Fourier amplitude left out of the FFT"),
        ("kvalue_accuracy", "accuracy of Fourier-space values"),
        ("xvalue_accuracy", "accuracy of real-space values"),
    )
) + (
    Option(
        "stepk_minimum_hlr",
        "float",
        None,
        "smallest FFT field in half-light radii",
        minimum=0.0,
        min_open=True,
        default_text="GalSim's",
    ),
    Option(
        "minimum_fft_size", "int", None, "smallest FFT size", minimum=16, default_text="GalSim's"
    ),
    Option(
        "maximum_fft_size", "int", None, "largest FFT size", minimum=16, default_text="GalSim's"
    ),
)
GSPARAMS = {o.name: o for o in GSPARAMS_OPTIONS}
#: The keys of ``[instrument]``, declared once (needed by magnitudes and CCD noise).
INSTRUMENT_OPTIONS: tuple[Option, ...] = (
    Option(
        "pixel_scale",
        "float",
        None,
        "arcsec per pixel (sky level)",
        minimum=0.0,
        min_open=True,
        default_text="—",
    ),
    Option(
        "exptime", "float", None, "exposure time, s", minimum=0.0, min_open=True, default_text="—"
    ),
    Option(
        "gain", "float", None, "electrons per ADU", minimum=0.0, min_open=True, default_text="—"
    ),
    Option("zeropoint", "float", None, "magnitude zero-point Z_p", default_text="—"),
)
INSTRUMENT = {o.name: o for o in INSTRUMENT_OPTIONS}
#: The keys of ``[structure]``, declared once (their checks, the table of docs/config.md,
#: ``simulate --n-cases/--n-realizations``).
STRUCTURE_OPTIONS: tuple[Option, ...] = (
    Option("n_cases", "int", None, "number of cases", minimum=1, default_text="required"),
    Option(
        "n_realizations",
        "int",
        None,
        "realizations per case (stamps = n_cases × n_realizations)",
        minimum=1,
        default_text="required",
    ),
    Option(
        "per_realization",
        "choice_list",
        ["angle"],
        "parameter groups redrawn for every realization; the "
        'others are drawn once per case. Groups: `"shear"` (g1, g2), `"galaxy"` (all of '
        '`[galaxy]`, implies `"angle"`), `"angle"` (position angle only), `"psf"` (field position '
        "and random PSF parameters)",
        choices=VARY_GROUPS,
    ),
    Option(
        "snc",
        "choice",
        "none",
        'shape-noise cancellation (below; `"pairs"` needs an even n_realizations)',
        choices=SNC_MODES,
    ),
    Option("stamp_size", "int", 64, "stamp size S in pixels", minimum=8, maximum=4096),
    Option(
        "offset",
        "float",
        0.5,
        "the true centre is the stamp centre plus an offset uniform in ±`offset` "
        "pixels (per realization)",
        allowed_text="[0, stamp_size/4]",
    ),
    Option(
        "n_x",
        "int",
        None,
        "stamps per row of the `--stamps` grid image",
        minimum=1,
        default_text="ceil(sqrt(N))",
    ),
    Option(
        "common",
        "bool",
        False,
        "common random numbers: every case draws the **same** realizations "
        "(galaxies, position angles, offsets, noise); see below",
    ),
    Option(
        "antithetic",
        "bool",
        False,
        "antithetic noise: realizations come in twins `2k, 2k+1` alike in everything but "
        "the sign of their noise (and of metacal's fixnoise), so that every term odd in the "
        "noise cancels within a twin; see below",
    ),
)
STRUCTURE = {o.name: o for o in STRUCTURE_OPTIONS}
_INSTRUMENT_KEYS = {"pixel_scale", "exptime", "gain", "zeropoint"}


@dataclass(frozen=True)
class StructureSpec:
    """Cases x realizations, what varies per realization, shape-noise cancellation."""

    n_cases: int
    n_realizations: int
    per_realization: frozenset[str]
    snc: str
    stamp_size: int
    offset: float
    n_x: int | None = None
    #: Common random numbers: every case draws the same galaxies, offsets and noise.
    common: bool = False
    #: Antithetic noise: realizations ``2k, 2k+1`` are twins with opposite noise.
    antithetic: bool = False

    @property
    def group_size(self) -> int:
        """Realizations sharing their per-realization parameters (an SNC group)."""
        return {"ring": self.n_realizations, "pairs": 2, "none": 1}[self.snc]

    @property
    def n_groups(self) -> int:
        return self.n_realizations // self.group_size

    @property
    def n_stamps(self) -> int:
        return self.n_cases * self.n_realizations

    @property
    def grid_nx(self) -> int:
        """Stamps per row of the grid image (``n_x``, default ceil(sqrt(N)))."""
        return self.n_x if self.n_x else max(1, math.ceil(math.sqrt(self.n_stamps)))

    def varies(self, group: str) -> bool:
        """Whether ``group`` is redrawn per realization (``galaxy`` implies ``angle``)."""
        return group in self.per_realization or (
            group == "angle" and "galaxy" in self.per_realization
        )


@dataclass(frozen=True)
class SimConfig:
    """A validated simulation configuration (picklable)."""

    path: str
    sha256: str
    raw: dict[str, Any]
    overrides: tuple[str, ...]
    structure: StructureSpec
    shear: dict[str, Distribution]
    field: dict[str, Distribution] | None
    psf: dict[str, Any]  # scalars and Distribution objects, resolved per case
    psf_varies: bool
    galaxy: GalaxySpec
    noise: NoiseSpec
    instrument: dict[str, float]
    catalog_rows: int = 0
    catalog_path: str | None = None
    gsparams: dict[str, float] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    #: ``[scene]`` (fields of galaxies, ``simulate --scene``), None when the config has none.
    scene: SceneSpec | None = None

    def to_json(self) -> str:
        """The effective configuration (overrides applied) as JSON text."""
        return json.dumps(self.raw, sort_keys=True, default=str)

    def with_structure(self, **changes: Any) -> SimConfig:
        return replace(self, structure=replace(self.structure, **changes))

    @property
    def gain(self) -> float | None:
        """The gain (e-/ADU) when the noise is CCD-like, else None (SNR by Eq. 10)."""
        if self.noise.type == "ccd" and self.noise.override_sigma is None:
            return self.instrument["gain"]
        return None


# --------------------------------------------------------------------------- loading


def load_config(
    path: str | os.PathLike,
    overrides: Sequence[str] = (),
    n_cases: int | None = None,
    n_realizations: int | None = None,
    scene: bool = False,
) -> SimConfig:
    """Read, override and validate a simulation config file (errors name the keys dotted:
    ``galaxy.rad: ...``; :func:`keys_as_written` names them as the file writes them).
    With ``scene`` (fields of galaxies, :mod:`megalut_cli.sim.scene`), ``[structure]`` may
    leave out ``n_cases`` and ``n_realizations`` (they are not used) and ``[scene]`` is
    parsed even when absent (its defaults)."""
    raw, sha = read_toml(path)
    raw = apply_overrides(raw, overrides)
    structure = (
        raw.setdefault("structure", {}) if isinstance(raw.get("structure", {}), dict) else None
    )
    if structure is None:
        raise ConfigError("structure: expected a table")
    if n_cases is not None:
        structure["n_cases"] = int(n_cases)
    if n_realizations is not None:
        structure["n_realizations"] = int(n_realizations)
    if scene:
        for key in ("n_cases", "n_realizations"):
            structure.setdefault(key, 1)
        raw.setdefault("scene", {})
    return validate_config(raw, path=str(path), sha256=sha, overrides=tuple(overrides))


@contextlib.contextmanager
def keys_as_written(
    path: str | os.PathLike, overrides: Sequence[str] = (), **given: Any
) -> Iterator[None]:
    """Errors of the config file ``path`` raised inside (:func:`load_config`) name their key
    where the user wrote it: the file and its table (``tp.toml: [galaxy] rad: ...``), or the
    dotted key of a ``KEY=VALUE`` override (``galaxy.rad: ...``). ``given``: the structure
    keys the caller set (``n_cases=100``), named dotted too."""
    try:
        yield
    except (ConfigError, InputError) as err:
        if type(err) not in (ConfigError, InputError):  # errors with their own fields
            raise
        source = config_source(path)
        if source is None:
            raise
        set_by_caller = [f"structure.{k}={v}" for k, v in given.items() if v is not None]
        top = _TOP_KEYS | set(source.raw)
        raise type(err)(
            where_written(str(err), [source], [*overrides, *set_by_caller], top)
        ) from None


# --------------------------------------------------------------------------- validation


def _parse_structure(raw: Mapping[str, Any]) -> StructureSpec:
    t = Table(raw.get("structure"), "structure", set(STRUCTURE))
    if raw.get("structure") is None:
        raise ConfigError("structure: missing [structure] table")
    for k in ("n_cases", "n_realizations"):
        if k not in t.data:
            raise ConfigError(f"structure.{k}: missing")
    n_cases, n_rea, per, snc, stamp, offset, n_x, common, antithetic = (
        t.option(o) for o in STRUCTURE_OPTIONS
    )
    multiple = (2 if snc == "pairs" else 1) * (2 if antithetic else 1)
    if n_rea % multiple:
        why = " and ".join(
            w for w, on in (("snc = 'pairs'", snc == "pairs"), ("antithetic", antithetic)) if on
        )
        needs = "an even number" if multiple == 2 else f"a multiple of {multiple}"
        raise ConfigError(f"structure.n_realizations: {why} needs {needs}, got {n_rea}")
    if offset < 0 or offset > stamp / 4:
        raise ConfigError(f"structure.offset: must be in [0, stamp_size/4], got {offset}")
    if common:
        _check_common(frozenset(per), snc)
    return StructureSpec(
        n_cases, n_rea, frozenset(per), snc, stamp, offset, n_x, common, antithetic
    )


def _check_common(per: frozenset[str], snc: str) -> None:
    """Refuse common-random-number sets that cannot mean anything."""
    if "galaxy" not in per:
        raise ConfigError(
            "structure.common: needs per_realization to include 'galaxy' (a new galaxy per "
            "realization group, the same one in every case)"
        )
    if "shear" in per:
        raise ConfigError(
            "structure.common: the shear must be drawn per case; remove 'shear' from "
            "per_realization"
        )
    if snc == "ring":
        raise ConfigError(
            "structure.common: snc = 'ring' makes one galaxy per case, nothing to share between "
            "cases; use snc = 'pairs' or 'none'"
        )


def _check_antithetic(galaxy: GalaxySpec, noise: NoiseSpec) -> None:
    """Refuse antithetic twins where a stamp's noise has no opposite."""
    kind = "gaussian" if noise.override_sigma is not None else noise.type
    if kind not in ("gaussian", "correlated"):
        raise ConfigError(
            f"structure.antithetic: needs Gaussian noise (noise.type 'gaussian' or 'correlated', "
            f"or noise.override_sigma); {kind!r} noise has no opposite"
        )
    if galaxy.real is not None and galaxy.real["hst_noise"] != "keep":
        raise ConfigError(
            "structure.antithetic: the HST noise of real galaxies is not negated; set "
            "galaxy.hst_noise = 'keep' or leave antithetic out"
        )


def _parse_instrument(raw: Mapping[str, Any]) -> dict[str, float]:
    t = Table(raw.get("instrument"), "instrument", set(INSTRUMENT))
    return {k: t.option(INSTRUMENT[k]) for k in t.data}


def _parse_gsparams(raw: Mapping[str, Any]) -> dict[str, float]:
    t = Table(raw.get("gsparams"), "gsparams", set(GSPARAMS))
    out: dict[str, float] = {k: t.option(GSPARAMS[k]) for k in t.data}
    if out:
        import galsim

        try:
            galsim.GSParams(**out)
        except (ValueError, TypeError, galsim.GalSimError) as err:
            raise ConfigError(f"gsparams: {err}") from None
    return out


def _parse_psf(raw: Mapping[str, Any], config_path: str) -> dict[str, Any]:
    t = check_table(raw.get("psf"), "psf", None, required=True)
    if "type" not in t:
        raise ConfigError("psf.type: missing")
    if t["type"] == "stamp" and "path" in t:  # a star image: same lookup as catalog.path
        t["path"] = str(resolve_beside(t["path"], "psf.path", config_path))
    if t["type"] == "stamp" and t.get("index") == "random":  # one star of the grid per case
        if t.get("stamp_size") is None or "path" not in t:
            raise ConfigError(
                "psf.index: 'random' needs psf.path and psf.stamp_size (a grid of stars)"
            )
        from megalut_cli.sim.psf import star_grid_size  # fitsio: not for --help

        t["stamp_size"] = check_int(t["stamp_size"], "psf.stamp_size", 3)
        n = star_grid_size(t["path"], t.get("hdu"), t["stamp_size"])
        t["index"] = {"type": "grid", "values": list(range(n))}
    elif isinstance(t.get("index"), str):
        raise ConfigError(
            f"psf.index: expected an integer, a distribution or 'random', got {t['index']!r}"
        )
    spec: dict[str, Any] = {}
    for k, v in t.items():
        if k != "type" and is_distribution_table(v) and v.get("type") in DIST_TYPES:
            spec[k] = parse_distribution(v, f"psf.{k}")
        else:
            spec[k] = v
    return spec


def validate_config(
    raw: Mapping[str, Any],
    path: str = "<config>",
    sha256: str = "",
    overrides: tuple[str, ...] = (),
) -> SimConfig:
    """Validate a parsed config mapping; return a :class:`SimConfig`."""
    if not isinstance(raw, Mapping):
        raise ConfigError("config: expected a table")
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise ConfigError(
            f"{unknown[0]}: unknown table or key (allowed: {', '.join(sorted(_TOP_KEYS))})"
        )
    if "description" in raw and not isinstance(raw["description"], str):
        raise ConfigError("description: expected a string")
    structure = _parse_structure(raw)
    instrument = _parse_instrument(raw)
    scene = parse_scene(raw, instrument) if "scene" in raw else None
    shear_t = check_table(raw.get("shear"), "shear", {"g1", "g2"})
    shear = parse_distributions(shear_t, "shear", ["g1", "g2"])
    galaxy = parse_galaxy(raw, instrument, path)
    noise = parse_noise(raw, instrument, path)
    if (
        galaxy.real is not None
        and galaxy.real["hst_noise"] != "keep"
        and noise.type in ("ccd", "correlated")
        and noise.override_sigma is None
    ):
        raise ConfigError(
            f"galaxy.hst_noise: {galaxy.real['hst_noise']!r} needs noise.type = 'gaussian' (the "
            "added noise makes up the rest of the variance); or set galaxy.hst_noise = 'keep'"
        )
    if structure.antithetic:
        _check_antithetic(galaxy, noise)
        if scene is not None:
            raise ConfigError("structure.antithetic: stamps only, not fields of galaxies ([scene])")
    psf = _parse_psf(raw, path)
    gsparams = _parse_gsparams(raw)
    field_t = check_table(raw.get("field"), "field", {"x", "y"})
    field_d = parse_distributions(field_t, "field", ["x", "y"]) if field_t else None
    if field_d is not None and len(field_d) != 2:
        raise ConfigError(f"field.{'y' if 'x' in field_d else 'x'}: missing")

    psf_dists = {k: v for k, v in psf.items() if isinstance(v, Distribution)}
    parts: dict[str, dict[str, Any]] = {
        "shear": shear,
        "field": field_d or {},
        "psf": psf_dists,
        "galaxy": galaxy.params,
        "angle": {"angle": galaxy.angle},
        "noise": noise.params,
    }
    profile = GALAXY_PROFILES[galaxy.profile]
    if profile.catalog and not isinstance(raw.get("catalog"), Mapping):
        raise ConfigError(f"galaxy.profile: {profile.name!r} {profile.catalog}")
    n_rows, cat_path = load_catalog_columns(raw, path, parts)
    if profile.select_rows is not None:
        n_rows = profile.select_rows(galaxy, parts, n_rows)
    psf.update(parts["psf"])
    galaxy = replace(galaxy, angle=parts["angle"]["angle"])
    if field_d is not None:
        field_d = parts["field"]

    # Ranges
    check_galaxy_ranges(galaxy, structure.stamp_size)
    gmax = [max(abs(x) for x in d.bounds()) for d in shear.values()]
    if gmax and math.hypot(*gmax, 0.0) >= 1.0:
        raise ConfigError("shear: the reduced shear |g| must stay < 1")
    if "sigma" in noise.params:
        check_bounds(noise.params["sigma"], 0.0, None, "the noise sigma")
    if "read_noise" in noise.params:
        check_bounds(noise.params["read_noise"], 0.0, None, "the read noise")

    # PSF: validated by the PSF module on both ends of every distribution.
    from megalut_cli.sim import psf as psf_mod  # fitsio: not for --help

    for end in (0, 1):
        spec = {k: (v.bounds()[end] if isinstance(v, Distribution) else v) for k, v in psf.items()}
        psf_mod.validate_psf_config(spec)
    varies = bool(
        psf_mod.psf_varies(
            {k: (v.bounds()[0] if isinstance(v, Distribution) else v) for k, v in psf.items()}
        )
    )
    if varies and field_d is None:
        field_d = {
            "x": parse_distribution({"type": "uniform", "min": 0.0, "max": 1.0}, "field.x"),
            "y": parse_distribution({"type": "uniform", "min": 0.0, "max": 1.0}, "field.y"),
        }

    return SimConfig(
        path=path,
        sha256=sha256,
        raw=json.loads(json.dumps(raw, default=str)),
        overrides=overrides,
        structure=structure,
        shear=shear,
        field=field_d,
        psf=psf,
        psf_varies=varies,
        galaxy=galaxy,
        noise=noise,
        instrument=instrument,
        catalog_rows=n_rows,
        catalog_path=cat_path,
        gsparams=gsparams,
        scene=scene,
    )
