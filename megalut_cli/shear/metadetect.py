"""m and c of a metadetection catalog of simulated scenes (``megalut evaluate`` on the rows of
``measure --metadetect``, predicted or not).

The response is that of the catalog means, R_ii = (<g_i>_ip - <g_i>_im) / (2 step), each mean
over its own version's rows after the same cuts, over the whole catalog; each field and sign
(an image) gets the estimate <g>_noshear / R, and m, c come from a fit of these against the
images' true shears (with ±g pairs: their difference and mean); errors from a bootstrap over
fields (docs/metadetect.md, "The bias of a scene set").
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from megalut_cli import expr
from megalut_cli.catalog import catalog_info, read_catalog_columns
from megalut_cli.errors import InputError, namer
from megalut_cli.measure.metacal_defaults import MDET_COLUMN, MDET_STEP_CARD, TYPES
from megalut_cli.shear.bias import stage_iv_requirement
from megalut_cli.shear.bootstrap import resample_counts
from megalut_cli.shear.response import header_step

#: The estimates evaluated, by preference: the networks' (``predict``), else the adaptive
#: moments' ellipticity of the measurement itself.
ESTIMATES: tuple[tuple[str, str], ...] = (("pre_g1", "pre_g2"), ("adamom_g1", "adamom_g2"))
#: The version of each response component: (plus, minus) for g1 and g2.
RESPONSE_VERSIONS = {0: ("1p", "1m"), 1: ("2p", "2m")}


@dataclass(frozen=True)
class ImageSums:
    """Per field (axis 0; with a ``tile`` column, per tile and field) and sign slot (axis 1:
    +g or no pair, -g): the true shear ``(F, 2, 2)``, and per version (axis 2,
    :data:`TYPES`) and component (axis 3) the weighted sums of the estimates and of the
    weights."""

    fields: np.ndarray
    true: np.ndarray
    sums: np.ndarray
    weights: np.ndarray


def image_sums(
    columns: Mapping[str, np.ndarray],
    keep: np.ndarray,
    estimate: Sequence[str],
    weight_columns: Sequence[str] | None,
) -> ImageSums:
    """The :class:`ImageSums` of the rows ``keep`` of a metadetection catalog."""
    version = np.char.strip(np.asarray(columns[MDET_COLUMN]).astype("U"))
    key = np.asarray(columns["field"], dtype=np.int64)
    if "tile" in columns:  # catalogs of several runs (megalut concat): a field per run
        key = np.stack([np.asarray(columns["tile"], dtype=np.int64), key], axis=1)
    fields, f_index = np.unique(key, axis=0, return_inverse=True)
    f_index = f_index.ravel()
    sign = np.asarray(columns["pair_sign"]) if "pair_sign" in columns else np.ones(len(keep))
    s_index = (sign < 0).astype(np.int64)
    n_f = len(fields)
    true = np.full((n_f, 2, 2), np.nan)
    for c, name in enumerate(("tru_g1", "tru_g2")):
        true[f_index, s_index, c] = np.asarray(columns[name], dtype=float)
    sums = np.zeros((n_f, 2, len(TYPES), 2))
    weights = np.zeros_like(sums)
    for v, kind in enumerate(TYPES):
        for c in (0, 1):
            w = np.ones(len(keep)) if weight_columns is None else columns[weight_columns[c]]
            w = np.where(keep & (version == kind), np.asarray(w, dtype=float), 0.0)
            g = np.where(w > 0, np.asarray(columns[estimate[c]], dtype=float), 0.0)
            np.add.at(sums[:, :, v, c], (f_index, s_index), w * g)
            np.add.at(weights[:, :, v, c], (f_index, s_index), w)
    return ImageSums(fields, true, sums, weights)


def bias_from_sums(
    sums: np.ndarray, weights: np.ndarray, true: np.ndarray, step: float
) -> np.ndarray:
    """``(R11, R22, m1, c1, m2, c2)`` from image sums ``(F, 2, V, C)`` (resampled: a leading
    axis of resamples is allowed) and the true shears ``(F, 2, C)``: responses from the
    totals, one estimate per image, a fit weighted by the images' noshear weights (m NaN
    without a lever arm)."""
    total, wtot = sums.sum(axis=-4), weights.sum(axis=-4)  # over fields: (..., 2, V, C)
    mean = np.divide(total.sum(axis=-3), wtot.sum(axis=-3))  # both signs: (..., V, C)
    noshear = TYPES.index("noshear")
    out = []
    resp = []
    for c, (plus, minus) in RESPONSE_VERSIONS.items():
        r = (mean[..., TYPES.index(plus), c] - mean[..., TYPES.index(minus), c]) / (2 * step)
        resp.append(r)
        out.append(r)
    for c in (0, 1):
        w = weights[..., noshear, c]  # (..., F, 2)
        with np.errstate(invalid="ignore", divide="ignore"):
            g = sums[..., noshear, c] / w / resp[c][..., None, None]
        t = np.broadcast_to(true[..., c], w.shape)
        ok = (w > 0) & np.isfinite(t)
        w = np.where(ok, w, 0.0)
        g, t = np.where(ok, g, 0.0), np.where(ok, t, 0.0)
        sw = w.sum(axis=(-2, -1))
        tm = (w * t).sum(axis=(-2, -1)) / sw
        gm = (w * g).sum(axis=(-2, -1)) / sw
        dt = t - tm[..., None, None]
        stt = (w * dt * dt).sum(axis=(-2, -1))
        lever = stt > 1e-12 * np.maximum(sw, 1.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            slope = np.where(
                lever, (w * dt * (g - gm[..., None, None])).sum(axis=(-2, -1)) / stt, 0
            )
        out.append(np.where(lever, slope - 1.0, np.nan))
        out.append(np.where(lever, gm - slope * tm, gm))
    return np.stack(out, axis=-1)


def is_metadetect_catalog(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a catalog of metadetection rows (an ``mdet_step`` column)."""
    return MDET_COLUMN in catalog_info(path)[1]


def evaluate_metadetect_file(
    path: str | os.PathLike,
    *,
    select: str | None = None,
    n_bootstrap: int = 200,
    seed: int = 1,
    names: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """:func:`evaluate_metadetect` of the catalog ``path`` (its ``MDETSTEP`` card)."""
    _, have, header = catalog_info(path)
    step = header_step(header, MDET_STEP_CARD)
    if step is None:
        raise InputError(f"{path}: a metadetection catalog without its {MDET_STEP_CARD} card")
    wanted = {MDET_COLUMN, "field", "tile", "pair_sign", "tru_g1", "tru_g2", "flags", "inner"}
    wanted |= {c for e in ESTIMATES for c in (*e, f"{e[0]}_w", f"{e[1]}_w")}
    if select is not None:
        wanted |= set(expr.columns_used(select))
    columns, _ = read_catalog_columns(path, [c for c in have if c in wanted])
    return evaluate_metadetect(
        columns,
        step,
        source=str(path),
        select=select,
        n_bootstrap=n_bootstrap,
        seed=seed,
        names=names,
    )


def evaluate_metadetect(
    columns: Mapping[str, np.ndarray],
    step: float,
    *,
    source: str = "catalog",
    select: str | None = None,
    n_bootstrap: int = 200,
    seed: int = 1,
    names: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """m and c of a metadetection catalog (module docstring), unweighted and, for predicted
    catalogs with weights, weighted; the result in the layout of ``evaluate --json``'s
    ``unweighted``/``weighted`` fits, with ``response`` and the counts."""
    name = namer(names)
    have = set(columns)
    missing = [c for c in (MDET_COLUMN, "field", "tru_g1", "tru_g2", "flags") if c not in have]
    if missing:
        raise InputError(
            f"{source}: a metadetection catalog of simulated scenes needs {', '.join(missing)} "
            "(megalut simulate --scene, then measure --metadetect)"
        )
    estimate = next((e for e in ESTIMATES if set(e) <= have), None)
    if estimate is None:
        raise InputError(f"{source}: no estimate columns ({' or '.join(map(str, ESTIMATES))})")
    version = np.char.strip(np.asarray(columns[MDET_COLUMN]).astype("U"))
    n = len(version)
    keep = np.asarray(columns["flags"]) == 0
    if "inner" in have:
        keep &= np.asarray(columns["inner"]) != 0
    if select is not None:
        keep &= expr.evaluate_rows(select, columns, n)
    for c in estimate:
        keep &= np.isfinite(np.asarray(columns[c], dtype=float))
    if not keep.any():
        raise InputError(f"{source}: no usable row (flags, inner, {name('select')}, NaN)")
    schemes = {"unweighted": None}
    weight_columns = (f"{estimate[0]}_w", f"{estimate[1]}_w")
    if set(weight_columns) <= have:
        schemes["weighted"] = weight_columns
    result: dict[str, Any] = {
        "input": source,
        "route": "metadetect",
        "estimate": list(estimate),
        "step": step,
        "select": select,
        "n_rows": n,
        "n_valid": int(keep.sum()),
        "rows_per_version": {
            k: int(
                (keep & (np.char.strip(np.asarray(columns[MDET_COLUMN]).astype("U")) == k)).sum()
            )
            for k in TYPES
        },
        "errors": f"bootstrap over fields ({n_bootstrap} resamples, seed {seed})",
    }
    for scheme, wcols in schemes.items():
        s = image_sums(columns, keep, estimate, wcols)
        result["n_fields"] = len(s.fields)
        value = bias_from_sums(s.sums, s.weights, s.true, step)
        counts = resample_counts(seed, len(s.fields), n_bootstrap)
        boot = []
        for block in counts:  # (F, b) multiplicities
            b_sums = np.einsum("fb,fsvc->bfsvc", block, s.sums)
            b_w = np.einsum("fb,fsvc->bfsvc", block, s.weights)
            boot.append(bias_from_sums(b_sums, b_w, s.true, step))
        with warnings.catch_warnings():  # m of a component without a lever arm: all NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            spread = np.nanstd(np.concatenate(boot), axis=0, ddof=1)
        fits = {}
        for c, comp in enumerate(("g1", "g2")):
            fits[comp] = {
                "m": _num(value[2 + 2 * c]),
                "m_err": _num(spread[2 + 2 * c]),
                "c": _num(value[3 + 2 * c]),
                "c_err": _num(spread[3 + 2 * c]),
                "R": _num(value[c]),
                "R_err": _num(spread[c]),
                "n_rows": int(s.weights[:, :, TYPES.index("noshear"), c].astype(bool).sum()),
            }
        result[scheme] = fits
    result["requirement"] = _requirement(result, list(schemes))
    return result


def _num(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _requirement(result: Mapping[str, Any], schemes: Sequence[str]) -> dict[str, Any]:
    scheme = schemes[-1]  # weighted when present; an m without lever arm is not judged
    fits = {comp: (f["m"], f["c"]) for comp, f in result[scheme].items()}
    return stage_iv_requirement(fits, scheme, undetermined="skip")


def format_metadetect(result: Mapping[str, Any]) -> str:
    """A text report of :func:`evaluate_metadetect`."""

    def pm(v: float | None, e: float | None) -> str:
        return "n/a" if v is None else f"{v:+.2e} ± {e:.1e}" if e is not None else f"{v:+.2e}"

    per = ", ".join(f"{k} {v}" for k, v in result["rows_per_version"].items())
    lines = [
        f"shear biases of {result['input']} (metadetection: responses of each version's means)",
        f"estimate: {', '.join(result['estimate'])}; rows: {result['n_rows']}, usable "
        f"{result['n_valid']} ({per}); {result['n_fields']} fields",
        f"errors: {result['errors']}",
    ]
    if result.get("select"):
        lines.append(f"row selection (every version): {result['select']}")
    for scheme in ("unweighted", "weighted"):
        if scheme not in result:
            continue
        lines += ["", scheme, f"  {'':4}{'m':^22} {'c':^22} {'R':^20}"]
        for comp, f in result[scheme].items():
            lines.append(
                f"  {comp:4}{pm(f['m'], f['m_err']):>22} {pm(f['c'], f['c_err']):>22} "
                f"{f['R']:>8.4f} ± {f['R_err']:.4f}"
            )
    req = result["requirement"]
    verdict = "met" if req["met"] else "NOT met (" + "; ".join(req["failures"]) + ")"
    lines.append(f"Stage IV requirement on {req['applies_to']} results: {verdict}")
    return "\n".join(lines)
