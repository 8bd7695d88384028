"""Named sums of a shear evaluation and what comes out of them: per-case averages and the
metacal mean and selection responses (Sheldon & Huff 2017, Sect. 5) that calibrate them.

One representation for the single-set (:mod:`megalut_cli.shear.evaluate`) and the paired
(:mod:`megalut_cli.shear.paired`) evaluations: per scheme ``s`` and component ``c`` the
sums ``s:w:c``, ``s:wpre:c``, ``s:wtru:c``, ``s:n:c`` (rows used), ``s:n:both``; with
metacal responses ``s:wR:ij``; with a selection or weights, per sheared version ``kind``
(``1p, 1m, 2p, 2m``), ``s:sw:i:kind`` and ``s:swpre:i:kind``. Sums are arrays whose axis 0
runs over the cases (further axes: e.g. bootstrap resamples).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from megalut_cli.measure.metacal_defaults import STEP_CARD
from megalut_cli.shear.bias import calibrate_by_response, rotate_spin2

#: How a metacal set's cases are calibrated: by the mean response over all of them, or by the
#: response at zero shear fitted over the cases' own responses (``megalut evaluate --response``).
RESPONSE_MEAN = "mean"
RESPONSE_ZERO_SHEAR = "zero-shear"
#: Fewest cases with usable rows for the fit of the response at zero shear (6 terms).
MIN_ZERO_SHEAR_CASES = 10


def row_values(
    scheme: str,
    weight: Mapping[str, np.ndarray],
    tru: Mapping[str, np.ndarray],
    pre: Mapping[str, np.ndarray],
    response: Mapping[tuple[int, int], np.ndarray] | None = None,
    sheared: Mapping[tuple[int, str], np.ndarray] | None = None,
    pre_noshear: Mapping[int, np.ndarray] | None = None,
    step: float | None = None,
    version_pre: Mapping[tuple[int, str], np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Per-row values of the sums of ``scheme``: ``weight``, ``tru`` and ``pre`` per
    component (``g1``, ``g2``; weight, truth and estimate 0 on unused rows), the metacal
    ``response[(i, j)]`` (0 on unused rows) and the weights ``sheared[(i, kind)]`` of the rows
    under each sheared version's selection, with the noshear estimates and the ``step``.
    With ``version_pre[(i, kind)]``, each sheared version's own estimates, the sums are
    those of the versions' means instead (``vw``, ``vwpre``): the response of the means,
    selection included, as metadetection takes it."""
    vals: dict[str, np.ndarray] = {}
    for comp, w in weight.items():
        vals[f"{scheme}:w:{comp}"] = w
        vals[f"{scheme}:wpre:{comp}"] = w * pre[comp]
        vals[f"{scheme}:wtru:{comp}"] = w * tru[comp]
        vals[f"{scheme}:n:{comp}"] = (w > 0).astype(float)
    if len(weight) == 2:
        vals[f"{scheme}:n:both"] = ((weight["g1"] > 0) & (weight["g2"] > 0)).astype(float)
    for (i, j), r in (response or {}).items():
        vals[f"{scheme}:wR:{i}{j}"] = weight[f"g{i}"] * r
    if sheared and version_pre is not None and step is not None:
        for (i, kind), w in sheared.items():
            vals[f"{scheme}:vw:{i}:{kind}"] = w
            vals[f"{scheme}:vwpre:{i}:{kind}"] = (
                w * np.nan_to_num(version_pre[(i, kind)]) / (2.0 * step)
            )
    elif sheared and pre_noshear is not None and step is not None:
        for (i, kind), w in sheared.items():
            vals[f"{scheme}:sw:{i}:{kind}"] = w
            # divided by 2 step here, so that a ratio of sums is the response term
            vals[f"{scheme}:swpre:{i}:{kind}"] = w * np.nan_to_num(pre_noshear[i]) / (2.0 * step)
    return vals


def metacal_response(
    sums: Mapping[str, np.ndarray], scheme: str, per_case: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """The mean metacal response ``R[i][j]`` of the rows behind ``sums`` (all cases: axis 0
    summed; with ``per_case``, each case's own), and the selection response (None without a
    selection or weights), each ``(2, 2, ...)``. With the versions' means in ``sums``
    (:func:`row_values` ``version_pre``), the response of the means, selection included,
    and None: ``(<g_i>_jp - <g_i>_jm) / (2 step)``, each mean over its own version's rows."""

    def ratio(num: str, den: str) -> np.ndarray:
        a, b = sums[num], sums[den]
        return a / b if per_case else a.sum(axis=0) / b.sum(axis=0)

    with np.errstate(invalid="ignore", divide="ignore"):
        if f"{scheme}:vw:1:1p" in sums:

            def version_mean(i: int, kind: str) -> np.ndarray:
                return ratio(f"{scheme}:vwpre:{i}:{kind}", f"{scheme}:vw:{i}:{kind}")

            means = [
                [version_mean(i, f"{j}p") - version_mean(i, f"{j}m") for j in (1, 2)]
                for i in (1, 2)
            ]
            return np.array(means), None
        mean = np.array(
            [[ratio(f"{scheme}:wR:{i}{j}", f"{scheme}:w:g{i}") for j in (1, 2)] for i in (1, 2)]
        )
        if f"{scheme}:sw:1:1p" not in sums:
            return mean, None

        def avg(i: int, kind: str) -> np.ndarray:
            return ratio(f"{scheme}:swpre:{i}:{kind}", f"{scheme}:sw:{i}:{kind}")

        selection = np.array([[avg(i, f"{j}p") - avg(i, f"{j}m") for j in (1, 2)] for i in (1, 2)])
    return mean, selection


def response_design(shears: np.ndarray) -> np.ndarray:
    """The terms of a case's response against its true shear ``(n_cases, 2)``: 1, g1, g2,
    |g|^2 and the spin-4 pair g1^2 - g2^2, 2 g1 g2. Metacal's step composes with the case's
    shear, so a sheared case's response carries ``1 - S4(g)`` (docs/metacal.md)."""
    g1, g2 = shears[:, 0], shears[:, 1]
    return np.column_stack([np.ones_like(g1), g1, g2, g1**2 + g2**2, g1**2 - g2**2, 2 * g1 * g2])


def zero_shear_weights(shears: np.ndarray) -> np.ndarray | None:
    """Weights ``a`` (one per case; 0 where the shear is not finite) such that ``a @ R_case``
    is the intercept of a least-squares fit of the cases' responses against
    :func:`response_design`: the response at zero shear. None with fewer than
    :data:`MIN_ZERO_SHEAR_CASES` cases or shears that do not determine the fit."""
    ok = np.all(np.isfinite(shears), axis=1)
    if ok.sum() < MIN_ZERO_SHEAR_CASES:
        return None
    design = response_design(shears[ok])
    if np.linalg.matrix_rank(design) < design.shape[1]:
        return None
    weights = np.zeros(len(shears))
    weights[ok] = np.linalg.pinv(design)[0]
    return weights


def calibration_response(
    sums: Mapping[str, np.ndarray], scheme: str, shears: np.ndarray | None = None
) -> tuple[np.ndarray, str]:
    """The response that calibrates the cases behind ``sums``, mean plus selection
    response, ``(2, 2, ...)``, and how it was taken: ``"zero-shear"`` (the intercept of
    the cases' own responses against their true ``shears``, :func:`zero_shear_weights`)
    when ``shears`` are given and determine it, else ``"mean"`` (over all the cases)."""
    weights = None if shears is None else zero_shear_weights(shears)
    if weights is None:
        mean, selection = metacal_response(sums, scheme)
        return (mean if selection is None else mean + selection), RESPONSE_MEAN
    mean, selection = metacal_response(sums, scheme, per_case=True)
    r = mean if selection is None else mean + selection
    used = weights != 0
    zero = np.tensordot(r[:, :, used], weights[used], axes=([2], [0]))
    return zero, RESPONSE_ZERO_SHEAR


def case_estimates(
    sums: Mapping[str, np.ndarray],
    scheme: str,
    theta: np.ndarray | None = None,
    zero_shear: bool = False,
) -> dict[str, dict[str, np.ndarray]]:
    """Per-case true and estimated averages (NaN where the case has no usable row) and row
    counts of each component summed; with metacal sums, the estimates calibrated by the
    response plus the selection response, ``(R + R_S)^-1 <g>``: at zero shear with
    ``zero_shear`` where the cases determine it (:func:`calibration_response`), else the
    mean over all the cases; with the PSF angles ``theta`` of the cases, also the ``plus``
    and ``cross`` components."""
    out: dict[str, dict[str, np.ndarray]] = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for comp in ("g1", "g2"):
            w = sums.get(f"{scheme}:w:{comp}")
            if w is None:
                continue
            use = w > 0
            out[comp] = {
                "tru": np.where(use, sums[f"{scheme}:wtru:{comp}"] / w, np.nan),
                "pre": np.where(use, sums[f"{scheme}:wpre:{comp}"] / w, np.nan),
                "n_rows": np.where(use, sums[f"{scheme}:n:{comp}"], 0.0),
            }
    if f"{scheme}:wR:11" in sums:
        shears = case_shears(out) if zero_shear else None
        r = calibration_response(sums, scheme, shears)[0]
        out["g1"]["pre"], out["g2"]["pre"] = calibrate_by_response(
            r[0, 0], r[0, 1], r[1, 0], r[1, 1], out["g1"]["pre"], out["g2"]["pre"]
        )
    if theta is not None:
        n_both = sums[f"{scheme}:n:both"]
        for kind in ("tru", "pre"):
            plus, cross = rotate_spin2(out["g1"][kind], out["g2"][kind], theta)
            out.setdefault("plus", {})[kind] = plus
            out.setdefault("cross", {})[kind] = cross
        use = np.isfinite(out["plus"]["pre"])
        out["plus"]["n_rows"] = np.where(use, n_both, 0.0)
        out["cross"]["n_rows"] = out["plus"]["n_rows"]
    return out


def case_shears(per_case: Mapping[str, Mapping[str, np.ndarray]]) -> np.ndarray:
    """The true shear of each case ``(n_cases, 2)`` from :func:`case_estimates`' averages
    (NaN where a case has no usable row; further axes, e.g. resamples, reduced)."""
    cols = []
    for comp in ("g1", "g2"):
        tru = np.asarray(per_case[comp]["tru"], dtype=float)
        tru = tru.reshape(tru.shape[0], -1)
        seen = np.isfinite(tru)
        with np.errstate(invalid="ignore"):
            cols.append(np.where(seen, tru, 0.0).sum(axis=1) / seen.sum(axis=1))
    return np.stack(cols, axis=1)


def header_step(header: Mapping[str, Any], card: str = STEP_CARD) -> float | None:
    """The number of a header's ``MCALSTEP`` card (or ``card``), or None (no card, or not a
    number)."""
    step = header.get(card)
    return float(step) if isinstance(step, (int, float)) and not isinstance(step, bool) else None
