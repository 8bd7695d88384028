"""The option schema and the one validation vocabulary: same rule and message everywhere,
click options and docs tables generated from the declarations."""

from __future__ import annotations

import math
from dataclasses import asdict, fields
from pathlib import Path

import pytest
from pipeline_configs import write_pipeline
from sim_configs import write

from megalut_cli.doctables import TABLES, docs_files, render
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.nn.defaults import OPTIMIZERS, POINT_ITERATIONS, WEIGHT_ITERATIONS
from megalut_cli.nn.options import (
    OPTION,
    POINT_OPTION,
    TRAIN_OPTIONS,
    WEIGHT_OPTION,
    PointSpec,
    WeightSpec,
)
from megalut_cli.nn.train import TrainSettings
from megalut_cli.pipeline.file import load_pipeline
from megalut_cli.schema import (
    OneOf,
    Option,
    Required,
    Table,
    check_choice,
    check_float,
    check_int,
    check_params,
    check_table,
    kinds_table,
    resolve_path,
)
from megalut_cli.sim import psf as psf_mod
from megalut_cli.sim.config import load_config
from megalut_cli.sim.distributions import parse_distribution

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("value", [100, 100.0])
def test_integers_may_be_written_as_integral_floats(value):
    assert check_int(value, "k", 1) == 100 and isinstance(check_int(value, "k", 1), int)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (100.5, "k: expected an integer, got 100.5"),
        (True, "k: expected an integer, got True"),
        ("3", "k: expected an integer, got '3'"),
        (0, "k: must be >= 1, got 0"),
        (11, "k: must be <= 10, got 11"),
    ],
)
def test_bad_integers(value, message):
    with pytest.raises(ConfigError) as info:
        check_int(value, "k", 1, 10)
    assert str(info.value) == message


@pytest.mark.parametrize(
    ("kwargs", "value", "message"),
    [
        ({}, "x", "k: expected a number, got 'x'"),
        ({}, math.nan, "k: must be a finite number, got nan"),
        ({"lo": 0.0, "lo_open": True}, 0.0, "k: must be > 0, got 0.0"),
        ({"lo": 0.0, "hi": 1.0, "hi_open": True}, 1, "k: must be in [0, 1), got 1"),
    ],
)
def test_bad_numbers(kwargs, value, message):
    with pytest.raises(ConfigError) as info:
        check_float(value, "k", **kwargs)
    assert str(info.value) == message


def test_tables_and_choices():
    assert check_table(None, "t") == {}
    with pytest.raises(ConfigError, match=r"^t: missing \[t\] table$"):
        check_table(None, "t", required=True)
    with pytest.raises(ConfigError, match=r"^t\.b: unknown key \(allowed: a\)$"):
        check_table({"a": 1, "b": 2}, "t", {"a"})
    with pytest.raises(ConfigError, match=r"^k: unknown value 'c' \(expected one of a, b\)$"):
        check_choice("c", "k", ("a", "b"))


def test_n_cases_as_a_float_means_the_same_in_every_config(tmp_path):
    """`n_cases = 100.0` is accepted by a simulation config and a pipeline set alike."""
    sim = load_config(write(tmp_path), ["structure.n_cases=6.0"])
    assert sim.structure.n_cases == 6
    pipe = load_pipeline(
        write_pipeline(tmp_path), ["sets.tp.n_cases=6.0", "train_point.members=4.0"]
    )
    assert pipe.sets["tp"].config.structure.n_cases == 6
    assert pipe.train_point.members == 4
    assert parse_distribution({"type": "grid", "min": 0.0, "max": 1.0, "n": 3.0}, "k").values == (
        0.0,
        0.5,
        1.0,
    )
    for override, message in (
        ("structure.n_cases=6.5", "structure.n_cases: expected an integer, got 6.5"),
    ):
        with pytest.raises(ConfigError, match=message):
            load_config(write(tmp_path), [override])
    with pytest.raises(ConfigError, match="sets.tp.n_cases: expected an integer, got 6.5"):
        load_pipeline(write_pipeline(tmp_path), ["sets.tp.n_cases=6.5"])


def test_relative_paths_beside_the_naming_file_then_the_current_folder(tmp_path, monkeypatch):
    (tmp_path / "conf").mkdir()
    (tmp_path / "conf" / "a.fits").write_text("beside")
    (tmp_path / "a.fits").write_text("cwd")
    (tmp_path / "b.fits").write_text("cwd only")
    monkeypatch.chdir(tmp_path)
    assert (
        resolve_path("a.fits", "k", tmp_path / "conf") == (tmp_path / "conf" / "a.fits").resolve()
    )
    assert resolve_path("b.fits", "k", tmp_path / "conf") == (tmp_path / "b.fits").resolve()
    assert resolve_path("conf", "k", None, folder=True) == (tmp_path / "conf").resolve()
    with pytest.raises(InputError, match="^k: no such file 'c.fits'"):
        resolve_path("c.fits", "k", tmp_path / "conf")


def test_training_defaults_come_from_the_declarations():
    """The specs have one field per declaration, named as the option, with its default; a
    member's settings are derived from the spec and default to the same values."""
    for spec, iterations in ((PointSpec(), POINT_ITERATIONS), (WeightSpec(), WEIGHT_ITERATIONS)):
        assert [f.name for f in fields(spec)] == [o.name for o in spec.OPTIONS]
        assert {o.name for o in TRAIN_OPTIONS} <= {f.name for f in fields(spec)}
        for o in spec.OPTIONS:
            assert getattr(spec, o.name) == o.default, o.name
        assert spec.iterations == iterations
        settings = TrainSettings.of(spec, "msb", "cpu")
        for name in ("iterations", "batch_fraction", "batch_iterations", "optimizer", "precision"):
            assert getattr(settings, name) == getattr(spec, name)
    assert TrainSettings() == TrainSettings.of(PointSpec(), "msb", "cpu")
    assert PointSpec().features is not PointSpec().features  # a fresh list each
    assert OPTION["iterations"].default == POINT_ITERATIONS
    assert OPTION["optimizer"].choices and OPTION["normalization"].choices
    from megalut_cli.nn import normalization as norm

    assert (
        OPTION["normalization"].choices == norm.METHODS
        and OPTION["optimizer"].choices == OPTIMIZERS
    )


def test_a_spec_round_trips_through_its_dict():
    """A pipeline step's parameters are its spec's dict; the spec rebuilt from them is equal."""
    spec = PointSpec(
        features=["a", "b"],
        hidden=[3],
        select_cases="mean(snr) > 10",
        members=2,
        precision="float32",
    )
    assert PointSpec(**asdict(spec)) == spec
    assert asdict(spec)["precision"] == "float32" and "dtype" not in asdict(spec)
    weight = WeightSpec(select="snr > 10", seed=4)
    assert WeightSpec(**asdict(weight)) == weight


@pytest.mark.parametrize(
    ("command", "iterations"),
    [("train-point", POINT_ITERATIONS), ("train-weight", WEIGHT_ITERATIONS)],
)
def test_click_options_are_the_declarations(cli, command, iterations):
    params = {p.name: p for p in cli.get_command(None, command).params}
    for o in TRAIN_OPTIONS:
        p = params[o.name]
        expected = iterations if o.name == "iterations" else o.default
        assert p.default == expected, o.name
        assert o.help in p.help
        if o.kind == "choice":
            assert tuple(p.type.choices) == o.choices
        if o.minimum is not None:
            assert p.type.min == o.minimum
    if command == "train-point":
        assert tuple(params["cost"].type.choices) == POINT_OPTION["cost"].choices
    else:
        assert params["hidden"].default == ",".join(map(str, WEIGHT_OPTION["hidden"].default))


@pytest.mark.parametrize(
    ("flag", "value", "key"),
    [
        ("--members", "0", "members"),
        ("--batch-fraction", "0", "batch_fraction"),
        ("--valid-fraction", "1", "valid_fraction"),
        ("--optimizer", "sgd", "optimizer"),
    ],
)
def test_one_range_for_flag_and_pipeline_key(cli, runner, tmp_path, flag, value, key):
    """A value the declaration refuses is refused by the command line (usage error) and by
    a pipeline file (naming the key)."""
    r = runner.invoke(cli, ["train-point", __file__, "-o", str(tmp_path / "m.h5"), flag, value])
    assert r.exit_code == 2 and f"Invalid value for '{flag}'" in r.stderr
    with pytest.raises(ConfigError, match=f"^train_point.{key}: "):
        load_pipeline(
            write_pipeline(tmp_path),
            [
                f"train_point.{key}={value!r}"
                if key == "optimizer"
                else f"train_point.{key}={value}"
            ],
        )
    with pytest.raises(ConfigError, match=f"^{key}: "):
        PointSpec.from_values({key: int(value) if value.isdigit() else value})


def test_keep_larger_than_members(cli, runner, tmp_path):
    with pytest.raises(
        ConfigError, match=r"^train_weight.keep: must be <= train_weight.members \(2\), got 3$"
    ):
        load_pipeline(write_pipeline(tmp_path), ["train_weight.members=2", "train_weight.keep=3"])
    r = runner.invoke(
        cli,
        [
            "train-weight",
            __file__,
            "--model",
            __file__,
            "-o",
            str(tmp_path / "m.h5"),
            "--members",
            "2",
            "--keep",
            "3",
        ],
    )
    assert r.exit_code == 2 and "--keep: must be <= --members (2), got 3" in r.stderr


def test_an_option_declaration():
    o = Option("n", "int", 3, "How many.", minimum=1)
    assert o.cli_flag == "--n" and o.check(4.0, "t.n") == 4 and o.range_text() == ">= 1"
    assert Table({"n": 2}, "t").option(o) == 2 and Table({}, "t").option(o) == 3
    with pytest.raises(ValueError):
        Option("c", "choice", "a", "A choice without choices.")


@pytest.mark.parametrize("name", sorted(TABLES))
def test_docs_tables_are_current(name):
    """Every generated table of docs/ is what ``python -m megalut_cli.doctables`` writes."""
    pages = [p for p in docs_files(ROOT) if f"<!-- table: {name} -->" in p.read_text()]
    assert pages, f"no docs page holds the table {name}"
    for page in pages:
        text = page.read_text()
        assert render(text) == text, f"{page} is out of date: run python -m megalut_cli.doctables"


def test_a_new_psf_type_is_one_registration():
    """Registering a type makes it a valid psf.type with its own keys, checks and profile."""
    import galsim

    def check(spec, full, where):
        check_float(full["size"], f"{where}.size", 0.0, lo_open=True)

    kind = psf_mod.PsfType(
        "box",
        (Option("size", "float", 2.0, "side, pixels"),),
        check,
        lambda spec, x, y: (
            galsim.Box(spec.get("size", 2.0), spec.get("size", 2.0)),
            {"tru_psf_g1": 0.0, "tru_psf_g2": 0.0, "tru_psf_sigma": 0.0},
        ),
    )
    psf_mod.register_psf_type(kind)
    try:
        psf_mod.validate_psf_config({"type": "box", "size": 3.0})
        prof, truth = psf_mod.make_psf({"type": "box", "size": 3.0}, 0.5, 0.5)
        assert prof.flux == pytest.approx(1.0) and truth["tru_psf_g1"] == 0.0
        with pytest.raises(ConfigError, match=r"^psf.size: must be > 0, got -1"):
            psf_mod.validate_psf_config({"type": "box", "size": -1})
        with pytest.raises(ConfigError, match=r"^psf.sigma: unknown key for PSF type 'box'"):
            psf_mod.validate_psf_config({"type": "box", "sigma": 1.0})
        with pytest.raises(ValueError, match="already registered"):
            psf_mod.register_psf_type(kind)
    finally:
        del psf_mod.PSF_REGISTRY["box"]
    with pytest.raises(ConfigError, match="unknown PSF type 'box'"):
        psf_mod.validate_psf_config({"type": "box"})


def test_check_params_is_the_one_check_of_a_kind():
    """check_params: keys of the kind only (the kind says why it refuses another), its rules in
    order, each value given checked by its declaration (distributions and paths left to the
    reader), defaults where not given."""
    options = (
        Option("size", "float", 2.0, "side", minimum=0.0, min_open=True),
        Option("a", "dist", None, "a"),
        Option("b", "dist", None, "b"),
        Option("path", "path", None, "p"),
    )
    rules = (Required("size", "the side"), OneOf(("a", "b"), "needs one of a or b, got {got}"))
    with pytest.raises(ConfigError, match=r"^t\.c: unknown key \(allowed: a, b, path, size\)$"):
        check_params({"size": 1.0, "a": 1, "c": 2}, "t", options, rules)
    with pytest.raises(ConfigError, match=r"^t\.c: not mine$"):
        check_params({"c": 2}, "t", options, rules, lambda key: "not mine")
    with pytest.raises(ConfigError, match=r"^t\.size: missing \(the side\)$"):
        check_params({"a": 1}, "t", options, rules)
    with pytest.raises(ConfigError, match=r"^t\.a: needs one of a or b, got a, b$"):
        check_params({"size": 1.0, "a": 1, "b": 2}, "t", options, rules)
    with pytest.raises(ConfigError, match=r"^size: must be > 0, got -1$"):
        check_params({"size": -1, "a": 1}, "", options, rules)
    values = check_params({"size": 3, "a": {"type": "uniform"}, "path": 3}, "t", options, rules)
    assert values == {"size": 3.0, "a": {"type": "uniform"}, "b": None, "path": 3}
    table = kinds_table(
        (Option("type", "choice", None, "kind", choices=("x", "y")),),
        {"x": options[:2], "y": options[:1]},
        "types",
    )
    assert "| `size` | `x`, `y` | 2.0 | > 0 | side |" in table
    assert "| `a` | `x` | none | *dist* | a |" in table


def test_evaluation_bins_one_range(cli, runner, tmp_path):
    """``bins`` is declared once: the same upper bound on the command line and in a pipeline."""
    r = runner.invoke(cli, ["evaluate", __file__, "--by", "snr", "--bins", "1001"])
    assert r.exit_code == 2 and "Invalid value for '--bins'" in r.stderr
    with pytest.raises(ConfigError, match=r"^evaluate.bins: must be <= 1000, got 1001$"):
        load_pipeline(write_pipeline(tmp_path), ["evaluate.bins=1001"])
    assert load_pipeline(write_pipeline(tmp_path), ["evaluate.bins=7.0"]).evaluate.bins == 7


def test_pipeline_keys_are_the_declarations(tmp_path):
    """The top-level and [sets.X] keys a pipeline accepts, their defaults and ranges, are
    those declared in pipeline.config (unknown keys list them)."""
    from megalut_cli.pipeline.config import DEFAULT_SET_SEEDS, PIPELINE, SET_OPTION

    pipe = load_pipeline(write_pipeline(tmp_path))
    assert pipe.scale == PIPELINE["scale"].default and pipe.engine == PIPELINE["engine"].default
    assert pipe.description == "" or isinstance(pipe.description, str)
    with pytest.raises(
        ConfigError, match=r"^sets\.tp\.bogus: unknown key \(allowed: (.*)\)$"
    ) as err:
        load_pipeline(write_pipeline(tmp_path), ["sets.tp.bogus=1"])
    assert err.value.args[0].endswith(", ".join(sorted(SET_OPTION)) + ")")
    with pytest.raises(ConfigError, match=r"^bogus: unknown key \(allowed: "):
        load_pipeline(write_pipeline(tmp_path), ["bogus=1"])
    with pytest.raises(
        ConfigError,
        match=r"^sets\.tp\.scale_by: unknown value 'rows' \(expected one of both, cases, "
        r"realizations\)$",
    ):
        load_pipeline(write_pipeline(tmp_path), ["sets.tp.scale_by=rows"])
    with pytest.raises(ConfigError, match=r"^sets\.tw\.seed: must be >= 0, got -1$"):
        load_pipeline(write_pipeline(tmp_path), ["sets.tw.seed=-1"])
    with pytest.raises(ConfigError, match=r"^description: expected a string, got 3$"):
        load_pipeline(write_pipeline(tmp_path), ["description=3"])
    # integers written as integral floats, as everywhere
    assert (
        load_pipeline(write_pipeline(tmp_path), ["sets.vo.n_cases=3.0"])
        .sets["vo"]
        .config.structure.n_cases
        == 3
    )
    text = write_pipeline(tmp_path).read_text()
    unseeded = write_pipeline(
        tmp_path, "\n".join(line for line in text.splitlines() if not line.startswith("seed"))
    )
    assert {n: s.seed for n, s in load_pipeline(unseeded).sets.items()} == {
        n: DEFAULT_SET_SEEDS[n] for n in load_pipeline(unseeded).sets
    }
