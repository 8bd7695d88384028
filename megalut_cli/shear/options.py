"""The options of a bias evaluation, declared once: ``megalut evaluate`` flags and the
``[evaluate]``/``[evaluate_vp]`` keys of pipeline files (:class:`megalut_cli.schema.Option`);
and those of ``megalut predict`` (its click options, the defaults of
:func:`megalut_cli.shear.predict.predict_catalog`, the table of ``docs/catalogs.md``)."""

from __future__ import annotations

from dataclasses import replace

from megalut_cli.atomic import OVERWRITE_OPTION
from megalut_cli.parallel import NPROC_OPTION, SCHEDULER_OPTION
from megalut_cli.schema import Option
from megalut_cli.seeding import SEED_OPTION
from megalut_cli.shear.bias import GREAT3_SIGMA2_MIN_GROUND

#: Most bins of a conditional bias (``--by``).
MAX_BINS = 1000
#: Format name of the JSON written by ``megalut evaluate --json``.
JSON_FORMAT = "megalut.evaluation"
JSON_FORMAT_VERSION = "1.5"  # 1.1: "provenance"; 1.2: "error", "bootstrap"; 1.3: shear term;
# 1.4: metacal "response_at", "calibration_response"; 1.5: metacal "failures"

EVALUATE_OPTIONS: tuple[Option, ...] = (
    Option(
        "by",
        "str_list",
        [],
        "Conditional biases in equal-population bins of these columns (true or measured) "
        "or quantities, e.g. tru_rad,tru_sersicn,snr; 'mean(snr)' bins whole cases by their "
        "average S/N (paper Fig. 12), 'sqrt(tru_e1**2+tru_e2**2)' bins rows by |e|.",
        metavar="COL,COL",
        empty_ok=True,
    ),
    Option("bins", "int", 5, "Number of bins for --by.", minimum=1, maximum=MAX_BINS),
    Option(
        "select",
        "str",
        None,
        'Keep only the rows (realizations) where EXPR holds, e.g. "snr > 10 & '
        'adamom_sigma > 1.5" (studies selection biases).',
        metavar="EXPR",
    ),
    Option(
        "select_cases",
        "str",
        None,
        'Keep only the cases where EXPR of per-case aggregates holds, e.g. "mean(snr) > 10".',
        metavar="EXPR",
    ),
)
EVALUATE = {o.name: o for o in EVALUATE_OPTIONS}

#: Where the errors of m and c come from (``--errors``).
ERROR_CHOICES = ("auto", "fit", "bootstrap")
#: The response that calibrates a metacal set's cases (``--response``).
RESPONSE_CHOICES = ("auto", "mean", "zero-shear")
#: How a metacal evaluation takes the rows measured on some versions only (``--failures``).
FAILURES_CHOICES = ("exclude", "selection")
#: Bootstrap resamples of ``megalut evaluate`` by default.
N_BOOTSTRAP = 200
#: The number of bootstrap resamples, of ``evaluate`` and ``calibrate`` alike.
BOOTSTRAP_OPTION = Option(
    "bootstrap",
    "int",
    N_BOOTSTRAP,
    "Number of bootstrap resamples.",
    minimum=10,
    maximum=100000,
)
#: The options of ``megalut evaluate`` alone (not pipeline keys), files aside.
EVALUATE_CLI_OPTIONS: tuple[Option, ...] = (
    Option(
        "fail_above",
        "bool",
        False,
        "Exit with status EXIT when the Stage IV requirement (|m| < 2e-3, "
        "|c| < 2e-4 for every component) does not hold, on the weighted results when the catalog "
        "has weights, else on the unweighted ones.",
    ),
    Option(
        "sigma2_min",
        "float",
        GREAT3_SIGMA2_MIN_GROUND,
        "Damping term of the GREAT3 Q_c metric: 4 for ground branches, 1 for space.",
        minimum=0,
    ),
    Option(
        "errors",
        "choice",
        ERROR_CHOICES[0],
        "Where the errors of m and c come from: 'fit' (residual scatter "
        "over cases), 'bootstrap' (resample galaxies: realization groups, all their cases "
        "together; needs the 'rea' column), 'auto': bootstrap for common-random-number sets "
        "(header CRN = T), else fit.",
        choices=ERROR_CHOICES,
    ),
    BOOTSTRAP_OPTION,
    Option(
        "response",
        "choice",
        RESPONSE_CHOICES[0],
        "Metacal catalogs: the response that calibrates the cases: 'mean' over all of them, "
        "'zero-shear' (the intercept of a fit of each case's own response against its true "
        "shear; metacal's step composes with the case's shear, so the mean carries the drawn "
        "shears' spin-4 moments into m; needs 10 cases), 'auto': zero-shear for "
        "common-random-number sets (header CRN = T) with 10 cases or more, else mean.",
        choices=RESPONSE_CHOICES,
    ),
    Option(
        "failures",
        "choice",
        FAILURES_CHOICES[0],
        "Metacal catalogs: the rows whose noshear version is measured and a sheared one is "
        "not: 'exclude' them (every version measured), or count each version's failures as "
        "a selection, with its selection response ('selection': removes the bias of failures "
        "that depend on the shear, at up to twice the error of a common-random-number set; "
        "megalut calibrate's default; docs/evaluate.md).",
        choices=FAILURES_CHOICES,
    ),
)
EVALUATE_CLI = {o.name: o for o in EVALUATE_CLI_OPTIONS}

#: Fewest rows per chunk of ``megalut predict``.
MIN_CHUNK_ROWS = 1000

#: The options of ``megalut predict`` with a value (files aside).
PREDICT_OPTIONS: tuple[Option, ...] = (
    Option(
        "chunk_rows",
        "int",
        250_000,
        "Rows per chunk (memory bound and unit of work).",
        minimum=MIN_CHUNK_ROWS,
    ),
    Option(
        "strict",
        "bool",
        False,
        "Refuse (exit 1, nothing written) a catalog that lies outside the model's "
        "training domain instead of warning: noise, snr, sizes, flux and their joint "
        "coverage, the PSF's size and ellipticity, stamp sizes, recorded setup, no usable "
        "row, no PSF measurement, a recorded bias beyond the Stage IV requirement (metacal "
        "models: snr, resolution, usable rows and recorded bias only); docs/model-format.md.",
    ),
)
PREDICT = {o.name: o for o in PREDICT_OPTIONS}
#: Every option of ``megalut predict`` with a value, for the docs table.
ALL_PREDICT_OPTIONS: tuple[Option, ...] = (
    *PREDICT_OPTIONS,
    NPROC_OPTION,
    SCHEDULER_OPTION,
    OVERWRITE_OPTION,
)

#: Format name of the JSON written by ``megalut calibrate --json``.
CALIBRATION_FORMAT = "megalut.calibration"
CALIBRATION_FORMAT_VERSION = "1.1"  # 1.1: "failures"
#: Where the errors of ``megalut calibrate`` come from (``--errors``).
CALIBRATE_ERROR_CHOICES = ("auto", "jackknife", "bootstrap")
#: Jackknife patches of ``megalut calibrate`` by default.
N_PATCHES = 100

#: The options of ``megalut calibrate`` with a value (files aside).
CALIBRATE_OPTIONS: tuple[Option, ...] = (
    Option(
        "select",
        "str",
        None,
        'Keep only the objects where EXPR holds, e.g. "snr > 10 & adamom_sigma > 1.5" '
        "(metacal: on the noshear features, its selection response from the sheared ones).",
        metavar="EXPR",
    ),
    Option(
        "by",
        "str",
        None,
        "Calibrate in bins of this column or quantity as well: an integer column (e.g. a "
        "tomographic bin) value by value, else --bins equal-population bins (metacal: a "
        "measured column's bins are a selection, with its response); 'patch': about --bins "
        "patches of the sky (ra, dec; else x, y), each with its bootstrap error.",
        metavar="COL",
    ),
    Option(
        "bins",
        "int",
        5,
        "Number of bins for --by (a float column, or sky patches).",
        minimum=1,
        maximum=MAX_BINS,
    ),
    Option(
        "unweighted",
        "bool",
        False,
        "Ignore the weights pre_g1_w, pre_g2_w (every object counts the same).",
    ),
    Option(
        "errors",
        "choice",
        CALIBRATE_ERROR_CHOICES[0],
        "Where the errors come from: 'jackknife' over patches of the sky (ra, dec; else the "
        "image x, y), 'bootstrap' over objects (--bootstrap, --seed), 'auto': the jackknife "
        "when the catalog has positions, else the bootstrap.",
        choices=CALIBRATE_ERROR_CHOICES,
    ),
    Option(
        "patches",
        "int",
        N_PATCHES,
        "Jackknife patches: a regular grid of about this many cells over (ra cos dec, dec) "
        "or (x, y); empty cells are dropped.",
        minimum=2,
        maximum=100000,
    ),
    BOOTSTRAP_OPTION,
    replace(
        EVALUATE_CLI["failures"],
        default=FAILURES_CHOICES[1],
        help="Metacal catalogs: the objects whose noshear version is measured and a sheared "
        "one is not: count each version's failures as a selection ('selection': the response "
        "of the versions' means, each over its own measured objects, as metadetection takes "
        "it), or 'exclude' them (every version measured; biased where failures depend on the "
        "shear; docs/calibrate.md).",
    ),
)
CALIBRATE = {o.name: o for o in CALIBRATE_OPTIONS}
#: Every option of ``megalut calibrate`` with a value, for the docs table.
ALL_CALIBRATE_OPTIONS: tuple[Option, ...] = (*CALIBRATE_OPTIONS, SEED_OPTION, OVERWRITE_OPTION)
