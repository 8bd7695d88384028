"""Correlated noise (noise.type = "correlated"): correlation function, variance, seeds,
skymad, config errors."""

from __future__ import annotations

import fitsio
import galsim
import numpy as np
import pytest
from sim_configs import CF_FILE, NOISE_ONLY, write

from megalut_cli.catalog import read_catalog
from megalut_cli.errors import ConfigError
from megalut_cli.sim.config import CorrelationSource, load_config
from megalut_cli.sim.noise import StampNoise
from megalut_cli.sim.simulate import simulate

LAGS = ((1, 0), (0, 1), (1, 1), (1, -1), (2, 0), (0, 2))


def noise_stamps(
    source: CorrelationSource, sigma: float, n: int = 300, size: int = 32
) -> np.ndarray:
    """``n`` noise-only stamps, seeds 1..n."""
    noise = StampNoise("correlated", sigma=sigma, source=source)
    out = np.empty((n, size, size))
    for i in range(n):
        img = galsim.ImageF(size, size, scale=1.0)
        noise.add(img, i + 1)
        out[i] = img.array
    return out


def measured_cf(stamps: np.ndarray, dx: int, dy: int) -> tuple[float, float]:
    """Mean product of pixels (dx, dy) apart (zero-mean noise) and its standard error."""
    n = stamps.shape[1]
    xs0, xs1 = slice(max(0, -dx), n - max(0, dx)), slice(max(0, dx), n - max(0, -dx))
    ys0, ys1 = slice(max(0, -dy), n - max(0, dy)), slice(max(0, dy), n - max(0, -dy))
    per_stamp = (stamps[:, ys0, xs0] * stamps[:, ys1, xs1]).mean(axis=(1, 2))
    return float(per_stamp.mean()), float(per_stamp.std(ddof=1) / np.sqrt(len(per_stamp)))


def file_cf(dx: int, dy: int) -> float:
    """The COSMOS correlation-function file at a lag of (dx, dy) of its own pixels, normalised."""
    a = fitsio.read(str(CF_FILE))
    c = a.shape[0] // 2
    return float(a[c + dy, c + dx] / a[c, c])


def test_correlation_file_variance_and_correlation():
    """COSMOS correlation function at the simulation's pixel scale: the pixel variance is
    sigma^2 and the measured correlation at lags up to 2 pixels is the file's, within 4
    standard errors (and 0.02)."""
    sigma = 2.0
    stamps = noise_stamps(CorrelationSource("correlation", str(CF_FILE)), sigma)
    var, err = measured_cf(stamps, 0, 0)
    assert abs(var / sigma**2 - 1.0) < max(4 * err / sigma**2, 0.01), (var, err)
    for dx, dy in LAGS:
        xi, err = measured_cf(stamps, dx, dy)
        expect = file_cf(dx, dy)
        assert abs(xi / sigma**2 - expect) < min(4 * err / sigma**2 + 0.003, 0.02), (
            dx,
            dy,
            xi / sigma**2,
            expect,
        )
    assert file_cf(1, 0) > 0.4  # the test is not trivial: strongly correlated neighbours


def test_correlation_is_dilated_by_the_pixel_scale():
    """pixel_scale = 0.5 (source pixels half the simulation's): one simulation pixel spans two
    source pixels, so the correlation at lag 1 is the file's at lag 2."""
    stamps = noise_stamps(CorrelationSource("correlation", str(CF_FILE), pixel_scale=0.5), 1.0)
    for dx, dy in ((1, 0), (0, 1), (1, 1)):
        xi, err = measured_cf(stamps, dx, dy)
        assert abs(xi - file_cf(2 * dx, 2 * dy)) < 4 * err + 0.003, (
            dx,
            dy,
            xi,
            file_cf(2 * dx, 2 * dy),
        )
    var, err = measured_cf(stamps, 0, 0)
    assert abs(var - 1.0) < max(4 * err, 0.01)


def test_noise_image_source(tmp_path):
    """A noise image whose pixels are correlated along x only (w + w shifted by one pixel):
    its correlation (0.5 along x, 0 along y) and, without noise.sigma, its own pixel
    standard deviation are reproduced."""
    rng = np.random.default_rng(3)
    w = rng.normal(0.0, 3.0, (257, 256))
    field = w[:, 1:] + w[:, :-1] + 10.0  # a sky level: subtracted
    fitsio.write(str(tmp_path / "blank.fits"), field.astype(np.float32), clobber=True)
    cfg = load_config(
        write(tmp_path, NOISE_ONLY.replace("SOURCE", 'image = "blank.fits"')),
        n_cases=2,
        n_realizations=3,
    )
    sigma = cfg.noise.params["sigma"].bounds()[0]
    assert abs(sigma - np.sqrt(2) * 3.0) < 0.05 * np.sqrt(2) * 3.0
    stamps = noise_stamps(cfg.noise.source, 1.0)
    with fitsio.FITS(str(tmp_path / "ext.fits"), "rw", clobber=True) as f:  # the image in HDU 1
        f.write(None)
        f.write(field.astype(np.float32))
    in_ext = load_config(
        write(tmp_path, NOISE_ONLY.replace("SOURCE", 'image = "ext.fits"\nhdu = 1'), name="e.toml")
    )
    assert in_ext.noise.params["sigma"].bounds()[0] == pytest.approx(sigma, rel=1e-6)
    xi_x, ex = measured_cf(stamps, 1, 0)
    xi_y, ey = measured_cf(stamps, 0, 1)
    assert abs(xi_x - 0.5) < 4 * ex + 0.02 and abs(xi_y) < 4 * ey + 0.02, (xi_x, xi_y)


def test_simulate_seeds_skymad_and_workers(tmp_path):
    """Through simulate: tru_sky_sigma is sigma, the median skymad estimates it (a few % low), the
    same seed gives identical stamps with 1 or 2 workers, another seed other stamps."""
    cfg = load_config(
        write(tmp_path, NOISE_ONLY.replace("SOURCE", f'correlation = "{CF_FILE}"\nsigma = 1.5')),
        n_cases=4,
        n_realizations=50,
    )
    runs = {}
    for name, seed, nproc in (("a", 7, 1), ("b", 7, 2), ("c", 8, 1)):
        simulate(
            cfg,
            tmp_path / f"{name}.fits",
            stamps=tmp_path / f"{name}-st.fits",
            measure=True,
            seed=seed,
            nproc=nproc,
        )
        runs[name] = fitsio.read(str(tmp_path / f"{name}-st.fits"))
    assert np.array_equal(runs["a"], runs["b"])
    assert not np.allclose(runs["a"], runs["c"])
    t = read_catalog(tmp_path / "a.fits")
    assert np.all(np.asarray(t["tru_sky_sigma"]) == 1.5)
    # skymad (MAD of the ~124 edge pixels of a 32-pixel stamp) is biased low by finite
    # sampling, more so when neighbours are correlated: -1.4 % for white noise, -3 % here
    # (1000 stamps); the median of 200 stamps scatters by ~1.5 %.
    assert 0.92 < np.median(t["skymad"]) / 1.5 < 1.01, np.median(t["skymad"])


@pytest.mark.parametrize(
    "source,message",
    [
        ("", "noise.image: correlated noise needs exactly one of noise.image"),
        (
            f'image = "{CF_FILE}"\ncorrelation = "{CF_FILE}"',
            "noise.image: correlated noise needs exactly one",
        ),
        (f'correlation = "{CF_FILE}"', "noise.sigma: missing"),
        (
            f'correlation = "{CF_FILE}"\nsigma = 1.0\npixel_scale = 0.0',
            "noise.pixel_scale: must be > 0",
        ),
        (f'correlation = "{CF_FILE}"\nsigma = 1.0\nhdu = 1', "noise.hdu: only for noise.image"),
        (f'correlation = "{CF_FILE}"\nsigma = -1.0', "noise.sigma: the noise sigma must be >= 0"),
        (
            f'correlation = "{CF_FILE}"\nsigma = 1.0\nsky_mag = 20.0',
            "noise.sky_mag: not a key of noise type 'correlated'",
        ),
        (f'correlation = "{CF_FILE}"\nsigma = 1.0\nlength = 2.0', "noise.length: unknown key"),
    ],
)
def test_bad_correlated_configs(tmp_path, source, message):
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, NOISE_ONLY.replace("SOURCE", source)))


def test_cli_unusable_noise_file_is_one_line(tmp_path, runner, cli):
    (tmp_path / "table.fits").unlink(missing_ok=True)
    fitsio.write(str(tmp_path / "table.fits"), np.zeros(3, dtype=[("a", "f8")]))
    cfg = write(tmp_path, NOISE_ONLY.replace("SOURCE", 'image = "table.fits"\nsigma = 1.0'))
    result = runner.invoke(cli, ["simulate", str(cfg), "-o", str(tmp_path / "o.fits")])
    assert result.exit_code == 2, result.stderr
    lines = [ln for ln in result.stderr.strip().splitlines() if ln]
    assert len(lines) == 1 and "[noise] image" in lines[0], result.stderr
    missing = write(tmp_path, NOISE_ONLY.replace("SOURCE", 'image = "nothere.fits"'), name="m.toml")
    result = runner.invoke(cli, ["simulate", str(missing), "-o", str(tmp_path / "o.fits")])
    assert (
        result.exit_code == 1
        and "m.toml: [noise] image: no such file 'nothere.fits'" in result.stderr
    )


def test_real_galaxies_refuse_correlated_noise_unless_hst_noise_is_kept(tmp_path):
    """Correlated noise cannot fill up the symmetrized HST noise of real galaxies to sigma."""
    real = f"""
[structure]
n_cases = 1
n_realizations = 2
[galaxy]
profile = "real"
real_catalog = "{CF_FILE.parent / "real_galaxy_catalog_26_extension_example.fits"}"
pixel_scale = 0.2
flux = 200.0
[psf]
type = "gaussian"
sigma = 1.0
[noise]
type = "correlated"
correlation = "{CF_FILE}"
sigma = 1.0
"""
    cfg = write(tmp_path, real)
    with pytest.raises(
        ConfigError, match="galaxy.hst_noise: 'symmetrize' needs noise.type = 'gaussian'"
    ):
        load_config(cfg)
    assert load_config(cfg, ["galaxy.hst_noise=keep"]).noise.type == "correlated"
