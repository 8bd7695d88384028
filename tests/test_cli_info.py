"""Self-describing files (units, flag bits, carried cards and CONFIG, eval.json provenance)
and `megalut info` on catalogs, stamp images and models, through the CLI."""

from __future__ import annotations

import json
import random

import fitsio
import numpy as np
import pytest
from helpers import make_model, one_line

from megalut_cli import flags
from megalut_cli.catalog import header_cards, history_steps, write_catalog
from megalut_cli.columns import describe
from megalut_cli.provenance import sha256_file


def _table_header(path):
    with fitsio.FITS(str(path)) as f:
        return f["CATALOG"].read_header(), f["CATALOG"].get_colnames(), [h.get_extname() for h in f]


def _units(header, names) -> dict[str, str | None]:
    return {
        n: (header.get(f"TUNIT{i}").strip() if f"TUNIT{i}" in header else None)
        for i, n in enumerate(names, start=1)
    }


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """simulate --stamps -> measure -> predict -> evaluate --json, all through the CLI."""
    from click.testing import CliRunner

    from megalut_cli.cli import main

    tmp = tmp_path_factory.mktemp("chain")
    run = CliRunner().invoke
    cat, st, feat, sh, model, ev = (
        tmp / n for n in ("cat.fits", "st.fits", "feat.fits", "sh.fits", "m.h5", "ev.json")
    )
    make_model(model)
    steps = [
        [
            "simulate",
            "examples/fiducial/vo.toml",
            "-o",
            str(cat),
            "--stamps",
            str(st),
            "--n-cases",
            "3",
            "--n-realizations",
            "8",
            "--seed",
            "5",
        ],
        ["measure", str(st), str(cat), "-o", str(feat)],
        ["predict", str(feat), "--model", str(model), "-o", str(sh)],
        ["evaluate", str(sh), "--json", str(ev)],
    ]
    for args in steps:
        result = run(main, args)
        assert result.exit_code == 0, result.output
    return {"cat": cat, "st": st, "feat": feat, "sh": sh, "model": model, "ev": ev}


def test_describe_families():
    assert describe("adamom_sigma")[0] == "pixel"
    assert describe("psf_adamom_sigma") == ("pixel", "PSF: " + describe("adamom_sigma")[1])
    assert describe("pre_g1")[0] == describe("tru_g1")[0] == ""
    assert describe("pre_g1_w")[0] == ""
    assert describe("pre_flux")[0] == "adu"  # a prediction takes its target's unit
    assert describe("pre_whatever") is None and describe("tru_whatever") is None
    assert describe("mycolumn") is None


def test_history_cards_round_trip():
    rng = random.Random(3)
    for _ in range(300):
        words = [
            "".join(rng.choice("ab-/ ") for _ in range(rng.randint(0, 40)))
            for _ in range(rng.randint(1, 9))
        ]
        step = " ".join(words).strip() or "x"
        recs = [
            r
            for r in header_cards("f", history=[step], command="megalut last")
            if r["name"] == "HISTORY"
        ]
        values = [r["value"].rstrip() for r in recs]  # FITS readers strip trailing blanks
        assert all(len(v) <= 70 for v in values)
        assert history_steps(values) == [step, "megalut last"]


def test_units_comments_and_flag_bits_on_every_output(chain):
    for key in ("cat", "feat", "sh"):
        header, names, _ = _table_header(chain[key])
        units = _units(header, names)
        for i, name in enumerate(names, start=1):
            desc = describe(name)
            assert desc is not None, name  # every column megalut writes is known
            assert units[name] == desc[0], name
            assert header.get(f"TCOMM{i}").strip() == desc[1][:68]
    header, names, _ = _table_header(chain["sh"])
    units = _units(header, names)
    assert units["x"] == "pixel" and units["tru_flux"] == "adu" and units["tru_theta"] == "deg"
    assert units["adamom_sigma"] == "pixel" and units["pre_g1"] == "" and units["flags"] == ""
    bits = {int(k[7:]): header[k].strip() for k in header.keys() if k.startswith("FLAGBIT")}
    assert {1 << b: n for b, n in bits.items()} == flags.FLAG_NAMES


def test_unknown_column_gets_no_unit(tmp_path):
    out = tmp_path / "c.fits"
    write_catalog(out, {"x": np.ones(3), "mycol": np.ones(3)}, fmt="megalut.features")
    header, names, _ = _table_header(out)
    assert "TUNIT2" not in header and "TCOMM2" not in header and header["TUNIT1"] == "pixel"
    assert not any(k.startswith("FLAGBIT") for k in header.keys())  # no flags column


def test_measure_and_predict_carry_cards_comments_and_config(chain):
    sim, _, sim_ext = _table_header(chain["cat"])
    assert sim["MEASURED"] is False
    with fitsio.FITS(str(chain["cat"])) as f:
        config = f["CONFIG"].read()
    for key in ("feat", "sh"):
        header, _, exts = _table_header(chain[key])
        assert "CONFIG" in exts
        with fitsio.FITS(str(chain[key])) as f:
            assert f["CONFIG"].read().tobytes() == config.tobytes()
        for card in ("SEED", "NCASES", "CFGSHA", "NOISE"):
            assert header[card] == sim[card]
            assert header.get_comment(card) == sim.get_comment(card) != ""
        assert header["MEASURED"] is True  # not the simulation's stale F
        assert header.get_comment("MEASURED") == "the catalog holds measured features"
        assert sum(1 for k in header.keys() if k == "DATE") == 1


def test_evaluation_json_provenance(chain):
    from megalut_cli.nn.model import ShearModel

    prov = json.loads(chain["ev"].read_text())["provenance"]
    assert prov["creator"].startswith("megalut ") and prov["created"]
    assert prov["command"].startswith("megalut evaluate ")
    assert prov["versions"]["megalut"] and prov["versions"]["numpy"]
    src = prov["input"]
    assert src["sha256"] == sha256_file(chain["sh"])
    assert src["format"] == "megalut.predictions"
    assert src["model_sha256"] == ShearModel.load(chain["model"]).sha256
    steps = src["history"]
    assert [s.split()[1] for s in steps] == ["simulate", "measure", "predict"]
    assert f"-o {chain['feat']}" in steps[1]  # whole command lines, not cut at 70 characters


def test_info_catalog_text_and_json(runner, cli, chain):
    result = runner.invoke(cli, ["info", str(chain["sh"])])
    assert result.exit_code == 0, result.output
    out = result.output
    assert "megalut.predictions 1.0, 24 rows" in out
    assert any(
        line.split()[:3] == ["adamom_sigma", "float64", "pixel"] for line in out.splitlines()
    )
    n_flagged = int(
        np.count_nonzero(fitsio.read(str(chain["sh"]), "CATALOG", columns=["flags"])["flags"])
    )
    assert f"flags: {n_flagged} of 24 rows flagged" in out
    assert "1. megalut simulate" in out and "3. megalut predict" in out
    js = json.loads(runner.invoke(cli, ["info", str(chain["sh"]), "--json"]).output)
    assert js["kind"] == "catalog" and js["rows"] == 24 and js["format"] == "megalut.predictions"
    cols = {c["name"]: c for c in js["columns"]}
    assert cols["tru_rad"]["unit"] == "pixel" and cols["pre_g1"]["unit"] == ""
    assert (
        js["provenance"]["model_sha256"]
        == fitsio.read_header(str(chain["sh"]), "CATALOG")["MODELSHA"]
    )
    assert js["config"]["sha256"] == js["provenance"]["config_sha256"]
    assert "CONFIG" in js["extensions"]


def test_info_counts_flag_bits(runner, cli, tmp_path):
    out = tmp_path / "f.fits"
    fl = np.array(
        [0, flags.HSM_FAILED, flags.HSM_FAILED | flags.CENTROID_SHIFT, flags.BAD_FEATURES, 0]
    )
    write_catalog(out, {"x": np.arange(5.0), "flags": fl.astype(np.int32)}, fmt="megalut.features")
    js = json.loads(runner.invoke(cli, ["info", str(out), "--json"]).output)
    assert js["flags"]["rows_flagged"] == 3 and js["flags"]["rows_good"] == 2
    assert {k: v["rows"] for k, v in js["flags"]["bits"].items()} == {
        "HSM_FAILED": 2,
        "CENTROID_SHIFT": 1,
        "BAD_FEATURES": 1,
    }
    text = runner.invoke(cli, ["info", str(out)]).output
    assert "flags: 3 of 5 rows flagged" in text and "HSM_FAILED" in text


def test_info_stamp_image(runner, cli, chain):
    result = runner.invoke(cli, ["info", str(chain["st"]), "--json"])
    assert result.exit_code == 0, result.output
    js = json.loads(result.output)
    assert js["kind"] == "image" and js["format"] == "megalut.stamps"
    assert js["stamp_size"] == 64 and js["stamps"] == 24
    nx, ny = js["grid"]
    assert nx * ny >= 24 and js["shape"] == [ny * 64, nx * 64]
    assert "stamps: 24 of 64x64 pixels" in runner.invoke(cli, ["info", str(chain["st"])]).output


def test_info_model(runner, cli, chain):
    from megalut_cli.nn.model import ShearModel

    model = ShearModel.load(chain["model"])
    js = json.loads(runner.invoke(cli, ["info", str(chain["model"]), "--json"]).output)
    assert js["kind"] == "model" and js["sha256"] == model.sha256
    assert js["targets"] == model.targets and js["features"] == model.features
    kinds = sorted((c["kind"], c["output"]) for c in js["committees"])
    assert kinds == [
        ("point", "pre_g1"),
        ("point", "pre_g2"),
        ("weight", "pre_g1_w"),
        ("weight", "pre_g2_w"),
    ]
    c0 = js["committees"][0]
    assert len(c0["normalization"]["in_loc"]) == len(c0["features"])
    text = runner.invoke(cli, ["info", str(chain["model"])]).output
    assert "targets tru_g1, tru_g2" in text and "point  tru_g1 -> pre_g1" in text


def test_info_model_provenance_chain(runner, cli, tmp_path):
    """A model from train-point then train-weight lists both steps and their inputs."""
    tp = tmp_path / "tp.fits"
    args = [
        "simulate",
        "examples/fiducial/tp.toml",
        "-o",
        str(tp),
        "--measure",
        "--n-cases",
        "6",
        "--n-realizations",
        "8",
    ]
    assert runner.invoke(cli, args).exit_code == 0
    point, model = tmp_path / "p.h5", tmp_path / "m.h5"
    r = runner.invoke(
        cli, ["train-point", str(tp), "-o", str(point), "--iterations", "2", "--members", "2"]
    )
    assert r.exit_code == 0, r.output
    r = runner.invoke(
        cli,
        [
            "train-weight",
            str(tp),
            "--model",
            str(point),
            "-o",
            str(model),
            "--iterations",
            "2",
            "--members",
            "2",
        ],
    )
    assert r.exit_code == 0, r.output
    text = runner.invoke(cli, ["info", str(model)]).output
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("  1. megalut train-point"))
    assert lines[first + 2].startswith("  2. megalut train-weight")
    assert sha256_file(tp)[:12] in lines[first + 1] and sha256_file(point)[:12] in lines[first + 3]


def test_info_bad_inputs(runner, cli, tmp_path, chain):
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    r = runner.invoke(cli, ["info", str(text)])
    assert (
        r.exit_code == 1
        and "not a FITS catalog or image, HDF5 model, megalut JSON file" in one_line(r)
    )
    trunc = tmp_path / "trunc.fits"
    trunc.write_bytes(chain["sh"].read_bytes()[:5000])
    r = runner.invoke(cli, ["info", str(trunc)])
    assert r.exit_code == 1 and "truncated" in one_line(r)
    trunc_h5 = tmp_path / "trunc.h5"
    trunc_h5.write_bytes(chain["model"].read_bytes()[:3000])
    r = runner.invoke(cli, ["info", str(trunc_h5)])
    assert r.exit_code == 1 and "truncated" in one_line(r)
    other_h5 = tmp_path / "other.h5"
    import h5py

    with h5py.File(other_h5, "w") as f:
        f["x"] = np.arange(3)
    r = runner.invoke(cli, ["info", str(other_h5)])
    assert r.exit_code == 1 and "not a megalut model file" in one_line(r)
    assert runner.invoke(cli, ["info", str(tmp_path / "missing.fits")]).exit_code == 2
    assert runner.invoke(cli, ["info", str(tmp_path)]).exit_code == 2
    assert runner.invoke(cli, ["info"]).exit_code == 2


def test_help(runner, cli):
    result = runner.invoke(cli, ["info", "--help"])
    assert result.exit_code == 0 and "--json" in result.output and "Example" in result.output


def test_docs_tables_match_the_code():
    """docs/catalogs.md lists every known column with its unit, and every flag bit."""
    from pathlib import Path

    from megalut_cli.columns import COLUMNS

    text = (Path(__file__).resolve().parents[1] / "docs" / "catalogs.md").read_text()
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| `") and len(cells) >= 3:
            for name in cells[0].replace("`", "").split(","):
                rows[name.strip()] = cells[1:]
    for name, (unit, _) in COLUMNS.items():
        assert name in rows, f"docs/catalogs.md: column {name} missing"
        assert rows[name][0] == unit, f"docs/catalogs.md: {name} unit {rows[name][0]!r} != {unit!r}"
    for value, name in flags.FLAG_NAMES.items():
        bit = value.bit_length() - 1
        assert f"| {bit} | {value} | `{name}` | {flags.FLAG_DESCRIPTIONS[value]} |" in text, name


def test_predict_carries_user_cards_and_comments(runner, cli, tmp_path):
    from helpers import features_catalog

    src, model, out = tmp_path / "f.fits", tmp_path / "m.h5", tmp_path / "s.fits"
    make_model(model)
    write_catalog(
        src,
        features_catalog(50),
        fmt="megalut.features",
        cards={"OBSERVER": ("me", "who took the data"), "COMMENT": ["a user note", "second note"]},
    )
    r = runner.invoke(cli, ["predict", str(src), "--model", str(model), "-o", str(out)])
    assert r.exit_code == 0, r.output
    header = fitsio.read_header(str(out), "CATALOG")
    assert header["OBSERVER"] == "me" and header.get_comment("OBSERVER") == "who took the data"
    comments = [rec["value"] for rec in header.records() if rec["name"] == "COMMENT"]
    assert comments == ["a user note", "second note"]
    assert header["MLFORMAT"] == "megalut.predictions"
    assert sum(1 for rec in header.records() if rec["name"] == "MLFORMAT") == 1


def test_measure_without_catalog_carries_the_image_cards(runner, cli, chain, tmp_path):
    out = tmp_path / "f.fits"
    r = runner.invoke(cli, ["measure", str(chain["st"]), "-o", str(out)])
    assert r.exit_code == 0, r.output
    image = fitsio.read_header(str(chain["st"]), 0)
    header, _, _ = _table_header(out)
    for card in ("SEED", "CFGSHA", "NSTAMPS"):
        assert header[card] == image[card] and header.get_comment(card) == image.get_comment(card)
    assert header["MLFORMAT"] == "megalut.features" and "BITPIX" not in header.keys()[8:]
