"""The options of measure, predict and simulate and the shared ones come from their declarations."""

from __future__ import annotations

import inspect

import pytest

from megalut_cli.atomic import OVERWRITE_OPTION
from megalut_cli.engine import DEVICE_OPTION, ENGINE_OPTION, ENGINES, check_engine
from megalut_cli.errors import ConfigError
from megalut_cli.measure import stamps
from megalut_cli.measure.measure import measure_file_columns
from megalut_cli.measure.options import MEASURE, MEASURE_OPTIONS
from megalut_cli.parallel import NPROC_OPTION, SCHEDULER_OPTION
from megalut_cli.schema import DEFAULT_MARK, Option, docs_table

SHARED = (ENGINE_OPTION, DEVICE_OPTION, NPROC_OPTION, SCHEDULER_OPTION, OVERWRITE_OPTION)


def check_click_option(params: dict, o: Option, default: object = None) -> None:
    """The click parameter of ``o`` has its default, type bounds, choices and help."""
    p = params[o.name]
    assert p.default == (o.default if default is None else default), o.name
    if o.kind == "choice":
        assert tuple(p.type.choices) == o.choices, o.name
    if o.minimum is not None:
        assert p.type.min == o.minimum and p.type.min_open == o.min_open, o.name
    if o.envvar is not None:
        assert p.envvar == o.envvar
    if o.short:
        assert o.short in p.opts


def test_measure_options_are_the_declarations(cli):
    params = {p.name: p for p in cli.get_command(None, "measure").params}
    for o in (*MEASURE_OPTIONS, *SHARED):
        check_click_option(params, o)
    assert (
        params["stamp_size"].help
        == "Stamp size in pixels [default: the image's STAMPSZ header card]."
    )
    assert params["stars"].secondary_opts == ["--no-stars"]


def test_measure_library_defaults_and_choices_from_the_declarations():
    defaults = {k: v.default for k, v in inspect.signature(measure_file_columns).parameters.items()}
    for name in ("stamp_size", "gain", "stars", "morphology"):
        assert defaults[name] == MEASURE[name].default, name
    assert str(defaults["origin"]) == MEASURE["origin"].default
    assert (
        defaults["engine"] == ENGINE_OPTION.default and defaults["device"] == DEVICE_OPTION.default
    )
    assert MEASURE["origin"].choices == tuple(str(o) for o in stamps.ORIGINS)
    assert MEASURE["stamp_size"].minimum == stamps.MIN_STAMP_SIZE
    assert ENGINE_OPTION.choices == tuple(ENGINES)


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--stamp-size", "2"], "--stamp-size"),
        (["--origin", "2"], "--origin"),
        (["--gain", "0"], "--gain"),
        (["--engine", "gpu"], "--engine"),
        (["--device", "tpu"], "--device"),
        (["-j", "x"], "-j"),
    ],
)
def test_measure_refuses_what_the_declarations_refuse(cli, runner, args, flag):
    r = runner.invoke(cli, ["measure", __file__, "-o", "-", *args])
    assert r.exit_code == 2 and f"Invalid value for '{flag}" in r.stderr


def test_the_default_note_goes_where_the_help_says():
    marked = Option("n", "int", None, f"How many{DEFAULT_MARK}.", default_text="all")
    plain = Option("n", "int", None, "How many.", default_text="all")
    assert marked.cli_help() == "How many [default: all]."
    assert plain.cli_help() == "How many. [default: all]"
    assert marked.doc_help() == plain.doc_help() == "How many."
    table = docs_table([marked], keys=False).splitlines()
    assert (
        table[0] == "| option | default | allowed | meaning |"
        and table[2] == "| `--n` | all | any | How many. |"
    )


def test_engine_and_device_checked_in_the_one_vocabulary():
    assert check_engine("galsim") == "galsim"
    with pytest.raises(
        ConfigError, match=r"^engine: unknown value 'gpu' \(expected one of fast, galsim\)$"
    ):
        check_engine("gpu")


def test_simulate_options_are_the_declarations(cli):
    from megalut_cli.measure.options import MEASURE as MEASURED
    from megalut_cli.sim.options import SIMULATE, SIMULATE_OPTIONS
    from megalut_cli.sim.simulate import simulate

    params = {p.name: p for p in cli.get_command(None, "simulate").params}
    for o in (*SIMULATE_OPTIONS, *SHARED):
        check_click_option(params, o)
    assert params["morphology"].help == "With --measure: a" + MEASURED["morphology"].help[1:]
    defaults = {k: v.default for k, v in inspect.signature(simulate).parameters.items()}
    for name in ("measure", "seed", "morphology"):
        assert defaults[name] == SIMULATE[name].default, name


def test_predict_options_are_the_declarations(cli, runner, tmp_path):
    from megalut_cli.shear.options import PREDICT, PREDICT_OPTIONS
    from megalut_cli.shear.predict import CHUNK_ROWS, predict_catalog

    params = {p.name: p for p in cli.get_command(None, "predict").params}
    for o in (*PREDICT_OPTIONS, NPROC_OPTION, SCHEDULER_OPTION, OVERWRITE_OPTION):
        check_click_option(params, o)
    assert inspect.signature(predict_catalog).parameters["chunk_rows"].default == CHUNK_ROWS
    assert CHUNK_ROWS == PREDICT["chunk_rows"].default
    r = runner.invoke(
        cli,
        [
            "predict",
            __file__,
            "--model",
            __file__,
            "-o",
            str(tmp_path / "p.fits"),
            "--chunk-rows",
            str(PREDICT["chunk_rows"].minimum - 1),
        ],
    )
    assert r.exit_code == 2 and "Invalid value for '--chunk-rows'" in r.stderr
