"""The feature-set registry: sets declared once, read by the options, the column
descriptions and every measuring route; a new set is one registration."""

from __future__ import annotations

import galsim
import numpy as np
import pytest
from scipy.special import erf

from megalut_cli.columns import describe
from megalut_cli.measure.feature_registry import (
    Column,
    FeatureSet,
    register_feature_set,
    registered_feature_sets,
    unregister_feature_set,
)
from megalut_cli.measure.feature_sets import (
    BASE_SET,
    column_descriptions,
    optional_columns,
    requested_sets,
    set_options,
)
from megalut_cli.measure.measure import measure_image
from megalut_cli.measure.meds import measure_cutouts
from megalut_cli.measure.options import MEASURE
from megalut_cli.sim.options import SIMULATE


def peak_fraction(stamps: np.ndarray, origins: np.ndarray | None, base: dict) -> dict:
    """A toy concentration: the brightest pixel over the adaptive-moment flux."""
    return {"peak_frac": stamps.reshape(len(stamps), -1).max(axis=1) / base["adamom_flux"]}


@pytest.fixture
def peak_set():
    fs = register_feature_set(
        FeatureSet(
            "peak",
            (Column("peak_frac", "", "brightest pixel over adamom_flux"),),
            compute=peak_fraction,
            nan_when_flagged=("peak_frac",),
        )
    )
    yield fs
    unregister_feature_set("peak")


def gaussians(sigmas, size=33, flux=1000.0):
    return np.stack(
        [
            galsim.Gaussian(sigma=s, flux=flux).drawImage(nx=size, ny=size, scale=1.0).array
            for s in sigmas
        ]
    ).astype(np.float64)


def test_builtin_sets_and_their_options():
    names = [s.name for s in registered_feature_sets()]
    assert names[:2] == ["adamom", "morphology"]
    assert BASE_SET.names[-1] == "flags" and "skymad" not in BASE_SET.nan_when_flagged
    assert [o.name for o in set_options()] == ["morphology"]
    assert MEASURE["morphology"] == set_options()[0]
    assert SIMULATE["morphology"].help.startswith("With --measure: also the morphology")
    assert requested_sets({"morphology": True, "metacal": True}) == ("morphology",)
    assert requested_sets({"morphology": False}) == ()
    with pytest.raises(ValueError, match="always measured"):
        optional_columns(["adamom"])
    with pytest.raises(ValueError, match="unknown feature set"):
        optional_columns(["nope"])


def test_every_declared_column_is_described_for_the_fits_header():
    for name, (unit, text) in column_descriptions().items():
        assert describe(name) == (unit, text)
        assert describe(f"{name}_1p")[0] == unit  # the metacal versions too


def test_a_registered_set_is_measured_by_every_route(peak_set):
    sigmas = np.array([1.5, 2.5, 4.0])
    stamps = gaussians(sigmas)
    image = np.concatenate(stamps, axis=1)  # one row of three 33-px stamps
    grid = measure_image(image, 33, feature_sets=("peak",))
    cutouts = measure_cutouts(stamps, feature_sets=("peak",))
    for cols in (grid, cutouts):
        frac = cols["peak_frac"]
        # a more concentrated galaxy puts a larger share of its flux in its brightest pixel
        assert np.all(np.diff(frac) < 0)
        # a centred Gaussian's brightest pixel holds erf(1 / (2 sqrt(2) sigma))^2 of its flux
        np.testing.assert_allclose(frac, erf(0.5 / (np.sqrt(2) * sigmas)) ** 2, rtol=0.02)
    np.testing.assert_array_equal(grid["peak_frac"], cutouts["peak_frac"])
    assert optional_columns(("peak", "morphology")) == (
        "morph_conc",
        "morph_conc_inner",
        "morph_size_ratio",
        "peak_frac",
    )


def test_a_flagged_row_has_nan_in_every_set(peak_set):
    stamps = gaussians([2.0, 2.0])
    stamps[1] = -stamps[1]  # negative flux: flagged
    cols = measure_cutouts(stamps, feature_sets=("peak", "morphology"))
    assert cols["flags"][1] != 0 and cols["flags"][0] == 0
    for c in ("peak_frac", "morph_conc", "adamom_g1"):
        assert np.isfinite(cols[c][0]) and np.isnan(cols[c][1]), c


def test_a_set_and_its_columns_register_once(peak_set):
    with pytest.raises(ValueError, match="registered already"):
        register_feature_set(peak_set)
    with pytest.raises(ValueError, match="taken"):
        register_feature_set(FeatureSet("peak2", (Column("peak_frac", "", "again"),)))
