"""Shear biases of a GREAT3 constant-shear branch against its truth (paper Table 4).

The estimates are either a constant-shear *submission* (text, ``subfield g1 g2`` per
line) or a per-galaxy predictions catalog (FITS, with ``pre_g1, pre_g2``, optional
weights ``pre_g1_w, pre_g2_w`` and ``flags``, and a ``subfield`` column or GREAT3
``ID``s). The truth folder holds GREAT3's ``shear_params-SSS`` and
``starshape_parameters-SSS-0`` files (``.txt`` or ``.yaml``; ``truth/`` of branches
written by ``megalut simulate --great3``).

Subfields play the role of *cases* of :mod:`megalut_cli.shear.evaluate`: the estimates
of each subfield are averaged, ``<g> - g = m g + c`` is fitted over subfields (OLS, errors
from the residual scatter) in the pixel frame (g1, g2) and, with the PSF ellipticities of
the starshape files, in the PSF frame (plus, cross: rotated by ``-2 theta``, ``theta =
atan2(psf_g2, psf_g1) / 2``, as GREAT3's ``evaluate.py``), and GREAT3's ``Q_c`` follows
from the PSF-frame m, c with ``sigma2_min`` = 4 (ground) or 1 (space).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from megalut_cli.catalog import is_fits_file, read_catalog, require_columns
from megalut_cli.errors import InputError
from megalut_cli.great3 import layout as L
from megalut_cli.shear.bias import GREAT3_SIGMA2_MIN_GROUND
from megalut_cli.shear.evaluate import evaluate_columns, evaluation_provenance

log = logging.getLogger(__name__)


def branch_columns(
    shears: str | os.PathLike, truth_dir: str | os.PathLike
) -> dict[str, np.ndarray]:
    """Columns for :func:`megalut_cli.shear.evaluate.evaluate_columns`: the estimates of
    ``shears`` (submission or predictions catalog) joined with the truth of their subfield
    (``case`` = subfield, ``tru_g1, tru_g2``, and ``tru_psf_g1, tru_psf_g2`` when known)."""
    if is_fits_file(shears):
        table = read_catalog(shears)
        require_columns(table.colnames, ["pre_g1", "pre_g2"], shears)
        sub = L.subfield_column(table, str(shears))
        cols = {c: np.asarray(table[c]) for c in table.colnames if np.ndim(table[c]) == 1}
    else:
        sub, g1, g2 = L.read_submission(shears)
        cols = {"pre_g1": g1, "pre_g2": g2}
    present = np.unique(sub)
    truth = L.read_truth(truth_dir, present.tolist())
    idx = np.searchsorted(truth["subfield"], sub)
    cols.update(
        {
            "case": sub,
            "tru_g1": truth["g1"][idx],
            "tru_g2": truth["g2"][idx],
        }
    )
    for c in ("tru_psf_g1", "tru_psf_g2", "psf_adamom_g1", "psf_adamom_g2"):
        cols.pop(c, None)  # the PSF frame is the truth's
    if np.any(np.isfinite(truth["psf_g1"]) & np.isfinite(truth["psf_g2"])):
        cols["tru_psf_g1"] = truth["psf_g1"][idx]
        cols["tru_psf_g2"] = truth["psf_g2"][idx]
    else:
        log.warning("%s: no starshape_parameters files: no PSF frame", truth_dir)
    all_truth = L.read_truth(truth_dir)["subfield"]
    missing = np.setdiff1d(all_truth, present)
    if missing.size:
        log.warning(
            "%s: %d of the %d subfield(s) of the truth have no estimate (e.g. %s)",
            shears,
            missing.size,
            all_truth.size,
            ", ".join(map(str, missing[:5])),
        )
    return cols


def evaluate_branch(
    shears: str | os.PathLike,
    truth_dir: str | os.PathLike,
    *,
    sigma2_min: float = GREAT3_SIGMA2_MIN_GROUND,
    by: Sequence[str] | None = None,
    bins: int = 5,
    select: str | None = None,
    select_cases: str | None = None,
    names: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """m, c (pixel and PSF frames) and ``Q_c`` of ``shears`` against the truth in ``truth_dir``.

    ``names``: how messages name the arguments (see
    :func:`~megalut_cli.shear.evaluate.evaluate_catalog`).
    Returns the JSON-ready dict of :func:`megalut_cli.shear.evaluate.evaluate_columns`
    (cases are subfields) with a ``"great3"`` entry naming the truth folder.
    """
    cols = branch_columns(shears, truth_dir)
    if len(np.unique(cols["case"])) < 2:
        raise InputError(
            f"{shears}: estimates for fewer than 2 subfields: m and c cannot be fitted"
        )
    result = evaluate_columns(
        cols,
        by=by,
        bins=bins,
        select=select,
        select_cases=select_cases,
        source=str(shears),
        sigma2_min=sigma2_min,
        names=names,
    )
    result["input"] = str(shears)
    result["provenance"] = evaluation_provenance(shears)
    result["great3"] = {"truth": str(truth_dir), "n_subfields": int(len(np.unique(cols["case"])))}
    return result
