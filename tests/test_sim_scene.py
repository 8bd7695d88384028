"""Scenes (``megalut simulate --scene``, ``sim/scene.py`` and ``sim/scene_config.py``):
galaxy counts and positions, fluxes, ±g pairs with the same noise, the PSF image, a shear
seen by adaptive moments, determinism, the products and bad input."""

from __future__ import annotations

import fitsio
import galsim
import numpy as np
import pytest
from helpers import error_line, one_line
from scipy.stats import norm
from sim_configs import BULGEDISK, CF_FILE, COSMOSFIT, NOISE_ONLY, write

import megalut_cli.sim.scene as scene_module
from megalut_cli.errors import ConfigError, MegalutError
from megalut_cli.sim.config import load_config
from megalut_cli.sim.scene import (
    draw_field,
    draw_scenes,
    field_counts,
    field_units,
    scene_cards,
    separated_positions,
)
from megalut_cli.sim.scene_config import MASK_BAD_COLUMN, MASK_SATURATED

#: Round exponential galaxies, a Gaussian PSF, white noise; a constant shear.
SCENE = """
[structure]
stamp_size = 48

[shear]
g1 = 0.04
g2 = -0.02

[galaxy]
profile = "sersic"
sersicn = 1.0
rad = {type = "uniform", min = 1.5, max = 3.0}
flux = {type = "uniform", min = 100.0, max = 300.0}
ellipticity = {type = "uniform", min = 0.0, max = 0.4}

[psf]
type = "gaussian"
sigma = 1.5

[noise]
type = "gaussian"
sigma = 1.0

[scene]
density = 100
size = 96
pixel_scale = 0.2
n_fields = 2
pairs = true
"""


def scene_config(tmp_path, text: str = SCENE, **replace: str):
    return load_config(write(tmp_path, text, replace=replace or None), scene=True)


@pytest.mark.parametrize("border", [8, -12])
def test_galaxy_counts_follow_the_density(tmp_path, border):
    """Counts of mean density × the square inside ``border``; a negative border puts
    centres beyond the edges, whose light reaches into the field."""
    cfg = scene_config(tmp_path, **{"n_fields = 2": f"n_fields = 400\nborder = {border}"})
    s = cfg.scene
    area = ((96 - 2 * border) * 0.2 / 60.0) ** 2  # arcmin², inside the border
    mean = 100 * area * 400
    counts = field_counts(cfg, seed=5)
    assert abs(counts.sum() - mean) < 5 * np.sqrt(mean), (counts.sum(), mean)
    assert s.mean_count == pytest.approx(100 * area)
    # a field holds as many galaxies as counted, all inside the border (FITS 1-based pixels)
    lo, hi = 0.5 + border, 96.5 - border
    outside, light_in = 0, 0.0
    for unit in field_units(cfg, 5)[:4]:
        drawn = draw_field(unit)
        x, y = drawn.truth["x"], drawn.truth["y"]
        assert len(x) == counts[unit.field] > 0
        assert np.all((x >= lo) & (x <= hi) & (y >= lo) & (y <= hi))
        beyond = (x < 0.5) | (x > 96.5) | (y < 0.5) | (y > 96.5)
        outside += int(beyond.sum())
        light_in += float(drawn.flux_drawn[0][beyond].sum())
        assert np.all(drawn.flux_drawn[0][beyond] < drawn.truth["tru_flux"][beyond])
    assert (outside > 0 and light_in > 0) == (border < 0)


def test_min_separation_keeps_galaxies_apart(tmp_path):
    """``scene.min_separation``: every pair of a field at least that far apart, inside the
    border, as many galaxies as counted; 0 draws the very same pixels as no key."""
    d = 20.0
    cfg = scene_config(
        tmp_path,
        **{
            "n_fields = 2": f"n_fields = 40\nborder = 8\nmin_separation = {d}",
            "density = 100": "density = 60",
        },
    )
    assert cfg.scene.min_separation == d and cfg.scene.coverage < 0.3
    counts = field_counts(cfg, seed=5)
    closest = []
    for unit in field_units(cfg, 5):
        t = draw_field(unit).truth
        x, y = t["x"], t["y"]
        assert len(x) == counts[unit.field]
        assert np.all((x >= 8.5) & (x <= 88.5) & (y >= 8.5) & (y <= 88.5))
        if len(x) > 1:
            dist = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
            closest.append(dist[np.triu_indices(len(x), 1)].min())
    assert min(closest) >= d and min(closest) < 1.5 * d  # apart, yet packed
    assert scene_cards(cfg, 5)["MINSEP"][0] == d
    # the default: independent positions, the same pixels with min_separation = 0
    plain = scene_config(tmp_path)
    zero = scene_config(tmp_path, **{"n_fields = 2": "n_fields = 2\nmin_separation = 0"})
    np.testing.assert_array_equal(draw_scenes(zero, 3).images, draw_scenes(plain, 3).images)
    assert "MINSEP" not in scene_cards(zero, 3)


def test_a_jammed_placement_starts_again(monkeypatch):
    """A count in the Poisson tail that jams the square (25 galaxies 34 px apart in the
    isolated recipe's 186-px square: random sequential placement stops at galaxy 24 for
    this draw) is placed by starting the field again; a field that does not jam draws what
    one start draws; no place at all is still one line naming the keys to lower."""
    lo, hi, d = 32.5, 218.5, 34.0

    def place(seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        return separated_positions(rng.uniform(lo, hi, (25, 2)), rng, lo, hi, d, 0)

    xy = place(0)
    dist = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    assert len(xy) == 25 and dist[np.triu_indices(25, 1)].min() >= d
    assert np.all((xy >= lo) & (xy < hi))
    unjammed = place(1)
    monkeypatch.setattr(scene_module, "MAX_PLACEMENT_STARTS", 1)  # one start: as before
    with pytest.raises(MegalutError, match="galaxy 24 of 25 found no place"):
        place(0)
    np.testing.assert_array_equal(place(1), unjammed)
    monkeypatch.setattr(scene_module, "MAX_PLACEMENT_DRAWS", 50)
    monkeypatch.setattr(scene_module, "MAX_PLACEMENT_STARTS", 3)
    with pytest.raises(MegalutError, match="each of 3 placements .* scene.min_separation"):
        separated_positions(np.zeros((3, 2)), np.random.default_rng(0), 0.0, 1.0, 5.0, 7)


def test_fluxes_and_noise_add_up(tmp_path):
    cfg = scene_config(tmp_path, **{"density = 100": "density = 40"})
    unit = next(u for u in field_units(cfg, 2) if u.n_galaxies > 3)
    drawn = draw_field(unit)
    for j in range(2):
        clean = drawn.images[j].astype(np.float64) - drawn.noise
        # the image is the galaxies' drawn flux plus the noise field
        assert clean.sum() == pytest.approx(drawn.flux_drawn[j].sum(), rel=1e-4)
        # and the truth flux, within the noise (sigma 1 per pixel) and what edges cut
        assert abs(drawn.images[j].sum() - drawn.truth["tru_flux"].sum()) < (
            5 * 96 + (drawn.truth["tru_flux"] - drawn.flux_drawn[j]).sum() + 1.0
        )
    inside = (np.minimum(drawn.truth["x"], drawn.truth["y"]) > 24) & (
        np.maximum(drawn.truth["x"], drawn.truth["y"]) < 72
    )
    np.testing.assert_allclose(
        drawn.flux_drawn[0][inside], drawn.truth["tru_flux"][inside], rtol=0.01
    )
    assert np.std(drawn.noise) == pytest.approx(1.0, rel=0.05)
    np.testing.assert_array_equal(drawn.weight, 1.0)
    np.testing.assert_array_equal(drawn.mask, 0)


def test_pairs_share_galaxies_and_noise(tmp_path):
    cfg = scene_config(tmp_path)
    scenes = draw_scenes(cfg, seed=3)
    t, table = scenes.truth, scenes.image_table
    np.testing.assert_array_equal(table["pair_sign"], [1, -1, 1, -1])
    np.testing.assert_array_equal(table["field"], [0, 0, 1, 1])
    np.testing.assert_allclose(table["tru_g1"], [0.04, -0.04, 0.04, -0.04])
    for f in (0, 1):
        plus = (t["field"] == f) & (t["pair_sign"] == 1)
        minus = (t["field"] == f) & (t["pair_sign"] == -1)
        for name in ("galaxy", "tru_flux", "tru_rad", "tru_e1", "tru_e2"):
            np.testing.assert_array_equal(t[name][plus], t[name][minus])
        # the positions are lensed by each image's own shear (scene.shear_positions)
        assert not np.array_equal(t["x"][plus], t["x"][minus])
        np.testing.assert_array_equal(t["tru_g1"][minus], -t["tru_g1"][plus])
        np.testing.assert_array_equal(t["tru_g2"][minus], -t["tru_g2"][plus])
        assert np.all(t["tru_g1"][plus] == 0.04)
        # the images differ only where galaxies are: far from all of them, not at all
        diff = scenes.images[2 * f] - scenes.images[2 * f + 1]
        yy, xx = np.mgrid[1:97, 1:97]
        far = np.ones(diff.shape, bool)
        for x, y in zip(t["x"][plus | minus], t["y"][plus | minus]):
            far &= np.maximum(abs(xx - x), abs(yy - y)) > 25  # beyond half a 48-px stamp
        assert far.any()
        assert np.all(diff[far] == 0.0)
        assert np.abs(diff).max() > 0.01
    # the noise of the two images of a field is the same field of noise (to float32 rounding
    # where galaxies are; exactly elsewhere, above)
    drawn = draw_field(field_units(cfg, 3)[0])
    clean = drawn.images.astype(np.float64) - drawn.noise
    np.testing.assert_allclose(drawn.images[0] - clean[0], drawn.noise, atol=2e-5, rtol=0)
    np.testing.assert_allclose(drawn.images[1] - clean[1], drawn.noise, atol=2e-5, rtol=0)


def test_stars_saturation_and_bad_columns(tmp_path):
    """Stars are the PSF times their flux, unsheared (the same pixels in both images of a
    pair); saturated pixels are clipped and masked per image; bad columns are NaN and masked
    in both; galaxies and noise are those of the scene without them."""
    extra = "n_fields = 2\nstar_density = 300\nstar_flux_min = 2e3\nstar_flux_max = 2e5"
    cfg = scene_config(tmp_path, **{"n_fields = 2": extra + "\nbad_columns = 2"})
    plain = draw_field(field_units(scene_config(tmp_path), 5)[1])
    unit = field_units(cfg, 5)[1]
    drawn = draw_field(unit)
    n_stars = len(drawn.stars["x"])
    assert 0 < n_stars < 3 * 300 * (96 * 0.2 / 60) ** 2
    assert np.all((2e3 <= drawn.stars["flux"]) & (drawn.stars["flux"] <= 2e5))
    columns = np.flatnonzero(drawn.mask[0].any(axis=0))
    assert 1 <= len(columns) and np.all(drawn.mask[:, :, columns] == MASK_BAD_COLUMN)
    assert np.isnan(drawn.images[:, :, columns]).all()
    good = np.setdiff1d(np.arange(96), columns)
    starlight = drawn.images[:, :, good].astype(np.float64) - plain.images[:, :, good]
    # the same starlight in both images, and its flux that of the stars (each a Gaussian
    # of sigma 1.5 px: its integral over the field's good pixels)
    np.testing.assert_allclose(starlight[0], starlight[1], atol=0.05)

    def within(lo, hi, centre):
        return norm.cdf((hi - centre) / 1.5) - norm.cdf((lo - centre) / 1.5)

    fraction = within(0.5, 96.5, drawn.stars["x"]) - sum(
        within(c + 0.5, c + 1.5, drawn.stars["x"]) for c in columns
    )
    expected = np.sum(drawn.stars["flux"] * fraction * within(0.5, 96.5, drawn.stars["y"]))
    assert starlight[0].sum() == pytest.approx(expected, rel=1e-3)
    assert np.all(starlight[0] > -0.05)
    # saturation: clipped at the level and masked, per image
    level = float(np.nanmax(drawn.images)) / 2
    cfg = scene_config(tmp_path, **{"n_fields = 2": f"{extra}\nsaturation = {level}"})
    sat = draw_field(field_units(cfg, 5)[1])
    assert sat.stars["x"].tolist() == drawn.stars["x"].tolist()
    clipped = sat.mask == MASK_SATURATED
    assert clipped.any() and np.all(sat.images[clipped] == np.float32(level))
    np.testing.assert_array_equal(sat.mask[~clipped], 0)
    assert np.nanmax(sat.images) == np.float32(level)
    full = drawn.images.copy()
    full[:, :, columns] = sat.images[:, :, columns]
    np.testing.assert_array_equal(sat.images[~clipped], full[~clipped])


def test_a_sequence_of_shears_goes_field_by_field(tmp_path):
    """``{type = "sequence"}``: field k takes the k-th value (cycling), whatever the seed."""
    text = SCENE.replace("g1 = 0.04", 'g1 = {type = "sequence", values = [0.04, 0.0, -0.02]}')
    text = text.replace("n_fields = 2", "n_fields = 4")
    cfg = scene_config(tmp_path, text)
    for seed in (1, 2):
        g1 = [draw_field(u).g1 for u in field_units(cfg, seed)]
        assert g1 == [0.04, 0.0, -0.02, 0.04]


def test_psf_image_at_the_field_centre(tmp_path):
    scenes = draw_scenes(scene_config(tmp_path), seed=1)
    psf = scenes.psfs[0]
    assert psf.shape == (33, 33)
    assert psf.sum() == pytest.approx(1.0, abs=1e-6)
    assert np.unravel_index(np.argmax(psf), psf.shape) == (16, 16)
    mom = galsim.hsm.FindAdaptiveMom(galsim.ImageF(psf, scale=1.0))
    assert mom.moments_centroid.x == pytest.approx(17.0, abs=1e-3)  # 1-based centre
    # the Gaussian PSF of sigma 1.5 px, convolved with the pixel
    assert mom.moments_sigma == pytest.approx(np.sqrt(1.5**2 + 1 / 12), rel=0.02)


def test_a_known_shear_is_seen_by_adaptive_moments(tmp_path):
    """Noiseless round galaxies at low density: the mean adaptive-moment shape of cutouts
    around the true positions moves with +g and -g by about the expected amount."""
    g = 0.05
    cfg = scene_config(
        tmp_path,
        **{
            "g1 = 0.04\ng2 = -0.02": f"g1 = {g}\ng2 = 0.0",
            'ellipticity = {type = "uniform", min = 0.0, max = 0.4}': "ellipticity = 0.0",
            'rad = {type = "uniform", min = 1.5, max = 3.0}': "rad = 2.5",
            'type = "gaussian"\nsigma = 1.0': 'type = "none"',
            "density = 100": "density = 30",
            "size = 96": "size = 256\nborder = 16",
            "n_fields = 2": "n_fields = 3",
        },
    )
    scenes = draw_scenes(cfg, seed=7)
    t = scenes.truth
    psf_sigma = galsim.hsm.FindAdaptiveMom(galsim.ImageF(scenes.psfs[0])).moments_sigma
    shapes = {1: [], -1: []}
    sigmas = []
    for i in range(len(scenes.images)):
        rows = np.flatnonzero(t["image"] == i)
        x, y = t["x"][rows], t["y"][rows]
        for k in range(len(rows)):
            others = np.hypot(x - x[k], y - y[k])
            if np.sort(others)[1:2].min(initial=1e9) < 24:  # a neighbour: left out
                continue
            ix, iy = int(round(x[k])), int(round(y[k]))
            cut = scenes.images[i][iy - 1 - 12 : iy - 1 + 12, ix - 1 - 12 : ix - 1 + 12]
            mom = galsim.hsm.FindAdaptiveMom(galsim.ImageF(np.ascontiguousarray(cut)))
            shapes[int(t["pair_sign"][rows[k]])].append(
                (mom.observed_shape.g1, mom.observed_shape.g2)
            )
            sigmas.append(mom.moments_sigma)
    plus, minus = np.mean(shapes[1], axis=0), np.mean(shapes[-1], axis=0)
    assert len(shapes[1]) >= 10
    # the PSF dilutes the shear by about the resolution 1 - sigma_psf² / sigma_obs²
    expected = g * (1.0 - psf_sigma**2 / np.mean(sigmas) ** 2)
    response = (plus[0] - minus[0]) / 2.0
    assert response > 0
    assert response == pytest.approx(expected, rel=0.15), (response, expected)
    assert abs(plus[1]) < 0.002 and abs(minus[1]) < 0.002


@pytest.mark.parametrize("shear_positions", [True, False])
def test_positions_are_lensed_about_the_field_centre(tmp_path, shear_positions):
    """With ``shear_positions`` (the default) each image's galaxies sit where the image's
    shear takes them about the field's centre, as on the sky: the light's centroids
    (adaptive moments, noiseless, no neighbour within 20 px) at the truth table's ``x, y``,
    which are the source positions moved by (g1, g2) for +g and (-g1, -g2) for -g; without
    it, at the source positions in both images."""
    g1, g2, size = 0.06, -0.04, 256
    flag = str(shear_positions).lower()
    cfg = scene_config(
        tmp_path,
        **{
            "g1 = 0.04\ng2 = -0.02": f"g1 = {g1}\ng2 = {g2}",
            'type = "gaussian"\nsigma = 1.0': 'type = "none"',
            "density = 100": "density = 30",
            "size = 96": f"size = {size}\nborder = 16\nshear_positions = {flag}",
        },
    )
    scenes = draw_scenes(cfg, seed=11)
    t = scenes.truth
    plus, minus = t["pair_sign"] == 1, t["pair_sign"] == -1
    c = (size + 1) / 2.0
    dx, dy = t["x"][plus] - c, t["y"][plus] - c
    # the -g image's positions are the +g image's moved by -g twice over: undo both
    ux, uy = t["x"][minus] - c, t["y"][minus] - c
    norm = np.sqrt(1 - g1**2 - g2**2)
    if shear_positions:
        # the source positions: +g's positions with the inverse of the shear matrix
        sx, sy = ((1 - g1) * dx - g2 * dy) / norm, (-g2 * dx + (1 + g1) * dy) / norm
        np.testing.assert_allclose(((1 - g1) * sx - g2 * sy) / norm, ux, atol=1e-9)
        np.testing.assert_allclose((-g2 * sx + (1 + g1) * sy) / norm, uy, atol=1e-9)
        assert np.max(np.hypot(ux - dx, uy - dy)) > 0.5
    else:
        np.testing.assert_array_equal(ux, dx)
        np.testing.assert_array_equal(uy, dy)
    offsets = []
    for i in range(len(scenes.images)):
        rows = np.flatnonzero(t["image"] == i)
        x, y = t["x"][rows], t["y"][rows]
        for k in range(len(rows)):
            if np.sort(np.hypot(x - x[k], y - y[k]))[1:2].min(initial=1e9) < 20:
                continue
            ix, iy = int(round(x[k])), int(round(y[k]))
            if min(ix, iy) < 13 or max(ix, iy) > size - 12:
                continue
            cut = scenes.images[i][iy - 13 : iy + 11, ix - 13 : ix + 11]
            mom = galsim.hsm.FindAdaptiveMom(galsim.ImageF(np.ascontiguousarray(cut)))
            # the cut's pixel (1, 1) is the image's (ix - 12, iy - 12)
            offsets.append(
                (mom.moments_centroid.x + ix - 13 - x[k], mom.moments_centroid.y + iy - 13 - y[k])
            )
    offsets = np.array(offsets)
    assert len(offsets) >= 20
    assert np.max(np.abs(offsets)) < 0.02, np.max(np.abs(offsets))
    assert scene_cards(cfg, 11)["SHEARPOS"][0] is shear_positions


def test_a_lensed_scene_is_the_unlensed_scene_sheared_as_a_whole(tmp_path):
    """Noiseless, a nearly point-like PSF: the scene drawn at shear g is GalSim's shear of
    the whole unsheared scene about the field's centre (an InterpolatedImage of it), to the
    PSF's and the pixel's own shear (4.9 % of the peak at most); shearing the profiles
    only leaves the neighbours where they were, and the images differ by the galaxies
    (85 %)."""
    g1, g2, size = 0.1, 0.05, 128

    def image(g1: float, g2: float, lensed: bool) -> np.ndarray:
        cfg = scene_config(
            tmp_path,
            **{
                "g1 = 0.04\ng2 = -0.02": f"g1 = {g1}\ng2 = {g2}",
                'type = "gaussian"\nsigma = 1.0': 'type = "none"',
                "sigma = 1.5": "sigma = 0.5",
                "size = 96": f"size = {size}\nborder = 24\nshear_positions = {str(lensed).lower()}",
                "n_fields = 2": "n_fields = 1",
                "pairs = true": "pairs = false",
            },
        )
        return draw_scenes(cfg, seed=5).images[0].astype(np.float64)

    whole = galsim.InterpolatedImage(galsim.ImageD(image(0.0, 0.0, True), scale=1.0))
    sheared = whole.shear(g1=g1, g2=g2).drawImage(nx=size, ny=size, scale=1.0, method="no_pixel")
    inner = slice(16, size - 16)
    for lensed, within in ((True, 0.07), (False, None)):
        drawn = image(g1, g2, lensed)
        diff = np.abs(drawn - sheared.array)[inner, inner].max() / drawn.max()
        if within:
            assert diff < within, diff
        else:
            assert diff > 0.3, diff


def test_the_seed_decides_every_pixel(tmp_path):
    cfg = scene_config(tmp_path)
    a, b = draw_scenes(cfg, seed=4), draw_scenes(cfg, seed=4)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.truth["x"], b.truth["x"])
    c = draw_scenes(cfg, seed=5)
    assert not np.array_equal(a.truth["x"][:3], c.truth["x"][:3])
    # a field is the same drawn alone or among others
    more = load_config(write(tmp_path, SCENE.replace("n_fields = 2", "n_fields = 3")), scene=True)
    np.testing.assert_array_equal(draw_scenes(more, seed=4).images[:4], a.images)


@pytest.mark.parametrize(
    "replace",
    [
        {"n_fields = 2": "n_fields = 3\nborder = -20"},  # light from beyond the edges too
        {
            "sersicn = 1.0": 'sersicn = {type = "uniform", min = 0.8, max = 4.0}',
            'rad = {type = "uniform", min = 1.5, max = 3.0}': "rad = 7.0",  # capped stamps
            "n_fields = 2": "n_fields = 1\nshear_positions = false",
        },
        {'profile = "sersic"\nsersicn = 1.0': 'profile = "gaussian"'},
    ],
    ids=["exponential", "sersic", "gaussian"],
)
def test_the_fast_engine_draws_galsims_scenes(tmp_path, replace):
    """The batched renderer's scenes are GalSim's within 1e-6 of the peak pixel (docs/
    engines.md's tolerance), galaxy by galaxy on the field's pixels (``tru_flux_drawn``);
    the noise, positions and truth identical."""
    cfg = scene_config(tmp_path, **replace)
    fast, ref = draw_scenes(cfg, seed=6, engine="fast"), draw_scenes(cfg, seed=6, engine="galsim")
    for name in ref.truth:
        if name != "tru_flux_drawn":
            np.testing.assert_array_equal(fast.truth[name], ref.truth[name], err_msg=name)
    np.testing.assert_allclose(
        fast.truth["tru_flux_drawn"], ref.truth["tru_flux_drawn"], rtol=1e-6, atol=1e-4
    )
    noise = np.stack([draw_field(u).noise for u in field_units(cfg, 6, "galsim")])
    clean = ref.images - np.repeat(noise, 2, axis=0)
    assert np.abs(clean).max() > 1  # galaxies, not noise
    assert np.abs(fast.images - ref.images).max() <= 1e-6 * np.abs(clean).max()
    assert scene_cards(cfg, 6, "fast")["ENGINE"][0] == "fast"


def test_profiles_the_renderer_cannot_draw_go_through_galsim(tmp_path):
    """Knots (or any profile but a single Sersic or Gaussian): GalSim's pixels whatever the
    engine, and the ENGINE card says so."""
    cfg = scene_config(
        tmp_path, **{"sersicn = 1.0": "sersicn = 1.0\nknots = 5\nknots_fraction = 0.3"}
    )
    fast, ref = draw_scenes(cfg, seed=6, engine="fast"), draw_scenes(cfg, seed=6, engine="galsim")
    np.testing.assert_array_equal(fast.images, ref.images)
    assert scene_cards(cfg, 6, "fast")["ENGINE"][0] == "galsim"


@pytest.mark.parametrize(
    "engine, message",
    [("fast", "scene field 0: drawFFT requires"), ("galsim", "scene field 0, galaxy 0: FFT too")],
)
def test_an_fft_beyond_the_cap_stops_either_engine_naming_the_field(tmp_path, engine, message):
    """An FFT beyond gsparams.maximum_fft_size: one line naming the scene field, whichever
    engine draws (GalSim 2.7+ would only warn and draw)."""
    cfg = scene_config(tmp_path, **{"[psf]": "[gsparams]\nmaximum_fft_size = 32\n\n[psf]"})
    with pytest.raises(MegalutError, match="^" + message) as err:
        draw_scenes(cfg, seed=6, engine=engine)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "text",
    [BULGEDISK, COSMOSFIT, NOISE_ONLY.replace("SOURCE", f'correlation = "{CF_FILE}"\nsigma = 1.5')],
    ids=["bulgedisk", "cosmos_fit", "correlated-noise"],
)
def test_other_profiles_and_noises(tmp_path, text):
    text += "\n[scene]\ndensity = 60\nsize = 64\npixel_scale = 0.2\npairs = true\n"
    cfg = load_config(write(tmp_path, text), scene=True)
    scenes = draw_scenes(cfg, seed=2)
    assert scenes.images.shape == (2, 64, 64)
    assert np.all(np.isfinite(scenes.images))
    n = int(scenes.image_table["n_gal"][0])
    assert len(scenes.truth["x"]) == 2 * n
    drawn = draw_field(field_units(cfg, 2)[0])
    np.testing.assert_array_equal(
        drawn.images[0] - drawn.images[1] == 0, drawn.images[0] == drawn.images[1]
    )
    if "correlated" in text:  # noise-only galaxies (flux 0): the pair is identical
        np.testing.assert_array_equal(drawn.images[0], drawn.images[1])
        assert np.std(drawn.noise) == pytest.approx(1.5, rel=0.2)
        # correlated: neighbouring pixels covary
        r = np.corrcoef(drawn.noise[:, :-1].ravel(), drawn.noise[:, 1:].ravel())[0, 1]
        assert r > 0.1


@pytest.mark.parametrize(
    "replace, key",
    [
        ({"density = 100": "density = 0"}, "scene.density"),
        ({"size = 96": "size = 8"}, "scene.size"),
        ({"n_fields = 2": "n_fields = 2\nborder = 48"}, "scene.border"),
        ({"n_fields = 2": "n_fields = 2\nborder = -48"}, "scene.border"),
        ({"n_fields = 2": "n_fields = 2\ninner_border = 48"}, "scene.inner_border"),
        ({"n_fields = 2": "n_fields = 2\ninner_border = -1"}, "scene.inner_border"),
        ({"n_fields = 2": "n_fields = 2\npsf_size = 32"}, "scene.psf_size"),
        ({"pixel_scale = 0.2": ""}, "scene.pixel_scale"),
        ({"pixel_scale = 0.2": "pixel_scale = 0.2\ncolour = 1"}, "scene.colour"),
        ({"[scene]": "[instrument]\npixel_scale = 0.1\n[scene]"}, "scene.pixel_scale"),
        ({"n_fields = 2": "n_fields = 2\nmin_separation = -1"}, "scene.min_separation"),
        (
            {"n_fields = 2": "n_fields = 2\nborder = 20\nmin_separation = 60"},
            "scene.min_separation",
        ),
        ({"n_fields = 2": "n_fields = 2\nmin_separation = 30"}, "scene.min_separation"),
        ({"n_fields = 2": "n_fields = 2\nstar_flux_max = 10"}, "scene.star_flux_max"),
        ({"n_fields = 2": "n_fields = 2\nstar_flux_min = 0"}, "scene.star_flux_min"),
        ({"n_fields = 2": "n_fields = 2\nsaturation = -1"}, "scene.saturation"),
        ({"n_fields = 2": "n_fields = 2\nbad_columns = -1"}, "scene.bad_columns"),
    ],
)
def test_bad_scene_keys_are_refused(tmp_path, replace, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        scene_config(tmp_path, **replace)


def test_the_command_writes_both_products(runner, cli, tmp_path):
    cfg = write(tmp_path, SCENE.replace("pairs = true", "pairs = false"))
    truth, images = tmp_path / "truth.fits", tmp_path / "scenes.fits"
    args = ["simulate", str(cfg), "-o", str(truth), "--scene", str(images), "--pairs", "-j", "1"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    with fitsio.FITS(str(images)) as f:
        assert [h.get_extname() for h in f] == ["SCI", "WGT", "MSK", "PSF", "IMAGES"]
        sci = f["SCI"].read()
        assert sci.shape == (4, 96, 96) and sci.dtype == np.float32
        assert f["WGT"].read().shape == (4, 96, 96)
        assert f["MSK"].read().shape == (4, 96, 96)
        assert f["PSF"].read().shape == (4, 33, 33)
        table = f["IMAGES"].read()
        assert f["SCI"].read_header()["PAIRS"] is True
    np.testing.assert_array_equal(table["pair_sign"], [1, -1, 1, -1])
    rows = fitsio.read(str(truth), ext="CATALOG")
    assert len(rows) == table["n_gal"].sum()
    for name in ("field", "pair_sign", "x", "y", "tru_flux", "tru_rad", "tru_g1", "tru_g2"):
        assert name in rows.dtype.names
    # the same pixels from two workers; an existing output is refused, nothing replaced
    before = images.stat().st_mtime_ns
    result = runner.invoke(cli, args)
    error_line(result, 1, "exists")
    assert images.stat().st_mtime_ns == before
    other = tmp_path / "j2.fits"
    args2 = ["simulate", str(cfg), "-o", str(tmp_path / "t2.fits"), "--scene", str(other)]
    result = runner.invoke(cli, [*args2, "--pairs", "-j", "2"])
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(fitsio.read(str(other), ext="SCI"), sci)


def test_the_stars_table_and_cards(runner, cli, tmp_path):
    cfg = write(tmp_path, SCENE)
    truth, images = tmp_path / "truth.fits", tmp_path / "scenes.fits"
    extra = ["scene.star_density=200", "scene.saturation=500", "scene.bad_columns=3"]
    args = ["simulate", str(cfg), "-o", str(truth), "--scene", str(images), *extra]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    stars = fitsio.read(str(truth), ext="STARS")
    assert set(stars.dtype.names) == {"image", "field", "pair_sign", "x", "y", "flux"}
    np.testing.assert_array_equal(np.unique(stars["image"]), [0, 1, 2, 3])
    header = fitsio.read_header(str(images), ext="SCI")
    assert (header["STARDENS"], header["SATURATE"], header["BADCOLS"]) == (200.0, 500.0, 3.0)
    masks = fitsio.read(str(images), ext="MSK")
    assert np.any(masks & MASK_BAD_COLUMN) and np.any(masks & MASK_SATURATED)


@pytest.mark.parametrize(
    "extra, code, words",
    [
        (["--pairs"], 2, ("--pairs needs --scene",)),
        (["--scene", "S.fits", "--measure"], 2, ("--measure",)),
        (["--scene", "S.fits", "--n-cases", "3"], 2, ("--n-cases",)),
        (["--scene", "S.fits", "scene.density=-1"], 2, ("density",)),
        (["--scene", "S.fits", "scene.n_fields=100000", "scene.size=4096"], 1, ("memory",)),
    ],
)
def test_bad_input_one_line_and_nothing_written(runner, cli, tmp_path, extra, code, words):
    cfg = write(tmp_path, SCENE)
    out = tmp_path / "t.fits"
    extra = [str(tmp_path / e) if e == "S.fits" else e for e in extra]
    result = runner.invoke(cli, ["simulate", str(cfg), "-o", str(out), *extra])
    error_line(result, code, *words)
    assert not out.exists() and not (tmp_path / "S.fits").exists()


def test_a_missing_table_key_names_the_file(runner, cli, tmp_path):
    cfg = write(tmp_path, SCENE.replace("pixel_scale = 0.2", ""))
    result = runner.invoke(
        cli, ["simulate", str(cfg), "-o", str(tmp_path / "t.fits"), "--scene", "s.fits"]
    )
    assert result.exit_code == 2
    assert "pixel_scale" in one_line(result)
