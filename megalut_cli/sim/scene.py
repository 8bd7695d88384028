"""Scenes: square fields of galaxies at random positions (``megalut simulate --scene``).

Each field holds a Poisson number of galaxies (mean ``scene.density`` × the square inside
``scene.border``, which reaches beyond the field's edges when it is negative) at uniform
random positions (with ``scene.min_separation``, each redrawn
until it lies that far from those placed before it), drawn from the config's ``[galaxy]`` table
by its registered profile, all lensed by one constant shear per field (``[shear]``, drawn
per field), convolved with the config's PSF (``[psf]``, one per field, at a field position
of ``[field]`` when it varies) and drawn by GalSim on a float32 image; then the config's
noise is added as one field of noise (``[noise]``: Gaussian, correlated, or CCD without the
sources' own Poisson noise). With ``scene.pairs`` every field is drawn at +g and −g with the
same galaxies and the very same noise pixels (the metadetect test recipe).

Field ``f`` draws everything from generators seeded by ``(seed, STREAM_SCENE, f, key)``
(:func:`megalut_cli.seeding.rng_for`), so a field never depends on the others nor on the
worker that draws it. Returns arrays; the command layer writes the files (docs/scenes.md).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli.engine import DEFAULT_ENGINE
from megalut_cli.errors import MegalutError
from megalut_cli.measure.defaults import CELLS_FORMAT, INNER_CARD
from megalut_cli.parallel import executor, map_ordered
from megalut_cli.seeding import STREAM_SCENE, rng_for
from megalut_cli.sim.config import SimConfig
from megalut_cli.sim.distributions import Distribution, sample_level
from megalut_cli.sim.draw import (
    fft_too_large,
    get_psf,
    psf_cache_key,
    psf_includes_pixel,
    renders_galaxies,
    set_up_galsim,
    stamp_renderer,
)
from megalut_cli.sim.intrinsic import ellipticity_components, galaxy_fluxes, mag_from_flux
from megalut_cli.sim.noise import StampNoise, make_noise
from megalut_cli.sim.profiles import GALAXY_PROFILES
from megalut_cli.sim.scene_config import MASK_BAD_COLUMN, MASK_SATURATED, SceneSpec

#: Sub-keys of rng_for(seed, STREAM_SCENE, field, KEY).
_COUNT_KEY, _FIELD_KEY, _GALAXY_KEY, _POSITION_KEY, _NOISE_KEY, _KNOT_KEY, _TWIN_KEY = range(7)
_STAR_KEY, _DEFECT_KEY = 7, 8
#: Largest science cube (pixels of all images together; 1 GiB in float32): fail early.
MAX_SCENE_PIXELS = 2**28
#: With ``scene.min_separation``: the most draws of one galaxy's position before the field's
#: placement starts again.
MAX_PLACEMENT_DRAWS = 10_000
#: ... and the most fresh starts of a field's placement before giving up.
MAX_PLACEMENT_STARTS = 100


def scene_spec(config: SimConfig) -> SceneSpec:
    """The config's ``[scene]`` (load it with ``load_config(..., scene=True)``)."""
    if config.scene is None:
        raise MegalutError("the config has no [scene] table (load it for a scene)")
    return config.scene


def separated_positions(
    xy: np.ndarray, rng: np.random.Generator, lo: float, hi: float, distance: float, fld: int
) -> np.ndarray:
    """Random sequential placement: each position of ``xy`` (n, 2), in turn, redrawn
    uniformly in ``[lo, hi)²`` from ``rng`` until it lies at least ``distance`` from every
    position placed before it (a grid of cells of side ``distance`` finds the neighbours).
    A galaxy that finds no place in :data:`MAX_PLACEMENT_DRAWS` draws (a count in the
    Poisson tail can jam the square) starts the field's placement again from fresh uniform
    positions, at most :data:`MAX_PLACEMENT_STARTS` times; a field that never jams draws
    exactly what it drew before the restarts existed."""
    xy = xy.copy()
    for _ in range(MAX_PLACEMENT_STARTS):
        jammed = _place(xy, rng, lo, hi, distance)
        if jammed is None:
            return xy
        xy = rng.uniform(lo, hi, xy.shape)
    raise MegalutError(
        f"scene field {fld}: galaxy {jammed + 1} of {len(xy)} found no place "
        f"{distance:g} px from the others in {MAX_PLACEMENT_DRAWS} draws, in each of "
        f"{MAX_PLACEMENT_STARTS} placements of the field; lower scene.density or "
        "scene.min_separation"
    )


def _place(
    xy: np.ndarray, rng: np.random.Generator, lo: float, hi: float, distance: float
) -> int | None:
    """One random sequential placement of ``xy`` in place; the index of the galaxy that
    found no place (the placement is then incomplete), or None."""
    placed: dict[tuple[int, int], list[int]] = {}
    d2 = distance * distance
    for k in range(len(xy)):
        for draw in range(MAX_PLACEMENT_DRAWS + 1):
            cx, cy = (int((c - lo) // distance) for c in xy[k])
            near = [
                j
                for i in (cx - 1, cx, cx + 1)
                for jj in (cy - 1, cy, cy + 1)
                for j in placed.get((i, jj), ())
            ]
            if not near or np.min(np.sum((xy[near] - xy[k]) ** 2, axis=1)) >= d2:
                placed.setdefault((cx, cy), []).append(k)
                break
            if draw == MAX_PLACEMENT_DRAWS:
                return k
            xy[k] = rng.uniform(lo, hi, 2)
    return None


def field_counts(config: SimConfig, seed: int) -> np.ndarray:
    """The number of galaxies of every field (Poisson, mean density × area)."""
    s = scene_spec(config)
    return np.array(
        [
            int(rng_for(seed, STREAM_SCENE, f, _COUNT_KEY).poisson(s.mean_count))
            for f in range(s.n_fields)
        ],
        dtype=np.int64,
    )


def check_scene_size(config: SimConfig) -> None:
    """Refuse scenes whose images would not fit in memory."""
    s = scene_spec(config)
    pixels = s.n_images * s.size**2
    if pixels > MAX_SCENE_PIXELS:
        raise MegalutError(
            f"scene: {s.n_images} images of {s.size}² pixels ({pixels:.3g} pixels) would not fit "
            f"in memory (at most {MAX_SCENE_PIXELS:.3g}); lower scene.n_fields or scene.size"
        )


@dataclass(frozen=True)
class FieldUnit:
    """Plain, picklable description of one field to draw."""

    config: SimConfig
    seed: int
    field: int
    n_galaxies: int
    #: the place of the field's first galaxy in the run (real galaxies in turn: ``"each"``)
    sequence_start: int = 0
    #: ``fast``: Sersic and Gaussian galaxies through the batched renderer (GalSim's pixels
    #: to ~1e-7 of the peak); ``galsim``: one ``drawImage`` per galaxy
    engine: str = DEFAULT_ENGINE


@dataclass
class DrawnField:
    """One drawn field: its images (one per sign), weight, mask, PSF image and truth."""

    field: int
    signs: tuple[int, ...]  # +1 (and -1 with pairs)
    images: np.ndarray  # (n_signs, N, N) float32, noise included
    weight: np.ndarray  # (N, N) float32: inverse noise variance (1 when noiseless)
    mask: np.ndarray  # (n_signs, N, N) int32: MASK_SATURATED, MASK_BAD_COLUMN bits
    psf: np.ndarray  # (P, P) float32, sums to 1, centred on the central pixel
    noise: np.ndarray  # (N, N) float32: the noise added to every image of the field
    g1: float
    g2: float
    sky_sigma: float
    #: one row per galaxy: ``x, y`` (FITS 1-based), its truth (``tru_*``, shear of sign +1)
    truth: dict[str, np.ndarray] = field(default_factory=dict)
    #: the flux of each galaxy on the field's pixels, per sign (n_signs, n_galaxies)
    flux_drawn: np.ndarray = field(default_factory=lambda: np.zeros((1, 0)))
    #: correlated noise: another realization of it, independent of ``noise`` (the cells'
    #: ``NOISE`` cube, for metadetection's fixnoise); None otherwise
    noise_twin: np.ndarray | None = None
    #: the field's stars: ``x, y`` (FITS 1-based), ``flux`` (the same in every image)
    stars: dict[str, np.ndarray] = field(default_factory=dict)
    #: each image's galaxy centres (n_signs, n_galaxies, 2), FITS 1-based: ``truth``'s
    #: ``x, y`` lensed by the image's shear with ``scene.shear_positions``, else those
    positions: np.ndarray = field(default_factory=lambda: np.zeros((1, 0, 2)))


def _scalar(values: dict[str, np.ndarray]) -> dict[str, float]:
    return {k: float(v[0]) for k, v in values.items()}


def lensed_positions(
    x: np.ndarray, y: np.ndarray, g1: float, g2: float, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``x, y`` (FITS 1-based) moved by the shear (g1, g2) about the field's centre
    ``(size + 1)/2``: GalSim's shear matrix, the one that shears the profiles (area kept;
    the shear by (-g1, -g2) is its inverse)."""
    import galsim

    centre = (size + 1) / 2.0
    (a, b), (c, d) = galsim.Shear(g1=g1, g2=g2).getMatrix()
    dx, dy = x - centre, y - centre
    return centre + a * dx + b * dy, centre + c * dx + d * dy


@dataclass(frozen=True)
class FieldDraw:
    """The random draws of one field (before any drawing of pixels)."""

    psf_spec: dict[str, Any]  # scalar PSF parameters
    position: tuple[float, float]  # field position of the PSF (0, 0 without [field])
    noise: StampNoise
    noise_seed: int
    g1: float  # the field's shear (sign +1)
    g2: float
    #: one row per galaxy: ``x, y`` (FITS 1-based) and its truth (``tru_*``)
    truth: dict[str, np.ndarray]
    theta: np.ndarray  # position angles (degrees, not reduced to [0, 180))
    #: the stars: ``x, y`` (FITS 1-based) and ``flux``; empty arrays without stars
    stars: dict[str, np.ndarray]
    #: the bad columns' x (FITS 1-based)
    bad_columns: np.ndarray


def field_defects(s: SceneSpec, seed: int, fld: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The stars (``x, y``, ``flux``) and bad columns of field ``fld``, from their own
    generators (a scene without them draws nothing more)."""
    stars = {k: np.zeros(0) for k in ("x", "y", "flux")}
    if s.star_density > 0:
        rng = rng_for(seed, STREAM_SCENE, fld, _STAR_KEY)
        n = int(rng.poisson(s.mean_stars))
        xy = rng.uniform(0.5, s.size + 0.5, (n, 2))
        log_flux = rng.uniform(np.log(s.star_flux_min), np.log(s.star_flux_max), n)
        stars = {"x": xy[:, 0], "y": xy[:, 1], "flux": np.exp(log_flux)}
    columns = np.zeros(0, dtype=np.int64)
    if s.bad_columns > 0:
        rng = rng_for(seed, STREAM_SCENE, fld, _DEFECT_KEY)
        columns = np.unique(rng.integers(1, s.size + 1, int(rng.poisson(s.bad_columns))))
    return stars, columns


def field_parameters(
    config: SimConfig, seed: int, fld: int, n: int, sequence_start: int = 0
) -> FieldDraw:
    """The draws of field ``fld`` with ``n`` galaxies (``sequence_start``: the place of its
    first galaxy in the run)."""
    s = scene_spec(config)
    nrows = config.catalog_rows
    rng_f = rng_for(seed, STREAM_SCENE, fld, _FIELD_KEY)
    here = np.array([fld])  # a sequence's place: the field
    shear = _scalar(sample_level(config.shear, rng_f, 1, nrows, here))
    psf_dists = {k: v for k, v in config.psf.items() if isinstance(v, Distribution)}
    psf_vals = _scalar(sample_level(psf_dists, rng_f, 1, nrows, here))
    fpos = _scalar(sample_level(config.field or {}, rng_f, 1, nrows, here))
    spec = {k: psf_vals.get(k, v) for k, v in config.psf.items()}
    noise = make_noise(
        config.noise.type,
        _scalar(sample_level(config.noise.params, rng_f, 1, nrows, here)),
        config.instrument,
        config.noise.override_sigma,
        config.noise.source,
    )
    noise_seed = int(rng_for(seed, STREAM_SCENE, fld, _NOISE_KEY).integers(1, 2**31 - 1))

    gal = config.galaxy
    rng_g = rng_for(seed, STREAM_SCENE, fld, _GALAXY_KEY)
    gvals = sample_level(gal.params, rng_g, n, nrows)
    sequence = sequence_start + np.arange(n)
    galaxy_truth = GALAXY_PROFILES[gal.profile].truth(gal, gvals, sequence)
    theta = gal.angle.sample(rng_g, n) if n else np.zeros(0)
    rng_p = rng_for(seed, STREAM_SCENE, fld, _POSITION_KEY)
    lo, hi = 0.5 + s.border, s.size + 0.5 - s.border
    xy = rng_p.uniform(lo, hi, (n, 2))
    if s.min_separation > 0:
        xy = separated_positions(xy, rng_p, lo, hi, s.min_separation, fld)
    t: dict[str, np.ndarray] = {"x": xy[:, 0], "y": xy[:, 1]}
    t["tru_g1"] = np.full(n, shear.get("g1", 0.0))
    t["tru_g2"] = np.full(n, shear.get("g2", 0.0))
    t.update(galaxy_truth.columns)
    if gal.knots:
        knot_rng = rng_for(seed, STREAM_SCENE, fld, _KNOT_KEY)
        t["tru_knots"] = np.round(gvals["knots"]).astype(np.int64)
        t["tru_knots_fraction"] = np.where(t["tru_knots"] > 0, gvals["knots_fraction"], 0.0)
        t["tru_knot_seed"] = knot_rng.integers(1, 2**31 - 1, n)
    flux = galaxy_fluxes(
        gal.flux_mode, gvals[gal.flux_mode], galaxy_truth.flux_rad, config.instrument
    )
    t["tru_flux"] = flux
    inst = config.instrument
    if gal.flux_mode == "mag":
        t["tru_mag"] = gvals["mag"]
    elif all(k in inst for k in ("zeropoint", "exptime", "gain")):
        t["tru_mag"] = mag_from_flux(flux, inst["zeropoint"], inst["exptime"], inst["gain"])
    e1, e2 = ellipticity_components(galaxy_truth.ellipticity, theta)
    t["tru_e1"], t["tru_e2"] = e1, e2
    t["tru_ell"], t["tru_theta"] = galaxy_truth.ellipticity, np.mod(theta, 180.0)
    t["tru_sky_sigma"] = np.full(n, noise.sky_sigma)
    if config.field:
        t["tru_field_x"] = np.full(n, fpos["x"])
        t["tru_field_y"] = np.full(n, fpos["y"])
    position = (fpos.get("x", 0.0), fpos.get("y", 0.0))
    g1, g2 = shear.get("g1", 0.0), shear.get("g2", 0.0)
    stars, columns = field_defects(s, seed, fld)
    return FieldDraw(spec, position, noise, noise_seed, g1, g2, t, theta, stars, columns)


def draw_field(unit: FieldUnit) -> DrawnField:
    """Draw field ``unit.field``: every galaxy convolved with the PSF, drawn on a stamp
    around its position (side: GalSim's good size, at most ``structure.stamp_size``;
    by the batched renderer with the fast engine where it can, else by GalSim), whose
    overlap with the field is added to it; then the noise field."""
    set_up_galsim()
    import galsim

    cfg, s = unit.config, scene_spec(unit.config)
    d = field_parameters(cfg, unit.seed, unit.field, unit.n_galaxies, unit.sequence_start)
    spec, noise, t = d.psf_spec, d.noise, d.truth
    psf, psf_truth = get_psf(spec, *d.position, cfg.psf_varies, cfg.gsparams)
    method = "no_pixel" if psf_includes_pixel(spec) else "auto"
    signs = (1, -1) if s.pairs else (1,)
    n = unit.n_galaxies
    for name, value in psf_truth.items():
        t[name] = np.full(n, value)
    fields = [galsim.ImageF(s.size, s.size, scale=1.0) for _ in signs]
    flux_drawn = np.zeros((len(signs), n))
    max_stamp = cfg.structure.stamp_size
    lensed = [{**t, "tru_g1": sign * t["tru_g1"], "tru_g2": sign * t["tru_g2"]} for sign in signs]
    positions = np.zeros((len(signs), n, 2))
    for j, sign in enumerate(signs):
        if s.shear_positions:
            xy = lensed_positions(t["x"], t["y"], sign * d.g1, sign * d.g2, s.size)
        else:
            xy = (t["x"], t["y"])
        positions[j, :, 0], positions[j, :, 1] = xy
    if unit.engine == "fast" and renders_galaxies(cfg):
        key = psf_cache_key(spec, *d.position, cfg.psf_varies, cfg.gsparams)
        try:
            stamps = rendered_galaxies(cfg, psf, key, method, t, positions, signs, d.g1, d.g2)
        except MegalutError as err:
            raise MegalutError(f"scene field {unit.field}: {err}") from None
        for k in range(n):  # added in the galaxies' order, as GalSim's loop does
            for j, (x0, y0, stamp) in enumerate(stamps[k]):
                if stamp is not None:
                    flux_drawn[j, k] = add_overlap(fields[j].array, stamp, x0, y0)
    else:
        draw_galsim_galaxies(unit, psf, method, d.theta, lensed, positions, fields, flux_drawn)
    if len(d.stars["x"]):
        starlight = galsim.ImageF(s.size, s.size, scale=1.0)
        for x, y, flux in zip(d.stars["x"], d.stars["y"], d.stars["flux"]):
            _add_star(starlight, psf.withFlux(float(flux)), x, y, max_stamp, method)
        for f in fields:
            f += starlight
    noise_image = galsim.ImageF(s.size, s.size, scale=1.0)
    noise.add(noise_image, d.noise_seed)  # on an empty field: the same pixels for every sign
    images = np.stack([f.array + noise_image.array for f in fields]).astype(np.float32)
    mask = np.zeros(images.shape, dtype=np.int32)
    if s.saturation > 0:
        saturated = images >= s.saturation
        images[saturated] = s.saturation
        mask[saturated] |= MASK_SATURATED
    if len(d.bad_columns):
        images[:, :, d.bad_columns - 1] = np.nan
        mask[:, :, d.bad_columns - 1] |= MASK_BAD_COLUMN
    twin = None
    if noise.kind == "correlated":
        twin_seed = int(
            rng_for(unit.seed, STREAM_SCENE, unit.field, _TWIN_KEY).integers(1, 2**31 - 1)
        )
        twin_image = galsim.ImageF(s.size, s.size, scale=1.0)
        noise.add(twin_image, twin_seed)
        twin = twin_image.array.astype(np.float32)
    sigma = noise.sky_sigma
    weight = np.full((s.size, s.size), 1.0 / sigma**2 if sigma > 0 else 1.0, dtype=np.float32)
    psf_image = psf.drawImage(nx=s.psf_size, ny=s.psf_size, scale=1.0, method=method).array
    psf_image = (psf_image / np.sum(psf_image, dtype=np.float64)).astype(np.float32)
    return DrawnField(
        unit.field,
        signs,
        images,
        weight,
        mask,
        psf_image,
        noise_image.array.astype(np.float32),
        d.g1,
        d.g2,
        sigma,
        t,
        flux_drawn,
        twin,
        d.stars,
        positions,
    )


def draw_galsim_galaxies(
    unit: FieldUnit,
    psf: Any,
    method: str,
    theta: np.ndarray,
    lensed: list[dict[str, np.ndarray]],
    positions: np.ndarray,
    fields: list[Any],
    flux_drawn: np.ndarray,
) -> None:
    """The galaxies of a field drawn by GalSim one by one (any profile; ``lensed``: their
    truth per image), each on a stamp of GalSim's good size (at most
    ``structure.stamp_size``) around its ``positions``, added to ``fields``."""
    import galsim

    from megalut_cli.sim.galaxies import make_gsparams, oriented

    cfg = unit.config
    gsp = make_gsparams(cfg.gsparams)
    conv_gsp = gsp if cfg.gsparams else None
    profile = GALAXY_PROFILES[cfg.galaxy.profile]
    t = lensed[0]
    max_stamp = cfg.structure.stamp_size
    for k in range(len(theta)):
        base = profile.build(cfg.galaxy, t, k, gsp, 0.0)
        side = 0
        for j in range(len(lensed)):
            gal_k = oriented(base, lensed[j], k, theta[k])
            obj = galsim.Convolve(gal_k, psf, gsparams=conv_gsp)
            if not side:  # the same stamp size for both signs
                side = min(obj.getGoodImageSize(1.0), max_stamp)
                half = side // 2
            where = galsim.PositionD(*positions[j, k])
            ix, iy = int(np.floor(where.x + 0.5)), int(np.floor(where.y + 0.5))
            bounds = galsim.BoundsI(
                ix - half, ix - half + side - 1, iy - half, iy - half + side - 1
            )
            overlap = bounds & fields[j].bounds
            if not overlap.isDefined():
                continue
            stamp = galsim.ImageF(bounds, scale=1.0)
            try:
                obj.drawImage(image=stamp, center=where, method=method)
            except galsim.GalSimFFTSizeError as err:
                raise MegalutError(
                    f"scene field {unit.field}, galaxy {k}: {fft_too_large(err)}"
                ) from None
            except (galsim.GalSimError, MemoryError) as err:
                raise MegalutError(
                    f"scene field {unit.field}, galaxy {k}: GalSim could not draw it ({err})"
                ) from None
            fields[j][overlap] += stamp[overlap]
            flux_drawn[j, k] = float(np.sum(stamp[overlap].array, dtype=np.float64))


def galaxy_stamp_origins(
    positions: np.ndarray, side: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lower-left pixel (FITS 1-based) of each galaxy's stamp of ``side`` around
    ``positions`` (n, 2), as the GalSim loop places it, and the offset of each centre
    from the stamp's true centre: x0, y0, dx, dy."""
    ix = np.floor(positions[:, 0] + 0.5).astype(np.int64)
    iy = np.floor(positions[:, 1] + 0.5).astype(np.int64)
    x0, y0 = ix - side // 2, iy - side // 2
    return x0, y0, positions[:, 0] - x0 - (side - 1) / 2.0, positions[:, 1] - y0 - (side - 1) / 2.0


def rendered_galaxies(
    cfg: SimConfig,
    psf: Any,
    psf_key: str,
    method: str,
    truth: dict[str, np.ndarray],
    positions: np.ndarray,
    signs: tuple[int, ...],
    g1: float,
    g2: float,
) -> list[list[tuple[int, int, np.ndarray | None]]]:
    """Each galaxy's stamp in each image (x0, y0, pixels; None where it misses the field),
    rendered in batches of one stamp side by :class:`~megalut_cli.sim.render.StampRenderer`:
    the stamps the GalSim loop draws (its side from the +g galaxy, at most
    ``structure.stamp_size``), to ~1e-7 of their peak."""
    size = scene_spec(cfg).size
    profile = cfg.galaxy.profile
    rad, flux, e1, e2 = (truth[c] for c in ("tru_rad", "tru_flux", "tru_e1", "tru_e2"))
    sersicn = truth.get("tru_sersicn")
    n = len(rad)
    out: list[list[tuple[int, int, np.ndarray | None]]] = [
        [(0, 0, None)] * len(signs) for _ in range(n)
    ]
    if not n:
        return out
    any_size = stamp_renderer(cfg.structure.stamp_size, dict(cfg.gsparams))
    good = any_size.good_image_sizes(
        psf, psf_key, method, profile, rad, sersicn, e1, e2, signs[0] * g1, signs[0] * g2
    )
    side = np.minimum(good, cfg.structure.stamp_size)
    for j, sign in enumerate(signs):
        x0, y0, dx, dy = galaxy_stamp_origins(positions[j], side)
        hits = (x0 <= size) & (x0 + side > 1) & (y0 <= size) & (y0 + side > 1)
        for s_k in np.unique(side[hits]):
            idx = np.flatnonzero(hits & (side == s_k))
            renderer = stamp_renderer(int(s_k), dict(cfg.gsparams))
            stamps = renderer.draw(
                psf,
                psf_key,
                method,
                profile,
                rad[idx],
                flux[idx],
                None if sersicn is None else sersicn[idx],
                e1[idx],
                e2[idx],
                sign * g1,
                sign * g2,
                dx[idx],
                dy[idx],
            )
            for i, k in enumerate(idx):
                out[k][j] = (int(x0[k]), int(y0[k]), stamps[i])
    return out


def add_overlap(image: np.ndarray, stamp: np.ndarray, x0: int, y0: int) -> float:
    """Add the part of ``stamp`` (lower-left pixel ``x0, y0``, FITS 1-based) that lies on
    ``image`` to it; the flux added (float64 sum)."""
    ny, nx = image.shape
    sy, sx = stamp.shape
    a_x, b_x = max(x0, 1), min(x0 + sx - 1, nx)
    a_y, b_y = max(y0, 1), min(y0 + sy - 1, ny)
    if a_x > b_x or a_y > b_y:
        return 0.0
    part = stamp[a_y - y0 : b_y - y0 + 1, a_x - x0 : b_x - x0 + 1]
    image[a_y - 1 : b_y, a_x - 1 : b_x] += part
    return float(np.sum(part, dtype=np.float64))


def _add_star(image: Any, star: Any, x: float, y: float, max_stamp: int, method: str) -> None:
    """Add the PSF ``star`` (a GalSim object with its flux) at ``(x, y)`` (FITS 1-based) to
    ``image``, drawn on a stamp of GalSim's good size (at most ``max_stamp``) around it."""
    import galsim

    side = min(star.getGoodImageSize(1.0), max_stamp)
    ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
    half = side // 2
    bounds = galsim.BoundsI(ix - half, ix - half + side - 1, iy - half, iy - half + side - 1)
    overlap = bounds & image.bounds
    if overlap.isDefined():
        stamp = galsim.ImageF(bounds, scale=1.0)
        star.drawImage(image=stamp, center=galsim.PositionD(x, y), method=method)
        image[overlap] += stamp[overlap]


def field_units(config: SimConfig, seed: int, engine: str = DEFAULT_ENGINE) -> list[FieldUnit]:
    """One unit per field, with its galaxy count and place in the run."""
    counts = field_counts(config, seed)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return [
        FieldUnit(config, seed, f, int(c), int(a), engine)
        for f, (c, a) in enumerate(zip(counts, starts))
    ]


def iter_fields(
    config: SimConfig,
    seed: int,
    nproc: int = 1,
    scheduler: str | None = None,
    engine: str = DEFAULT_ENGINE,
) -> Iterator[DrawnField]:
    """Draw the fields in order, over ``nproc`` local workers or a Dask ``scheduler``
    (the same pixels for any of them), with ``engine`` (:class:`FieldUnit`)."""
    units = field_units(config, seed, engine)
    with executor(nproc, scheduler, len(units)) as pool:
        for _, drawn in map_ordered(draw_field, ((u.field, u) for u in units), pool, 8):
            yield drawn


@dataclass
class Scenes:
    """Every drawn image of a scene set, in order: field 0 (+g, then −g with pairs), field 1..."""

    images: np.ndarray  # (n_images, N, N) float32
    weights: np.ndarray  # (n_images, N, N) float32
    masks: np.ndarray  # (n_images, N, N) int32
    psfs: np.ndarray  # (n_images, P, P) float32
    #: one row per image: image, field, pair_sign, n_gal, tru_g1, tru_g2, tru_sky_sigma
    image_table: dict[str, np.ndarray]
    #: one row per galaxy per image: image, field, pair_sign, galaxy, x, y, tru_*, tru_flux_drawn
    truth: dict[str, np.ndarray]
    #: correlated noise: an independent realization per image (n_images, N, N), else None
    noise: np.ndarray | None = None
    #: with ``scene.star_density``: one row per star per image (image, field, pair_sign,
    #: x, y, flux), else None
    stars: dict[str, np.ndarray] | None = None


def star_rows(drawn: DrawnField, first_image: int) -> dict[str, np.ndarray]:
    """The star table rows of a drawn field: its stars once per image (sign)."""
    n = len(drawn.stars["x"])
    parts = [
        {
            "image": np.full(n, first_image + j, dtype=np.int64),
            "field": np.full(n, drawn.field, dtype=np.int64),
            "pair_sign": np.full(n, sign, dtype=np.int64),
            **{k: drawn.stars[k] for k in ("x", "y", "flux")},
        }
        for j, sign in enumerate(drawn.signs)
    ]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def truth_rows(drawn: DrawnField, first_image: int) -> dict[str, np.ndarray]:
    """The truth table rows of a drawn field: its galaxies once per image (sign)."""
    n = len(drawn.truth["x"])
    parts = []
    for j, sign in enumerate(drawn.signs):
        cols: dict[str, np.ndarray] = {
            "image": np.full(n, first_image + j, dtype=np.int64),
            "field": np.full(n, drawn.field, dtype=np.int64),
            "pair_sign": np.full(n, sign, dtype=np.int64),
            "galaxy": np.arange(n, dtype=np.int64),
        }
        for name, values in drawn.truth.items():
            cols[name] = sign * values if name in ("tru_g1", "tru_g2") else values
        cols["x"], cols["y"] = drawn.positions[j, :, 0], drawn.positions[j, :, 1]
        cols["tru_flux_drawn"] = drawn.flux_drawn[j]
        parts.append(cols)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def draw_scenes(
    config: SimConfig,
    seed: int,
    nproc: int = 1,
    scheduler: str | None = None,
    engine: str = DEFAULT_ENGINE,
) -> Scenes:
    """All the fields of ``config.scene``, in memory (:func:`check_scene_size` first),
    drawn with ``engine`` (:class:`FieldUnit`)."""
    check_scene_size(config)
    s = scene_spec(config)
    shape = (s.n_images, s.size, s.size)
    images = np.empty(shape, dtype=np.float32)
    weights = np.empty(shape, dtype=np.float32)
    masks = np.zeros(shape, dtype=np.int32)
    psfs = np.empty((s.n_images, s.psf_size, s.psf_size), dtype=np.float32)
    table: dict[str, list[Any]] = {
        k: [] for k in ("image", "field", "pair_sign", "n_gal", "tru_g1", "tru_g2", "tru_sky_sigma")
    }
    truths = []
    stars = []
    noise = None
    for drawn in iter_fields(config, seed, nproc, scheduler, engine):
        first = drawn.field * s.n_signs
        if drawn.noise_twin is not None and noise is None:
            noise = np.empty(shape, dtype=np.float32)
        for j, sign in enumerate(drawn.signs):
            i = first + j
            if noise is not None and drawn.noise_twin is not None:
                noise[i] = drawn.noise_twin  # the signs of a pair share it, as their noise
            images[i], weights[i], masks[i], psfs[i] = (
                drawn.images[j],
                drawn.weight,
                drawn.mask[j],
                drawn.psf,
            )
            for key, value in (
                ("image", i),
                ("field", drawn.field),
                ("pair_sign", sign),
                ("n_gal", len(drawn.truth["x"])),
                ("tru_g1", sign * drawn.g1),
                ("tru_g2", sign * drawn.g2),
                ("tru_sky_sigma", drawn.sky_sigma),
            ):
                table[key].append(value)
        truths.append(truth_rows(drawn, first))
        if s.star_density > 0:
            stars.append(star_rows(drawn, first))
    image_table = {
        k: np.asarray(v, dtype=np.int64 if k in ("image", "field", "pair_sign", "n_gal") else float)
        for k, v in table.items()
    }
    truth = {k: np.concatenate([t[k] for t in truths]) for k in truths[0]}
    star_table = {k: np.concatenate([t[k] for t in stars]) for k in stars[0]} if stars else None
    return Scenes(images, weights, masks, psfs, image_table, truth, noise, star_table)


#: File formats (``MLFORMAT``) of the scene images and of their truth table.
SCENES_FORMAT = CELLS_FORMAT
SCENE_TRUTH_FORMAT = "megalut.scene_truth"


def scene_cards(config: SimConfig, seed: int, engine: str = DEFAULT_ENGINE) -> dict[str, Any]:
    """Header cards of the scene products: seed, engine, the ``[scene]`` keys, noise and
    provenance."""
    s = scene_spec(config)
    drawn_by = engine if renders_galaxies(config) else "galsim"
    cards: dict[str, Any] = {
        "SEED": (seed, "seed of every random draw (megalut simulate --seed)"),
        "ENGINE": (drawn_by, "galaxies drawn by (megalut simulate --engine)"),
        "NFIELDS": (s.n_fields, "number of fields"),
        "NIMAGES": (s.n_images, "number of images (fields x signs)"),
        "PAIRS": (s.pairs, "every field at +g and -g, same galaxies and noise"),
        "FIELDSZ": (s.size, "side of a field, pixels"),
        "PIXSCALE": (s.pixel_scale, "arcsec per pixel"),
        "DENSITY": (s.density, "mean galaxies per arcmin2"),
        "BORDER": (s.border, "centres at least this far inside edges (<0 out)"),
        "SHEARPOS": (s.shear_positions, "galaxy positions lensed about the field centre"),
        **(
            {INNER_CARD: (s.inner_border, "border outside the inner region [pixels]")}
            if s.inner_border > 0
            else {}
        ),
        "PSFSZ": (s.psf_size, "side of the PSF images, pixels"),
        **(
            {"MINSEP": (s.min_separation, "galaxy centres at least this far apart, px")}
            if s.min_separation > 0
            else {}
        ),
        **_defect_cards(s),
        "XYORIGIN": (1, "x, y are FITS 1-based pixel coordinates"),
        "NOISE": (
            config.noise.type if config.noise.override_sigma is None else "gaussian",
            "noise model",
        ),
        "CFGFILE": (config.path.rsplit("/", 1)[-1], "simulation config file"),
        "CFGSHA": (config.sha256, "sha256 of the config file"),
    }
    if config.overrides:
        cards["CFGOVR"] = (" ".join(config.overrides), "config overrides (full set in CONFIG HDU)")
    return cards


def _defect_cards(s: SceneSpec) -> dict[str, Any]:
    """The cards of the stars, saturation and bad columns that are set."""
    cards: dict[str, Any] = {}
    if s.star_density > 0:
        cards["STARDENS"] = (s.star_density, "mean stars per arcmin2 (not sheared)")
        cards["STARFMIN"] = (s.star_flux_min, "smallest star flux (log-uniform)")
        cards["STARFMAX"] = (s.star_flux_max, "largest star flux")
    if s.saturation > 0:
        cards["SATURATE"] = (s.saturation, f"saturation level (MSK bit {MASK_SATURATED})")
    if s.bad_columns > 0:
        cards["BADCOLS"] = (
            s.bad_columns,
            f"mean bad columns per field (MSK bit {MASK_BAD_COLUMN})"[:68],
        )
    return cards


def plan_text(config: SimConfig, seed: int) -> str:
    """What drawing the scenes of ``config`` will do, in one line."""
    s = scene_spec(config)
    counts = field_counts(config, seed)
    return (
        f'{s.n_fields} field(s) of {s.size}x{s.size} px at {s.pixel_scale:g}"/px'
        + (" drawn at +g and -g" if s.pairs else "")
        + f" ({s.n_images} images), {s.density:g} galaxies/arcmin² = {s.mean_count:.1f} per "
        f"field on average ({int(counts.sum())} in all)"
        + (f", {s.star_density:g} stars/arcmin²" if s.star_density > 0 else "")
        + (f", saturation at {s.saturation:g}" if s.saturation > 0 else "")
        + (f", {s.bad_columns:g} bad columns per field" if s.bad_columns > 0 else "")
    )
