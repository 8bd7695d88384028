"""simulate(): stamp grid layout, --measure equals --stamps + measure, outputs and headers."""

from __future__ import annotations

import json

import fitsio
import numpy as np
import pytest
from sim_configs import write

from megalut_cli.catalog import read_catalog
from megalut_cli.errors import MegalutError
from megalut_cli.measure.features import FEATURE_COLUMNS
from megalut_cli.measure.measure import measure_file
from megalut_cli.sim.config import load_config
from megalut_cli.sim.simulate import simulate, simulate_table


def test_measure_equals_stamps_then_measure(tmp_path):
    """The key property: features of --measure == `megalut measure` on the --stamps image."""
    cfg = load_config(
        write(tmp_path),
        ['structure.per_realization=["galaxy"]', "structure.snc=none"],
        n_cases=3,
        n_realizations=5,
    )
    simulate(cfg, tmp_path / "direct.fits", measure=True, seed=9)
    simulate(cfg, tmp_path / "truth.fits", stamps=tmp_path / "stamps.fits", seed=9)
    measure_file(tmp_path / "stamps.fits", tmp_path / "truth.fits", tmp_path / "measured.fits")
    a = read_catalog(tmp_path / "direct.fits")
    b = read_catalog(tmp_path / "measured.fits")
    assert len(a) == 15
    assert (a["flags"] == 0).sum() >= 10
    for col in a.colnames:
        assert np.array_equal(np.asarray(a[col]), np.asarray(b[col]), equal_nan=True), col
    # --stamps and --measure together: same features again, image written
    simulate(cfg, tmp_path / "both.fits", stamps=tmp_path / "stamps2.fits", measure=True, seed=9)
    c = read_catalog(tmp_path / "both.fits")
    for col in FEATURE_COLUMNS:
        assert np.array_equal(np.asarray(a[col]), np.asarray(c[col]), equal_nan=True), col
    assert np.array_equal(
        fitsio.read(str(tmp_path / "stamps.fits")), fitsio.read(str(tmp_path / "stamps2.fits"))
    )


def test_grid_layout_and_headers(tmp_path):
    cfg = load_config(write(tmp_path), ["structure.n_x=4"], n_cases=2, n_realizations=5)
    simulate(cfg, tmp_path / "c.fits", stamps=tmp_path / "s.fits", seed=3)
    t = read_catalog(tmp_path / "c.fits")
    k = np.arange(10)
    S = 24
    np.testing.assert_array_equal(t["x"], (k % 4) * S + (S + 1) / 2)
    np.testing.assert_array_equal(t["y"], (k // 4) * S + (S + 1) / 2)
    np.testing.assert_array_equal(t["case"], np.repeat([0, 1], 5))
    np.testing.assert_array_equal(t["rea"], np.tile(np.arange(5), 2))
    assert t.colnames[:4] == ["case", "rea", "x", "y"]
    assert {
        "tru_g1",
        "tru_g2",
        "tru_e1",
        "tru_e2",
        "tru_flux",
        "tru_rad",
        "tru_sersicn",
        "tru_sb",
        "tru_psf_g1",
        "tru_psf_g2",
        "tru_psf_sigma",
        "tru_sky_sigma",
    } <= set(t.colnames)
    assert not any(c.startswith("adamom") for c in t.colnames)
    m = t.meta
    assert m["MLFORMAT"] == "megalut.simulation"
    assert (m["SEED"], m["NCASES"], m["NREA"], m["STAMPSZ"], m["NSTAMPX"]) == (3, 2, 5, 24, 4)
    assert m["CFGSHA"] == cfg.sha256 and m["CFGOVR"] == "structure.n_x=4"
    img, hdr = fitsio.read(str(tmp_path / "s.fits"), header=True)
    assert img.shape == (3 * S, 4 * S) and img.dtype == np.float32
    assert hdr["STAMPSZ"] == S and hdr["NSTAMPX"] == 4 and hdr["NSTAMPS"] == 10
    assert hdr["MLFORMAT"] == "megalut.stamps"
    assert np.all(img[2 * S :, 2 * S :] == 0)  # the two unused grid slots
    stored = fitsio.read(str(tmp_path / "c.fits"), ext="CONFIG")
    cfg_json = json.loads(stored["config_json"][0])
    assert cfg_json["structure"]["n_cases"] == 2 and cfg_json["structure"]["n_x"] == 4
    assert cfg_json["galaxy"]["rad"] == {"type": "uniform", "min": 1.5, "max": 3.0}


def test_truth_only_catalog_matches_drawn_truth(tmp_path):
    cfg = load_config(write(tmp_path))
    simulate(cfg, tmp_path / "a.fits", seed=5)
    simulate(cfg, tmp_path / "b.fits", measure=True, seed=5)
    a, b = read_catalog(tmp_path / "a.fits"), read_catalog(tmp_path / "b.fits")
    for col in a.colnames:
        assert np.array_equal(np.asarray(a[col]), np.asarray(b[col])), col


def test_refuses_overwrite_and_same_paths(tmp_path):
    cfg = load_config(write(tmp_path))
    out = tmp_path / "c.fits"
    out.write_text("keep me")
    with pytest.raises(MegalutError, match="exists; pass overwrite=True"):
        simulate(cfg, out, measure=True)
    assert out.read_text() == "keep me"
    with pytest.raises(MegalutError, match="must be different files"):
        simulate(cfg, tmp_path / "x.fits", stamps=tmp_path / "x.fits")
    simulate(cfg, out, measure=True, overwrite=True)
    assert read_catalog(out)["case"].max() == 2


def test_failure_leaves_no_output(tmp_path, monkeypatch):
    cfg = load_config(write(tmp_path))

    from megalut_cli.sim import draw

    def boom(unit):  # the first unit is drawn (and streamed to the catalog), the second fails
        if unit.case_start > 0:
            raise MegalutError("simulated failure")
        return draw.draw_unit(unit)

    monkeypatch.setattr("megalut_cli.sim.simulate.draw_unit", boom)
    with pytest.raises(MegalutError, match="simulated failure"):
        simulate(cfg, tmp_path / "c.fits", stamps=tmp_path / "s.fits", measure=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim.toml"]


def test_star_stamp_psf_path_beside_config(tmp_path, monkeypatch):
    """A `stamp` PSF read from a star image found beside the config; drawn without pixel."""
    import galsim

    star = galsim.Gaussian(sigma=1.5).drawImage(nx=21, ny=21, scale=1.0).array
    fitsio.write(str(tmp_path / "star.fits"), star.astype(np.float32))
    cfg_path = write(
        tmp_path, replace={'type = "gaussian"\nsigma = 1.5': 'type = "stamp"\npath = "star.fits"'}
    )
    monkeypatch.chdir(tmp_path.parent)
    cfg = load_config(cfg_path)
    simulate(cfg, tmp_path / "c.fits", measure=True, seed=2)
    t = read_catalog(tmp_path / "c.fits")
    assert (
        np.allclose(t["tru_psf_sigma"], t["tru_psf_sigma"][0]) and 1.4 < t["tru_psf_sigma"][0] < 1.7
    )
    assert (t["flags"] == 0).sum() >= 8


def test_in_memory_set_equals_the_written_files(tmp_path):
    """simulate_table (in memory) holds exactly the catalog and the stamps simulate writes."""
    cfg = load_config(write(tmp_path), n_cases=3, n_realizations=4)
    simulate(cfg, tmp_path / "c.fits", stamps=tmp_path / "s.fits", measure=True, seed=4)
    columns, stamps = simulate_table(cfg, 4, measure=True, keep_stamps=True)
    cat = read_catalog(tmp_path / "c.fits")
    assert list(columns) == cat.colnames
    for name, values in columns.items():
        assert np.array_equal(values, np.asarray(cat[name]), equal_nan=True), name
    image = fitsio.read(str(tmp_path / "s.fits"))
    size = cfg.structure.stamp_size
    for k, (x, y) in enumerate(zip(cat["x"], cat["y"])):  # FITS 1-based centres of the grid
        r0, c0 = int(y - (size + 1) / 2), int(x - (size + 1) / 2)
        assert np.array_equal(image[r0 : r0 + size, c0 : c0 + size], stamps[k])


def test_catalog_is_streamed_not_assembled(tmp_path):
    """The catalog goes to the file unit by unit: peak memory (traced after a warm-up run,
    which pays one-time buffers) does not grow with the rows and stays far below the
    catalog's size."""
    import tracemalloc

    peaks, sizes = {}, {}
    for n_rea in (50, 250, 1000):  # truth only: up to 4e5 rows, nothing drawn
        cfg = load_config(write(tmp_path), n_cases=400, n_realizations=n_rea)
        tracemalloc.start()
        try:
            simulate(cfg, tmp_path / "c.fits", seed=1, overwrite=True)
            _, peaks[n_rea] = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        cat = read_catalog(tmp_path / "c.fits")
        assert len(cat) == 400 * n_rea
        assert np.array_equal(cat["case"], np.repeat(np.arange(400), n_rea))
        sizes[n_rea] = sum(np.asarray(cat[c]).nbytes for c in cat.colnames)
    assert peaks[1000] < 1.2 * peaks[250] + 1e6, peaks
    assert peaks[1000] < sizes[1000] / 8, (peaks, sizes)


def test_cases_rendered_in_blocks_give_the_same_catalog_and_stamps(tmp_path, monkeypatch):
    """The fast engine renders a case in blocks of CASE_BLOCK realizations (a worker's memory
    does not grow with n_realizations): any block size gives the same stamps and features,
    with one PSF per realization as well (blocks then cut the PSF groups)."""
    from megalut_cli.sim import draw

    overrides = [
        'structure.per_realization=["galaxy", "psf"]',
        "structure.snc=none",
        "psf.sigma={type='uniform', min=1.5, max=2.5}",
    ]
    cfg = load_config(write(tmp_path), overrides, n_cases=2, n_realizations=23)
    whole = simulate_table(cfg, 4, measure=True, keep_stamps=True)
    monkeypatch.setattr(draw, "CASE_BLOCK", 5)
    blocks = simulate_table(cfg, 4, measure=True, keep_stamps=True)
    assert len(np.unique(whole[0]["tru_psf_sigma"])) == 46
    np.testing.assert_array_equal(whole[1], blocks[1])
    for name, values in whole[0].items():
        np.testing.assert_array_equal(values, blocks[0][name], err_msg=name)
