"""Stamp sources as a registry: a new input format is one module and a registration; the
work units, the measurer, the columns and the writing are the same for every source."""

from __future__ import annotations

from dataclasses import dataclass

import galsim
import numpy as np
import pytest
from helpers import FLOAT64_SUMS, assert_same_column

from megalut_cli.catalog import read_catalog_columns
from megalut_cli.measure.defaults import FORMAT
from megalut_cli.measure.measure import measure_file_columns, measure_image
from megalut_cli.measure.measurer import MeasureSettings, StampBatch, measure_cards
from megalut_cli.measure.source_registry import (
    COADD_IMAGES,
    CellSettings,
    Measured,
    MeasureRequest,
    StampSourceType,
    register_stamp_source,
    unregister_stamp_source,
)
from megalut_cli.measure.sources import registered_stamp_sources, stamp_source_for
from megalut_cli.measure.units import empty_columns, measure_units, n_units


@dataclass(frozen=True)
class NpyUnit:
    """Stamps ``start .. stop - 1`` of a ``.npy`` stack of stamps."""

    rows: np.ndarray
    path: str

    def batch(self, settings: MeasureSettings) -> StampBatch:
        stack = np.load(self.path, mmap_mode="r", allow_pickle=False)
        stamps = np.asarray(stack[self.rows], dtype=np.float64)
        return StampBatch(stamps, np.ones((len(stamps), 2)))


def measure_npy(request: MeasureRequest) -> Measured:
    stack = np.load(request.stamps_path, mmap_mode="r", allow_pickle=False)
    n, size = len(stack), stack.shape[-1]
    units = [
        NpyUnit(rows, request.stamps_path)
        for rows in np.array_split(np.arange(n), n_units(n, 1) * 3)
    ]
    columns = empty_columns(n, request.settings.feature_columns)
    measure_units(units, request.settings, columns)
    return Measured(
        {"index": np.arange(n), **columns}, measure_cards(request.settings, size), FORMAT
    )


@pytest.fixture
def npy_source():
    source = register_stamp_source(
        StampSourceType(
            "npy", lambda path: path.endswith(".npy"), lambda request: None, measure_npy
        )
    )
    yield source
    unregister_stamp_source("npy")


def test_the_builtin_sources_and_the_fallback():
    names = [s.name for s in registered_stamp_sources()]
    assert {"meds", "grid"} <= set(names)
    assert stamp_source_for("anything.fits").name == "grid"
    with pytest.raises(ValueError, match="registered already"):
        register_stamp_source(registered_stamp_sources()[0])


def test_a_coadds_given_arguments_in_order():
    """The images given with a coadd are the path fields of CellSettings, in the order of the
    arguments; cell_size and cell_border count as given where not their defaults."""
    from dataclasses import fields

    from megalut_cli.measure.options import MEASURE

    paths = [f.name for f in fields(CellSettings) if f.name.endswith("_path")]
    assert [i.field for i in COADD_IMAGES] == paths == ["weight_path", "mask_path", "noise_path"]
    size, border = MEASURE["cell_size"].default, MEASURE["cell_border"].default
    assert CellSettings(None, None, None, size, border).given() == []
    assert CellSettings(None, "m", "n", size, border + 1).given() == [
        "mask_path",
        "noise_path",
        "cell_border",
    ]
    assert CellSettings("w", None, None, size + 2, border).given() == ["weight_path", "cell_size"]


def test_a_toy_source_measures_as_the_grid_does(tmp_path, npy_source):
    rng = np.random.default_rng(3)
    stamps = np.stack(
        [
            galsim.Gaussian(sigma=s)
            .shear(g1=g1, g2=-g1)
            .withFlux(500.0)
            .drawImage(nx=24, ny=24, scale=1.0)
            .array
            for s, g1 in zip(rng.uniform(1.5, 3.0, 7), rng.uniform(-0.3, 0.3, 7))
        ]
    ) + rng.normal(0.0, 0.1, (7, 24, 24))
    np.save(tmp_path / "stack.npy", stamps)
    assert stamp_source_for(str(tmp_path / "stack.npy")) is npy_source
    columns, _ = measure_file_columns(
        tmp_path / "stack.npy", None, tmp_path / "out.fits", morphology=True
    )
    written, header = read_catalog_columns(tmp_path / "out.fits")
    grid = measure_image(np.concatenate(stamps, axis=1), 24, morphology=True)
    np.testing.assert_array_equal(written["index"], np.arange(7))
    for c in ("adamom_g1", "adamom_g2", "adamom_sigma", "skymad", "snr", "morph_conc", "flags"):
        assert_same_column(written[c], grid[c], c, FLOAT64_SUMS)  # morph_conc: 1 ulp on AMD
    assert header["MENGINE"].strip() == "fast" and header["MAXSHIFT"] == 6.0
