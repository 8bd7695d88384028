"""Figures of ``megalut evaluate --plot`` (matplotlib, the optional ``plot`` extra).

Top: residuals ``<g_est> - g`` of every case against its true shear, one panel per
component (``g1, g2`` and, with PSF columns, ``plus, cross``), unweighted then weighted
(paper Figs. 13, 14 and 19), with the fitted line; ``m, c`` are given in the panel's
title, clear of the data. The green band is the Stage IV requirement,
``|m g + c| < 2e-3 |g| + 2e-4``. Further rows: conditional ``m`` and ``c`` per
equal-population bin of each ``--by`` column (axis labelled with its unit) with 1-sigma
error bars (horizontal bars span the bin), against the bands ``|m| < 2e-3`` and
``|c| < 2e-4`` (paper Figs. 12 and 15). An overall fit with ``|m| > 0.1`` beyond its
1-sigma error (an untrained or mismatched model) gets a red frame and title, and a
warning line atop the figure (conditional bins are not flagged: faint or small galaxies
may carry such biases in a sound model).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from megalut_cli.atomic import atomic_output
from megalut_cli.columns import describe
from megalut_cli.errors import ArgumentValueError, MegalutError
from megalut_cli.shear.bias import STAGE_IV_C, STAGE_IV_M
from megalut_cli.shear.evaluate import WARN_M, large_m, m_too_large

_LABELS = {"g1": "g_1", "g2": "g_2", "plus": "g_+", "cross": r"g_\times"}
_COLORS = {"g1": "C0", "g2": "C1", "plus": "C2", "cross": "C3"}
_FORMATS = {".png": "png", ".pdf": "pdf", ".svg": "svg"}
#: The file name endings ``--plot`` accepts.
PLOT_SUFFIXES = tuple(_FORMATS)
#: How to install matplotlib: a command that works from a clone and from an installed
#: wheel alike (``pip install '.[plot]'`` in the clone does the same).
MATPLOTLIB_HINT = "pip install matplotlib"
_BAND = {"color": "#2ca02c", "alpha": 0.25, "lw": 0}
_WARN_COLOR = "#c00000"
_AGGREGATE = re.compile(r"^(mean|median|min|max|std)\((?P<col>\w+)\)$")


def _figure_class() -> Any:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise MegalutError(f"figures need matplotlib: {MATPLOTLIB_HINT}") from None
    return Figure


def check_plot_suffix(path: str | os.PathLike, argument: str = "plot_path") -> None:
    """A usage error (:class:`ArgumentValueError`, exit 2) unless ``path`` ends in a
    supported extension; its message names the supported ones."""
    if Path(path).suffix.lower() not in _FORMATS:
        raise ArgumentValueError(
            argument,
            f": {path}: unsupported figure type (use a name ending in {', '.join(PLOT_SUFFIXES)})",
        )


def check_plot_output(path: str | os.PathLike) -> None:
    """Fail early when the file type is not supported (exit 2) or matplotlib is missing."""
    check_plot_suffix(path)
    _figure_class()


def _arr(values: Any) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _fmt(v: float | None, e: float | None) -> str:
    if v is None:
        return "n/a"
    return f"{v:+.2e} ± {e:.1e}" if e is not None else f"{v:+.2e}"


def axis_label(column: str) -> str:
    """Axis label of a ``--by`` column or per-case aggregate: its name and unit
    (``tru_rad [pixel]``, ``mean(adamom_sigma) [pixel]``); no unit when not known."""
    agg = _AGGREGATE.match(column)
    desc = describe(agg["col"] if agg else column)
    if desc is None:
        return column
    return f"{column} [{desc[0]}]" if desc[0] else f"{column} (dimensionless)"


def _warn_frame(ax: Any) -> None:
    for spine in ax.spines.values():
        spine.set_edgecolor(_WARN_COLOR)
        spine.set_linewidth(2.0)


def _residual_panel(
    ax: Any, per_case: Mapping[str, Any], fit: Mapping[str, Any], comp: str, scheme: str
) -> None:
    tru, pre = _arr(per_case["tru"]), _arr(per_case["pre"])
    ok = np.isfinite(tru) & np.isfinite(pre)
    tru, res = tru[ok], pre[ok] - tru[ok]
    lim = max(float(np.max(np.abs(tru))) if tru.size else 0.1, 1e-3) * 1.1
    g = np.linspace(-lim, lim, 201)
    band = STAGE_IV_M * np.abs(g) + STAGE_IV_C
    ax.fill_between(g, -band, band, **_BAND, label="Stage IV requirement")
    ax.axhline(0.0, color="0.5", lw=0.6)
    ax.plot(tru, res, ".", ms=3, color=_COLORS[comp], alpha=0.7, label="cases")
    if fit["m"] is not None:
        ax.plot(g, fit["m"] * g + fit["c"], "-", color="k", lw=1, label="fit m g + c")
    ax.set_xlim(-lim, lim)
    ax.locator_params(axis="x", nbins=5)
    lab = _LABELS[comp]
    ax.set_xlabel(f"true shear ${lab}$ (dimensionless)", fontsize=8)
    ax.set_ylabel(rf"$\langle\hat{{{lab}}}\rangle - {lab}$ per case", fontsize=8)
    title = (
        f"{scheme} ${lab}$ ({fit['n_cases']} cases)\n"
        f"m = {_fmt(fit['m'], fit['m_err'])}\nc = {_fmt(fit['c'], fit['c_err'])}"
    )
    warn = m_too_large(fit["m"], fit["m_err"])
    if warn:
        title += f"\n|m| > {WARN_M:g}: model untrained or mismatched?"
        _warn_frame(ax)
    ax.set_title(title, fontsize=8, family="monospace", color=_WARN_COLOR if warn else "black")
    ax.tick_params(labelsize=7)
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 2))


def _conditional_panel(
    ax: Any, col: str, cond: Mapping[str, Any], scheme: str, key: str, comps: list[str]
) -> None:
    tol = STAGE_IV_M if key == "m" else STAGE_IV_C
    ax.axhspan(-tol, tol, **_BAND)
    ax.axhline(0.0, color="0.5", lw=0.6)
    bins = cond["bins"]
    if bins:
        lo, hi = _arr(b["lo"] for b in bins), _arr(b["hi"] for b in bins)
        center = _arr(b["center"] for b in bins)
        for k, comp in enumerate(comps):
            y = _arr(b[scheme][comp][key] for b in bins)
            e = _arr(b[scheme][comp][f"{key}_err"] for b in bins)
            x = center + (k - (len(comps) - 1) / 2) * 0.06 * (
                hi - lo
            )  # side by side within the bin
            ax.errorbar(
                x,
                y,
                yerr=np.where(np.isfinite(e), e, 0.0),
                xerr=[np.maximum(x - lo, 0), np.maximum(hi - x, 0)],
                fmt="o",
                ms=3,
                lw=0.8,
                elinewidth=0.8,
                color=_COLORS[comp],
                label=f"${_LABELS[comp]}$",
            )
    ax.set_xlabel(axis_label(col), fontsize=8)
    ax.set_ylabel("m (multiplicative bias)" if key == "m" else "c (additive bias)", fontsize=8)
    ax.set_title(f"{scheme} {key} by {col}", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 2))


def plot_evaluation(
    result: Mapping[str, Any], path: str | os.PathLike, overwrite: bool = False
) -> Path:
    """Draw the evaluation figure of ``result`` (from :mod:`.evaluate`) into ``path``
    (png/pdf/svg)."""
    check_plot_output(path)
    return save_figure(evaluation_figure(result), path, overwrite)


def save_figure(fig: Any, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write a matplotlib ``Figure`` atomically, its type from the suffix of ``path``."""
    fmt = _FORMATS[Path(path).suffix.lower()]
    with atomic_output(path, overwrite) as tmp:
        fig.savefig(tmp, format=fmt, dpi=100)
    return Path(path)


def evaluation_figure(result: Mapping[str, Any]) -> Any:
    """The matplotlib ``Figure`` of :func:`plot_evaluation` (not saved)."""
    Figure = _figure_class()
    schemes = [s for s in ("unweighted", "weighted") if s in result]
    comps = list(result[schemes[0]])
    if (result.get("psf_frame") or {}).get("round"):  # the PSF frame repeats g1, g2: not drawn
        comps = [c for c in comps if c not in ("plus", "cross")]
    conditional = result.get("conditional") or {}
    panels = [(scheme, comp) for scheme in schemes for comp in comps]
    ncols = max(2 * len(schemes), min(len(panels), 4))
    res_rows = -(-len(panels) // ncols)
    nrows = res_rows + len(conditional)
    fig = Figure(figsize=(3.4 * ncols, 3.3 * nrows + 0.6), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for i, (scheme, comp) in enumerate(panels):
        _residual_panel(
            axes[i // ncols][i % ncols],
            result["per_case"][scheme][comp],
            result[scheme][comp],
            comp,
            scheme,
        )
    for i in range(len(panels), res_rows * ncols):
        axes[i // ncols][i % ncols].set_visible(False)
    for r, (col, cond) in enumerate(conditional.items(), start=res_rows):
        k = 0
        for scheme in schemes:
            for key in ("m", "c"):
                _conditional_panel(axes[r][k], col, cond, scheme, key, comps)
                k += 1
        for j in range(k, ncols):
            axes[r][j].set_visible(False)
    req = result["requirement"]
    title = (
        f"{Path(str(result.get('input', ''))).name}: Stage IV |m| < {STAGE_IV_M:.0e}, "
        f"|c| < {STAGE_IV_C:.0e} ({req['applies_to']}: {'met' if req['met'] else 'NOT met'})"
    )
    warnings = large_m(result)
    if warnings:
        title += (
            f"\nWARNING: |m| > {WARN_M:g} in {len(warnings)} fit(s) ({warnings[0]}"
            f"{', ...' if len(warnings) > 1 else ''}): an untrained or mismatched model?"
        )
    fig.suptitle(title, fontsize=10, color=_WARN_COLOR if warnings else "black")
    handles, labels = axes[0][0].get_legend_handles_labels()
    for r in range(res_rows, nrows):  # the components' markers, from a conditional panel
        h, la = axes[r][0].get_legend_handles_labels()
        handles, labels = handles + h, labels + la
        break
    fig.legend(
        handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8, frameon=False
    )
    return fig


def plot_calibration(
    result: Mapping[str, Any], path: str | os.PathLike, overwrite: bool = False
) -> Path:
    """Draw the diagnostics of a calibration (from :mod:`.calibrate`) into ``path``."""
    check_plot_output(path)
    return save_figure(calibration_figure(result), path, overwrite)


def calibration_figure(result: Mapping[str, Any]) -> Any:
    """The diagnostics of a calibration without truth: per component the calibrated mean
    shear in bins of the PSF ellipticity with the fitted leakage ``g = alpha e_psf + c``
    (with PSF columns), and the mean shear of each ``--by`` bin (with ``--by``)."""
    Figure = _figure_class()
    profile = result.get("psf_profile")
    bins = result.get("bins") or []
    panels = (2 if profile else 0) + (1 if bins else 0) or 1
    fig = Figure(figsize=(4.0 * panels, 3.6), layout="constrained")
    axes = fig.subplots(1, panels, squeeze=False)[0]
    whole = result["all"]
    k = 0
    if profile:
        for i, comp in enumerate(("g1", "g2")):
            ax, p = axes[k], profile[comp]
            e = _arr(p["e_psf"])
            ax.errorbar(e, _arr(p["g"]), yerr=_arr(p["g_err"]), fmt="o", ms=4, label="binned")
            alpha, add = whole["alpha"][i], whole["additive"][i]
            if alpha is not None and add is not None:
                xs = np.linspace(e.min(), e.max(), 2)
                a_err = whole["alpha_err"][i]
                ax.plot(xs, add + alpha * xs, "-", label=f"alpha = {_fmt(alpha, a_err)}")
            ax.axhline(whole[comp], color="0.5", lw=0.8, ls="--", label="mean")
            ax.set_xlabel(f"PSF e{i + 1} ({result.get('frame', 'pixel')} frame)")
            ax.set_ylabel(f"calibrated {comp}")
            ax.legend(fontsize=7)
            k += 1
    if bins or not profile:
        ax = axes[k]
        entries = bins or [whole]
        x = np.arange(len(entries))
        for j, comp in enumerate(("g1", "g2")):
            ax.errorbar(
                x + (j - 0.5) * 0.15,
                _arr([b[comp] for b in entries]),
                yerr=_arr([b[f"{comp}_err"] for b in entries]),
                fmt="o",
                ms=4,
                label=comp,
            )
        labels = [
            str(b["value"]) if "value" in b else (f"{b['center']:.3g}" if "center" in b else "all")
            for b in entries
        ]
        ax.set_xticks(x, labels, fontsize=7)
        by = (result.get("by") or {}).get("quantity")
        ax.set_xlabel(f"bin of {by}" if by else "whole catalog")
        ax.set_ylabel("calibrated mean shear")
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.legend(fontsize=7)
    fig.suptitle(
        f"{Path(str(result.get('input', ''))).name}: {result['calibration']} route, "
        f"{result['scheme']}, {result.get('frame', 'pixel')} frame",
        fontsize=10,
    )
    return fig
