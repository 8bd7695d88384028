"""The batched renderer draws GalSim's pixels: same FFT grids, same stamps (to 1e-6 of the peak)."""

from __future__ import annotations

import galsim
import numpy as np
import pytest
from render_cases import RENDER_CASES, random_galaxies, render_setup, write_starfield

from megalut_cli.errors import MegalutError
from megalut_cli.sim.galaxies import base_profile, make_gsparams, shaped
from megalut_cli.sim.render import StampRenderer, can_render, fft_grid

#: Largest |fast - GalSim| pixel difference allowed, as a fraction of GalSim's peak pixel.
#: Achieved over the render grid below (every case, Sersic and Gaussian): 3.7e-7 (the
#: Gaussians of case 0; Sersic at most 2.2e-7), a few float32 roundings of the peak.
TOLERANCE = 1e-6

FIELDS = ("profile", "rad", "flux", "sersicn", "e1", "e2", "g1", "g2", "dx", "dy")


def _one(gals: dict, k: int) -> dict:
    return {f: (gals[f] if f == "profile" or gals[f] is None else gals[f][k]) for f in FIELDS}


def _galsim_object(psf: galsim.GSObject, gsparams: dict, g: dict) -> galsim.GSObject:
    """The galaxy ``g`` convolved with ``psf``, as ``megalut_cli/sim/draw.py`` builds it."""
    gsp = make_gsparams(gsparams)
    gal = shaped(
        base_profile(g["profile"], g["rad"], g["flux"], g["sersicn"], gsp),
        g["e1"],
        g["e2"],
        g["g1"],
        g["g2"],
    )
    return galsim.Convolve(gal, psf, gsparams=gsp if gsparams else None)


def _galsim_stamp(
    size: int, psf: galsim.GSObject, method: str, gsparams: dict, g: dict
) -> np.ndarray:
    """The stamp as ``megalut_cli/sim/draw.py`` draws it."""
    image = galsim.ImageF(size, size, scale=1.0)
    _galsim_object(psf, gsparams, g).drawImage(
        image=image, offset=(g["dx"], g["dy"]), method=method
    )
    return image.array.copy()


def _galsim_grid(
    size: int, psf: galsim.GSObject, method: str, gsparams: dict, g: dict
) -> tuple[int, int]:
    """(N, Nk) of GalSim's drawFFT_makeKImage for that stamp, built as drawImage builds it."""
    obj = _galsim_object(psf, gsparams, g)
    centring = -0.5 if size % 2 == 0 else 0.0
    prof = obj.shift(g["dx"] + centring, g["dy"] + centring)
    if method == "auto":
        prof = galsim.Convolve(
            prof, galsim.Pixel(1.0, gsparams=obj.gsparams), gsparams=obj.gsparams
        )
    view = galsim.ImageF(size, size, scale=1.0).view()
    view.setCenter(0, 0)
    kimage, n_fft = prof.drawFFT_makeKImage(view)
    return n_fft, kimage.array.shape[0] - 1


@pytest.fixture(scope="module")
def starfield(tmp_path_factory):
    return str(write_starfield(tmp_path_factory.mktemp("render") / "stars.fits"))


@pytest.mark.parametrize("case", range(len(RENDER_CASES)))
@pytest.mark.parametrize("profile", ["sersic", "gaussian"])
def test_stamps_and_grids_equal_galsim(case, profile, starfield):
    psf, method, gsparams, size, m = render_setup(RENDER_CASES[case], starfield)
    if profile == "gaussian":
        m = max(3, m // 3)
    gals = random_galaxies(100 + case, m, profile)
    renderer = StampRenderer(size, gsparams)
    stamps = renderer.draw(psf, ("psf", case), method, **gals)
    n_fft, n_k = renderer.grid_sizes(
        psf, ("psf", case), method, **{f: gals[f] for f in FIELDS if f != "flux"}
    )
    shapes = {f: gals[f] for f in ("profile", "rad", "sersicn", "e1", "e2", "g1", "g2")}
    good = renderer.good_image_sizes(psf, ("psf", case), method, **shapes)
    assert stamps.shape == (m, size, size) and stamps.dtype == np.float32
    for k in range(m):
        g = _one(gals, k)
        assert (int(n_fft[k]), int(n_k[k])) == _galsim_grid(size, psf, method, gsparams, g), g
        assert good[k] == _galsim_object(psf, gsparams, g).getGoodImageSize(1.0), g
        ref = _galsim_stamp(size, psf, method, gsparams, g)
        err = np.abs(stamps[k] - ref).max() / ref.max()
        assert err <= TOLERANCE, (k, g, err)


def test_wrapping_cases_are_covered(starfield):
    """The small Moffat and the oversampled Euclid PSF need Nk > N (GalSim wraps the k-image)."""
    for case in (3, 6):
        psf, method, gsparams, size, m = render_setup(RENDER_CASES[case], starfield)
        gals = random_galaxies(100 + case, m)
        n_fft, n_k = StampRenderer(size, gsparams).grid_sizes(
            psf, "p", method, **{f: gals[f] for f in FIELDS if f != "flux"}
        )
        assert (n_k > n_fft).any()


def test_batch_size_independence():
    psf = galsim.Gaussian(sigma=2.0)
    gals = random_galaxies(7, 12)
    renderer = StampRenderer(48)
    together = renderer.draw(psf, "g", "auto", **gals)
    alone = np.stack(
        [
            renderer.draw(
                psf,
                "g",
                "auto",
                **{f: (v if f == "profile" else v[k : k + 1]) for f, v in gals.items()},
            )
            for k in range(12)
        ]
    )
    np.testing.assert_array_equal(together, alone[:, 0])
    # a fresh renderer (cold caches) draws the same pixels
    np.testing.assert_array_equal(StampRenderer(48).draw(psf, "other", "auto", **gals), together)


@pytest.mark.parametrize("n_fft", [32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024, 1536])
def test_inverse_fft_is_scipys_bit_for_bit(n_fft):
    """numpy's single-precision pocketfft, in place, gives the pixels SciPy's gave (the
    renderer's FFT before; stamps made with it stay reproducible) on GalSim's FFT sizes
    (2^k and 3 x 2^k)."""
    import scipy.fft

    from megalut_cli.sim.render import inverse_fft_window

    rng = np.random.default_rng(n_fft)
    shape = (7, n_fft, n_fft // 2 + 1)
    k = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64)
    size = min(64, n_fft)
    rows = scipy.fft.ifft(k, axis=1, workers=1)[:, :size, :]
    expect = scipy.fft.irfft(rows, n=n_fft, axis=2, workers=1)[:, :, :size]
    got = inverse_fft_window(k.copy(), n_fft, size)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, expect)


def test_oversized_fft_is_one_line_error():
    renderer = StampRenderer(64, {"maximum_fft_size": 256})
    gals = random_galaxies(1, 1)
    gals.update(sersicn=np.array([4.0]), rad=np.array([10.0]))
    with pytest.raises(MegalutError, match="maximum_fft_size") as err:
        renderer.draw(galsim.Gaussian(sigma=2.0), "g", "auto", **gals)
    assert "\n" not in str(err.value)


def test_bad_input_is_megaluterror():
    renderer = StampRenderer(32)
    gals = random_galaxies(1, 2)
    with pytest.raises(MegalutError, match="profile"):
        renderer.draw(galsim.Gaussian(sigma=2.0), "g", "auto", **{**gals, "profile": "real"})
    with pytest.raises(MegalutError, match="method"):
        renderer.draw(galsim.Gaussian(sigma=2.0), "g", "phot", **gals)
    with pytest.raises(MegalutError, match="< 1"):
        renderer.draw(
            galsim.Gaussian(sigma=2.0), "g", "auto", **{**gals, "g1": np.array([1.0, 0.0])}
        )
    with pytest.raises(MegalutError, match="finite"):
        renderer.draw(
            galsim.Gaussian(sigma=2.0), "g", "auto", **{**gals, "rad": np.array([np.nan, 1.0])}
        )
    with pytest.raises(MegalutError, match="Sersic n=9"):
        renderer.draw(
            galsim.Gaussian(sigma=2.0), "g", "auto", **{**gals, "sersicn": np.array([9.0, 1.0])}
        )
    empty = {f: (v if f == "profile" else v[:0]) for f, v in gals.items()}
    assert renderer.draw(galsim.Gaussian(sigma=2.0), "g", "auto", **empty).shape == (0, 32, 32)


def test_can_render():
    assert can_render("sersic") and can_render("gaussian")
    assert not can_render("real") and not can_render("exponential")


def test_fft_grid_follows_galsim_rules():
    gsp = galsim.GSParams()
    # N = good_fft_size(2 pi / stepk), at least minimum_fft_size (128); maxk below pi: Nk = N
    prof = galsim.Convolve(galsim.Gaussian(sigma=2.0), galsim.Pixel(1.0))
    n_fft, n_k = fft_grid(np.array([prof.stepk]), np.array([prof.maxk]), 16, gsp)
    assert (
        n_fft[0] == max(galsim.Image.good_fft_size(prof.getGoodImageSize(1.0)), 128)
        and n_k[0] == n_fft[0]
    )
    # a large maxk: Nk = 2 ceil(maxk / dk)
    n_fft, n_k = fft_grid(np.array([1.0]), np.array([10.0]), 16, gsp)
    assert n_fft[0] == 128 and n_k[0] == 2 * int(np.ceil(10.0 / (2 * np.pi / 128)))
    # the stamp and minimum_fft_size set lower bounds
    assert fft_grid(np.array([3.0]), np.array([1.0]), 200, gsp)[0][0] == 256
    assert (
        fft_grid(np.array([3.0]), np.array([1.0]), 8, galsim.GSParams(minimum_fft_size=96))[0][0]
        == 96
    )


def test_sersic_k_profile_matches_galsim_kvalue():
    """The reconstructed radial table equals GalSim's kValue to rounding, including the
    low-k quartic, the spline, GalSim's jump to its high-k asymptote and the asymptote, for
    gridded and continuous n."""
    from megalut_cli.sim.render import sersic_table

    gsp = galsim.GSParams()
    for n in (0.5, 1.2345, 4.567, 6.2):
        table = sersic_table(n, gsp)
        unit = galsim.Sersic(n, scale_radius=1.0, gsparams=gsp)
        q = np.geomspace(1e-4 * np.exp(table.params[0]), 2000.0, 3000)
        ours = table.kvalue(q)
        theirs = np.array([unit.kValue(float(x), 0.0).real for x in q])
        # achieved (2026-11-26): 2.4e-13 relative, 1.7e-13 absolute
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-15)
        # the fast form (cubics per 1/256 octave of q^2, no logarithm): achieved 8.7e-12
        np.testing.assert_allclose(table.kvalue(q, fast=True), theirs, rtol=0, atol=4e-11)
        assert table.stepk == unit.stepk and table.maxk == unit.maxk


def test_fast_form_takes_the_cubic_of_the_octave_and_leading_mantissa_bits():
    """The fast form evaluates, at q^2 in octave ``e`` (``lo <= e < hi``), the cubic of row
    ``first + 256 (e - lo) + m`` (``m`` the first 8 mantissa bits of q^2) at the rest of the
    mantissa, and the exact form elsewhere (outside the octaves, and on rows marked NaN): bit
    for bit, on q^2 at the edges of every octave and of every row, 0, and far outside."""
    from megalut_cli.sim.render import sersic_table, stack_profiles
    from megalut_cli.sim.render_nb import FAST_BITS, radial_values

    gsp = galsim.GSParams()
    for n in (0.5, 2.0, 4.567):
        eparams, eint, coef, fcoef = stack_profiles([sersic_table(n, gsp)])
        kind, _, _, lo, hi, first = (int(v) for v in eint[0])
        octaves = np.arange(lo - 3, hi + 3, dtype=float)
        rows = np.arange(1 << FAST_BITS) / (1 << FAST_BITS)
        q2 = np.ldexp(1.0 + rows, octaves[:, None].astype(int)).ravel()
        q2 = np.concatenate([[0.0, 5e-324], q2, np.nextafter(q2, 0), np.nextafter(q2, np.inf)])
        bits = q2.view(np.int64)
        e = (bits >> 52) - 1023
        row = first + ((e - lo) << FAST_BITS) + ((bits >> (52 - FAST_BITS)) & 255)
        inside = (e >= lo) & (e < hi)
        row = np.where(inside, row, 0)
        fast = inside & ~np.isnan(fcoef[row, 0])
        t = (bits & ((1 << (52 - FAST_BITS)) - 1)) * 2.0 ** -(52 - FAST_BITS)
        c = fcoef[row]
        expected = np.where(
            fast,
            c[:, 0] + t * (c[:, 1] + t * (c[:, 2] + t * c[:, 3])),
            radial_values(q2, eparams[0], eint[0], coef, fcoef, False),
        )
        got = radial_values(q2, eparams[0], eint[0], coef, fcoef, True)
        assert kind == 0 and fast.sum() > 1000 and (~fast).sum() > 1000
        assert got.tobytes() == expected.tobytes(), n
