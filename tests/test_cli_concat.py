"""`megalut concat`: the catalogs of many tiles as one, their provenance checked; calibrate on
the concatenation equals the rows' calibration, objects told apart by tile and id."""

from __future__ import annotations

import numpy as np
from helpers import assert_ok, invoke_fails, metacal_predictions

from megalut_cli.catalog import read_catalog_columns, write_catalog
from megalut_cli.shear.calibrate import calibrate_columns


def tiles(tmp_path, n=2, prefix="tile", **cards):
    paths = []
    for k in range(n):
        cat = metacal_predictions(n=2000, seed=20 + k, weights=True)
        path = tmp_path / f"{prefix}{k}.fits"
        write_catalog(
            path,
            cat,
            fmt="megalut.predictions",
            cards={"MCALSTEP": 0.01, "MODELSHA": "abc", "MEDSFILE": f"t{k}.meds", **cards},
            history=[f"megalut predict t{k}"],
        )
        paths.append(path)
    return paths


def test_concat_keeps_rows_tiles_and_provenance(runner, cli, tmp_path):
    a, b = tiles(tmp_path)
    out = tmp_path / "all.fits"
    assert_ok(runner.invoke(cli, ["concat", str(a), str(b), "-o", str(out)]))
    cols, header = read_catalog_columns(out)
    ca, _ = read_catalog_columns(a)
    cb, _ = read_catalog_columns(b)
    np.testing.assert_array_equal(
        cols["pre_g1_noshear"], np.r_[ca["pre_g1_noshear"], cb["pre_g1_noshear"]]
    )
    np.testing.assert_array_equal(cols["tile"], np.repeat([0, 1], 2000))
    assert header["NTILES"] == 2 and header["MODELSHA"] == "abc" and "MEDSFILE" not in header
    hist = "\n".join(header["HISTORY"])
    assert "tile 0: tile0.fits, 2000 rows, sha256" in hist and "megalut concat" in hist
    # the concatenation calibrates as the rows do
    whole = calibrate_columns(cols, header=header, errors="bootstrap", n_bootstrap=10)
    joined = {k: np.r_[ca[k], cb[k]] for k in ca}
    direct = calibrate_columns(joined, header=header, errors="bootstrap", n_bootstrap=10)
    assert whole.result["all"]["g1"] == direct.result["all"]["g1"]


def test_concat_refuses_what_is_not_one_catalog(runner, cli, tmp_path):
    a, b = tiles(tmp_path)
    c = tiles(
        tmp_path / "other" if (tmp_path / "other").mkdir() is None else tmp_path, 1, MCALSTEP=0.02
    )[0]
    out = tmp_path / "x.fits"
    invoke_fails(runner, cli, ["concat", str(a), str(c), "-o", str(out)], 1, "MCALSTEP")
    invoke_fails(runner, cli, ["concat", str(a), str(a), "-o", str(out)], 2, "twice")
    invoke_fails(runner, cli, ["concat", str(a), "-o", str(out)], 2, "at least two")
    cols, _ = read_catalog_columns(b)
    cols.pop("size_2m")
    write_catalog(
        tmp_path / "d.fits",
        cols,
        fmt="megalut.predictions",
        cards={"MCALSTEP": 0.01, "MODELSHA": "abc"},
    )
    invoke_fails(
        runner, cli, ["concat", str(a), str(tmp_path / "d.fits"), "-o", str(out)], 1, "size_2m"
    )
    write_catalog(tmp_path / "cal.fits", {"g1": np.zeros(3)}, fmt="megalut.calibrated")
    invoke_fails(
        runner,
        cli,
        ["concat", str(tmp_path / "cal.fits"), str(a), "-o", str(out)],
        1,
        "calibrate the concatenated",
    )
    assert not out.exists()
