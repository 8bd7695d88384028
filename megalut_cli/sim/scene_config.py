"""The ``[scene]`` table of a simulation config: fields of galaxies at random positions
(``megalut simulate --scene``; drawn by :mod:`megalut_cli.sim.scene`, docs/scenes.md).

Every key is declared once here (:data:`SCENE_OPTIONS`: checks, docs table); the table is
optional, its keys have defaults, and ``pixel_scale`` falls back on
``instrument.pixel_scale``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from megalut_cli.errors import ConfigError
from megalut_cli.schema import Option, Table

#: Largest mean fraction of the placement square (side size - 2 border + min_separation)
#: covered by disks of diameter ``min_separation`` around the galaxies: random sequential
#: placement jams near 55 %, and a field's Poisson count may well exceed the mean.
MAX_COVERAGE = 0.3
#: Bits of the scenes' ``MSK`` cube: a saturated pixel, a pixel of a bad column.
MASK_SATURATED = 1
MASK_BAD_COLUMN = 2
#: The keys of ``[scene]``, declared once (checks, the table of docs/scenes.md).
SCENE_OPTIONS: tuple[Option, ...] = (
    Option(
        "density",
        "float",
        20.0,
        "galaxies per arcmin²: each field holds a Poisson number of mean density × area "
        "(the square inside `border`, or beyond the edges where it is negative)",
        minimum=0.0,
        min_open=True,
        maximum=1e5,
    ),
    Option("size", "int", 200, "side of a (square) field, pixels", minimum=16, maximum=8192),
    Option(
        "pixel_scale",
        "float",
        None,
        "arcsec per pixel (sets the area of a field in arcmin²; galaxy and PSF sizes stay "
        "in pixels)",
        minimum=0.0,
        min_open=True,
        default_text="instrument.pixel_scale",
    ),
    Option("n_fields", "int", 1, "number of fields (one constant shear each)", minimum=1),
    Option(
        "pairs",
        "bool",
        False,
        "draw every field at +g and −g with the same galaxies and the same noise "
        "(`simulate --pairs`)",
    ),
    Option(
        "border",
        "int",
        0,
        "galaxy centres stay at least this many pixels inside the field's edges (before "
        "`shear_positions` moves them); negative: they reach this many pixels beyond them, "
        "so the sky goes on past the field (neighbours' light at its edges, lensed positions "
        "bringing galaxies in as they take others out)",
        allowed_text="(−size/2, size/2)",
    ),
    Option(
        "inner_border",
        "int",
        0,
        "pixels at each edge outside the fields' inner region (card `INNERBRD`, as for "
        "overlapping coadd cells): `measure --metadetect` marks the detections whose "
        "unsheared position lies there `inner = 0`, and `evaluate` and `calibrate` leave "
        "them out; 0: every detection is inner",
        minimum=0,
        allowed_text="[0, size/2)",
    ),
    Option(
        "shear_positions",
        "bool",
        True,
        "lens the galaxies' positions as well as their profiles: each centre moves by the "
        "field's shear about the field's centre, (size + 1)/2, the point metadetection "
        "shears a cell about, so neighbours' separations respond to the shear as on the sky; "
        "false: only the profiles are sheared (every scene drawn before this key)",
    ),
    Option(
        "psf_size",
        "int",
        33,
        "side of the PSF image at the field centre (odd: the PSF centred on a pixel)",
        minimum=5,
        maximum=1025,
        allowed_text="odd, [5, 1025]",
    ),
    Option(
        "min_separation",
        "float",
        0.0,
        "galaxy centres lie at least this many pixels apart (before `shear_positions`): each "
        "galaxy is redrawn until it does from those placed before it (isolated galaxies; "
        "coverage: the mean fraction of the centres' square, widened by it, under disks of "
        "this diameter); 0: independent uniform positions",
        minimum=0.0,
        allowed_text=f"[0, size − 2 border]; mean coverage ≤ {100 * MAX_COVERAGE:g} %",
    ),
    Option(
        "star_density",
        "float",
        0.0,
        "stars per arcmin²: each field holds a Poisson number of mean star_density × the "
        "field's area, at uniform positions, not sheared (the same in every image of a pair): "
        "the PSF times a flux drawn log-uniformly in [star_flux_min, star_flux_max]; 0: none",
        minimum=0.0,
        maximum=1e5,
    ),
    Option(
        "star_flux_min",
        "float",
        1e3,
        "smallest star flux (the stars' fluxes are log-uniform)",
        minimum=0.0,
        min_open=True,
    ),
    Option(
        "star_flux_max",
        "float",
        1e6,
        "largest star flux",
        minimum=0.0,
        min_open=True,
        allowed_text="≥ star_flux_min",
    ),
    Option(
        "saturation",
        "float",
        0.0,
        "pixels above this value (noise included) are set to it and masked "
        f"(`MSK` bit {MASK_SATURATED}, per image); 0: no saturation",
        minimum=0.0,
    ),
    Option(
        "bad_columns",
        "float",
        0.0,
        "mean number of bad columns per field (Poisson; the same in every image of a "
        f"pair): whole columns set to NaN and masked (`MSK` bit {MASK_BAD_COLUMN}); 0: none",
        minimum=0.0,
        maximum=1e4,
    ),
)
SCENE = {o.name: o for o in SCENE_OPTIONS}


@dataclass(frozen=True)
class SceneSpec:
    """The ``[scene]`` table, checked (plain, picklable)."""

    density: float
    size: int
    pixel_scale: float
    n_fields: int
    pairs: bool
    border: int
    psf_size: int
    shear_positions: bool = True
    inner_border: int = 0
    min_separation: float = 0.0
    star_density: float = 0.0
    star_flux_min: float = 1e3
    star_flux_max: float = 1e6
    saturation: float = 0.0
    bad_columns: float = 0.0

    @property
    def n_signs(self) -> int:
        """Images per field: 2 with ``pairs`` (+g, −g), else 1."""
        return 2 if self.pairs else 1

    @property
    def n_images(self) -> int:
        return self.n_fields * self.n_signs

    @property
    def area_arcmin2(self) -> float:
        """The area galaxy centres are drawn in (the square inside the border), arcmin²."""
        side = (self.size - 2 * self.border) * self.pixel_scale / 60.0
        return side * side

    @property
    def mean_count(self) -> float:
        """Mean number of galaxies per field."""
        return self.density * self.area_arcmin2

    @property
    def mean_stars(self) -> float:
        """Mean number of stars per field (over the whole field)."""
        side = self.size * self.pixel_scale / 60.0
        return self.star_density * side * side

    @property
    def has_defects(self) -> bool:
        """Whether the images get stars, saturation or bad columns (masks not all zero)."""
        return self.star_density > 0 or self.saturation > 0 or self.bad_columns > 0

    @property
    def coverage(self) -> float:
        """The mean fraction of the placement square (the centres' square, widened by
        ``min_separation``) covered by disks of diameter ``min_separation`` (0 without)."""
        d = self.min_separation
        side = self.size - 2 * self.border + d
        return self.mean_count * math.pi * d * d / 4.0 / (side * side)


def parse_scene(raw: Mapping[str, Any], instrument: Mapping[str, float]) -> SceneSpec:
    """The ``[scene]`` table of the config ``raw`` (defaults where absent)."""
    t = Table(raw.get("scene"), "scene", set(SCENE))
    density, size, scale, n_fields, pairs, border, inner, shear_pos, psf_size, min_sep, *defects = (
        t.option(o) for o in SCENE_OPTIONS
    )
    star_density, flux_min, flux_max, saturation, bad_columns = (float(v) for v in defects)
    inst_scale = instrument.get("pixel_scale")
    if scale is None:
        if inst_scale is None:
            raise ConfigError(
                "scene.pixel_scale: missing (arcsec per pixel; or give instrument.pixel_scale)"
            )
        scale = float(inst_scale)
    elif inst_scale is not None and not math.isclose(scale, inst_scale, rel_tol=1e-9):
        raise ConfigError(
            f"scene.pixel_scale: {scale:g} differs from instrument.pixel_scale = {inst_scale:g}; "
            "give one of them"
        )
    if not -size / 2 < border < size / 2:
        raise ConfigError(
            f"scene.border: must be in (-size/2, size/2) = ({-size / 2:g}, {size / 2:g}), "
            f"got {border}"
        )
    if not inner < size / 2:
        raise ConfigError(
            f"scene.inner_border: must be in [0, size/2) = [0, {size / 2:g}), got {inner}"
        )
    if psf_size % 2 == 0:
        raise ConfigError(f"scene.psf_size: must be odd (centred on a pixel), got {psf_size}")
    if min_sep > size - 2 * border:
        raise ConfigError(
            f"scene.min_separation: must be at most size - 2 border = {size - 2 * border} "
            f"(the side of the square holding the centres), got {min_sep:g}"
        )
    if flux_max < flux_min:
        raise ConfigError(
            f"scene.star_flux_max: must be at least star_flux_min = {flux_min:g}, got {flux_max:g}"
        )
    spec = SceneSpec(
        float(density),
        size,
        float(scale),
        n_fields,
        pairs,
        border,
        psf_size,
        bool(shear_pos),
        inner,
        float(min_sep),
        star_density,
        flux_min,
        flux_max,
        saturation,
        bad_columns,
    )
    if spec.coverage > MAX_COVERAGE:
        raise ConfigError(
            f"scene.min_separation: {spec.mean_count:.1f} galaxies per field on average, "
            f"{min_sep:g} px apart, would cover {100 * spec.coverage:.0f} % of the "
            f"placement square (at most {100 * MAX_COVERAGE:g} %); lower scene.density or "
            "scene.min_separation, or widen scene.size"
        )
    return spec
