"""GSParams as plain numbers, GalSim's version and FFT sizes, without GalSim: as GalSim's."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from megalut_cli.sim.gsparams import GsParams, galsim_version, good_fft_size

SETTINGS = (
    {},
    {"folding_threshold": 1e-2},
    {"minimum_fft_size": 96.0, "maximum_fft_size": 256, "stepk_minimum_hlr": 4},
    {"kvalue_accuracy": 1e-6, "maxk_threshold": 5e-4, "table_spacing": 2},
)


@pytest.mark.parametrize("settings", SETTINGS)
def test_values_text_and_object_are_galsims(settings):
    ours, theirs = GsParams(**settings), galsim.GSParams(**settings)
    assert repr(ours) == repr(theirs)  # the text that names disk-cache entries
    assert GsParams.of(theirs) == ours and GsParams.of(ours) is ours
    assert ours.galsim() == theirs
    for name in ("minimum_fft_size", "maximum_fft_size", "folding_threshold", "kvalue_accuracy"):
        value = getattr(ours, name)
        assert value == getattr(theirs, name) and type(value) is type(getattr(theirs, name))
    stored = np.array(ours.values(), dtype=np.float64)  # as the disk cache keeps them
    assert GsParams.from_values(stored) == ours and hash(GsParams.from_values(stored)) == hash(ours)


def test_defaults_are_galsims():
    assert repr(GsParams()) == repr(galsim.GSParams())


def test_good_fft_size_is_galsims():
    sizes = list(range(0, 20_000)) + [2**k + d for k in range(14, 20) for d in (-1, 0, 1)]
    assert [good_fft_size(n) for n in sizes] == [galsim.Image.good_fft_size(n) for n in sizes]


def test_galsim_version_is_the_imported_one():
    assert galsim_version() == galsim.__version__
