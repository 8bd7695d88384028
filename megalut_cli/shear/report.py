"""The text report of an evaluation result (:func:`megalut_cli.shear.evaluate.evaluate_catalog`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from megalut_cli.shear.bias import STAGE_IV_C, STAGE_IV_M
from megalut_cli.shear.bootstrap import ERROR_BOOTSTRAP
from megalut_cli.shear.evaluate import SCHEMES


def error_note(result: Mapping[str, Any]) -> str:
    """One line saying which errors the result quotes."""
    boot = result.get("bootstrap")
    if result.get("error") != ERROR_BOOTSTRAP or not boot:
        return "errors: from the fit (residual scatter of the per-case averages about the line)"
    what = (
        "common-random-number set: the cases share their galaxies"
        if boot["crn"]
        else "galaxy groups"
    )
    shears = (
        " + the drawn shears' term from the excess residuals (docs/evaluate.md)"
        if boot.get("shear_term")
        else ""
    )
    return (
        f"errors: bootstrap over galaxies ({what}; {boot['groups']} groups of {boot['group_size']} "
        f"realization(s) resampled across all cases, {boot['resamples']} resamples, "
        f"seed {boot['seed']}){shears}"
    )


def _pm(v: float | None, e: float | None) -> str:
    if v is None:
        return f"{'undetermined':>21}"
    err = f"{e:.1e}" if e is not None else "  n/a  "
    return f"{v:+.2e} ± {err}"


def _pm_short(v: float | None, e: float | None) -> str:
    if v is None:
        return f"{'n/a':^17}"
    return f"{v:+.1e}±{e:.1e}" if e is not None else f"{v:+.1e}±  n/a  "


def _ok(fit: Mapping[str, Any]) -> str:
    m, c = fit["m"], fit["c"]
    if m is None or c is None:
        return "?"
    return "ok" if abs(m) < STAGE_IV_M and abs(c) < STAGE_IV_C else "OUT"


def _matrix(r: Any) -> str:
    return (
        "[["
        + "], [".join(", ".join("n/a" if v is None else f"{v:+.4f}" for v in row) for row in r)
        + "]]"
    )


def metacal_lines(mcal: Mapping[str, Any] | None) -> list[str]:
    """The report lines of a metacal evaluation: what is calibrated, by which responses."""
    if not mcal:
        return []
    zero = mcal.get("response_at") == "zero-shear"
    means = mcal.get("failures") == "selection"  # the response of the versions' means
    how = (
        ("R(0) of the versions' means, at zero shear" if zero else "R of the versions' means")
        if means
        else ("R(0) + R_sel(0), at zero shear" if zero else "<R> + R_sel")
    )
    lines = [
        f"metacal: {', '.join(mcal['estimate'])} calibrated by ({how})^-1, step {mcal['step']:g}"
        + (
            "; each version's failures a selection"
            if means
            else "; rows failing on a sheared version excluded (calibrate's default counts "
            "them as a selection: --failures selection)"
        )
    ]
    for scheme, r in mcal["response"].items():
        sel = mcal["selection_response"].get(scheme)
        lines.append(
            f"  {scheme}: {'R' if means else '<R>'} = {_matrix(r)}"
            + (f", R_sel = {_matrix(sel)}" if sel is not None else "")
            + (f"; at zero shear {_matrix(mcal['calibration_response'][scheme])}" if zero else "")
        )
    return lines


def format_table(result: Mapping[str, Any]) -> str:
    """A readable text report of an evaluation result."""
    lines = [f"shear biases of {result['input']}"]
    lines.append(
        f"rows: {result['n_rows']} in catalog, {result['n_selected']} selected, "
        f"{result['n_valid']} usable (flags == 0, finite estimates)"
    )
    if result.get("select"):
        lines.append(f"row selection: {result['select']}")
    if result.get("select_cases"):
        lines.append(f"case selection: {result['select_cases']}")
    round_psf = bool(result.get("psf_frame") and result["psf_frame"].get("round"))
    hidden = ("plus", "cross") if round_psf else ()  # identical to g1, g2: kept in JSON only
    if result.get("psf_frame"):
        note = " (round PSF in every case: same as g1, g2, not repeated)" if round_psf else ""
        lines.append(
            f"PSF frame (plus, cross) from {', '.join(result['psf_frame']['columns'])}{note}"
        )
    lines.append(f"Stage IV requirement: |m| < {STAGE_IV_M:.0e}, |c| < {STAGE_IV_C:.0e}")
    lines.append(error_note(result))
    lines += metacal_lines(result.get("metacal"))
    header = f"  {'':6}{'m':^22}   {'c':^22}  {'cases':>6} {'rows':>10}  req"
    for scheme in SCHEMES:
        if scheme not in result:
            continue
        lines += [
            "",
            f"{scheme} (per-case {'weighted ' if scheme == 'weighted' else ''}averages)",
            header,
        ]
        for comp, f in result[scheme].items():
            if comp in hidden:
                continue
            lines.append(
                f"  {comp:6}{_pm(f['m'], f['m_err']):>22}   {_pm(f['c'], f['c_err']):>22}  "
                f"{f['n_cases']:>6} {f['n_rows']:>10}  {_ok(f)}"
            )
    q = result.get("q_c")
    if q:
        frame = "+/x" if q["frame"] == "psf" else "1/2"
        vals = ", ".join(
            f"{s} {q[s]:.1f}" if q.get(s) is not None else f"{s} n/a" for s in SCHEMES if s in q
        )
        lines += ["", f"GREAT3 Q_c ({frame} frame, sigma2_min={q['sigma2_min']:g}): {vals}"]
    req = result["requirement"]
    verdict = "met" if req["met"] else "NOT met (" + "; ".join(req["failures"]) + ")"
    lines.append(f"Stage IV requirement on {req['applies_to']} results: {verdict}")
    for col, cond in (result.get("conditional") or {}).items():
        for scheme in SCHEMES:
            if not cond["bins"] or scheme not in cond["bins"][0]:
                continue
            comps = list(cond["bins"][0][scheme])
            lines += [
                "",
                f"conditional biases by {col} "
                f"({len(cond['bins'])} equal-population bins, {scheme})",
            ]
            for frame in (comps[:2], comps[2:]):
                if not frame or frame[0] in hidden:
                    continue
                head = f"  {'range':^23} {'rows':>9} {'cases':>6}"
                for comp in frame:
                    head += f"  {'m_' + comp:^17} {'c_' + comp:^17}"
                lines.append(head)
                for b in cond["bins"]:
                    f0 = b[scheme][frame[0]]
                    row = f"  [{b['lo']:10.4g},{b['hi']:10.4g}] {b['n_rows']:>9} {f0['n_cases']:>6}"
                    for comp in frame:
                        f = b[scheme][comp]
                        row += f"  {_pm_short(f['m'], f['m_err'])} {_pm_short(f['c'], f['c_err'])}"
                    lines.append(row)
    return "\n".join(lines)
