"""The readers of megalut_cli.great3.layout on files byte for byte as GREAT3 wrote them.

The fixtures reproduce the writers of the public GREAT3 code (great3-public):

* ``great3sims/mapper.py`` ``writeCatalog(type='txt')`` (called by ``fitsToTextCatalog``
  from ``great3sims/builder.py`` ``packagePublic`` for ``galaxy_catalog-SSS.txt`` and
  ``star_catalog-SSS.txt``): one ``# name`` line per column, then ``numpy.savetxt`` with
  its default format ``%.18e`` (so integer IDs and centres are written as floats), space
  separated. Constant-PSF branches: galaxies ``x, y, ID``, stars ``x, y``; variable-PSF
  branches add ``x_tile_index, y_tile_index, tile_x_pos_deg, tile_y_pos_deg,
  x_field_true_deg, y_field_true_deg`` to both.
* ``writeDict(type='txt')`` (``packageTruth`` for ``shear_params-SSS`` and
  ``starshape_parameters-SSS-E``, ``packagePublic`` for ``subfield_offset-SSS`` and
  ``epoch_dither-SSS-E``): ``# k1 k2 ... `` (keys sorted, trailing space), then
  ``str(v1) str(v2) ... `` (Python 2 ``str``: 12 significant digits), each line ending in
  ``\\n``; the ``.yaml`` twin comes from ``yaml.dump`` (flow style ``{k: v, ...}``).
* ``presubmission_script/presubmission.py`` ``print_constant_summary``: one
  ``field g1 g2`` line per subfield, ``str()`` of the values, no header.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from megalut_cli import catalog
from megalut_cli.catalog import read_catalog, write_image
from megalut_cli.errors import InputError
from megalut_cli.great3 import layout as L

#: galaxy_catalog-003.txt of a 2x2 grid of 24-pixel stamps (centres 11, 35), constant PSF.
GALAXY_CONSTANT = (
    "# x\n"
    "# y\n"
    "# ID\n"
    "1.100000000000000000e+01 1.100000000000000000e+01 3.000000000000000000e+06\n"
    "3.500000000000000000e+01 1.100000000000000000e+01 3.001000000000000000e+06\n"
    "1.100000000000000000e+01 3.500000000000000000e+01 3.000001000000000000e+06\n"
    "3.500000000000000000e+01 3.500000000000000000e+01 3.001001000000000000e+06\n"
)

VARIABLE_COLUMNS = [
    "x",
    "y",
    "ID",
    "x_tile_index",
    "y_tile_index",
    "tile_x_pos_deg",
    "tile_y_pos_deg",
    "x_field_true_deg",
    "y_field_true_deg",
]

#: galaxy_catalog-199.txt of a variable-PSF branch (GREAT3's largest IDs, tile columns).
GALAXY_VARIABLE = "".join(f"# {c}\n" for c in VARIABLE_COLUMNS) + (
    "4.751000000000000000e+03 4.751000000000000000e+03 1.990990990000000000e+08 "
    "4.000000000000000000e+00 3.000000000000000000e+00 1.234567890123456690e+00 "
    "5.000000000000000000e-01 9.876543210987653865e+00 2.500000000000000000e+00\n"
    "2.300000000000000000e+01 4.751000000000000000e+03 1.990000990000000000e+08 "
    "0.000000000000000000e+00 3.000000000000000000e+00 1.000000000000000021e-02 "
    "5.000000000000000000e-01 7.142857142857142461e-02 2.500000000000000000e+00\n"
)

#: star_catalog-000.txt of a constant-PSF ground branch (3x3 stars of 48 pixels).
STAR_CONSTANT = "# x\n# y\n" + "".join(
    f"{x:.18e} {y:.18e}\n" for y in (23, 71, 119) for x in (23, 71, 119)
)


def _savetxt(names: list[str], rows: list[tuple]) -> str:
    """What GREAT3's writeCatalog writes: '# name' lines + numpy.savetxt(catalog) (fmt '%.18e')."""
    dtype = [
        (n, int if n in ("x", "y", "ID", "x_tile_index", "y_tile_index") else float) for n in names
    ]
    buf = io.BytesIO()
    np.savetxt(buf, np.array(rows, dtype=dtype))
    return "".join(f"# {n}\n" for n in names) + buf.getvalue().decode()


def test_fixtures_are_what_numpy_savetxt_writes():
    """The hand-written fixtures are byte for byte numpy.savetxt's output for GREAT3's schema."""
    assert GALAXY_CONSTANT == _savetxt(
        ["x", "y", "ID"],
        [(11, 11, 3000000), (35, 11, 3001000), (11, 35, 3000001), (35, 35, 3001001)],
    )
    assert GALAXY_VARIABLE == _savetxt(
        VARIABLE_COLUMNS,
        [
            (4751, 4751, 199099099, 4, 3, 1.2345678901234567, 0.5, 9.876543210987654, 2.5),
            (23, 4751, 199000099, 0, 3, 0.01, 0.5, 0.5 / 7, 2.5),
        ],
    )
    assert STAR_CONSTANT == _savetxt(
        ["x", "y"], [(x, y) for y in (23, 71, 119) for x in (23, 71, 119)]
    )


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
@pytest.mark.parametrize("tail", ["", "\n", "  \n"])
def test_galaxy_catalog_constant_psf(tmp_path, newline, tail):
    p = tmp_path / "galaxy_catalog-003.txt"
    p.write_bytes((GALAXY_CONSTANT + tail).replace("\n", newline).encode())
    for t in (L.read_galaxy_catalog(p), catalog.read_any_catalog(p), catalog.read_text_catalog(p)):
        assert t.colnames == ["x", "y", "ID"]
        assert t["ID"].dtype == np.int64
        np.testing.assert_array_equal(t["ID"], [3_000_000, 3_001_000, 3_000_001, 3_001_001])
        np.testing.assert_array_equal(t["x"], [11, 35, 11, 35])
        np.testing.assert_array_equal(t["y"], [11, 11, 35, 35])
    # the IDs encode subfield, column and row; the centres are the builder's (xmin + xmax) // 2
    s, c, r = L.split_ids(t["ID"])
    np.testing.assert_array_equal(s, 3)
    np.testing.assert_array_equal(t["x"], c * 24 + 11)
    np.testing.assert_array_equal(t["y"], r * 24 + 11)
    np.testing.assert_array_equal(t["ID"], L.galaxy_catalog(3, 2, 2, 24)["ID"])
    assert L.catalog_stamp_size(t["x"], 48) == 24


def test_galaxy_catalog_variable_psf(tmp_path):
    p = tmp_path / "galaxy_catalog-199.txt"
    p.write_text(GALAXY_VARIABLE)
    t = L.read_galaxy_catalog(p)
    assert t.colnames == VARIABLE_COLUMNS
    for c in ("ID", "x_tile_index", "y_tile_index"):
        assert t[c].dtype == np.int64, c
    np.testing.assert_array_equal(t["ID"], [199_099_099, 199_000_099])
    np.testing.assert_array_equal(L.split_ids(t["ID"])[1], [99, 0])
    np.testing.assert_array_equal(t["x"], [4751, 23])
    np.testing.assert_array_equal(t["x_tile_index"], [4, 0])
    assert t["tile_x_pos_deg"][0] == 1.2345678901234567  # %.18e round-trips doubles exactly
    assert t["x_field_true_deg"][1] == 0.5 / 7
    assert t["tile_x_pos_deg"].dtype == np.float64


def test_star_catalog(tmp_path):
    p = tmp_path / "star_catalog-000.txt"
    p.write_text(STAR_CONSTANT)
    t = catalog.read_any_catalog(p)
    assert t.colnames == ["x", "y"] and len(t) == 9
    np.testing.assert_array_equal(t["x"][:4], [23, 71, 119, 23])
    np.testing.assert_array_equal(t["y"][::3], [23, 71, 119])


def test_text_catalog_bad_input_names_the_file(tmp_path):
    p = tmp_path / "galaxy_catalog-000.txt"
    lines = GALAXY_CONSTANT.splitlines(keepends=True)
    p.write_text("".join(lines[:4]) + lines[4][:30] + "\n")  # a truncated row
    with pytest.raises(
        InputError, match=r"galaxy_catalog-000\.txt: line 5: 2 value\(s\), expected 3"
    ):
        L.read_galaxy_catalog(p)
    p.write_text("".join(lines[3:]))  # header lines lost
    with pytest.raises(InputError, match=r"galaxy_catalog-000\.txt: no '# name' header"):
        L.read_galaxy_catalog(p)
    p.write_text("# x\n# y\n" + "".join(lines[3:]))  # a name line lost: 2 names, 3 values
    with pytest.raises(
        InputError, match=r"galaxy_catalog-000\.txt: the '#' header lines do not name the 3"
    ):
        L.read_galaxy_catalog(p)
    p.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(
        InputError, match=r"galaxy_catalog-000\.txt: neither a FITS file nor a text catalog"
    ):
        L.read_galaxy_catalog(p)


# --------------------------------------------------------------------------- writeDict files

#: Python 2 str() of floats: 12 significant digits.
SHEAR_TXT = "# g1 g2 \n0.0134245325233 -0.0270384719183 \n"
SHEAR_YAML = "{g1: 0.013424532523264, g2: -0.02703847191834}\n"
#: constant PSF: writeStarParameters' dict; variable PSF adds n_star_actual.
STARSHAPE_TXT = (
    "# epoch_index psf_g1 psf_g2 subfield_index \n0 0.0123456789012 -4.56789012345e-05 7 \n"
)
STARSHAPE_VARIABLE_TXT = (
    "# epoch_index n_star_actual psf_g1 psf_g2 subfield_index \n0 3 -0.00912345678901 0.0123 7 \n"
)
STARSHAPE_FAILED_TXT = "# epoch_index psf_g1 psf_g2 subfield_index \n0 -10.0 -10.0 8 \n"
STARSHAPE_YAML = (
    "{epoch_index: 0, psf_g1: 0.012345678901234, psf_g2: -4.5678901234e-05, subfield_index: 7}\n"
)


@pytest.mark.parametrize(
    "name, text, expected",
    [
        ("shear_params-007.txt", SHEAR_TXT, {"g1": 0.0134245325233, "g2": -0.0270384719183}),
        ("shear_params-007.yaml", SHEAR_YAML, {"g1": 0.013424532523264, "g2": -0.02703847191834}),
        (
            "starshape_parameters-007-0.txt",
            STARSHAPE_TXT,
            {
                "epoch_index": 0,
                "psf_g1": 0.0123456789012,
                "psf_g2": -4.56789012345e-05,
                "subfield_index": 7,
            },
        ),
        (
            "starshape_parameters-007-0.yaml",
            STARSHAPE_YAML,
            {
                "epoch_index": 0,
                "psf_g1": 0.012345678901234,
                "psf_g2": -4.5678901234e-05,
                "subfield_index": 7,
            },
        ),
        (
            "starshape_parameters-007-0.txt",
            STARSHAPE_VARIABLE_TXT,
            {
                "epoch_index": 0,
                "n_star_actual": 3,
                "psf_g1": -0.00912345678901,
                "psf_g2": 0.0123,
                "subfield_index": 7,
            },
        ),
        (
            "subfield_offset-007.txt",
            "# offset_deg_x offset_deg_y \n0.0 0.0 \n",
            {"offset_deg_x": 0.0, "offset_deg_y": 0.0},
        ),
        (
            "epoch_dither-007-3.txt",
            "# xdither_pixels ydither_pixels \n0.312345678901 -0.0987654321098 \n",
            {"xdither_pixels": 0.312345678901, "ydither_pixels": -0.0987654321098},
        ),
    ],
)
def test_write_dict_files(tmp_path, name, text, expected):
    p = tmp_path / name
    p.write_text(text)
    assert L.read_dict_file(p) == expected
    p.write_bytes(text.replace("\n", "\r\n").encode())
    assert L.read_dict_file(p) == expected


def test_our_truth_files_are_great3_write_dict(tmp_path):
    """write_truth's .txt files have writeDict's layout (sorted keys, trailing spaces)."""
    L.write_truth(tmp_path, [4], [0.0134245325233], [-0.02], [0.0123], [-4.5e-05])
    assert (tmp_path / "shear_params-004.txt").read_text() == "# g1 g2 \n0.0134245325233 -0.02 \n"
    assert (
        tmp_path / "starshape_parameters-004-0.txt"
    ).read_text() == "# psf_g1 psf_g2 \n0.0123 -4.5e-05 \n"


def test_read_truth_on_great3_truth_folder(tmp_path):
    d = tmp_path / "truth"
    d.mkdir()
    (d / "shear_params-007.txt").write_text(SHEAR_TXT)
    (d / "shear_params-007.yaml").write_text(SHEAR_YAML)
    (d / "starshape_parameters-007-0.txt").write_text(STARSHAPE_TXT)
    (d / "starshape_parameters-007-0.yaml").write_text(STARSHAPE_YAML)
    (d / "shear_params-008.yaml").write_text("{g1: -0.03, g2: 0.01}\n")  # .yaml only
    (d / "starshape_parameters-008-0.txt").write_text(STARSHAPE_FAILED_TXT)
    t = L.read_truth(d)
    np.testing.assert_array_equal(t["subfield"], [7, 8])
    assert (
        t["g1"][0] == 0.0134245325233 and t["g2"][0] == -0.0270384719183
    )  # the .txt is read first
    assert t["psf_g1"][0] == 0.0123456789012 and t["psf_g2"][0] == -4.56789012345e-05
    assert t["g1"][1] == -0.03
    assert math.isnan(t["psf_g1"][1]) and math.isnan(t["psf_g2"][1])  # GREAT3's -10: failed


def test_dict_file_bad_input_names_the_file(tmp_path):
    with pytest.raises(InputError, match=r"shear_params-001\.txt: no such file"):
        L.read_dict_file(tmp_path / "shear_params-001.txt")
    p = tmp_path / "shear_params-002.txt"
    p.write_text("# g1 g2 \n0.01 \n")
    with pytest.raises(InputError, match=r"shear_params-002\.txt: expected a '# key \.\.\.' line"):
        L.read_dict_file(p)
    p.write_text("# g1 g2 \n0.01 abc \n")
    with pytest.raises(InputError, match=r"shear_params-002\.txt: not a number"):
        L.read_dict_file(p)
    p.write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(InputError, match=r"shear_params-002\.txt: not a readable"):
        L.read_dict_file(p)
    y = tmp_path / "shear_params-003.yaml"
    y.write_text("g1 = 0.01\n")
    with pytest.raises(InputError, match=r"shear_params-003\.yaml: no 'key: value'"):
        L.read_dict_file(y)


# --------------------------------------------------------------------------- submissions


def test_presubmission_output_and_evaluation(tmp_path):
    """presubmission.py's constant-shear output ('field g1 g2', str() values) is read and
    evaluated against a truth folder in GREAT3's own text layout: m and c come out exactly."""
    from megalut_cli.great3.evaluate import evaluate_branch

    g1 = [0.0134245325233, -0.0270384719183, 0.0412345678901, -0.00501234567891]
    g2 = [-0.0211111111111, 0.00333333333333, 0.0298765432109, -0.0456789012345]
    d = tmp_path / "truth"
    d.mkdir()
    for s in range(4):
        (d / f"shear_params-{s:03d}.txt").write_text(f"# g1 g2 \n{g1[s]!r} {g2[s]!r} \n")
        (d / f"starshape_parameters-{s:03d}-0.txt").write_text(
            f"# epoch_index psf_g1 psf_g2 subfield_index \n0 0.0{s + 1} -0.01 {s} \n"
        )
    m, c = 0.02, -0.001
    sub = tmp_path / "cgc.out"
    sub.write_text(
        "".join(f"{s} {(1 + m) * g1[s] + c!s} {(1 + m) * g2[s] + c!s}\n" for s in range(4))
    )
    s, e1, e2 = L.read_submission(sub)
    assert s.dtype == np.int64
    np.testing.assert_array_equal(s, [0, 1, 2, 3])
    np.testing.assert_allclose(e1, (1 + m) * np.array(g1) + c, rtol=1e-15)
    res = evaluate_branch(sub, d)
    for comp in ("g1", "g2"):
        assert res["unweighted"][comp]["m"] == pytest.approx(m, abs=1e-9)
        assert res["unweighted"][comp]["c"] == pytest.approx(c, abs=1e-10)
    assert res["great3"]["n_subfields"] == 4


# --------------------------------------------------------------------------- measure


def _subfield(tmp_path, catalog_text: str):
    """A 2x2 subfield of 24-pixel stamps (subfield 3): sheared Gaussian galaxies at the
    true stamp centres, a 3x3 star field, and the galaxy catalog ``catalog_text``."""
    import galsim

    s = 24
    psf = galsim.Gaussian(sigma=1.3).shear(g1=0.05, g2=-0.02)
    shears = [
        (0.3, 0.0),
        (-0.3, 0.0),
        (0.0, 0.3),
        (0.0, -0.3),
    ]  # grid order: (0,0) (1,0) (0,1) (1,1)
    img = np.zeros((2 * s, 2 * s))
    for k, (a, b) in enumerate(shears):
        col, row = k % 2, k // 2
        gal = galsim.Convolve(galsim.Gaussian(sigma=2.0, flux=100.0).shear(g1=a, g2=b), psf)
        img[row * s : (row + 1) * s, col * s : (col + 1) * s] = gal.drawImage(
            nx=s, ny=s, scale=1.0
        ).array
    img += np.random.default_rng(3).normal(0.0, 0.01, img.shape)
    stars = np.zeros((3 * s, 3 * s))
    for k in range(9):
        r, c = divmod(k, 3)
        stars[r * s : (r + 1) * s, c * s : (c + 1) * s] = psf.drawImage(nx=s, ny=s, scale=1.0).array
    write_image(tmp_path / "image-003-0.fits", img, fmt="test")
    write_image(tmp_path / "starfield_image-003-0.fits", stars, fmt="test")
    (tmp_path / "galaxy_catalog-003.txt").write_text(catalog_text)
    return shears


def test_measure_a_subfield_with_great3_text_catalog(runner, cli, tmp_path):
    """`megalut measure` on a subfield whose galaxy catalog is GREAT3's text file: the
    stamps are those of the grid, the IDs pass through as integers, the PSF is the star's."""
    shears = _subfield(tmp_path, GALAXY_CONSTANT)
    out, grid = tmp_path / "features-003.fits", tmp_path / "grid.fits"
    common = ["--stamp-size", "24", "--psf", str(tmp_path / "starfield_image-003-0.fits")]
    r = runner.invoke(
        cli,
        [
            "measure",
            str(tmp_path / "image-003-0.fits"),
            str(tmp_path / "galaxy_catalog-003.txt"),
            "-o",
            str(out),
            "--origin",
            "0",
            *common,
        ],
    )
    assert r.exit_code == 0, r.output
    r = runner.invoke(
        cli, ["measure", str(tmp_path / "image-003-0.fits"), "-o", str(grid), *common]
    )
    assert r.exit_code == 0, r.output
    f, g = read_catalog(out), read_catalog(grid)
    assert f.colnames[:3] == ["x", "y", "ID"]
    assert f["ID"].dtype.kind == "i"
    np.testing.assert_array_equal(f["ID"], [3_000_000, 3_001_000, 3_000_001, 3_001_001])
    np.testing.assert_array_equal(f["x"], [11, 35, 11, 35])
    assert (f["flags"] == 0).all()
    for c in (
        "adamom_g1",
        "adamom_g2",
        "adamom_sigma",
        "adamom_flux",
        "snr",
        "psf_adamom_g1",
        "psf_adamom_sigma",
    ):
        np.testing.assert_allclose(
            f[c], g[c], rtol=1e-12, err_msg=c
        )  # the same stamps as in grid order
    # the galaxies' shapes follow their shears (sheared by +-0.3, PSF of ellipticity 0.05)
    g1s = np.array([a for a, _ in shears])
    g2s = np.array([b for _, b in shears])
    assert np.all(np.sign(f["adamom_g1"][g1s != 0]) == np.sign(g1s[g1s != 0]))
    assert np.all(np.sign(f["adamom_g2"][g2s != 0]) == np.sign(g2s[g2s != 0]))
    assert f["psf_adamom_g1"][0] == pytest.approx(0.05, abs=0.01)


def test_measure_passes_variable_psf_columns_through(runner, cli, tmp_path):
    """A variable-PSF galaxy catalog (GREAT3's nine columns) on the same 2x2 subfield."""
    rows = [
        (11, 11, 3000000, 0, 0, 0.1, 0.2, 1.1, 1.2),
        (35, 11, 3001000, 0, 0, 0.3, 0.2, 1.3, 1.2),
        (11, 35, 3000001, 0, 0, 0.1, 0.4, 1.1, 1.4),
        (35, 35, 3001001, 0, 0, 0.3, 0.4, 1.3, 1.4),
    ]
    _subfield(tmp_path, _savetxt(VARIABLE_COLUMNS, rows))
    out = tmp_path / "f.fits"
    r = runner.invoke(
        cli,
        [
            "measure",
            str(tmp_path / "image-003-0.fits"),
            str(tmp_path / "galaxy_catalog-003.txt"),
            "-o",
            str(out),
            "--origin",
            "0",
            "--stamp-size",
            "24",
        ],
    )
    assert r.exit_code == 0, r.output
    f = read_catalog(out)
    assert f.colnames[:9] == VARIABLE_COLUMNS
    np.testing.assert_array_equal(f["ID"], [3_000_000, 3_001_000, 3_000_001, 3_001_001])
    np.testing.assert_array_equal(f["x_field_true_deg"], [1.1, 1.3, 1.1, 1.3])
    assert (f["flags"] == 0).all()
