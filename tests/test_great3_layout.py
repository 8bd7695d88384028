"""GREAT3 layout: names, IDs, text catalogs, star fields, submissions, truth files."""

from __future__ import annotations

import math

import numpy as np
import pytest

from megalut_cli import catalog
from megalut_cli.catalog import write_catalog, write_image
from megalut_cli.errors import InputError, MegalutError
from megalut_cli.great3 import layout as L


def test_names():
    assert L.image_name(7) == "image-007-0.fits"
    assert L.starfield_name(12, 0) == "starfield_image-012-0.fits"
    assert L.galaxy_catalog_name(199, "fits") == "galaxy_catalog-199.fits"
    assert L.shear_params_name(3) == "shear_params-003.txt"
    assert L.starshape_name(3, 0, "yaml") == "starshape_parameters-003-0.yaml"


@pytest.mark.parametrize("size", [48, 96])
def test_grid_centres_and_ids_follow_great3_builder(size):
    """great3sims: x = (xmin + xmax) // 2 with xmin = col S, xmax = (col + 1) S - 1;
    x_field_pos = (x + 1 + S/2) // S - 1 (= column);
    ID = 1e6 subfield + 1e3 x_field_pos + y_field_pos."""
    cat = L.galaxy_catalog(17, 5, 3, size)
    col, row = np.arange(15) % 5, np.arange(15) // 5
    xmin, xmax = col * size, (col + 1) * size - 1
    np.testing.assert_array_equal(cat["x"], (xmin + xmax) // 2)
    np.testing.assert_array_equal(cat["y"], (row * size + (row + 1) * size - 1) // 2)
    x_field_pos = (cat["x"] + 1 + size // 2) // size - 1
    y_field_pos = (cat["y"] + 1 + size // 2) // size - 1
    np.testing.assert_array_equal(cat["ID"], 17_000_000 + 1000 * x_field_pos + y_field_pos)
    s, c, r = L.split_ids(cat["ID"])
    assert (s == 17).all() and (c == col).all() and (r == row).all()
    assert cat["x"][0] == (23 if size == 48 else 47)
    with pytest.raises(MegalutError, match="subfield"):
        L.galaxy_catalog(1000, 2, 2, size)


def test_text_catalog_great3_style(tmp_path):
    """GREAT3's writeCatalog: one '# name' line per column, then numpy.savetxt rows (%.18e)."""
    p = tmp_path / "galaxy_catalog-000.txt"
    p.write_text(
        "# x\n# y\n# ID\n"
        "2.300000000000000000e+01 2.300000000000000000e+01 0.000000000000000000e+00\n"
        "7.100000000000000000e+01 2.300000000000000000e+01 1.000000000000000000e+03\n"
    )
    t = catalog.read_text_catalog(p)
    assert t.colnames == ["x", "y", "ID"]
    assert t["ID"].dtype == np.int64 and list(t["ID"]) == [0, 1000]
    assert list(t["x"]) == [23.0, 71.0]
    # one-line header, comments after the header, blank lines
    p2 = tmp_path / "c.txt"
    p2.write_text("# a comment\n# x y ID\n\n1 2 3\n# trailing comment\n4 5 6\n")
    t2 = catalog.read_text_catalog(p2)
    assert t2.colnames == ["x", "y", "ID"] and len(t2) == 2


def test_text_catalog_roundtrip_and_fits(tmp_path):
    cat = L.galaxy_catalog(2, 4, 4, 48)
    catalog.write_text_catalog(tmp_path / "c.txt", cat)
    assert (tmp_path / "c.txt").read_text().startswith("# x\n# y\n# ID\n23 23 2000000\n")
    t = L.read_galaxy_catalog(tmp_path / "c.txt")
    np.testing.assert_array_equal(t["ID"], cat["ID"])
    write_catalog(tmp_path / "c.fits", cat, fmt="great3.catalog")
    assert catalog.is_fits_file(tmp_path / "c.fits") and not catalog.is_fits_file(
        tmp_path / "c.txt"
    )
    np.testing.assert_array_equal(L.read_galaxy_catalog(tmp_path / "c.fits")["x"], cat["x"])
    with pytest.raises(MegalutError, match="exists"):
        catalog.write_text_catalog(tmp_path / "c.txt", cat)


@pytest.mark.parametrize(
    "text, message",
    [
        ("1 2 3\n", "no '# name' header"),
        ("# x\n# y\n1 2\n3\n", "line 4: 1 value"),
        ("# x\n# y\n1 abc\n", "line 3: not a number"),
        ("# x y z\n1 2\n", "do not name the 2 column"),
        ("# x\n# x\n1 2\n", "duplicate column"),
    ],
)
def test_text_catalog_errors_name_the_file(tmp_path, text, message):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(InputError, match=message) as err:
        catalog.read_text_catalog(p)
    assert str(p) in str(err.value)


def test_galaxy_catalog_checks(tmp_path):
    p = tmp_path / "g.txt"
    p.write_text("# x\n# y\n1 2\n")
    with pytest.raises(InputError, match="missing column.*ID"):
        L.read_galaxy_catalog(p)
    p.write_text("# x\n# y\n# ID\n")
    with pytest.raises(InputError, match="no rows"):
        L.read_galaxy_catalog(p)
    with pytest.raises(InputError, match="no such file"):
        L.read_galaxy_catalog(tmp_path / "missing.txt")


def _starfield(tmp_path, size=16, empty=False, nan=False):
    import galsim

    img = np.zeros((3 * size, 3 * size))
    if not empty:
        for k in range(9):
            r, c = divmod(k, 3)
            img[r * size : (r + 1) * size, c * size : (c + 1) * size] = (
                galsim.Gaussian(sigma=1.5 + 0.1 * k).drawImage(nx=size, ny=size, scale=1.0).array
            )
    if nan:
        img[5, 5] = np.nan
    p = tmp_path / "starfield_image-000-0.fits"
    write_image(p, img, fmt="test", overwrite=True)
    return p


def test_read_starfield(tmp_path):
    stars = L.read_starfield(_starfield(tmp_path), 16)
    assert stars.shape == (9, 16, 16)
    assert stars[0].sum() > stars[8].sum() * 0.99  # all flux-1 Gaussians
    with pytest.raises(InputError, match="no star"):
        L.read_starfield(_starfield(tmp_path, empty=True), 16)
    with pytest.raises(InputError, match="NaN"):
        L.read_starfield(_starfield(tmp_path, nan=True), 16)
    with pytest.raises(InputError, match="does not divide"):
        L.read_starfield(_starfield(tmp_path), 20)


def test_submission_roundtrip_and_checks(tmp_path):
    p = tmp_path / "sub.txt"
    L.write_submission(p, [2, 0, 1], [0.01, -0.02, 0.03], [0.0, 0.1, -1e-3])
    lines = p.read_text().splitlines()
    assert len(lines) == 3 and lines[0].split()[0] == "0" and lines[2].split()[0] == "2"
    data = np.loadtxt(p)  # what GREAT3's evaluate.py does
    assert data.shape == (3, 3)
    s, g1, g2 = L.read_submission(p)
    np.testing.assert_array_equal(s, [0, 1, 2])
    np.testing.assert_array_equal(g1, [-0.02, 0.03, 0.01])
    with pytest.raises(MegalutError, match="subfield.*1"):
        L.write_submission(tmp_path / "nan.txt", [0, 1], [0.0, np.nan], [0.0, 0.0])
    with pytest.raises(MegalutError, match="duplicate"):
        L.write_submission(tmp_path / "dup.txt", [0, 0], [0.0, 0.0], [0.0, 0.0])
    assert not (tmp_path / "nan.txt").exists()
    bad = tmp_path / "bad.txt"
    bad.write_text("# subfield g1 g2\n0 0.1 0.2\n1 0.1\n")
    with pytest.raises(InputError, match="line 3"):
        L.read_submission(bad)
    bad.write_text("0.5 0.1 0.2\n")
    with pytest.raises(InputError, match="subfield indices"):
        L.read_submission(bad)


def test_submission_from_catalog():
    ids = L.galaxy_ids(np.array([0, 0, 0, 1, 1, 1]), np.zeros(6), np.arange(6))
    t = {
        "ID": ids,
        "pre_g1": np.array([0.1, 0.3, 9.0, 0.0, 0.2, np.nan]),
        "pre_g2": np.array([0.0, 0.0, 9.0, 1.0, 1.0, 1.0]),
        "pre_g1_w": np.array([1.0, 3.0, 1.0, 1.0, 1.0, 1.0]),
        "pre_g2_w": np.ones(6),
        "flags": np.array([0, 0, 1, 0, 0, 0]),
    }
    s, g1, g2, n = L.submission_from_catalog(t)
    np.testing.assert_array_equal(s, [0, 1])
    np.testing.assert_allclose(g1, [0.2, 0.1])
    np.testing.assert_allclose(g2, [0.0, 1.0])
    np.testing.assert_array_equal(n, [2, 2])
    _, g1w, _, _ = L.submission_from_catalog(t, weighted=True)
    np.testing.assert_allclose(g1w, [(0.1 + 0.9) / 4, 0.1])
    with pytest.raises(InputError, match="subfield"):
        L.submission_from_catalog({"pre_g1": np.zeros(2), "pre_g2": np.zeros(2)})


def test_truth_files(tmp_path):
    d = tmp_path / "truth"
    L.write_truth(d, [0, 1], [0.01, -0.02], [0.0, 0.03], [0.05, 0.0], [-0.01, 0.02])
    assert (d / "shear_params-001.txt").read_text() == "# g1 g2 \n-0.02 0.03 \n"  # GREAT3 writeDict
    t = L.read_truth(d)
    np.testing.assert_array_equal(t["subfield"], [0, 1])
    np.testing.assert_allclose(t["g1"], [0.01, -0.02])
    np.testing.assert_allclose(t["psf_g2"], [-0.01, 0.02])
    # GREAT3's own files: yaml flow style, failed PSF shapes flagged -10
    g = tmp_path / "g3"
    g.mkdir()
    (g / "shear_params-000.yaml").write_text("{g1: 0.0123, g2: -0.0456}\n")
    (g / "starshape_parameters-000-0.yaml").write_text("{psf_g1: -10.0, psf_g2: -10.0}\n")
    (g / "shear_params-001.yaml").write_text("g1: 1.0e-02\ng2: -3.0e-02\n")
    t = L.read_truth(g)
    np.testing.assert_allclose(t["g1"], [0.0123, 0.01])
    assert math.isnan(t["psf_g1"][0]) and math.isnan(t["psf_g1"][1])
    with pytest.raises(InputError, match="subfield 5"):
        L.read_truth(g, [0, 5])
    with pytest.raises(InputError, match="no shear_params"):
        L.read_truth(tmp_path)


def test_subfield_files_and_stamp_size(tmp_path):
    with pytest.raises(
        InputError,
        match="subfield 4: missing image-004-0.fits, galaxy_catalog-004.txt, "
        "starfield_image-004-0.fits",
    ):
        L.subfield_files(tmp_path, 4)
    for name in (L.image_name(4), L.galaxy_catalog_name(4, "fits"), L.starfield_name(4)):
        (tmp_path / name).write_text("x")
    f = L.subfield_files(tmp_path, 4)
    assert f["catalog"].name == "galaxy_catalog-004.fits"
    assert L.find_subfields(tmp_path) == [4]
    cat = L.galaxy_catalog(4, 100, 100, 48)
    assert L.catalog_stamp_size(cat["x"], 4800) == 48
    with pytest.raises(InputError, match="stamp size"):
        L.catalog_stamp_size(cat["x"], 4801)
