"""Library tests of `megalut run`: pipeline files, validation, steps, manifest, --skip-existing."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
from pipeline_configs import TINY_PIPELINE, write_pipeline

from megalut_cli.errors import ConfigError, InputError, MegalutError
from megalut_cli.nn.defaults import DEFAULT_FEATURES
from megalut_cli.pipeline.file import load_pipeline, parse_pipeline, scaled_size
from megalut_cli.pipeline.run import format_summary, run_pipeline
from megalut_cli.pipeline.steps import MANIFEST

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

FIDUCIAL = Path(__file__).resolve().parents[1] / "examples" / "fiducial"


def _raw(name: str) -> dict:
    return tomllib.loads((FIDUCIAL / name).read_text())


def test_default_pipeline_is_the_scaled_fiducial_setup() -> None:
    pipe = load_pipeline(None)
    seeds = [s.seed for s in pipe.sets.values()]
    assert len(set(seeds)) == 3
    assert pipe.train_point.seed != pipe.train_weight.seed
    for name in ("tp", "tw", "vo"):
        effective = pipe.sets[name].config.raw
        example = _raw(f"{name}.toml")
        # Table 1: the same distributions, PSF, noise and shears as the example configs
        for table in ("shear", "galaxy", "psf", "noise"):
            assert effective[table] == example[table], (name, table)
        s, e = effective["structure"], example["structure"]
        assert s["stamp_size"] == e["stamp_size"] == 64
        assert s["per_realization"] == e["per_realization"]
        assert s["offset"] == e["offset"]
    assert pipe.sets["tp"].config.structure.snc == "ring"
    # scaled down: 90-degree pairs in TW and VO (documented deviation), far fewer stamps
    assert {pipe.sets[n].config.structure.snc for n in ("tw", "vo")} == {"pairs"}
    assert (
        sum(s.config.structure.n_stamps for s in pipe.sets.values()) <= 1.5e6
    )  # 1/33 of the paper
    assert pipe.train_point.features == list(DEFAULT_FEATURES)
    assert pipe.train_point.hidden == [5, 5] and pipe.train_weight.hidden == [5]
    assert pipe.train_point.select_cases == "mean(snr) > 10"
    assert pipe.train_weight.select is None
    assert pipe.train_point.members == pipe.train_weight.members == 8


def test_example_pipeline_has_paper_sizes_and_scales() -> None:
    path = FIDUCIAL / "pipeline.toml"
    pipe = load_pipeline(path)
    sizes = {
        n: (s.config.structure.n_cases, s.config.structure.n_realizations)
        for n, s in pipe.sets.items()
    }
    assert sizes == {
        "tp": (5000, 2000),
        "vp": (5000, 10000),
        "tw": (200, 100000),
        "vo": (200, 100000),
    }
    assert pipe.sets["tw"].config.structure.snc == "none"
    assert pipe.train_point.select_cases == "mean(snr) > 10"
    small = load_pipeline(path, ["scale=0.01"])
    sizes = {
        n: (s.config.structure.n_cases, s.config.structure.n_realizations)
        for n, s in small.sets.items()
    }
    assert sizes == {"tp": (500, 200), "vp": (500, 1000), "tw": (200, 1000), "vo": (200, 1000)}
    # the galaxy of every TP case does not change with the scale (seeded per case)
    assert small.sets["tp"].seed == pipe.sets["tp"].seed


def test_scaled_size() -> None:
    assert scaled_size(2000, 0.1, 1) == 200
    assert scaled_size(10, 0.01, 2) == 2
    assert scaled_size(1001, 0.1, 1, even=True) == 100
    assert scaled_size(15, 0.1, 1, even=True) == 2


def test_set_tables_merge_and_typed_tables_replace(tmp_path: Path) -> None:
    text = TINY_PIPELINE.replace(
        'simulation = {structure = {per_realization = ["galaxy"], snc = "pairs"}}\n\n[train_point]',
        'simulation = {structure = {per_realization = ["galaxy"], snc = "pairs"}, '
        'noise = {sigma = 0.5}, galaxy = {rad = {type = "constant", value = 2.5}}}\n\n'
        "[train_point]",
    )
    assert text != TINY_PIPELINE
    pipe = load_pipeline(write_pipeline(tmp_path, text))
    vo = pipe.sets["vo"].config.raw
    assert vo["noise"] == {"type": "gaussian", "sigma": 0.5}
    assert vo["galaxy"]["rad"] == {"type": "constant", "value": 2.5}
    assert vo["galaxy"]["flux"]["min"] == 150.0
    assert pipe.sets["tw"].config.raw["noise"]["sigma"] == 1.0
    # the shared [simulation] table is a base, never changed by one set for the next
    raw = tomllib.loads(TINY_PIPELINE)
    raw["simulation"]["structure"].update(n_cases=5, n_realizations=4)
    del raw["sets"]["tp"]["simulation"]
    del raw["sets"]["tw"]["n_cases"], raw["sets"]["tw"]["n_realizations"]
    pipe = parse_pipeline(raw, base_dir=tmp_path)
    assert pipe.sets["tp"].config.structure.n_cases == 24
    assert (
        pipe.sets["tw"].config.structure.n_cases,
        pipe.sets["tw"].config.structure.n_realizations,
    ) == (5, 4)
    assert raw["simulation"]["structure"] == {"stamp_size": 24, "n_cases": 5, "n_realizations": 4}


@pytest.mark.parametrize(
    ("override", "message", "error"),
    [
        ("bogus=1", "bogus: unknown key", ConfigError),
        ("sets.vo.seed=2", "sets.vo.seed: 2 is also the seed of sets.tw", ConfigError),
        ("sets.tp.sed=4", "sets.tp.sed: unknown key", ConfigError),
        ("sets.tw.scale_by=rows", "sets.tw.scale_by: unknown value 'rows'", ConfigError),
        (
            'train_point.features=["adamom_g1", "adamom_g3"]',
            "train_point.features: no column 'adamom_g3'",
            ConfigError,
        ),
        ("train_point.members=0", "train_point.members: must be >= 1", ConfigError),
        (
            "train_point.hidden=[5, 0]",
            "train_point.hidden: expected a list of positive integers",
            ConfigError,
        ),
        ("train_point.select_cases='mean(snr) >'", "train_point.select_cases", ConfigError),
        ("train_point.select_cases='mean(nope) > 1'", "unknown column(s) nope", ConfigError),
        ("train_weight.select='snr > 10 & adamom_size > 1'", "train_weight.select", ConfigError),
        (
            "train_weight.batch_fraction=0",
            "train_weight.batch_fraction: must be in (0, 1]",
            ConfigError,
        ),
        ('evaluate.by=["nope"]', "evaluate.by: no column nope", ConfigError),
        ("evaluate.plot=3", "evaluate.plot: expected true or false", ConfigError),
        ("scale=0", "scale: must be > 0", ConfigError),
        ("scale=nan", "scale: must be a finite number", ConfigError),
        ("sets.tp.simulation.galaxy.rad=-1", "sets.tp: galaxy.rad", ConfigError),
        ("sets.tp.n_cases=1", "sets.tp.n_cases: at least 2 cases", ConfigError),
        ("sets.tp.config=missing.toml", "sets.tp.config: no such file", InputError),
        ("sets=3", "sets: expected a table", ConfigError),
        ('reference.model="nope.h5"', "reference.model: no such file 'nope.h5'", InputError),
        (
            'reference={model="fiducial", set="tq"}',
            "reference.set: unknown value 'tq'",
            ConfigError,
        ),
        ('reference={set="vo"}', "reference.model: missing", ConfigError),
    ],
)
def test_bad_pipeline_names_the_key(
    tmp_path: Path, override: str, message: str, error: type
) -> None:
    path = write_pipeline(tmp_path)
    with pytest.raises(error) as info:
        load_pipeline(path, [override])
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_set_and_relative_config(tmp_path: Path) -> None:
    raw = tomllib.loads(TINY_PIPELINE)
    del raw["sets"]["vo"]
    with pytest.raises(ConfigError, match=r"sets\.vo: missing"):
        parse_pipeline(raw, base_dir=tmp_path)
    raw = tomllib.loads(TINY_PIPELINE)
    del raw["simulation"]
    with pytest.raises(ConfigError, match=r"sets\.tp\.config: missing"):
        parse_pipeline(raw, base_dir=tmp_path)
    # a set can take its config from a file beside the pipeline
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "tp.toml").write_text((FIDUCIAL / "tp.toml").read_text())
    text = TINY_PIPELINE.replace("[sets.tp]\n", '[sets.tp]\nconfig = "sub/tp.toml"\n')
    pipe = load_pipeline(write_pipeline(tmp_path, text))
    tp = pipe.sets["tp"].config
    assert tp.structure.n_cases == 24 and tp.structure.stamp_size == 64
    assert tp.raw["galaxy"] == _raw("tp.toml")["galaxy"]


def _statuses(result) -> dict[str, str]:
    return {r.name: r.status for r in result.steps}


def test_run_end_to_end_and_skip_existing(tmp_path: Path) -> None:
    path = write_pipeline(tmp_path)
    wd = tmp_path / "work"
    res = run_pipeline(load_pipeline(path), wd)
    assert set(_statuses(res).values()) == {"ran"}
    for name in (
        "tp.fits",
        "tw.fits",
        "vo.fits",
        "point.h5",
        "trained.h5",
        "model.h5",
        "vo-shears.fits",
        "evaluation.json",
        MANIFEST,
    ):
        assert (wd / name).is_file(), name
    assert not (wd / "evaluation.png").exists()  # evaluate.plot = false
    ev = json.loads((wd / "evaluation.json").read_text())
    for scheme in ("unweighted", "weighted"):
        for comp in ("g1", "g2"):
            assert set(ev[scheme][comp]) >= {"m", "m_err", "c", "c_err", "n_cases", "n_rows"}
    assert ev == res.evaluation
    manifest = json.loads((wd / MANIFEST).read_text())
    assert set(manifest["steps"]) == set(_statuses(res))
    assert manifest["steps"]["simulate-vo"]["params"]["seed"] == 3
    assert manifest["steps"]["train-weight"]["inputs"].keys() == {"tw.fits", "point.h5"}
    # the product: the trained networks with their own validation recorded (predict reports it)
    from megalut_cli.nn.model import ShearModel
    from megalut_cli.nn.population import SIMULATED_BIAS_ATTR

    recorded = ShearModel.load(wd / "model.h5").validation[SIMULATED_BIAS_ATTR]
    assert recorded["m_g1"] == ev["weighted"]["g1"]["m"] and recorded["input"] == "vo-shears.fits"
    assert SIMULATED_BIAS_ATTR not in ShearModel.load(wd / "trained.h5").validation

    # Refuses to touch existing products without a flag, before doing anything.
    with pytest.raises(
        MegalutError,
        match="exists; use skip_existing=True to reuse the up-to-date products or overwrite=True",
    ):
        run_pipeline(load_pipeline(path), wd)

    # Nothing changed: every step is skipped, the evaluation is the same.
    again = run_pipeline(load_pipeline(path), wd, skip_existing=True)
    assert set(_statuses(again).values()) == {"skipped"}
    assert again.evaluation == ev

    # A fixed model (the shipped one) validated beside the trained one: two more steps and a
    # second table, on the same rows of vo.
    ref = run_pipeline(load_pipeline(path, ['reference.model="fiducial"']), wd, skip_existing=True)
    assert [n for n, s in _statuses(ref).items() if s == "ran"] == [
        "predict-reference",
        "evaluate-reference",
    ]
    assert ref.evaluation == ev
    assert ref.evaluation_reference["weighted"]["g1"]["n_rows"] == ev["weighted"]["g1"]["n_rows"]
    assert ref.evaluation_reference["weighted"]["g1"]["m"] != ev["weighted"]["g1"]["m"]
    summary = format_summary(ref)
    assert (
        "== VO: overall validation (evaluation.json) ==" in summary
        and "the shipped model fiducial (models/fiducial.h5) on vo" in summary
    )

    # A training setting changed: that step and everything downstream re-run.
    changed = run_pipeline(
        load_pipeline(path, ["train_weight.iterations=12"]), wd, skip_existing=True
    )
    assert _statuses(changed) == {
        "simulate-tp": "skipped",
        "simulate-tw": "skipped",
        "simulate-vo": "skipped",
        "train-point": "skipped",
        "train-weight": "ran",
        "predict": "ran",
        "evaluate": "ran",
        "model": "ran",
    }
    # A new VO seed: the VO simulation and what depends on it.
    reseeded = run_pipeline(
        load_pipeline(path, ["train_weight.iterations=12", "sets.vo.seed=7"]),
        wd,
        skip_existing=True,
    )
    assert [n for n, s in _statuses(reseeded).items() if s == "ran"] == [
        "simulate-vo",
        "predict",
        "evaluate",
        "model",
    ]
    assert (
        reseeded.evaluation["unweighted"]["g1"]["m"] != changed.evaluation["unweighted"]["g1"]["m"]
    )

    # A product deleted or modified: its step runs again; an untouched product is trusted.
    os.remove(wd / "vo-shears.fits")
    with open(wd / "point.h5", "ab") as f:
        f.write(b"x")
    fixed = run_pipeline(
        load_pipeline(path, ["train_weight.iterations=12", "sets.vo.seed=7"]),
        wd,
        skip_existing=True,
    )
    assert [n for n, s in _statuses(fixed).items() if s == "ran"] == [
        "train-point",
        "train-weight",
        "predict",
        "evaluate",
        "model",
    ]

    # --overwrite redoes everything; the simulations are reproducible from the file.
    before = (wd / "tp.fits").read_bytes()
    redo = run_pipeline(load_pipeline(path), wd, overwrite=True)
    assert set(_statuses(redo).values()) == {"ran"}
    _same_catalog(before, (wd / "tp.fits").read_bytes())


def _same_catalog(a: bytes, b: bytes) -> None:
    """Equal FITS files apart from the DATE card of the headers."""
    import re

    def strip(x: bytes) -> bytes:
        return re.sub(rb"DATE    = '[^']*'", b"DATE", x)

    assert strip(a) == strip(b)


def test_moments_retry_key_reaches_the_simulations() -> None:
    """``moments_retry`` is part of the simulation steps' keys when set, absent otherwise (the
    work folders of earlier runs stay up to date)."""
    from megalut_cli.pipeline.run import build_steps

    def sims(pipe):
        return [s for s in build_steps(pipe, nproc=1) if s.name.startswith("simulate-")]

    plain = load_pipeline(None, ["scale=0.01"])
    retry = load_pipeline(None, ["scale=0.01", "moments_retry=0.5"])
    assert plain.moments_retry == 0.0 and retry.moments_retry == 0.5
    assert all("moments_retry" not in s.params for s in sims(plain))
    assert all(s.params["moments_retry"] == 0.5 for s in sims(retry))
    with pytest.raises(ConfigError, match="moments_retry"):
        load_pipeline(None, ["moments_retry=1.5"])
