"""The one measurer: a batch of stamps in, every column and flag out, the same for grid,
MEDS and simulated stamps."""

from __future__ import annotations

import galsim
import numpy as np
from helpers import FLOAT32_SUMS, assert_same_column

from megalut_cli import flags as fl
from megalut_cli.measure.measurer import (
    Measurer,
    MeasureSettings,
    MetacalSettings,
    PsfImages,
    StampBatch,
    metacal_columns,
)

S = 32
STEP = 0.01


def galaxies(n: int, seed: int = 1, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """``n`` noisy exponential galaxies convolved with a Gaussian PSF of sigma 1.5 px, and the
    PSF image."""
    rng = np.random.default_rng(seed)
    psf = galsim.Gaussian(sigma=1.5)
    stamps = np.stack(
        [
            galsim.Convolve(galsim.Exponential(half_light_radius=2.0, flux=300.0), psf)
            .drawImage(nx=S, ny=S, scale=1.0)
            .array
            for _ in range(n)
        ]
    ) + rng.normal(0.0, noise, (n, S, S))
    return stamps, psf.drawImage(nx=S, ny=S, scale=1.0).array


def test_a_failed_psf_flags_its_row_and_blanks_its_features():
    stamps, psf = galaxies(3)
    images = np.stack([psf, np.zeros_like(psf)])  # the second PSF cannot be measured
    batch = StampBatch(stamps, np.ones((3, 2)), psfs=PsfImages(images, np.array([0, 1, 0])))
    cols = Measurer(MeasureSettings(feature_sets=("morphology",))).measure(batch)
    assert cols["flags"].tolist() == [0, fl.PSF_FAILED, 0]
    for c in ("adamom_g1", "morph_conc", "psf_adamom_sigma"):
        assert np.isnan(cols[c][1]) and np.isfinite(cols[c][[0, 2]]).all(), c
    np.testing.assert_allclose(cols["psf_adamom_sigma"][[0, 2]], 1.5, rtol=0.03)
    assert np.isfinite(cols["skymad"]).all()  # the sky is still measured


def test_masked_pixels_are_counted_left_out_and_flag_a_central_defect():
    stamps, _ = galaxies(2)
    masked = np.zeros(stamps.shape, bool)
    masked[0, 2, 2:5] = True  # off centre: measured without it
    masked[1, 15:17, 15:17] = True  # at the centre: MASKED_PIXELS
    cols = Measurer(MeasureSettings()).measure(StampBatch(stamps, np.ones((2, 2)), masked=masked))
    assert cols["n_masked"].tolist() == [3, 4]
    assert cols["flags"][0] == 0 and cols["flags"][1] & fl.MASKED_PIXELS
    assert np.isnan(cols["adamom_g1"][1])


def test_metacal_responds_to_shear_and_leaves_out_what_it_cannot_use():
    stamps, psf = galaxies(4)
    stamps[3, 0, 0] = np.nan  # BAD_PIXELS: no metacal versions
    settings = MeasureSettings(metacal=MetacalSettings(STEP, 5))
    batch = StampBatch(stamps, np.ones((4, 2)), psfs=PsfImages(psf[None], np.zeros(4, np.int64)))
    cols = Measurer(settings).measure(batch)
    names = [c for c in cols if c.endswith(("_noshear", "_1p", "_1m", "_2p", "_2m"))]
    assert names[: 5 * 11] == metacal_columns(settings.feature_columns)
    for kind in ("noshear", "1p", "1m", "2p", "2m"):
        assert cols[f"flags_{kind}"].tolist()[3] & fl.BAD_PIXELS
        assert np.isnan(cols[f"adamom_g1_{kind}"][3])
        assert np.isnan(cols[f"psf_adamom_sigma_{kind}"][3])
    r11 = (cols["adamom_g1_1p"] - cols["adamom_g1_1m"])[:3] / (2 * STEP)
    r22 = (cols["adamom_g2_2p"] - cols["adamom_g2_2m"])[:3] / (2 * STEP)
    r12 = (cols["adamom_g1_2p"] - cols["adamom_g1_2m"])[:3] / (2 * STEP)
    # a resolved round galaxy responds to a shear along either axis alike, not across
    assert np.all((r11 > 0.3) & (r11 < 1.2)) and np.all(np.abs(r11 / r22 - 1) < 0.05)
    assert np.all(np.abs(r12) < 0.05)
    # the target PSF: round, dilated by 1 + 2 step
    np.testing.assert_allclose(cols["psf_adamom_g1_noshear"][:3], 0.0, atol=1e-6)
    np.testing.assert_allclose(cols["psf_adamom_sigma_1p"][:3], 1.5 * 1.02, rtol=0.02)


def test_psf_grouping_changes_nothing_but_rounding():
    """A PSF given once for all stamps, or once per stamp (a grid of PSF stamps), gives the
    same metacal columns to float32 rounding (:data:`helpers.FLOAT32_SUMS`: one PSF and
    several take matrix products of different shapes, whose float32 sums differ in the last
    bits on some CPUs) and the same flags: sources may pass distinct images or repeated
    ones."""
    stamps, psf = galaxies(3)
    settings = MeasureSettings(metacal=MetacalSettings(STEP, 5))
    shared = PsfImages(psf[None], np.zeros(3, np.int64))
    repeated = PsfImages(np.stack([psf, psf, psf]), np.arange(3))
    a = Measurer(settings).measure(StampBatch(stamps, np.ones((3, 2)), psfs=shared))
    b = Measurer(settings).measure(StampBatch(stamps, np.ones((3, 2)), psfs=repeated))
    assert list(a) == list(b)
    for c in a:
        assert_same_column(a[c], b[c], c, FLOAT32_SUMS)


def test_masked_stamps_near_mask_and_filled_metacal():
    """``mask_margin``: a masked pixel of the stamp within it flags NEAR_MASK (NaN features,
    every version skipped), ``mask_dist`` its distance. Metacal takes the masked pixels
    filled from their neighbours (what they held never reaches the operation) and leaves
    them out of every version's moments: a masked column 11 px from a galaxy leaves its
    response within 1e-4 of the unmasked one (1e-5 measured)."""
    stamps, psf = galaxies(3, noise=1e-4)
    masked = np.zeros(stamps.shape, bool)
    masked[0, :, 15 + 6] = True  # a column 5.5 px from the centre (15.5, 15.5): flagged
    masked[1, :, 15 + 12] = True  # 11.5 px: measured
    psfs = PsfImages(psf[None], np.zeros(3, np.int64))
    settings = MeasureSettings(metacal=MetacalSettings(STEP, 5), mask_margin=10.0)
    garbage = np.where(masked, 1e4, stamps)
    cols = Measurer(settings).measure(
        StampBatch(garbage, np.ones((3, 2)), masked=masked, psfs=psfs)
    )
    np.testing.assert_allclose(cols["mask_dist"][:2], [np.hypot(5.5, 0.5), np.hypot(11.5, 0.5)])
    assert np.isinf(cols["mask_dist"][2])
    assert cols["flags"][0] & fl.NEAR_MASK and cols["flags"][1] == 0 == cols["flags"][2]
    for kind in ("noshear", "1p"):
        assert cols[f"flags_{kind}"][0] & fl.NEAR_MASK and np.isnan(cols[f"adamom_g1_{kind}"][0])
    clean = Measurer(settings).measure(
        StampBatch(stamps, np.ones((3, 2)), masked=np.where(masked, False, masked), psfs=psfs)
    )
    same = Measurer(settings).measure(StampBatch(stamps, np.ones((3, 2)), masked=masked, psfs=psfs))
    for c in ("adamom_g1_1p", "adamom_g1_1m", "adamom_sigma_noshear"):
        assert same[c][1] == cols[c][1], c  # the masked pixels' values never matter
    response = (cols["adamom_g1_1p"] - cols["adamom_g1_1m"]) / (2 * STEP)
    unmasked = (clean["adamom_g1_1p"] - clean["adamom_g1_1m"]) / (2 * STEP)
    assert abs(response[1] / unmasked[1] - 1) < 1e-4, (response[1], unmasked[1])
