"""Galaxy models beyond a single Sersic: bulge + disk, knots, COSMOS parametric fits.

Flux, half-light radius and ellipticity of the drawn light are checked against what the
parameters imply, on large noiseless stamps sampled at pixel centres (no pixel response,
no PSF), with stated tolerances.
"""

from __future__ import annotations

import math
from pathlib import Path

import fitsio
import galsim
import numpy as np
import pytest
from scipy.special import gamma
from sim_configs import BULGEDISK, COSMOS, COSMOSFIT, write

from megalut_cli.catalog import read_catalog
from megalut_cli.errors import ConfigError
from megalut_cli.sim.config import load_config
from megalut_cli.sim.galaxies import galaxy_profile, oriented
from megalut_cli.sim.profiles import cosmos_fit
from megalut_cli.sim.profiles.common import composite_hlr, sersic_b
from megalut_cli.sim.simulate import simulate
from megalut_cli.sim.structure import draw_case

N_IMG = 512  # stamp side for the light-integration tests (pixels)


def row(**values: float) -> dict[str, np.ndarray]:
    """A one-row truth table."""
    return {k: np.array([v]) for k, v in values.items()}


def bulgedisk_row(**changes: float) -> dict[str, np.ndarray]:
    values = dict(
        tru_flux=1000.0,
        tru_rad=np.nan,
        tru_ell=0.0,
        tru_disk_rad=8.0,
        tru_disk_sersicn=1.0,
        tru_bulge_fraction=0.4,
        tru_bulge_rad=3.0,
        tru_bulge_sersicn=4.0,
        tru_bulge_ell=0.0,
        tru_bulge_dtheta=0.0,
        tru_bulge_dx=0.0,
        tru_bulge_dy=0.0,
        tru_g1=0.0,
        tru_g2=0.0,
        tru_e1=0.0,
        tru_e2=0.0,
    )
    values.update(changes)
    return row(**values)


def draw(obj: galsim.GSObject, n: int = N_IMG, method: str = "no_pixel") -> np.ndarray:
    """Surface brightness sampled at pixel centres (``no_pixel``) or the light integrated
    over each pixel (``auto``, needed where the profile is cuspy: n = 4 centres)."""
    return obj.drawImage(nx=n, ny=n, scale=1.0, method=method).array.astype(np.float64)


def radii(n: int = N_IMG) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[:n, :n] - (n - 1) / 2.0  # drawImage centres the profile on the true centre
    return x, y


def unweighted_chi(img: np.ndarray) -> complex:
    """Distortion (Q11 - Q22 + 2i Q12) / (Q11 + Q22) of the unweighted second moments."""
    x, y = radii(img.shape[0])
    f = img.sum()
    xc, yc = (img * x).sum() / f, (img * y).sum() / f
    q11 = (img * (x - xc) ** 2).sum() / f
    q22 = (img * (y - yc) ** 2).sum() / f
    q12 = (img * (x - xc) * (y - yc)).sum() / f
    return complex(q11 - q22, 2 * q12) / (q11 + q22)


def sersic_r2(n: float, hlr: float) -> float:
    """<r^2> of an untruncated round Sersic profile."""
    return hlr**2 * gamma(4 * n) / (gamma(2 * n) * float(sersic_b(n)) ** (2 * n))


def predicted_moments(
    components: list[tuple[float, float, float, float, float, float, float]],
) -> np.ndarray:
    """Second moments of a sum of sheared Sersic profiles (flux, n, hlr, g, beta_deg, dx, dy)."""
    f = np.array([c[0] for c in components])
    centres = np.array([[c[5], c[6]] for c in components])
    mean = (f[:, None] * centres).sum(0) / f.sum()
    q = np.zeros((2, 2))
    for flux, n, hlr, g, beta, dx, dy in components:
        a = galsim.Shear(g=g, beta=beta * galsim.degrees).getMatrix()
        d = np.array([dx, dy]) - mean
        q += flux * (0.5 * sersic_r2(n, hlr) * a @ a.T + np.outer(d, d))
    return q / f.sum()


def chi_of(q: np.ndarray) -> complex:
    return complex(q[0, 0] - q[1, 1], 2 * q[0, 1]) / (q[0, 0] + q[1, 1])


# --------------------------------------------------------------------------- half-light radius


@pytest.mark.parametrize(
    "frac,ratio,nb", [(0.0, 0.5, 4.0), (1.0, 0.3, 4.0), (0.3, 0.4, 4.0), (0.7, 2.0, 2.5)]
)
def test_composite_hlr_encloses_half_of_the_drawn_light(frac, ratio, nb):
    """The composite half-light radius holds half of the light of a drawn round bulge + disk
    (integrated over pixels, flux known): |fraction - 0.5| < 0.004."""
    h = float(composite_hlr(frac, ratio, nb))
    disk_rad = 12.0 / min(1.0, ratio)  # the smaller component: 12 px, well sampled
    t = bulgedisk_row(
        tru_disk_rad=disk_rad,
        tru_bulge_rad=ratio * disk_rad,
        tru_bulge_fraction=frac,
        tru_bulge_sersicn=nb,
    )
    img = draw(galaxy_profile(t, 0), method="auto")
    x, y = radii()
    inside = img[np.hypot(x, y) <= h * disk_rad].sum() / 1000.0
    assert abs(inside - 0.5) < 0.004, (h, inside)
    assert min(1.0, ratio) <= h <= max(1.0, ratio)


def test_bulgedisk_config_sets_the_composite_radius(tmp_path):
    """profile = "bulgedisk": rad is the composite half-light radius; disk and bulge radii
    follow from the fraction and the ratio; every drawn parameter is in the truth."""
    cfg = load_config(write(tmp_path, BULGEDISK), n_cases=5, n_realizations=4)
    d = draw_case(cfg, 11, 2)
    t = d.truth
    for col in (
        "tru_bulge_fraction",
        "tru_bulge_rad",
        "tru_disk_rad",
        "tru_bulge_sersicn",
        "tru_bulge_ell",
        "tru_bulge_dtheta",
        "tru_bulge_dx",
        "tru_bulge_dy",
        "tru_knots",
        "tru_knots_fraction",
        "tru_knot_seed",
    ):
        assert col in t, col
    h = composite_hlr(
        t["tru_bulge_fraction"], t["tru_bulge_rad"] / t["tru_disk_rad"], t["tru_bulge_sersicn"]
    )
    np.testing.assert_allclose(h * t["tru_disk_rad"], t["tru_rad"], rtol=1e-10)
    assert np.all((t["tru_bulge_fraction"] >= 0.1) & (t["tru_bulge_fraction"] <= 0.5))
    assert np.all(t["tru_bulge_sersicn"] == 4.0)
    # one galaxy per case (ring): same knots for every realization
    assert len(set(t["tru_knot_seed"])) == 1
    np.testing.assert_allclose(t["tru_sb"], t["tru_flux"] / (np.pi * t["tru_rad"] ** 2))


# --------------------------------------------------------------------------- flux and shape


def test_bulgedisk_flux_and_unweighted_ellipticity():
    """A bulge (n = 2, so that its unweighted moments converge inside the stamp) and a disk of
    different ellipticities, angles and centres: drawn flux = tru_flux (1e-3) and the
    unweighted-moment distortion equals the parameters' prediction (2e-3), also after the
    galaxy is oriented at 30 degrees (prediction rotated by 60 degrees)."""
    t = bulgedisk_row(
        tru_ell=0.4,
        tru_bulge_sersicn=2.0,
        tru_bulge_ell=0.2,
        tru_bulge_dtheta=35.0,
        tru_bulge_dx=4.5,
        tru_bulge_dy=-3.0,
        tru_disk_rad=18.0,
        tru_bulge_rad=9.0,
    )
    base = galaxy_profile(t, 0)
    img = draw(base)
    assert abs(img.sum() / 1000.0 - 1.0) < 1e-3
    q = predicted_moments(
        [(600.0, 1.0, 18.0, 0.4, 0.0, 0.0, 0.0), (400.0, 2.0, 9.0, 0.2, 35.0, 4.5, -3.0)]
    )
    chi = chi_of(q)
    assert abs(unweighted_chi(img) - chi) < 2e-3, (unweighted_chi(img), chi)
    turned = draw(oriented(base, t, 0, 30.0))
    assert abs(unweighted_chi(turned) - chi * np.exp(2j * np.deg2rad(30.0))) < 2e-3


@pytest.mark.parametrize("n", [1.0, 4.0])
def test_single_component_adaptive_moments_give_its_ellipticity(n):
    """Bulge-only (n = 4) and disk-only galaxies are elliptical profiles: HSM adaptive moments
    of the noiseless stamp recover the ellipticity |e| at 2 theta (1e-3)."""
    if n == 1.0:
        t = bulgedisk_row(tru_bulge_fraction=0.0, tru_ell=0.3)
    else:
        # the adaptive weight of a de Vaucouleurs profile shrinks onto its cusp: a large one
        t = bulgedisk_row(
            tru_bulge_fraction=1.0, tru_bulge_rad=48.0, tru_bulge_ell=0.3, tru_bulge_dtheta=0.0
        )
    gal = oriented(galaxy_profile(t, 0), t, 0, 20.0)
    res = galsim.hsm.FindAdaptiveMom(
        gal.drawImage(nx=N_IMG, ny=N_IMG, scale=1.0, method="no_pixel")
    )
    expect = 0.3 * np.exp(2j * np.deg2rad(20.0))
    assert abs(complex(res.observed_shape.g1, res.observed_shape.g2) - expect) < 1e-3


def test_lensing_shear_applies_after_the_intrinsic_shape():
    """A round disk lensed by g: the adaptive-moment shape is g (5e-6)."""
    t = bulgedisk_row(tru_bulge_fraction=0.0, tru_g1=0.05, tru_g2=-0.03)
    gal = oriented(galaxy_profile(t, 0), t, 0, 73.0)
    res = galsim.hsm.FindAdaptiveMom(gal.drawImage(nx=256, ny=256, scale=1.0, method="no_pixel"))
    # achieved 1.5e-6 (g1), 4.7e-7 (g2)
    assert abs(res.observed_shape.g1 - 0.05) < 5e-6 and abs(res.observed_shape.g2 + 0.03) < 5e-6


# --------------------------------------------------------------------------- knots


def knots_row(seed: int, fraction: float = 1.0, **changes: float) -> dict[str, np.ndarray]:
    t = bulgedisk_row(**{"tru_bulge_fraction": 0.0, "tru_disk_rad": 10.0, **changes})
    t.update(row(tru_knots=50, tru_knots_fraction=fraction, tru_knot_seed=seed))
    t["tru_knots"] = t["tru_knots"].astype(np.int64)
    return t


def test_knots_flux_profile_and_seed():
    """Knots (GalSim RandomKnots) hold their flux fraction exactly; over many seeds they
    follow the disk profile (half of the knots' light inside the disk's hlr, +-0.03); the
    same seed gives the same galaxy, another seed another one."""
    psf = galsim.Gaussian(sigma=1.0)
    x, y = radii(128)
    inside = []
    for seed in range(1, 31):
        gal = galaxy_profile(knots_row(seed), 0)
        assert abs(gal.flux - 1000.0) < 1e-9
        img = galsim.Convolve(gal, psf).drawImage(nx=128, ny=128, scale=1.0).array
        inside.append(img[np.hypot(x, y) <= 10.0].sum() / img.sum())
    assert abs(np.mean(inside) - 0.5) < 0.03, np.mean(inside)
    mixed = galaxy_profile(knots_row(7, fraction=0.3, tru_bulge_fraction=0.2, tru_bulge_rad=3.0), 0)
    assert abs(mixed.flux - 1000.0) < 1e-9
    a, b, c = (
        galsim.Convolve(galaxy_profile(knots_row(seed), 0), psf)
        .drawImage(nx=64, ny=64, scale=1.0)
        .array
        for seed in (5, 5, 6)
    )
    assert np.array_equal(a, b) and not np.allclose(a, c)


def test_knot_seeds_follow_the_galaxy_draws(tmp_path):
    """Knot seeds come from their own stream: a Sersic config gains knots without changing
    its other draws, and with per-realization galaxies every galaxy has its own seed."""
    plain = load_config(write(tmp_path, name="a.toml"), n_cases=2, n_realizations=4)
    knotty = load_config(
        write(
            tmp_path,
            name="b.toml",
            replace={"angle = {type": "knots = 12\nknots_fraction = 0.2\nangle = {type"},
        ),
        n_cases=2,
        n_realizations=4,
    )
    a, b = draw_case(plain, 4, 1).truth, draw_case(knotty, 4, 1).truth
    for col in a:
        np.testing.assert_array_equal(a[col], b[col])
    assert np.all(b["tru_knots"] == 12) and len(set(b["tru_knot_seed"])) == 1
    per_rea = load_config(
        write(
            tmp_path,
            name="c.toml",
            replace={
                "angle = {type": "knots = 12\nknots_fraction = 0.2\nangle = {type",
                'snc = "ring"': 'snc = "none"',
                'per_realization = ["angle"]': 'per_realization = ["galaxy"]',
            },
        ),
        n_cases=2,
        n_realizations=4,
    )
    assert len(set(draw_case(per_rea, 4, 1).truth["tru_knot_seed"])) == 4


# --------------------------------------------------------------------------- COSMOS fits


def fit_truth(index: int, fit: str, pixel_scale: float, step: float = 0.0) -> dict[str, np.ndarray]:
    """Truth of catalog row ``index`` as the config machinery builds it."""
    data = fitsio.read(str(COSMOS))
    gvals = {"fit_ident": np.array([float(data["IDENT"][index])])}
    for part in ["sersic", "bulgedisk"] if fit == "auto" else [fit]:
        for name, (col, el) in cosmos_fit.COSMOS_FIT_COLUMNS[part].items():
            v = data[col][index] if el is None else data[col][index][el]
            gvals[name] = np.array([float(v)])
    made = cosmos_fit.fit_truth(gvals, fit, pixel_scale, step)
    t = {
        "tru_ell": made.ellipticity,
        "tru_g1": np.zeros(1),
        "tru_g2": np.zeros(1),
        "tru_flux": np.array([1.0]),
    }
    t.update(made.columns)  # tru_rad among them
    return t


@pytest.mark.parametrize(
    "index", [0, 4]
)  # row 0: single Sersic; row 4: bulge + disk (use_bulgefit)
def test_cosmos_fit_is_galsims_parametric_galaxy(index):
    """A cosmos_fit galaxy oriented at the fit's own disk angle is GalSim's parametric COSMOS
    galaxy (COSMOSCatalog._buildParametric) of that row, dilated to simulation pixels:
    images agree to 3e-7 of their peak; its tru_rad holds half of its light (+-0.003)."""
    data = fitsio.read(str(COSMOS))
    record = {name: data[name][index] for name in data.dtype.names}
    assert bool(record["use_bulgefit"]) == (index == 4)
    ref = galsim.COSMOSCatalog._buildParametric(record, 0.05, galsim.GSParams(), chromatic=False)
    scale = 0.03  # arcsec per simulation pixel: large galaxies, well sampled
    ref = ref.withFlux(1.0).dilate(1.0 / scale)
    t = fit_truth(index, "auto", scale, step=0.05)
    beta = record["bulgefit"][7] if record["use_bulgefit"] else record["sersicfit"][7]
    ours = oriented(galaxy_profile(t, 0), t, 0, math.degrees(beta))
    a, b = draw(ours, 384), draw(ref, 384)
    assert np.max(np.abs(a - b)) < 3e-7 * b.max()  # achieved 8.5e-8 (row 0), 3.9e-8 (row 4)
    x, y = radii(384)
    round_t = dict(t, tru_ell=np.zeros(1))
    if "tru_bulge_ell" in t:
        round_t["tru_bulge_ell"] = np.zeros(1)
    img = draw(galaxy_profile(round_t, 0), 384, method="auto")
    frac = img[np.hypot(x, y) <= t["tru_rad"][0]].sum()
    assert abs(frac - 0.5) < 0.003, frac  # achieved 3.6e-4 (row 0), 9.5e-4 (row 4)


def test_cosmos_fit_config_samples_usable_rows(tmp_path):
    """fit = "bulgedisk" keeps the 36 rows GalSim builds as bulge + disk; sizes in pixels of
    pixel_scale arcsec, or dilated to rad; magnitudes jointly sampled from the same row."""
    cfg = load_config(
        write(tmp_path, COSMOSFIT, replace={'fit = "auto"': 'fit = "bulgedisk"'}),
        n_cases=20,
        n_realizations=2,
    )
    assert cfg.catalog_rows == 36
    data = fitsio.read(str(COSMOS))
    by_ident = {int(i): k for k, i in enumerate(data["IDENT"])}
    for case in range(20):
        t = draw_case(cfg, 5, case).truth
        k = by_ident[int(t["tru_cosmos_ident"][0])]
        assert data["use_bulgefit"][k] == 1
        assert abs(t["tru_mag"][0] - data["mag_auto"][k]) < 1e-9
        assert abs(t["tru_disk_rad"][0] - data["hlr"][k][2] / 0.1) < 1e-9
        b = data["flux"][k][1] / (data["flux"][k][1] + data["flux"][k][2])
        assert abs(t["tru_bulge_fraction"][0] - b) < 1e-12
    sized = load_config(
        write(tmp_path, COSMOSFIT, name="r.toml", replace={"pixel_scale = 0.1": "rad = 4.0"}),
        n_cases=3,
        n_realizations=2,
    )
    t = draw_case(sized, 5, 0).truth
    assert np.allclose(t["tru_rad"], 4.0)


# --------------------------------------------------------------------------- config errors


@pytest.mark.parametrize(
    "replace,message",
    [
        (
            {'bulge_fraction = {type = "uniform", min = 0.1, max = 0.5}': "bulge_fraction = 1.5"},
            "galaxy.bulge_fraction: the bulge's flux fraction must be <= 1.0",
        ),
        (
            {'bulge_fraction = {type = "uniform", min = 0.1, max = 0.5}\n': ""},
            "galaxy.bulge_fraction: missing",
        ),
        (
            {"bulge_rad_ratio = 0.4": "bulge_rad_ratio = 0.0"},
            "galaxy.bulge_rad_ratio: the bulge-to-disk",
        ),
        ({"bulge_rad_ratio = 0.4": "bulge_sersicn = 8.0"}, "galaxy.bulge_sersicn: GalSim supports"),
        (
            {"bulge_rad_ratio = 0.4": "bulge_ellipticity = 1.0"},
            "galaxy.bulge_ellipticity: the modulus must be < 1",
        ),
        (
            {"bulge_rad_ratio = 0.4": "bulge_dx = 50.0"},
            "galaxy.bulge_dx: the bulge offset must stay",
        ),
        ({"bulge_rad_ratio = 0.4": "bulge_size = 1.0"}, "galaxy.bulge_size: unknown key"),
        ({"knots_fraction = 0.2\n": ""}, "galaxy.knots_fraction: missing"),
        (
            {"knots_fraction = 0.2": "knots_fraction = 2.0"},
            "galaxy.knots_fraction: the knots' fraction",
        ),
        (
            {'profile = "bulgedisk"': 'profile = "sersic"\nsersicn = 1.0'},
            "galaxy.bulge_fraction: only for profile = 'bulgedisk'",
        ),
    ],
)
def test_bad_bulgedisk_configs(tmp_path, replace, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        load_config(write(tmp_path, BULGEDISK, replace=replace))


@pytest.mark.parametrize(
    "replace,message",
    [
        ({'fit = "auto"': 'fit = "double"'}, "galaxy.fit: unknown value 'double'"),
        (
            {"pixel_scale = 0.1": "pixel_scale = 0.1\nrad = 3.0"},
            "galaxy.pixel_scale: profile 'cosmos_fit' needs exactly one",
        ),
        (
            {"pixel_scale = 0.1": "pixel_scale = 0.1\nellipticity = 0.2"},
            "galaxy.ellipticity: not a key of profile 'cosmos_fit'",
        ),
        ({"[catalog]": "[other]"}, "other: unknown table"),
        ({'select = "mag_auto < 23"': 'select = "mag_auto < 10"'}, "catalog.select: no usable row"),
    ],
)
def test_bad_cosmos_fit_configs(tmp_path, replace, message):
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, COSMOSFIT, replace=replace))


def test_cosmos_fit_needs_a_catalog_table(tmp_path):
    text = COSMOSFIT.split("[catalog]")[0] + COSMOSFIT.split('select = "mag_auto < 23"\n')[1]
    with pytest.raises(
        ConfigError, match="galaxy.profile: 'cosmos_fit' samples the rows of a \\[catalog\\]"
    ):
        load_config(write(tmp_path, text))


def test_cli_bad_model_config_is_one_line_exit_2(tmp_path, runner, cli):
    cfg = write(tmp_path, BULGEDISK, replace={"bulge_rad_ratio = 0.4": "bulge_rad_ratio = -1.0"})
    result = runner.invoke(cli, ["simulate", str(cfg), "-o", str(tmp_path / "o.fits")])
    assert result.exit_code == 2
    lines = [ln for ln in result.stderr.strip().splitlines() if ln]
    assert (
        len(lines) == 1
        and "[galaxy] bulge_rad_ratio" in lines[0]
        and "Traceback" not in result.stderr
    )


REALGAL = Path(__file__).resolve().parents[1] / "examples" / "realgal"


@pytest.mark.parametrize(
    "name", sorted(p.name for p in REALGAL.glob("*.toml") if not p.name.startswith("pipeline"))
)
def test_realgal_examples_simulate_through_the_cli(name, runner, cli, tmp_path):
    """Every examples/realgal config simulates and measures at a tiny size through the CLI."""
    out = tmp_path / "o.fits"
    result = runner.invoke(
        cli,
        [
            "simulate",
            str(REALGAL / name),
            "-o",
            str(out),
            "--measure",
            "--n-cases",
            "2",
            "--n-realizations",
            "2",
            "--seed",
            "5",
            "noise.sigma=0.1",
        ],
    )
    assert result.exit_code == 0, result.stderr
    t = read_catalog(out)
    assert len(t) == 4 and np.all(np.asarray(t["flags"]) == 0)
    assert np.all(np.isfinite(np.asarray(t["adamom_g1"])))
    expect = {
        "tp-bulgedisk.toml": "tru_bulge_fraction",
        "tw-bulgedisk.toml": "tru_bulge_fraction",
        "tp-knots.toml": "tru_knot_seed",
        "tw-knots.toml": "tru_knot_seed",
        "tp-cosmosfit.toml": "tru_cosmos_ident",
        "tw-cosmosfit.toml": "tru_cosmos_ident",
        "tp-corrnoise.toml": "tru_sky_sigma",
        "tw-corrnoise.toml": "tru_sky_sigma",
        "fiducial.toml": "tru_twin_rad",
        "crn-fiducial.toml": "tru_twin_rad",
        "crn-ground.toml": "tru_twin_rad",
        "tp-ground-sersic.toml": "tru_sersicn",
        "tw-ground-sersic.toml": "tru_sersicn",
        "tp-ground-cosmosfit.toml": "tru_cosmos_ident",
        "tw-ground-cosmosfit.toml": "tru_cosmos_ident",
        "vo-crn-ground.toml": "tru_sersicn",
    }[name]
    assert expect in t.colnames


def test_ring_members_are_rotated_copies_and_workers_agree(tmp_path):
    """A bulge + disk with knots and an offset bulge on a ring of 2 (theta, theta + 90 deg),
    unlensed, noiseless, centred: the second stamp is the first rotated by 90 degrees (1e-4
    of the peak). Stamps are identical with 1 and 2 workers."""
    cfg = load_config(
        write(
            tmp_path,
            BULGEDISK,
            replace={
                "knots = 12": "knots = 12\nbulge_dx = 0.6\nbulge_dy = -0.4",
                'type = "gaussian"\nsigma = 1.0': 'type = "none"',
                "stamp_size = 32": "stamp_size = 32\noffset = 0.0",
                'g1 = {type = "uniform", min = -0.05, max = 0.05}': "g1 = 0.0",
            },
        ),
        n_cases=3,
        n_realizations=2,
    )
    simulate(cfg, tmp_path / "a.fits", stamps=tmp_path / "a-st.fits", seed=2)
    simulate(cfg, tmp_path / "b.fits", stamps=tmp_path / "b-st.fits", seed=2, nproc=2)
    a = fitsio.read(str(tmp_path / "a-st.fits"))
    assert np.array_equal(a, fitsio.read(str(tmp_path / "b-st.fits")))
    s = 32
    for case in range(3):
        k = 2 * case  # stamps 2c and 2c+1 of the grid (n_x = 3)
        first = a[(k // 3) * s : (k // 3 + 1) * s, (k % 3) * s : (k % 3 + 1) * s]
        second = a[
            ((k + 1) // 3) * s : ((k + 1) // 3 + 1) * s, ((k + 1) % 3) * s : ((k + 1) % 3 + 1) * s
        ]
        # +90 deg counterclockwise with y up: new[y, x] = old at (x, y) -> (y, -x)
        assert np.max(np.abs(np.rot90(first, k=-1) - second)) < 1e-4 * first.max()
        assert np.max(np.abs(np.rot90(first, k=1) - second)) > 1e-2 * first.max()  # not symmetric


# --------------------------------------------------------------------------- the registry


def test_a_new_galaxy_profile_is_one_registration(tmp_path):
    """Registering a profile makes it a valid galaxy.profile: its own keys checked (a key of
    other profiles refused, naming them), its truth columns written, drawn by GalSim (the
    fast engine hands it over), and listed in the docs tables."""
    from sim_configs import TINY

    from megalut_cli.doctables import TABLES
    from megalut_cli.schema import Option, Required
    from megalut_cli.sim.distributions import parse_distribution
    from megalut_cli.sim.profiles import GALAXY_PROFILES, GalaxyProfile, register_galaxy_profile
    from megalut_cli.sim.profiles.base import GalaxySpec, ProfileTruth
    from megalut_cli.sim.profiles.common import FLUX, ONE_FLUX, flux_mode, position_angle
    from megalut_cli.sim.simulate import simulate_table

    def parse(given, values, instrument, config_path):
        mode = flux_mode(given, instrument)
        params = {k: parse_distribution(given[k], f"galaxy.{k}") for k in ("scale_radius", mode)}
        params["ellipticity"] = parse_distribution(0.0, "galaxy.ellipticity")
        return GalaxySpec("expo", params, position_angle({"angle": 0.0}), mode, 0.0)

    def truth(spec, drawn, sequence):
        rad = 1.6783469900166608 * drawn["scale_radius"]  # GalSim's Exponential hlr / r0
        columns = {"tru_rad": rad, "tru_scale_radius": drawn["scale_radius"]}
        return ProfileTruth(columns, drawn["ellipticity"], rad)

    def build(spec, t, k, gsparams, pad_pixels):
        return galsim.Exponential(
            scale_radius=float(t["tru_scale_radius"][k]),
            flux=float(t["tru_flux"][k]),
            gsparams=gsparams,
        )

    scale = Option("scale_radius", "dist", None, "scale radius, pixels", default_text="required")
    rules = (Required("scale_radius", "scale radius in pixels"), ONE_FLUX)
    profile = GalaxyProfile(
        "expo",
        "an exponential disk",
        (scale, FLUX),
        rules,
        parse,
        truth,
        build,
        truth_columns=("tru_scale_radius",),
    )
    galaxy = TINY[TINY.index("[galaxy]") : TINY.index("[psf]")]

    def config(table: str) -> Path:
        return write(
            tmp_path,
            TINY,
            replace={
                galaxy: f'[galaxy]\nprofile = "expo"\n{table}\n\n',
                'type = "gaussian"\nsigma = 1.0': 'type = "none"',
            },
        )

    register_galaxy_profile(profile)
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_galaxy_profile(profile)
        columns, stamps = simulate_table(
            load_config(config("scale_radius = 2.0\nflux = 100.0")),
            3,
            keep_stamps=True,
            engine="fast",
        )
        assert np.allclose(columns["tru_scale_radius"], 2.0)
        assert np.allclose(columns["tru_flux"], 100.0)
        assert abs(float(stamps[0].sum()) - 100.0) < 2.0  # 24-px stamps hold most of the light
        owners = "'cosmos_fit' or 'bulgedisk' or 'gaussian' or 'sersic'"
        with pytest.raises(ConfigError, match=rf"^galaxy\.rad: only for profile = {owners}$"):
            load_config(config("scale_radius = 2.0\nflux = 1.0\nrad = 1.0"))
        missing = r"^galaxy\.scale_radius: missing \(scale radius in pixels\)$"
        with pytest.raises(ConfigError, match=missing):
            load_config(config("flux = 1.0"))
        assert "`expo`" in TABLES["galaxy-profiles"]() and "`scale_radius`" in TABLES["galaxy"]()
    finally:
        del GALAXY_PROFILES["expo"]
    with pytest.raises(ConfigError, match="galaxy.profile: unknown value 'expo'"):
        load_config(config("flux = 1.0"))
