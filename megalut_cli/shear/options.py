"""The options of a bias evaluation, declared once: ``megalut evaluate`` flags and the
``[evaluate]``/``[evaluate_vp]`` keys of pipeline files (:class:`megalut_cli.schema.Option`);
and those of ``megalut predict`` (its click options, the defaults of
:func:`megalut_cli.shear.predict.predict_catalog`, the table of ``docs/catalogs.md``)."""

from __future__ import annotations

from megalut_cli.atomic import OVERWRITE_OPTION
from megalut_cli.parallel import NPROC_OPTION, SCHEDULER_OPTION
from megalut_cli.schema import Option

#: Most bins of a conditional bias (``--by``).
MAX_BINS = 1000

EVALUATE_OPTIONS: tuple[Option, ...] = (
    Option("by", "str_list", [], "Conditional biases in equal-population bins of these columns (true or measured) "
           "or quantities, e.g. tru_rad,tru_sersicn,snr; 'mean(snr)' bins whole cases by their average S/N (paper "
           "Fig. 12), 'sqrt(tru_e1**2+tru_e2**2)' bins rows by |e|.", metavar="COL,COL", empty_ok=True),
    Option("bins", "int", 5, "Number of bins for --by.", minimum=1, maximum=MAX_BINS),
    Option("select", "str", None, "Keep only the rows (realizations) where EXPR holds, e.g. \"snr > 10 & "
           "adamom_sigma > 1.5\" (studies selection biases).", metavar="EXPR"),
    Option("select_cases", "str", None, "Keep only the cases where EXPR of per-case aggregates holds, e.g. "
           "\"mean(snr) > 10\".", metavar="EXPR"),
)
EVALUATE = {o.name: o for o in EVALUATE_OPTIONS}

#: Fewest rows per chunk of ``megalut predict``.
MIN_CHUNK_ROWS = 1000

#: The options of ``megalut predict`` with a value (files aside).
PREDICT_OPTIONS: tuple[Option, ...] = (
    Option("chunk_rows", "int", 250_000, "Rows per chunk (memory bound and unit of work).", minimum=MIN_CHUNK_ROWS),
)
PREDICT = {o.name: o for o in PREDICT_OPTIONS}
#: Every option of ``megalut predict`` with a value, for the docs table.
ALL_PREDICT_OPTIONS: tuple[Option, ...] = (*PREDICT_OPTIONS, NPROC_OPTION, SCHEDULER_OPTION, OVERWRITE_OPTION)
