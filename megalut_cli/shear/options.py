"""The options of a bias evaluation, declared once: ``megalut evaluate`` flags and the
``[evaluate]``/``[evaluate_vp]`` keys of pipeline files (:class:`megalut_cli.schema.Option`)."""

from __future__ import annotations

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
