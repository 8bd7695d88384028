"""`megalut run` for the paper's Sects. 6 and 7: pretraining, VP set, named pipelines, `extends`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from pipeline_configs import PRETRAIN_VP, TINY_PIPELINE, write_pipeline

from megalut_cli import __version__
from megalut_cli.catalog import catalog_info, read_catalog
from megalut_cli.errors import ConfigError, InputError, MegalutError
from megalut_cli.nn.model import ShearModel
from megalut_cli.pipeline.file import load_pipeline
from megalut_cli.pipeline.run import build_steps, run_pipeline
from megalut_cli.pipeline.steps import MANIFEST, sha_text, step_key
from megalut_cli.shear.predict import predict_columns

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
FIVE = ["adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4"]
OLD_STEPS = [
    "simulate-tp",
    "simulate-tw",
    "simulate-vo",
    "train-point",
    "train-weight",
    "predict",
    "evaluate",
    "model",
]
NEW_STEPS = [
    "simulate-pretrain",
    "simulate-tp",
    "simulate-tw",
    "simulate-vo",
    "simulate-vp",
    "pretrain-point",
    "train-point",
    "predict-vp",
    "evaluate-vp",
    "train-weight",
    "predict",
    "evaluate",
    "model",
]


def _statuses(result) -> dict[str, str]:
    return {r.name: r.status for r in result.steps}


def _ran(result) -> list[str]:
    return [n for n, s in _statuses(result).items() if s == "ran"]


def test_pretraining_vp_and_skip_existing(tmp_path: Path) -> None:
    path = write_pipeline(tmp_path, TINY_PIPELINE + PRETRAIN_VP)
    wd = tmp_path / "work"
    res = run_pipeline(load_pipeline(path), wd)
    assert list(_statuses(res)) == NEW_STEPS and set(_statuses(res).values()) == {"ran"}

    # Pretraining on the ellipticities of the low-noise set (targets tru_e1, tru_e2) ...
    pre = ShearModel.load(wd / "pretrain.h5")
    assert list(pre.point) == ["tru_e1", "tru_e2"]
    cat = read_catalog(wd / "pretrain.fits")
    assert np.all(cat["tru_g1"] == 0) and np.all(cat["tru_g2"] == 0)  # no shear in this set
    est = predict_columns(pre, {c: np.asarray(cat[c]) for c in cat.colnames})
    ok = np.isfinite(est["pre_e1"])
    assert (
        np.corrcoef(est["pre_e1"][ok], np.asarray(cat["tru_e1"])[ok])[0, 1] > 0.9
    )  # it learned e1
    # ... then train-point continues those networks on TP with the shear targets (e -> g by
    # position).
    point = ShearModel.load(wd / "point.h5")
    assert list(point.point) == ["tru_g1", "tru_g2"]
    assert point.provenance["inputs"]["init_from"]["sha256"] == pre.sha256
    for g, e in (("tru_g1", "tru_e1"), ("tru_g2", "tru_e2")):
        np.testing.assert_array_equal(
            point.point[g].in_loc, pre.point[e].in_loc
        )  # the same normalisation
        assert point.point[g].hidden == pre.point[e].hidden == (5, 5)

    # VP: point estimates only (no weights), evaluated unweighted with the paper's case selection.
    _, cols, _ = catalog_info(wd / "vp-shears.fits")
    assert {"pre_g1", "pre_g2"} <= set(cols) and "pre_g1_w" not in cols
    ev_vp = json.loads((wd / "evaluation-vp.json").read_text())
    assert ev_vp == res.evaluation_vp
    assert "unweighted" in ev_vp and "weighted" not in ev_vp
    assert ev_vp["select_cases"] == "mean(snr) > 10"
    assert (
        list(ev_vp["conditional"]) == ["tru_rad"]
        and len(ev_vp["conditional"]["tru_rad"]["bins"]) == 2
    )
    assert "weighted" in res.evaluation  # VO as before

    manifest = json.loads((wd / MANIFEST).read_text())
    assert set(manifest["steps"]) == set(NEW_STEPS)
    assert manifest["steps"]["train-point"]["inputs"].keys() == {"tp.fits", "pretrain.h5"}
    assert manifest["steps"]["predict-vp"]["inputs"].keys() == {"vp.fits", "point.h5"}

    again = run_pipeline(load_pipeline(path), wd, skip_existing=True)
    assert set(_statuses(again).values()) == {"skipped"} and again.evaluation_vp == ev_vp
    # A pretraining setting: everything downstream of the pretraining, no simulation.
    changed = run_pipeline(load_pipeline(path, ["pretrain.iterations=12"]), wd, skip_existing=True)
    assert _ran(changed) == NEW_STEPS[5:]
    # A VP evaluation setting: that step only.
    rebinned = run_pipeline(
        load_pipeline(path, ["pretrain.iterations=12", "evaluate_vp.bins=3"]),
        wd,
        skip_existing=True,
    )
    assert _ran(rebinned) == ["evaluate-vp"]
    # A new VP seed: the VP simulation, its predictions and evaluation.
    reseeded = run_pipeline(
        load_pipeline(path, ["pretrain.iterations=12", "evaluate_vp.bins=3", "sets.vp.seed=9"]),
        wd,
        skip_existing=True,
    )
    assert _ran(reseeded) == ["simulate-vp", "predict-vp", "evaluate-vp"]
    # A modified pretraining product: re-trained, and everything after it.
    with open(wd / "pretrain.h5", "ab") as f:
        f.write(b"x")
    fixed = run_pipeline(
        load_pipeline(path, ["pretrain.iterations=12", "evaluate_vp.bins=3", "sets.vp.seed=9"]),
        wd,
        skip_existing=True,
    )
    assert _ran(fixed) == NEW_STEPS[5:]


def test_named_pipelines_share_the_sets(tmp_path: Path) -> None:
    """Fig. 19 as two pipelines in one work folder: the same point estimators, two weightings."""
    text = TINY_PIPELINE.replace("[evaluate]\n", '[evaluate]\nselect = "snr > 20"\n') + PRETRAIN_VP
    base = write_pipeline(tmp_path, text, "base.toml")
    sub = tmp_path / "variants"
    sub.mkdir()
    select = write_pipeline(
        sub,
        'extends = "../base.toml"\nname = "select"\n[train_weight]\nselect = "snr > 20"\n',
        "select.toml",
    )
    wd = tmp_path / "work"
    first = run_pipeline(load_pipeline(base), wd)
    assert first.evaluation["select"] == "snr > 20"
    with pytest.raises(MegalutError, match="exists; use skip_existing=True"):
        run_pipeline(load_pipeline(select), wd)
    res = run_pipeline(load_pipeline(select), wd, skip_existing=True)
    statuses = _statuses(res)
    assert [n for n, s in statuses.items() if s == "skipped"] == NEW_STEPS[:5]  # the sets, once
    assert [n for n, s in statuses.items() if s == "copied"] == [  # the same work: copied
        "select/pretrain-point",
        "select/train-point",
        "select/predict-vp",
        "select/evaluate-vp",
    ]
    assert _ran(res) == [
        "select/train-weight",
        "select/predict",
        "select/evaluate",
        "select/model",
    ]
    assert (wd / "point.h5").read_bytes() == (wd / "select" / "point.h5").read_bytes()
    model = ShearModel.load(wd / "select" / "model.h5")
    assert next(iter(model.weight.values())).training["select"] == "snr > 20"
    assert json.loads((wd / "select" / "evaluation.json").read_text()) == res.evaluation
    assert res.evaluation["weighted"]["g1"] != first.evaluation["weighted"]["g1"]  # other weights
    assert (
        res.evaluation["unweighted"]["g1"] == first.evaluation["unweighted"]["g1"]
    )  # same estimates
    manifest = json.loads((wd / MANIFEST).read_text())
    assert set(manifest["pipelines"]) == {"", "select"}
    assert manifest["steps"]["select/train-point"]["copied_from"] == "train-point"
    assert manifest["steps"]["select/train-point"]["key"] == manifest["steps"]["train-point"]["key"]
    # Both stay up to date side by side.
    assert set(_statuses(run_pipeline(load_pipeline(base), wd, skip_existing=True)).values()) == {
        "skipped"
    }
    assert set(_statuses(run_pipeline(load_pipeline(select), wd, skip_existing=True)).values()) == {
        "skipped"
    }
    # Other features: the pretraining itself differs, nothing is copied.
    feat = run_pipeline(
        load_pipeline(select, ["name=feat", f"train_point.features={FIVE[:4]}"]),
        wd,
        skip_existing=True,
    )
    assert "copied" not in _statuses(feat).values() and "feat/pretrain-point" in _ran(feat)


def test_extends_rebases_every_path_key_and_keeps_shipped_names(tmp_path: Path) -> None:
    """The one rule for the path keys of an extended file (pipeline.config.PATH_TABLES): relative
    to that file; a shipped model's name is not a path."""
    from megalut_cli.nn.shipped import shipped_model

    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "tp.toml").write_text((EXAMPLES / "fiducial" / "tp.toml").read_text())
    shutil.copyfile(shipped_model("fiducial-1e6"), tmp_path / "base" / "ref.h5")
    text = TINY_PIPELINE.replace("[sets.tp]\n", '[sets.tp]\nconfig = "tp.toml"\n')
    write_pipeline(tmp_path / "base", text + '[reference]\nmodel = "ref.h5"\n', "base.toml")
    child = write_pipeline(tmp_path, 'extends = "base/base.toml"\n', "child.toml")
    pipe = load_pipeline(child)
    assert pipe.reference is not None and pipe.reference.model == tmp_path / "base" / "ref.h5"
    assert pipe.sets["tp"].config.structure.stamp_size == 64
    write_pipeline(tmp_path / "base", text + '[reference]\nmodel = "fiducial"\n', "named.toml")
    named = load_pipeline(write_pipeline(tmp_path, 'extends = "base/named.toml"\n', "child2.toml"))
    assert named.reference is not None and named.reference.model == shipped_model("fiducial")


def test_extends_merges_and_keeps_relative_configs(tmp_path: Path) -> None:
    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "tp.toml").write_text((EXAMPLES / "fiducial" / "tp.toml").read_text())
    text = TINY_PIPELINE.replace("[sets.tp]\n", '[sets.tp]\nconfig = "tp.toml"\n')
    write_pipeline(tmp_path / "base", text, "base.toml")
    child = write_pipeline(
        tmp_path,
        'extends = "base/base.toml"\nname = "v2"\n[train_point]\nhidden = [3]\n'
        "[sets.vo]\nseed = 7\n",
        "child.toml",
    )
    pipe = load_pipeline(child)
    assert pipe.name == "v2" and pipe.train_point.hidden == [3]
    assert pipe.train_point.members == 2  # inherited
    assert pipe.sets["vo"].seed == 7 and pipe.sets["vo"].config.structure.n_cases == 8
    assert (
        pipe.sets["tp"].config.structure.stamp_size == 64
    )  # base/tp.toml, relative to the base file
    assert pipe.sets["tp"].config.structure.n_cases == 24
    assert "extends" not in pipe.raw
    base_sha = load_pipeline(tmp_path / "base" / "base.toml").sha256
    assert pipe.sha256 != base_sha
    (tmp_path / "a.toml").write_text('extends = "b.toml"\n')
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n')
    with pytest.raises(
        ConfigError, match=r"b.toml: extends: 'a.toml' makes a cycle \(a.toml -> b.toml -> a.toml\)"
    ):
        load_pipeline(tmp_path / "a.toml")
    (tmp_path / "c.toml").write_text('extends = "missing.toml"\n')
    with pytest.raises(InputError, match="extends: no such file"):
        load_pipeline(tmp_path / "c.toml")
    (tmp_path / "d.toml").write_text("extends = 3\n")
    with pytest.raises(ConfigError, match="extends: expected the path of a pipeline file"):
        load_pipeline(tmp_path / "d.toml")


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train_weight.select='snr > 10 & nope > 1'", "train_weight.select: "),
        ("train_weight.select='snr >'", "train_weight.select: "),
        ("evaluate.select='nope > 1'", "evaluate.select: "),
        ("evaluate.select='mean(snr) > 1'", "evaluate.select: "),
        ("evaluate_vp.select_cases='mean(nope) > 1'", "evaluate_vp.select_cases: "),
        ("evaluate_vp.select='pre_g1_w > 0'", "evaluate_vp.select: "),  # no weights on VP
        ('evaluate_vp.by=["nope"]', "evaluate_vp.by: no column nope in the vp catalog"),
        ("evaluate_vp.bogus=1", "evaluate_vp.bogus: unknown key"),
        ("pretrain.select_cases='mean(nope) > 1'", "pretrain.select_cases: "),
        (
            'pretrain.features=["adamom_g1"]',
            "pretrain.features: the pretraining uses the features and hidden",
        ),
        ("pretrain.hidden=[3]", "pretrain.hidden: the pretraining uses the features and hidden"),
        ("pretrain.bogus=1", "pretrain.bogus: unknown key"),
        (
            'pretrain.targets=["tru_e1"]',
            "pretrain.targets: no committee to start train_point's tru_g2 from",
        ),
        (
            'pretrain.targets=["tru_e1", "nope"]',
            "pretrain.targets: no column 'nope' in the pretrain catalog",
        ),
        (
            'pretrain.targets=["tru_e1", "adamom_g1"]',
            "pretrain.targets: 'adamom_g1' is also a feature",
        ),
        (
            "sets.pretrain.simulation.structure.snc='ring'",
            "sets.pretrain: the target tru_e1 changes within a case",
        ),
        (
            'train_point.features=["adamom_g1", "tru_field_x"]',
            "train_point.features: no column 'tru_field_x'",
        ),
        ("sets.vp.seed=1", "sets.vp.seed: 1 is also the seed of sets.tp"),
        ("sets.vp.bogus=1", "sets.vp.bogus: unknown key"),
        ("sets.extra.seed=8", "sets.extra: unknown key"),
        ("name='a/b'", "name: expected a folder name"),
        ("name=3", "name: expected a folder name"),
        ("name='tp.fits'", "name: expected a folder name"),
        ("extends='other.toml'", "extends: only a pipeline file can extend another"),
    ],
)
def test_bad_keys_one_line(tmp_path: Path, override: str, message: str) -> None:
    path = write_pipeline(tmp_path, TINY_PIPELINE + PRETRAIN_VP)
    with pytest.raises(ConfigError) as info:
        load_pipeline(path, [override])
    assert message in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "pretrain.iterations=5",
            "pretrain: there is no set to pretrain on: add a [sets.pretrain] table",
        ),
        ("evaluate_vp.bins=3", "evaluate_vp: there is no set to evaluate: add a [sets.vp] table"),
    ],
)
def test_step_without_its_set(tmp_path: Path, override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_pipeline(write_pipeline(tmp_path), [override])


def test_old_pipelines_parse_with_the_same_steps_and_keys() -> None:
    """Pipeline files without the new keys: the same steps, products and manifest keys as before."""
    models = EXAMPLES.parent / "models"
    for pipe in (
        load_pipeline(None),
        load_pipeline(models / "fiducial-pipeline.toml", ["scale=0.001"]),
    ):
        assert pipe.name == "" and pipe.pretrain is None and pipe.evaluate_vp is None
        assert set(pipe.sets) == {"tp", "tw", "vo"}
        steps = build_steps(pipe)
        # the default adds the second table (the shipped model on vo) after the old steps
        extra = ["predict-reference", "evaluate-reference"] if pipe.reference is not None else []
        assert [s.name for s in steps] == OLD_STEPS + extra
        assert [o for s in steps for o in s.outputs][:6] == [
            "tp.fits",
            "tw.fits",
            "vo.fits",
            "point.h5",
            "trained.h5",
            "vo-shears.fits",
        ]
        shas = {"tp.fits": "a" * 64, "tw.fits": "b" * 64, "point.h5": "c" * 64}
        for step in steps:
            inputs = {n: shas.get(n, "d" * 64) for n in step.inputs}
            old = sha_text(
                {"step": step.name, "params": step.params, "inputs": inputs, "megalut": __version__}
            )
            assert step_key(step, inputs) == old, step.name  # manifests written before stay valid
        evaluate = next(s for s in steps if s.name == "evaluate")
        assert evaluate.params.keys() == {"by", "bins", "select", "select_cases", "plot"}


def test_fiducial_example_validates_point_estimates_on_vp_as_fig_12() -> None:
    pipe = load_pipeline(EXAMPLES / "fiducial" / "pipeline.toml")
    assert (
        pipe.sets["vp"].config.structure.n_cases,
        pipe.sets["vp"].config.structure.n_realizations,
    ) == (5000, 10000)
    assert pipe.evaluate_vp is not None and pipe.evaluate_vp.select_cases == "mean(snr) > 10"
    assert pipe.evaluate_vp.by[0] == "mean(snr)"  # bins of whole cases by their average S/N
    assert {"simulate-vp", "predict-vp", "evaluate-vp"} <= {s.name for s in build_steps(pipe)}


def test_example_pipelines_of_sects_6_and_7() -> None:
    varpsf = {
        v: load_pipeline(EXAMPLES / "varpsf" / f"pipeline{v}.toml") for v in ("", "-field", "-psf")
    }
    for v, pipe in varpsf.items():
        sizes = {
            n: (s.config.structure.n_cases, s.config.structure.n_realizations)
            for n, s in pipe.sets.items()
        }
        assert sizes == {
            "pretrain": (20000, 50),
            "tp": (5000, 2000),
            "tw": (200, 100000),
            "vo": (200, 100000),
            "vp": (5000, 10000),
        }
        assert pipe.sets["pretrain"].config.raw["noise"]["sigma"] == 0.1  # low noise (TP: 1.0)
        assert pipe.sets["tp"].config.raw["noise"]["sigma"] == 1.0
        assert pipe.pretrain is not None and pipe.pretrain.targets == ["tru_e1", "tru_e2"]
        assert pipe.train_point.hidden == [10, 10] and pipe.train_weight.hidden == [10]
        assert pipe.evaluate_vp is not None and pipe.evaluate_vp.select_cases == "mean(snr) > 10"
        assert pipe.name == v[1:]
        # the three setups share their sets: the same simulation steps (keys)
        assert [step_key(s, {}) for s in build_steps(pipe)[:5]] == [
            step_key(s, {}) for s in build_steps(varpsf[""])[:5]
        ]
    assert varpsf[""].train_point.features == FIVE
    assert varpsf["-field"].train_point.features == [*FIVE, "tru_field_x", "tru_field_y"]
    assert varpsf["-psf"].train_point.features == [
        *FIVE,
        "tru_psf_g1",
        "tru_psf_g2",
        "tru_psf_sigma",
    ]

    euclid = load_pipeline(EXAMPLES / "euclid" / "pipeline.toml")
    selected = load_pipeline(EXAMPLES / "euclid" / "pipeline-select.toml")
    sizes = {
        n: (s.config.structure.n_cases, s.config.structure.n_realizations)
        for n, s in euclid.sets.items()
    }
    assert sizes == {
        "pretrain": (10000, 100),
        "tp": (4000, 2000),
        "tw": (200, 200000),
        "vo": (200, 400000),
    }
    assert euclid.train_point.features == [
        "adamom_g1",
        "adamom_g2",
        "adamom_sigma",
        "adamom_logflux",
        "adamom_rho4",
    ]
    cut = "snr > 10 & adamom_sigma > 1.5"
    assert euclid.evaluate.select == selected.evaluate.select == cut
    assert euclid.train_weight.select is None and selected.train_weight.select == cut
    assert selected.name == "select" and selected.train_point == euclid.train_point
    small = load_pipeline(EXAMPLES / "euclid" / "pipeline.toml", ["scale=0.001"])
    assert (
        small.sets["vo"].config.structure.n_realizations == 400
        and small.sets["vo"].config.structure.n_cases == 200
    )


def test_cli_prints_vp_and_vo_tables(runner, cli, tmp_path: Path) -> None:
    path = write_pipeline(tmp_path, 'name = "nn"\n' + TINY_PIPELINE + PRETRAIN_VP)
    wd = tmp_path / "wd"
    result = runner.invoke(cli, ["run", str(path), "--workdir", str(wd)])
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert out.index("== VP: point estimates (nn/evaluation-vp.json) ==") < out.index(
        "== VO: overall validation"
    )
    assert "case selection: mean(snr) > 10" in out and "conditional biases by tru_rad" in out
    assert f"products in {wd}/: nn/evaluation.json, nn/evaluation-vp.json, manifest.json" in out
    assert (
        (wd / "nn" / "model.h5").is_file()
        and (wd / "tp.fits").is_file()
        and not (wd / "model.h5").exists()
    )
    bad = runner.invoke(
        cli, ["run", str(path), "pretrain.hidden=[3]", "--workdir", str(tmp_path / "other")]
    )
    assert bad.exit_code == 2
    err = bad.stderr if hasattr(bad, "stderr") else bad.output
    assert "pretrain.hidden: the pretraining uses" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "other").exists()


def test_correlated_noise_pipeline_differs_from_fiducial_1e6_by_its_noise_only() -> None:
    """The premise of the comparison in docs/realgal.md: same sets, seeds and training, other
    noise."""
    white = load_pipeline(EXAMPLES.parent / "models" / "fiducial-1e6-pipeline.toml")
    corr = load_pipeline(EXAMPLES / "realgal" / "pipeline-corrnoise-1e6.toml")
    assert white.train_point == corr.train_point and white.train_weight == corr.train_weight
    assert set(white.sets) == set(corr.sets) == {"tp", "tw", "vo"}
    for name, spec in corr.sets.items():
        a, b = json.loads(white.sets[name].config.to_json()), json.loads(spec.config.to_json())
        assert spec.seed == white.sets[name].seed
        noise_a, noise_b = a.pop("noise"), b.pop("noise")
        assert (
            noise_a["type"] == "gaussian"
            and noise_b["type"] == "correlated"
            and noise_b["sigma"] == noise_a["sigma"]
        )
        a.pop("description", None), b.pop("description", None)
        assert a == b, name


def test_bulge_disk_pipeline_differs_from_fiducial_1e6_by_its_galaxies_only() -> None:
    """Same sets, seeds, sizes, PSF, noise and training as fiducial-1e6; bulge + disk galaxies
    with the same size, brightness and (disk) shape distributions."""
    sersic = load_pipeline(EXAMPLES.parent / "models" / "fiducial-1e6-pipeline.toml")
    bd = load_pipeline(EXAMPLES / "realgal" / "pipeline-bulgedisk-1e6.toml")
    assert sersic.train_point == bd.train_point and sersic.train_weight == bd.train_weight
    for name, spec in bd.sets.items():
        a, b = json.loads(sersic.sets[name].config.to_json()), json.loads(spec.config.to_json())
        assert spec.seed == sersic.sets[name].seed
        gal_a, gal_b = a.pop("galaxy"), b.pop("galaxy")
        assert gal_a["profile"] == "sersic" and gal_b["profile"] == "bulgedisk"
        assert all(gal_a[k] == gal_b[k] for k in ("rad", "sb", "ellipticity", "angle"))
        a.pop("description", None), b.pop("description", None)
        assert a == b, name
