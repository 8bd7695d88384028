"""The calibrated mean shear of a catalog without truth (``megalut calibrate``).

Input: the output of ``megalut predict``. Two routes:

- metacal catalogs (``pre_g1_noshear`` ..., ``mcal_r11 .. mcal_r22``, the sheared versions'
  ``pre_*_<type>``; header ``MCALSTEP``): ``g = (<R> + R_sel)^-1 <g_est>`` with the mean
  response ``<R>`` of the objects used and the selection response ``R_sel`` of the
  selection, the weights and the bin (taken on the sheared versions; Sheldon & Huff 2017,
  Sect. 5), through the sums of :mod:`megalut_cli.shear.response`;
- metadetection catalogs (``mdet_step``, header ``MDETSTEP``): one row per detection per
  version; ``g = R^-1 <g_est>_noshear`` with ``R`` from each sheared version's own
  detections, detection included (the same sums, each version's rows its "selection");
- simulation-calibrated catalogs: the (weighted) means of ``pre_g1, pre_g2``.

Errors: a delete-one jackknife over patches of the sky (a regular grid over
``(ra cos dec, dec)``, else the image ``x, y``), or a bootstrap over objects; the response
is recomputed in every jackknife sample and resample. PSF leakage: the calibrated
estimates regressed on the PSF ellipticity ``psf_adamom_g1, psf_adamom_g2`` of each object,
``g_i = alpha_i e_psf,i + c_i`` (weighted least squares), with errors from the same samples.

Frame: with the per-object Jacobian columns (``dudcol`` .. ``dvdrow``, from MEDS or an
image's WCS) every estimate, response, weight and PSF ellipticity is turned to the world
frame (u, v) first (:mod:`megalut_cli.shear.frame`); without them the pixel frame stays.

The per-object catalog (:func:`calibrated_catalog`) holds each object's estimate multiplied by
the inverse total response of its bin: valid for averages over many objects, not for one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli import expr
from megalut_cli.catalog import VersionColumns
from megalut_cli.concat import TILE_COLUMN
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.measure.metacal_defaults import DEFAULT_STEP, MDET_COLUMN, MDET_STEP_CARD, TYPES
from megalut_cli.seeding import STREAM_CALIBRATE
from megalut_cli.shear.bias import calibrate_by_response
from megalut_cli.shear.bootstrap import resample_counts, spread
from megalut_cli.shear.conditional import assign_bins, equal_population_edges
from megalut_cli.shear.evaluate import (
    ESTIMATE_COLUMNS,
    RESPONSE_COLUMNS,
    SHEARED_TYPES,
    WEIGHT_COLUMNS,
    check_by,
)
from megalut_cli.shear.frame import (
    FRAME_CARD,
    FRAME_TEXT,
    JACOBIAN_COLUMNS,
    PIXEL_FRAME,
    WORLD_FRAME,
    Frames,
    catalog_frames,
    has_jacobian,
    response_offset,
    response_to_world,
    spin2_to_world,
    versions_to_world,
    weights_to_world,
)
from megalut_cli.shear.options import (
    CALIBRATE,
    CALIBRATE_ERROR_CHOICES,
    CALIBRATION_FORMAT,
    CALIBRATION_FORMAT_VERSION,
    FAILURES_CHOICES,
    MAX_BINS,
)
from megalut_cli.shear.response import header_step, metacal_response, row_values

log = logging.getLogger(__name__)

ROUTE_METACAL = "metacal"
#: Metadetection catalogs (``measure --metadetect``): one row per detection per version.
ROUTE_METADETECT = "metadetect"
#: The columns whose values are the independent units of a metadetection catalog's errors
#: (a field's images share galaxies and noise), in order of preference.
MDET_UNIT_COLUMNS = ("field", "image", "cell")
#: The column of catalogs detected in cells (``measure --metadetect``, ``--detect``) saying
#: whether a detection lies in its cell's inner region: only those rows count (each object
#: of overlapping cells once).
INNER_COLUMN = "inner"
ROUTE_SIMULATION = "simulation"
#: The PSF ellipticity of each object (measured: real data has no true PSF).
PSF_SHAPE_COLUMNS = ("psf_adamom_g1", "psf_adamom_g2")
#: Smallest rms PSF ellipticity about its mean for a leakage fit (below: alpha undetermined).
MIN_PSF_SPREAD = 1e-4
#: Position columns, in order of preference: on the sky (degrees), else on the image.
POSITION_COLUMNS = (("ra", "dec"), ("x", "y"))
#: Columns passed through to the per-object catalog when the input has them.
PASS_COLUMNS = (
    "tile",
    "id",
    "object_id",
    "number",
    "subfield",
    "case",
    "rea",
    "ra",
    "dec",
    "x",
    "y",
)
#: ``--by patch``: bins that are patches of the sky (about ``--bins`` of them), unless the
#: catalog has a column of that name.
PATCH_BY = "patch"
#: The columns that make each row an epoch of an object (``measure --epochs``).
EPOCH_COLUMNS = ("id", "cutout")
#: Format of the per-object catalog of ``megalut calibrate -o``.
CATALOG_FORMAT = "megalut.calibrated"
#: Error methods.
JACKKNIFE, BOOTSTRAP = CALIBRATE_ERROR_CHOICES[1], CALIBRATE_ERROR_CHOICES[2]
_NO_TRUTH = {"g1": None, "g2": None}


@dataclass(frozen=True)
class CalibrationPlan:
    """What a catalog allows and what is asked: the route, the weights, the selection, the
    binning, the PSF and position columns, the error method and the columns to read."""

    source: str
    route: str
    weighted: bool
    step: float | None
    select: str | None
    by: str | None
    by_kind: str | None  # "column", "row" (a numeric expression) or "patch" (sky patches)
    by_versioned: bool  # metacal: the sheared versions have their own values of ``by``
    psf: tuple[str, str] | None
    positions: tuple[str, str] | None
    errors: str
    has_flags: bool
    frame: str  # WORLD_FRAME with the per-object Jacobian columns, else PIXEL_FRAME
    epochs: bool  # rows are epochs of objects (columns id and cutout, measure --epochs)
    unit: str | None  # metadetection: the column of the independent units (cells)
    columns: tuple[str, ...]
    pass_through: tuple[str, ...]
    names: dict[str, str] = field(default_factory=dict)
    failures: str = CALIBRATE["failures"].default  # metacal: "selection" or "exclude"

    @property
    def scheme(self) -> str:
        return "weighted" if self.weighted else "unweighted"

    @property
    def failures_select(self) -> bool:
        """Whether each metacal version's failures are a selection (the response of the
        versions' means)."""
        return self.route == ROUTE_METACAL and self.failures == "selection"

    def name(self, arg: str) -> str:
        """How messages name the argument ``arg``."""
        return self.names.get(arg, arg)


def plan_calibration(
    colnames: Sequence[str],
    header: Mapping[str, Any] | None = None,
    *,
    select: str | None = None,
    by: str | None = None,
    unweighted: bool = CALIBRATE["unweighted"].default,
    errors: str = CALIBRATE["errors"].default,
    source: str = "catalog",
    names: Mapping[str, str] | None = None,
    failures: str | None = None,
) -> CalibrationPlan:
    """Check a catalog's columns (and header) against what is asked; raise
    :class:`InputError` for a catalog that cannot be calibrated, :class:`ConfigError` for
    an argument that does not fit it. ``failures`` None: the default of a metacal catalog
    (each version's failures a selection); a value asks for it, and ``"selection"`` is
    refused on other catalogs."""
    given = dict(names or {})
    have = set(colnames)
    header = header or {}
    if errors not in CALIBRATE_ERROR_CHOICES:
        raise ConfigError(
            f"{given.get('errors', 'errors')}: unknown value {errors!r} "
            f"(expected one of {', '.join(CALIBRATE_ERROR_CHOICES)})"
        )
    if failures is not None and failures not in FAILURES_CHOICES:
        raise ConfigError(
            f"{given.get('failures', 'failures')}: unknown value {failures!r} "
            f"(expected one of {', '.join(FAILURES_CHOICES)})"
        )
    metacal = [c for c in RESPONSE_COLUMNS if c in have]
    if MDET_COLUMN in have:
        route = ROUTE_METADETECT
        missing = [c for c in (*ESTIMATE_COLUMNS, "flags") if c not in have]
        if missing:
            raise InputError(
                f"{source}: a metadetection catalog ({MDET_COLUMN}) lacks {', '.join(missing)}: "
                "predict it first"
            )
        weight_cols = list(WEIGHT_COLUMNS)
    elif metacal:
        route = ROUTE_METACAL
        needed = [
            *RESPONSE_COLUMNS,
            *(f"{c}_{kind}" for kind in TYPES for c in ESTIMATE_COLUMNS),
            "flags_noshear",
        ]
        missing = [c for c in needed if c not in have]
        if missing:
            raise InputError(
                f"{source}: a metacal catalog (with {', '.join(metacal)}) lacks "
                f"{', '.join(missing)}"
            )
        weight_cols = [f"{c}_{kind}" for c in WEIGHT_COLUMNS for kind in TYPES]
    else:
        route = ROUTE_SIMULATION
        missing = [c for c in ESTIMATE_COLUMNS if c not in have]
        if missing:
            raise InputError(
                f"{source}: calibrate needs the estimates of 'megalut predict' (pre_g1, pre_g2; "
                f"on a metacal catalog also pre_g*_<type> and mcal_r11 .. mcal_r22); "
                f"missing: {', '.join(missing)}"
            )
        weight_cols = list(WEIGHT_COLUMNS)
    if failures == "selection" and route != ROUTE_METACAL:
        raise InputError(
            f"{source}: {given.get('failures', 'failures')} selection applies to a metacal "
            "catalog of stamps (mcal_r11 .. mcal_r22 and each version's estimates)"
            + (
                ": a metadetection catalog's response counts each version's own detections already"
                if route == ROUTE_METADETECT
                else ""
            )
        )
    if failures is None:
        failures = CALIBRATE["failures"].default
    weighted = not unweighted and all(c in have for c in weight_cols)
    if not unweighted and not weighted and any(c in have for c in weight_cols):
        log.warning(
            "%s: only some of the weight columns %s present; unweighted",
            source,
            ", ".join(weight_cols),
        )
    step = None
    if route == ROUTE_METACAL:
        step = header_step(header) or DEFAULT_STEP
    elif route == ROUTE_METADETECT:
        step = header_step(header, MDET_STEP_CARD)
        if step is None:
            raise InputError(f"{source}: a metadetection catalog without its {MDET_STEP_CARD} card")
    if select is not None:
        expr.check_expression(select, list(colnames))
    by_kind = None
    by_versioned = False
    by_used: list[str] = []
    if by == PATCH_BY and PATCH_BY not in have:
        by_kind = "patch"
    elif by is not None:
        key = given.get("by", "by")
        by_kind = check_by([by], list(colnames), key, source)[by]
        if by_kind == "case":
            raise ConfigError(f"{key} {by}: per-case aggregates do not apply to calibrate")
        by_used = [by] if by_kind == "column" else expr.columns_used(by)
        by_versioned = route == ROUTE_METACAL and any(f"{c}_1p" in have for c in by_used)
    psf = PSF_SHAPE_COLUMNS if all(c in have for c in PSF_SHAPE_COLUMNS) else None
    positions = next((p for p in POSITION_COLUMNS if all(c in have for c in p)), None)
    unit = None
    if route == ROUTE_METADETECT:
        psf = None  # its PSF columns are the round target's
        positions = None  # x, y are within each cell: the cells are the units
        unit = next((c for c in MDET_UNIT_COLUMNS if c in have), None)
        if by_kind == "patch":
            raise ConfigError(
                f"{given.get('by', 'by')} {PATCH_BY}: not for a metadetection catalog"
            )
        if errors == JACKKNIFE and unit is None:
            raise InputError(
                f"{source}: a jackknife over cells needs a {' or '.join(MDET_UNIT_COLUMNS)} "
                f"column; use {given.get('errors', 'errors')} bootstrap"
            )
        if errors == "auto":
            errors = JACKKNIFE if unit is not None else BOOTSTRAP
    if by_kind == "patch":
        if positions is None:
            raise InputError(
                f"{source}: {given.get('by', 'by')} {PATCH_BY} needs positions (ra, dec or x, y)"
            )
        if errors == JACKKNIFE:
            raise ConfigError(
                f"{given.get('by', 'by')} {PATCH_BY}: a jackknife over the patches cannot give "
                f"one patch's error; use {given.get('errors', 'errors')} bootstrap"
            )
        errors = BOOTSTRAP
    if errors == "auto":
        errors = JACKKNIFE if positions is not None else BOOTSTRAP
    elif errors == JACKKNIFE and positions is None and unit is None:
        raise InputError(
            f"{source}: a jackknife over patches needs positions (ra, dec or x, y); "
            f"use {given.get('errors', 'errors')} bootstrap"
        )
    has_flags = "flags" in have
    frame = WORLD_FRAME if has_jacobian(have) else PIXEL_FRAME
    epochs = all(c in have for c in EPOCH_COLUMNS)
    if frame == WORLD_FRAME and by_versioned:
        log.warning(
            "%s: the bins of %s change between the sheared versions, which are pixel-frame "
            "shears: the bins' selection responses are exact for cutouts turned by multiples "
            "of 45 degrees or flipped only",
            source,
            by,
        )
    cols: list[str] = list(JACOBIAN_COLUMNS) if frame == WORLD_FRAME else []
    cols += [INNER_COLUMN] if INNER_COLUMN in have else []
    cols += [*EPOCH_COLUMNS, TILE_COLUMN] if epochs else []
    if route == ROUTE_METADETECT:
        cols += [MDET_COLUMN, *ESTIMATE_COLUMNS, "flags", *([unit] if unit else [])]
    elif route == ROUTE_METACAL:
        cols += [*RESPONSE_COLUMNS, "flags_noshear"]
        cols += [f"{c}_{kind}" for kind in TYPES for c in ESTIMATE_COLUMNS]
        if failures == "selection":  # a version is measured where its flags are 0
            cols += [f"flags_{kind}" for kind in SHEARED_TYPES]
        used = (expr.columns_used(select) if select is not None else []) + by_used
        cols += [f"{c}_{kind}" for kind in TYPES for c in used if f"{c}_{kind}" in have]
    else:
        cols += list(ESTIMATE_COLUMNS)
        if has_flags:
            cols.append("flags")
    if weighted:
        cols += weight_cols
    cols += (expr.columns_used(select) if select is not None else []) + by_used
    cols += [*(psf or ()), *(positions or ())]
    passed = tuple(c for c in PASS_COLUMNS if c in have)
    if by_kind == "column" and by is not None and by not in passed:
        passed += (by,)
    cols += passed
    return CalibrationPlan(
        source,
        route,
        weighted,
        step,
        select,
        by,
        by_kind,
        by_versioned,
        psf,
        positions,
        errors,
        has_flags,
        frame,
        epochs,
        unit,
        tuple(dict.fromkeys(c for c in cols if c in have)),
        passed,
        given,
        failures,
    )


# --------------------------------------------------------------------------- patches


def sky_patches(a: np.ndarray, b: np.ndarray, n_patches: int, sky: bool = True) -> np.ndarray:
    """Patch index of each object on a regular grid of about ``n_patches`` cells (as square
    as the footprint allows) over ``(ra cos dec, dec)`` (``sky``; degrees, RA wrapped about
    the footprint's mean) or the plane ``(a, b)``; occupied cells numbered from 0, -1 for
    non-finite positions."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ok = np.isfinite(a) & np.isfinite(b)
    out = np.full(a.size, -1, dtype=np.int64)
    if not ok.any():
        return out
    x, y = a[ok], b[ok]
    if sky:
        rad = np.deg2rad(x)
        ra0 = np.rad2deg(np.arctan2(np.mean(np.sin(rad)), np.mean(np.cos(rad))))
        x = ((x - ra0 + 180.0) % 360.0 - 180.0) * np.cos(np.deg2rad(y))
    wx, wy = float(np.ptp(x)), float(np.ptp(y))
    if wx <= 0 and wy <= 0:
        nx = ny = 1
    elif wy <= 0:
        nx, ny = n_patches, 1
    elif wx <= 0:
        nx, ny = 1, n_patches
    else:
        nx = max(1, round(math.sqrt(n_patches * wx / wy)))
        ny = max(1, round(n_patches / nx))
    ix = np.clip(((x - x.min()) / (wx or 1.0) * nx).astype(np.int64), 0, nx - 1)
    iy = np.clip(((y - y.min()) / (wy or 1.0) * ny).astype(np.int64), 0, ny - 1)
    out[ok] = np.unique(iy * nx + ix, return_inverse=True)[1].ravel()
    return out


# --------------------------------------------------------------------------- per-object values


@dataclass
class _Objects:
    """Per-object quantities of a catalog under a plan."""

    n: int
    selected: np.ndarray
    valid: dict[int, np.ndarray]  # component -> usable estimate (and response)
    pre: dict[int, np.ndarray]  # 0 where not valid
    weight: dict[int, np.ndarray]  # 0 where not used
    response: dict[tuple[int, int], np.ndarray] | None
    sheared: dict[tuple[int, str], np.ndarray] | None  # weight under each version's selection
    pre_noshear: dict[int, np.ndarray] | None
    psf: tuple[np.ndarray, np.ndarray] | None
    # failures as a selection: each sheared version's own estimate (weights in ``sheared``)
    version_pre: dict[tuple[int, str], np.ndarray] | None = None


def _metadetect_objects(columns: Mapping[str, np.ndarray], plan: CalibrationPlan) -> _Objects:
    """The rows of a metadetection catalog as the sums of :mod:`.response` take them: the
    noshear detections' estimates and weights; no per-row response; under each sheared
    version its own detections' weights and estimates, so that the "selection" response of
    the sums, ``(<g_i>_jp - <g_i>_jm) / (2 step)`` over each version's detections, is the
    whole response (detection included)."""
    n = len(np.asarray(columns[MDET_COLUMN]))
    if n == 0:
        raise InputError(f"{plan.source}: the catalog has no rows")
    version = np.char.strip(np.asarray(columns[MDET_COLUMN]).astype("U"))
    unknown = sorted(set(np.unique(version)) - set(TYPES))
    if unknown:
        raise InputError(
            f"{plan.source}: {MDET_COLUMN} holds {', '.join(unknown[:3])}: expected "
            f"{', '.join(TYPES)}"
        )
    selected = np.ones(n, dtype=bool)
    if plan.select is not None:
        selected = expr.evaluate_rows(plan.select, columns, n)
    raw = {i: np.asarray(columns[f"pre_g{i}"], dtype=float) for i in (1, 2)}
    ok = selected & (np.asarray(columns["flags"]) == 0)
    ok &= np.isfinite(raw[1]) & np.isfinite(raw[2])
    if INNER_COLUMN in columns:  # overlapping cells: each object in its one inner region
        ok &= np.asarray(columns[INNER_COLUMN]) != 0
    w = {i: np.ones(n) for i in (1, 2)}
    if plan.weighted:
        for i in (1, 2):
            w[i] = np.asarray(columns[f"pre_g{i}_w"], dtype=float)
            if np.any(ok & (w[i] < 0)):
                raise InputError(f"{plan.source}: column pre_g{i}_w has negative weights")
    usable = {i: ok & np.isfinite(w[i]) & (w[i] > 0) for i in (1, 2)}
    noshear = version == "noshear"
    valid = {i: usable[i] & noshear for i in (1, 2)}
    if not (valid[1] | valid[2]).any():
        raise InputError(f"{plan.source}: no usable noshear detection (flags, NaN, selection)")
    missing = [k for k in SHEARED_TYPES if not np.any(usable[1] & (version == k))]
    if missing:
        raise InputError(f"{plan.source}: no usable detection of version {', '.join(missing)}")
    pre = {i: np.where(valid[i], raw[i], 0.0) for i in (1, 2)}
    weight = {i: np.where(valid[i], w[i], 0.0) for i in (1, 2)}
    response = {(i, j): np.zeros(n) for i in (1, 2) for j in (1, 2)}
    sheared = {
        (i, kind): np.where(usable[i] & (version == kind), w[i], 0.0)
        for i in (1, 2)
        for kind in SHEARED_TYPES
    }
    own = {i: np.where(ok, raw[i], 0.0) for i in (1, 2)}
    return _Objects(n, selected, valid, pre, weight, response, sheared, own, None)


def _objects(columns: Mapping[str, np.ndarray], plan: CalibrationPlan) -> _Objects:
    if plan.route == ROUTE_METADETECT:
        obj = _metadetect_objects(columns, plan)
        return _to_world(obj, columns, plan) if plan.frame == WORLD_FRAME else obj
    n = len(np.asarray(columns[plan.columns[0]]))
    if n == 0:
        raise InputError(f"{plan.source}: the catalog has no rows")
    metacal = plan.route == ROUTE_METACAL
    view = VersionColumns(columns, "noshear") if metacal else columns
    selected = np.ones(n, dtype=bool)
    if plan.select is not None:
        selected = expr.evaluate_rows(plan.select, view, n)
        if not selected.any():
            raise InputError(f"{plan.source}: no row passes {plan.name('select')} {plan.select!r}")
    if INNER_COLUMN in columns:  # overlapping cells: each object in its one inner region
        selected &= np.asarray(columns[INNER_COLUMN]) != 0
    suffix = "_noshear" if metacal else ""
    base = selected.copy()
    if metacal:
        base &= np.asarray(columns["flags_noshear"]) == 0
    elif plan.has_flags:
        base &= np.asarray(columns["flags"]) == 0
    raw = {i: np.asarray(columns[f"pre_g{i}{suffix}"], dtype=float) for i in (1, 2)}
    resp = None
    if metacal:
        resp = {
            (i, j): np.asarray(columns[f"mcal_r{i}{j}"], dtype=float)
            for i in (1, 2)
            for j in (1, 2)
        }
    valid, pre, weight = {}, {}, {}
    for i in (1, 2):
        ok = base & np.isfinite(raw[i])
        if resp is not None and not plan.failures_select:
            ok &= np.isfinite(resp[(i, 1)]) & np.isfinite(resp[(i, 2)])
        valid[i] = ok
        pre[i] = np.where(ok, raw[i], 0.0)
        w = np.ones(n)
        if plan.weighted:
            wcol = f"pre_g{i}_w{suffix}"
            w = np.asarray(columns[wcol], dtype=float)
            bad = ok & (w < 0)
            if bad.any():
                raise InputError(
                    f"{plan.source}: column {wcol} has {int(bad.sum())} negative weight(s)"
                )
        weight[i] = np.where(ok & np.isfinite(w) & (w > 0), w, 0.0)
    n_valid = int((valid[1] | valid[2]).sum())
    if n_valid == 0:
        raise InputError(
            f"{plan.source}: all {int(selected.sum())} selected rows failed (flags != 0 or NaN "
            "estimates); nothing to calibrate"
        )
    if not (weight[1].any() or weight[2].any()):
        raise InputError(
            f"{plan.source}: the weights {', '.join(WEIGHT_COLUMNS)} are zero on every usable row"
        )
    response = sheared = pre_noshear = None
    psf = None
    if plan.psf is not None:
        psf = tuple(np.asarray(columns[c], dtype=float) for c in plan.psf)  # type: ignore[assignment]
    if plan.failures_select:
        sheared, version_pre = _version_selections(columns, plan, n)
        obj = _Objects(n, selected, valid, pre, weight, None, sheared, None, psf, version_pre)
        return _to_world(obj, columns, plan) if plan.frame == WORLD_FRAME else obj
    if resp is not None:
        response = {k: np.where(valid[k[0]], r, 0.0) for k, r in resp.items()}
        pre_noshear = raw
        # usable whatever the selection: failures are not a selection
        usable = np.asarray(columns["flags_noshear"]) == 0
        for i in (1, 2):
            usable &= np.isfinite(raw[i])
            for j in (1, 2):
                usable &= np.isfinite(resp[(i, j)])
        sheared = {}
        for kind in SHEARED_TYPES:
            sel = usable.copy()
            if plan.select is not None:
                sel &= expr.evaluate_rows(plan.select, VersionColumns(columns, kind), n)
            for i in (1, 2):
                w = (
                    np.asarray(columns[f"pre_g{i}_w_{kind}"], dtype=float)
                    if plan.weighted
                    else np.ones(n)
                )
                sheared[(i, kind)] = np.where(sel & np.isfinite(w) & (w > 0), w, 0.0)
    obj = _Objects(n, selected, valid, pre, weight, response, sheared, pre_noshear, psf)
    return _to_world(obj, columns, plan) if plan.frame == WORLD_FRAME else obj


def _version_selections(
    columns: Mapping[str, np.ndarray], plan: CalibrationPlan, n: int
) -> tuple[dict[tuple[int, str], np.ndarray], dict[tuple[int, str], np.ndarray]]:
    """With each version's failures a selection: the weight of every object under each
    sheared version (0 where that version failed, has a NaN estimate or fails the selection
    taken on its own features) and that version's own estimates."""
    inside = np.ones(n, dtype=bool)
    if INNER_COLUMN in columns:
        inside = np.asarray(columns[INNER_COLUMN]) != 0
    weights, estimates = {}, {}
    for kind in SHEARED_TYPES:
        sel = inside.copy()
        if plan.select is not None:
            sel &= expr.evaluate_rows(plan.select, VersionColumns(columns, kind), n)
        if f"flags_{kind}" in columns:
            sel &= np.asarray(columns[f"flags_{kind}"]) == 0
        for i in (1, 2):
            est = np.asarray(columns[f"pre_g{i}_{kind}"], dtype=float)
            w = np.ones(n)
            if plan.weighted:
                w = np.asarray(columns[f"pre_g{i}_w_{kind}"], dtype=float)
            ok = sel & np.isfinite(est) & np.isfinite(w) & (w > 0)
            weights[(i, kind)] = np.where(ok, w, 0.0)
            estimates[(i, kind)] = np.where(ok, est, 0.0)
    return weights, estimates


def _to_world(obj: _Objects, columns: Mapping[str, np.ndarray], plan: CalibrationPlan) -> _Objects:
    """The pixel-frame quantities of ``obj`` in the world frame of each object's Jacobian
    (:mod:`megalut_cli.shear.frame`): estimates ``Q (g + R eta)`` (``R = 1`` on the
    simulation route), responses ``Q R Q^T``, weights and sheared versions mixed as the
    components are; an object is used in both components or in neither."""
    frames = catalog_frames(columns)
    known = np.isfinite(frames.rotation).all(axis=(1, 2)) & np.isfinite(frames.distortion).all(
        axis=1
    )
    if not known.any():
        raise InputError(
            f"{plan.source}: no object has a usable Jacobian ({', '.join(JACOBIAN_COLUMNS)})"
        )
    both = obj.valid[1] & obj.valid[2] & known
    if not both.any():
        raise InputError(
            f"{plan.source}: no selected object is usable in both components with a Jacobian"
        )
    zero = lambda a: np.where(both, np.nan_to_num(a), 0.0)  # noqa: E731
    offset = response = sheared = pre_noshear = version_pre = None
    if obj.version_pre is not None:  # failures a selection: no per-object response needed
        filled = _filled_responses(columns, known)
        offset = response_offset(frames, {k: zero(r) for k, r in filled.items()})
        sheared, version_pre = _versions_to_world(obj, frames, known, filled)
    elif obj.response is not None:
        pixel_r = {k: zero(r) for k, r in obj.response.items()}
        offset = response_offset(frames, pixel_r)
        response = {k: zero(r) for k, r in response_to_world(frames, pixel_r).items()}
    g1, g2 = spin2_to_world(frames, zero(obj.pre[1]), zero(obj.pre[2]), offset)
    weight = {i: zero(w) for i, w in weights_to_world(frames, obj.weight).items()}
    if obj.sheared is not None and obj.pre_noshear is not None and obj.response is not None:
        usable = known & np.isfinite(obj.pre_noshear[1]) & np.isfinite(obj.pre_noshear[2])
        full_r = {k: np.where(usable, np.nan_to_num(r), 0.0) for k, r in obj.response.items()}
        n1, n2 = spin2_to_world(
            frames,
            np.where(usable, obj.pre_noshear[1], 0.0),
            np.where(usable, obj.pre_noshear[2], 0.0),
            response_offset(frames, full_r),
        )
        pre_noshear = {1: np.where(usable, n1, np.nan), 2: np.where(usable, n2, np.nan)}
        per_kind = {
            kind: weights_to_world(
                frames, {i: np.where(usable, obj.sheared[(i, kind)], 0.0) for i in (1, 2)}
            )
            for kind in SHEARED_TYPES
        }
        sheared = {}
        for i in (1, 2):
            world = versions_to_world(frames, {kind: per_kind[kind][i] for kind in SHEARED_TYPES})
            for kind in SHEARED_TYPES:
                sheared[(i, kind)] = np.where(usable, world[kind], 0.0)
    psf = None
    if obj.psf is not None:
        psf = spin2_to_world(frames, obj.psf[0], obj.psf[1])
    return _Objects(
        obj.n,
        obj.selected,
        {1: both, 2: both},
        {1: g1, 2: g2},
        weight,
        response,
        sheared,
        pre_noshear,
        psf,
        version_pre,
    )


def _filled_responses(
    columns: Mapping[str, np.ndarray], known: np.ndarray
) -> dict[tuple[int, int], np.ndarray]:
    """Each object's metacal response, the mean one (over the objects with a ``known`` frame
    and every version measured) where a version failed; zero when none has them all."""
    resp = {
        (i, j): np.asarray(columns[f"mcal_r{i}{j}"], dtype=float) for i in (1, 2) for j in (1, 2)
    }
    measured = np.all([np.isfinite(r) for r in resp.values()], axis=0) & known
    if not measured.any():  # the grid's residual shear then left uncorrected
        return {k: np.zeros(len(known)) for k in resp}
    return {k: np.where(measured, r, np.mean(r[measured])) for k, r in resp.items()}


def _versions_to_world(
    obj: _Objects,
    frames: Frames,
    known: np.ndarray,
    responses: Mapping[tuple[int, int], np.ndarray],
) -> tuple[dict[tuple[int, str], np.ndarray], dict[tuple[int, str], np.ndarray]]:
    """With each version's failures a selection: the world versions' weights and estimates
    (``sheared``, ``version_pre`` of :class:`_Objects`). Each sheared version's own estimates,
    on the objects it measured with a ``known`` frame, become ``Q (g_v + R eta)`` with the
    object's ``responses``; the world versions' weights and weighted estimates are linear in
    the pixel versions' (:func:`versions_to_world`), and their ratio is the estimate."""
    assert obj.version_pre is not None and obj.sheared is not None
    weights: dict[int, dict[str, np.ndarray]] = {1: {}, 2: {}}
    weighted: dict[int, dict[str, np.ndarray]] = {1: {}, 2: {}}
    for kind in SHEARED_TYPES:
        use = known & (obj.sheared[(1, kind)] > 0) & (obj.sheared[(2, kind)] > 0)
        offset = response_offset(frames, {k: np.where(use, r, 0.0) for k, r in responses.items()})
        est = spin2_to_world(
            frames,
            np.where(use, obj.version_pre[(1, kind)], 0.0),
            np.where(use, obj.version_pre[(2, kind)], 0.0),
            offset,
        )
        w = weights_to_world(
            frames, {i: np.where(use, obj.sheared[(i, kind)], 0.0) for i in (1, 2)}
        )
        for i in (1, 2):
            weights[i][kind] = w[i]
            weighted[i][kind] = w[i] * est[i - 1]
    sheared, version_pre = {}, {}
    for i in (1, 2):
        total = versions_to_world(frames, weights[i])
        products = versions_to_world(frames, weighted[i])
        for kind in SHEARED_TYPES:
            sheared[(i, kind)] = total[kind]
            with np.errstate(invalid="ignore", divide="ignore"):
                version_pre[(i, kind)] = np.where(
                    total[kind] != 0, products[kind] / total[kind], 0.0
                )
    return sheared, version_pre


def _row_sums(obj: _Objects, plan: CalibrationPlan) -> dict[str, np.ndarray]:
    """Per-object values whose sums give every estimate: those of
    :func:`megalut_cli.shear.response.row_values` and the PSF-leakage moments."""
    s = plan.scheme
    zeros = np.zeros(obj.n)
    vals = row_values(
        s,
        {f"g{i}": obj.weight[i] for i in (1, 2)},
        {"g1": zeros, "g2": zeros},
        {f"g{i}": obj.pre[i] for i in (1, 2)},
        obj.response,
        obj.sheared,
        obj.pre_noshear,
        plan.step,
        version_pre=obj.version_pre,
    )
    vals = {k: v for k, v in vals.items() if ":wtru:" not in k}
    vals["n"] = (obj.valid[1] | obj.valid[2]).astype(float)
    if obj.psf is not None:
        e = obj.psf
        ok = obj.valid[1] & obj.valid[2] & np.isfinite(e[0]) & np.isfinite(e[1])
        for i in (1, 2):
            w = np.where(ok, obj.weight[i], 0.0)
            ei = np.where(ok, e[i - 1], 0.0)
            vals[f"L:w:{i}"] = w
            vals[f"L:we:{i}"] = w * ei
            vals[f"L:wee:{i}"] = w * ei * ei
            for j in (1, 2):
                vals[f"L:wg:{i}{j}"] = w * obj.pre[j]
                vals[f"L:wge:{i}{j}"] = w * obj.pre[j] * ei
    return vals


def _version_of(name: str) -> str:
    """The metacal version whose selection a sum belongs to (``noshear`` for most)."""
    if any(f":{q}:" in name for q in ("sw", "swpre", "vw", "vwpre")):
        return name.rsplit(":", 1)[1]
    return "noshear"


# --------------------------------------------------------------------------- estimates


def _estimates(t: Mapping[str, np.ndarray], plan: CalibrationPlan) -> dict[str, Any]:
    """The calibrated means, responses and PSF leakage from the totals ``t`` (each of shape
    ``(1, ...)``: axis 0 is summed by :func:`metacal_response`)."""
    s = plan.scheme
    with np.errstate(invalid="ignore", divide="ignore"):
        raw = [t[f"{s}:wpre:g{i}"][0] / t[f"{s}:w:g{i}"][0] for i in (1, 2)]
        shape = raw[0].shape
        selection = None
        if plan.route != ROUTE_SIMULATION:
            mean, selection = metacal_response(t, s)
            r = mean if selection is None else mean + selection
        else:
            mean = np.array([[np.ones(shape), np.zeros(shape)], [np.zeros(shape), np.ones(shape)]])
            r = mean
        g1, g2 = calibrate_by_response(r[0, 0], r[0, 1], r[1, 0], r[1, 1], raw[0], raw[1])
        out: dict[str, Any] = {"g": np.array([g1, g2]), "R": mean, "R_sel": selection}
        if plan.psf is not None:
            det = r[0, 0] * r[1, 1] - r[0, 1] * r[1, 0]
            inv = np.array([[r[1, 1], -r[0, 1]], [-r[1, 0], r[0, 0]]]) / det
            alpha, add = [], []
            for i in (1, 2):
                w = t[f"L:w:{i}"][0]
                ebar = t[f"L:we:{i}"][0] / w
                var = t[f"L:wee:{i}"][0] / w - ebar**2
                gbar = cov = 0.0
                for j in (1, 2):
                    gj = t[f"L:wg:{i}{j}"][0] / w
                    gbar = gbar + inv[i - 1, j - 1] * gj
                    cov = cov + inv[i - 1, j - 1] * (t[f"L:wge:{i}{j}"][0] / w - gj * ebar)
                a = np.where(var > MIN_PSF_SPREAD**2, cov / var, np.nan)
                alpha.append(a)
                add.append(gbar - a * ebar)
            out["alpha"] = np.array(alpha)
            out["additive"] = np.array(add)
    return out


def _totals(
    vals: Mapping[str, np.ndarray],
    bins: Mapping[str, np.ndarray],
    n_bins: int,
    unit: np.ndarray | None = None,
    n_units: int = 0,
) -> dict[str, np.ndarray]:
    """Sums of ``vals`` per bin (``bins[version]``: each object's bin, -1 outside), and with
    ``unit`` per (bin, unit): arrays ``(n_bins,)`` or ``(n_bins, n_units)``."""
    out = {}
    for name, v in vals.items():
        b = bins[_version_of(name)]
        keep = b >= 0
        if unit is None:
            out[name] = np.bincount(b[keep], weights=v[keep], minlength=n_bins)
        else:
            keep &= unit >= 0
            key = b[keep] * n_units + unit[keep]
            out[name] = np.bincount(key, weights=v[keep], minlength=n_bins * n_units).reshape(
                n_bins, n_units
            )
    return out


def _jackknife_error(samples: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Delete-one jackknife error over the last axis, counting the ``used`` samples (a
    patch holding objects of the bin); NaN with fewer than 2."""
    n = used.sum(axis=-1)
    finite = used & np.isfinite(samples)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = np.where(finite, samples, 0.0)
        mean = x.sum(axis=-1, keepdims=True) / finite.sum(axis=-1, keepdims=True)
        var = (n - 1) / n * np.where(finite, (x - mean) ** 2, 0.0).sum(axis=-1)
    return np.where((n >= 2) & (finite.sum(axis=-1) == n), np.sqrt(var), np.nan)


def _sample_errors(
    vals: Mapping[str, np.ndarray],
    totals: Mapping[str, np.ndarray],
    bins: Mapping[str, np.ndarray],
    n_bins: int,
    plan: CalibrationPlan,
    patches: np.ndarray | None,
    n_bootstrap: int,
    seed: int,
    objects: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Errors of ``g``, ``alpha`` and ``additive`` per bin: the jackknife over ``patches``
    (``totals``: the sums of every object; objects without a patch are never left out) or
    the bootstrap over objects (the response recomputed in every sample; ``objects``: the
    object of each row, whose rows are drawn together)."""
    keys = ("g", "alpha", "additive") if plan.psf is not None else ("g",)
    if patches is not None:
        n_units = int(patches.max()) + 1 if patches.size and patches.max() >= 0 else 0
        per = _totals(vals, bins, n_bins, patches, n_units)
        samples = _estimates({k: (totals[k][:, None] - v)[None] for k, v in per.items()}, plan)
        used = per["n"] > 0  # (n_bins, n_units)
        return {k: _jackknife_error(samples[k], used) for k in keys}
    # bootstrap over the objects that enter any sum
    involved = np.flatnonzero(np.any(np.stack([v != 0 for v in vals.values()]), axis=0))
    names = list(vals)
    # the values of each (version, bin), gathered once: (names of that version, its objects)
    parts = []
    for version, b in bins.items():
        rows = [i for i, k in enumerate(names) if _version_of(k) == version]
        b = b[involved]
        for k in range(n_bins):
            inside = np.flatnonzero(b == k)
            if rows and inside.size:
                sub = np.stack([vals[names[r]][involved[inside]] for r in rows])
                parts.append((rows, k, inside, sub))
    boot: dict[str, list[np.ndarray]] = {k: [] for k in names}
    group = np.arange(involved.size)
    if objects is not None and involved.size:
        group = codes(objects[involved])
    for drawn in resample_counts(seed, int(group.max()) + 1, n_bootstrap, STREAM_CALIBRATE):
        counts = drawn[group]
        block = {k: np.zeros((n_bins, counts.shape[1])) for k in names}
        for rows, k, inside, sub in parts:
            # einsum: no BLAS threads, whose spinning costs more than it gains on busy cores
            for r, total in zip(rows, np.einsum("ij,jk->ik", sub, counts[inside])):
                block[names[r]][k] = total
        for k in names:
            boot[k].append(block[k])
    samples = _estimates({k: np.concatenate(v, axis=1)[None] for k, v in boot.items()}, plan)
    return {key: np.apply_along_axis(spread, -1, samples[key]) for key in keys}


# --------------------------------------------------------------------------- bins


@dataclass
class _Binning:
    """Each object's bin under every metacal version, and what describes the bins."""

    bins: dict[str, np.ndarray]  # version -> bin of each object (-1: none)
    entries: list[dict[str, Any]]  # "lo", "hi", "center" or "value" per bin
    kind: str  # "all", "quantile", "value"


def _binning(
    columns: Mapping[str, np.ndarray], obj: _Objects, plan: CalibrationPlan, n_bins: int
) -> _Binning:
    metacal = plan.route == ROUTE_METACAL
    versions = ("noshear", *SHEARED_TYPES) if plan.route != ROUTE_SIMULATION else ("noshear",)
    if plan.by is None:
        zero = np.zeros(obj.n, dtype=np.int64)
        return _Binning({v: zero for v in versions}, [{}], "all")
    by = plan.by
    if plan.by_kind == "patch":
        assert plan.positions is not None
        a, b = (np.asarray(columns[c], dtype=float) for c in plan.positions)
        sky = plan.positions == POSITION_COLUMNS[0]
        patch = sky_patches(a, b, n_bins, sky=sky)
        entries = []
        for k in range(int(patch.max()) + 1):
            inside = patch == k
            entries.append(
                {
                    "value": k,
                    plan.positions[0]: float(np.median(a[inside])),
                    plan.positions[1]: float(np.median(b[inside])),
                }
            )
        return _Binning({v: patch for v in versions}, entries, "patch")

    def values(version: str) -> np.ndarray:
        view = VersionColumns(columns, version) if metacal else columns
        if plan.by_kind == "column":
            return np.asarray(view[by])
        return expr.evaluate_row_values(by, view, obj.n)

    used = obj.valid[1] | obj.valid[2]
    v0 = values("noshear")
    key = plan.name("by")
    if v0.dtype.kind not in "iubf":
        raise ConfigError(f"{key} {by}: not a numeric column")
    if v0.dtype.kind in "iub":  # value by value (e.g. a tomographic bin)
        levels = np.unique(v0[used])
        if levels.size > MAX_BINS:
            raise ConfigError(
                f"{key} {by}: {levels.size} distinct values, more than {MAX_BINS} bins"
            )

        def assign(v: np.ndarray) -> np.ndarray:
            pos = np.clip(np.searchsorted(levels, v), 0, levels.size - 1)
            return np.where(levels[pos] == v, pos, -1).astype(np.int64)

        entries = [{"value": int(x)} for x in levels]
        bins = {version: assign(values(version)) for version in versions}
        return _Binning(bins, entries, "value")
    v0 = np.asarray(v0, dtype=float)
    edges = equal_population_edges(v0[used], n_bins, by, key)
    bins = {
        version: assign_bins(v0 if version == "noshear" else values(version).astype(float), edges)
        for version in versions
    }
    entries = []
    for k in range(edges.size - 1):
        inside = v0[used & (bins["noshear"] == k)]
        entries.append(
            {
                "lo": float(edges[k]),
                "hi": float(edges[k + 1]),
                "center": float(np.median(inside)) if inside.size else None,
            }
        )
    return _Binning(bins, entries, "quantile")


# --------------------------------------------------------------------------- entry points


@dataclass
class Calibration:
    """A calibration: ``result`` (JSON-ready: ``"all"``, ``"bins"``...), and what the
    per-object catalog needs (:func:`calibrated_catalog`)."""

    result: dict[str, Any]
    plan: CalibrationPlan
    responses: np.ndarray  # (n_bins + 1, 2, 2) total responses: "all", then each bin
    rows: np.ndarray  # bool: objects usable in both components
    bin_of: np.ndarray  # each object's (noshear) bin, -1 without one
    estimates: dict[int, np.ndarray]  # uncalibrated estimate per component (0 where unusable)
    weights: dict[int, np.ndarray]
    psf: tuple[np.ndarray, np.ndarray] | None = None  # PSF ellipticity, in the plan's frame


def _json(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return [_json(v) for v in x]
    v = float(x)
    return v if math.isfinite(v) else None


def calibrate_columns(
    columns: Mapping[str, np.ndarray],
    *,
    header: Mapping[str, Any] | None = None,
    select: str | None = None,
    by: str | None = None,
    bins: int = CALIBRATE["bins"].default,
    unweighted: bool = CALIBRATE["unweighted"].default,
    errors: str = CALIBRATE["errors"].default,
    n_patches: int = CALIBRATE["patches"].default,
    n_bootstrap: int = CALIBRATE["bootstrap"].default,
    seed: int = 1,
    source: str = "catalog",
    names: Mapping[str, str] | None = None,
    failures: str | None = None,
) -> Calibration:
    """Calibrate the estimates of ``columns`` (a mapping of arrays, e.g. read from the output
    of ``megalut predict``; ``header`` its header, for ``MCALSTEP``), for the whole catalog
    and, with ``by``, for each bin. See the module's docstring; ``names``: how messages name
    the arguments (``select``, ``by``, ``errors``, ``failures``). ``failures`` (metacal):
    ``"selection"`` (None, the default) the noshear estimates of the objects whose noshear
    version is measured, calibrated by the response of the versions' means, each over its own
    measured objects; ``"exclude"`` the objects with every version measured, each with its
    own response."""
    colnames = list(columns.colnames) if hasattr(columns, "colnames") else list(columns)
    plan = plan_calibration(
        colnames,
        header,
        select=select,
        by=by,
        unweighted=unweighted,
        errors=errors,
        source=source,
        names=names,
        failures=failures,
    )
    if n_patches < 2 or n_bootstrap < 2:
        raise ConfigError("calibrate needs at least 2 patches and 2 bootstrap resamples")
    obj = _objects(columns, plan)
    vals = _row_sums(obj, plan)
    objects = object_index(columns) if plan.epochs else None
    patches = None
    if plan.errors == JACKKNIFE and plan.positions is not None:
        a, b = (np.asarray(columns[c]) for c in plan.positions)
        patches = sky_patches(a, b, n_patches, sky=plan.positions == POSITION_COLUMNS[0])
        if patches.max() < 1:
            raise InputError(
                f"{plan.source}: the positions {', '.join(plan.positions)} fall in a single "
                f"patch; use {plan.name('errors')} bootstrap"
            )
    groups = objects  # what the bootstrap draws together: an object's epochs, or a cell
    if plan.unit is not None:  # metadetection: cell by cell
        cells = codes(np.asarray(columns[plan.unit]))
        if plan.errors == JACKKNIFE:
            patches = cells
            if patches.max() < 1:
                raise InputError(
                    f"{plan.source}: one {plan.unit} only; use {plan.name('errors')} bootstrap"
                )
        else:
            groups = cells
    versions = ("noshear", *SHEARED_TYPES) if plan.route != ROUTE_SIMULATION else ("noshear",)
    whole = _Binning({v: np.zeros(obj.n, dtype=np.int64) for v in versions}, [{}], "all")
    binnings = [whole] + ([_binning(columns, obj, plan, bins)] if plan.by is not None else [])
    has_selection = plan.select is not None or plan.weighted
    out_entries: list[dict[str, Any]] = []
    responses = []
    for index, binning in enumerate(binnings):
        n_b = len(binning.entries)
        totals = _totals(vals, binning.bins, n_b)
        est = _estimates({k: v[None] for k, v in totals.items()}, plan)
        err = _sample_errors(
            vals, totals, binning.bins, n_b, plan, patches, n_bootstrap, seed, groups
        )
        with_sel = est["R_sel"] is not None and (has_selection or (index > 0 and plan.by_versioned))
        for k in range(n_b):
            mean = est["R"][:, :, k]
            sel = est["R_sel"][:, :, k] if with_sel else None
            if plan.route == ROUTE_METADETECT:  # the detections' response is the whole one
                mean, sel = est["R_sel"][:, :, k], None
            total = mean + sel if sel is not None else mean
            responses.append(total)
            entry: dict[str, Any] = {
                **({"bin": k} if index else {}),
                **binning.entries[k],
                "n_objects": int(totals["n"][k]),
                "g1": _json(est["g"][0, k]),
                "g2": _json(est["g"][1, k]),
                "g1_err": _json(err["g"][0, k]),
                "g2_err": _json(err["g"][1, k]),
                "response": _json(mean),
                "selection_response": None if sel is None else _json(sel),
                "scheme": plan.scheme,
            }
            if plan.psf is not None:
                entry["alpha"] = _json(est["alpha"][:, k])
                entry["alpha_err"] = _json(err["alpha"][:, k])
                entry["additive"] = _json(est["additive"][:, k])
                entry["additive_err"] = _json(err["additive"][:, k])
            out_entries.append(entry)
    errors_entry: dict[str, Any] = (
        {
            "method": JACKKNIFE,
            "positions": list(plan.positions or ()),
            **({"units": plan.unit} if plan.unit is not None else {}),
            "patches": int(patches.max()) + 1 if patches is not None else 0,
            "patches_asked": int(n_patches),
        }
        if patches is not None
        else {
            "method": BOOTSTRAP,
            "resamples": int(n_bootstrap),
            "seed": int(seed),
            **({"units": plan.unit} if plan.unit is not None else {}),
        }
    )
    result: dict[str, Any] = {
        "format": CALIBRATION_FORMAT,
        "format_version": CALIBRATION_FORMAT_VERSION,
        "input": plan.source,
        "calibration": plan.route,
        "metacal_step": plan.step,
        "failures": plan.failures if plan.route == ROUTE_METACAL else None,
        "scheme": plan.scheme,
        "weights": (
            [f"{c}_noshear" if plan.route == ROUTE_METACAL else c for c in WEIGHT_COLUMNS]
            if plan.weighted
            else None
        ),
        "frame": plan.frame,
        "frame_convention": FRAME_TEXT[plan.frame],
        "n_rows": obj.n,
        "n_selected": int(obj.selected.sum()),
        "select": plan.select,
        "by": None,
        "errors": errors_entry,
        "psf_columns": list(plan.psf) if plan.psf is not None else None,
        "all": out_entries[0],
    }
    bin_of = binnings[-1].bins["noshear"] if plan.by is not None else np.zeros(obj.n, np.int64)
    cal = Calibration(
        result,
        plan,
        np.array(responses),
        obj.valid[1] & obj.valid[2],
        bin_of,
        obj.pre,
        obj.weight,
        obj.psf,
    )
    profile = psf_profile(cal)
    if profile is not None:
        result["psf_profile"] = profile
    if objects is not None:
        usable = obj.valid[1] | obj.valid[2]
        result["epochs"] = {
            "rows": int(usable.sum()),
            "objects": int(np.unique(objects[usable]).size),
            "note": "rows are epochs of objects (measure --epochs): n_objects counts rows",
        }
    if plan.by is not None:
        result["by"] = {"quantity": plan.by, "binning": binnings[1].kind}
        result["bins"] = out_entries[1:]
    return cal


def calibrated_catalog(
    columns: Mapping[str, np.ndarray], cal: Calibration
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The per-object catalog of a calibration, and its header cards: the objects usable
    in both components, the input's id and position columns, ``g1, g2`` (each estimate
    times the inverse total response of its bin, of the whole catalog outside any bin),
    ``weight`` (the mean of the two components' weights) and ``weight_g1, weight_g2``,
    ``bin`` and the total response ``R11 .. R22`` of the object's bin, and with PSF columns
    ``psf_g1, psf_g2``, all in the calibration's frame (``SHFRAME``). Valid for averages over
    many objects, not for one object."""
    keep = cal.rows
    bin_of = cal.bin_of[keep]
    resp = cal.responses[np.where(bin_of >= 0, bin_of + 1, 0)] if cal.plan.by else None
    if resp is None:
        resp = np.broadcast_to(cal.responses[0], (int(keep.sum()), 2, 2))
    g1, g2 = calibrate_by_response(
        resp[:, 0, 0],
        resp[:, 0, 1],
        resp[:, 1, 0],
        resp[:, 1, 1],
        cal.estimates[1][keep],
        cal.estimates[2][keep],
    )
    out: dict[str, np.ndarray] = {c: np.asarray(columns[c])[keep] for c in cal.plan.pass_through}
    w1, w2 = cal.weights[1][keep], cal.weights[2][keep]
    out.update(
        {
            "g1": g1,
            "g2": g2,
            "weight": 0.5 * (w1 + w2),
            "weight_g1": w1,
            "weight_g2": w2,
            "bin": bin_of.astype(np.int32),
        }
    )
    for i in (1, 2):
        for j in (1, 2):
            out[f"R{i}{j}"] = resp[:, i - 1, j - 1].astype(float)
    if cal.psf is not None:
        out["psf_g1"], out["psf_g2"] = cal.psf[0][keep], cal.psf[1][keep]
    if cal.plan.epochs:
        out = combine_epochs(out)
    cards: dict[str, Any] = {
        FRAME_CARD: (cal.plan.frame, "frame of g1, g2, R, psf_g: world (u, v) or pixel"),
        "CALROUTE": (cal.plan.route, "calibration: metacal responses or simulation-trained"),
        "CALSCHEM": (cal.plan.scheme, "weighted or unweighted means"),
        "CALNOTE": ("averages", "g1, g2 are valid for averages, not for one object"),
        "CALBY": (cal.plan.by or "", "the binning of the responses (--by), '' for none"),
        "CALNBIN": (len(cal.responses) - 1 if cal.plan.by else 0, "number of bins"),
    }
    for k, r in enumerate(cal.responses):
        for i in (1, 2):
            for j in (1, 2):
                value = float(r[i - 1, j - 1])
                if math.isfinite(value):  # a FITS card holds no NaN
                    where = f"bin {k - 1}" if k else "all"
                    cards[f"R{i}{j}B{k - 1}" if k else f"CALR{i}{j}"] = (
                        value,
                        f"total response, {where}",
                    )
    return out, cards


#: Equal-population bins of the PSF ellipticity in the leakage profile.
PROFILE_BINS = 8


def psf_profile(cal: Calibration, n_bins: int = PROFILE_BINS) -> dict[str, Any] | None:
    """The calibrated mean shear in equal-population bins of the PSF ellipticity, per
    component (the picture behind ``alpha``): each bin's weighted mean ``e_psf``, ``g`` (the
    estimates times the whole catalog's inverse total response), its error (the weighted
    scatter over sqrt of the effective count) and its objects; None without PSF columns."""
    if cal.psf is None:
        return None
    r = cal.responses[0]
    if not np.all(np.isfinite(r)) or abs(np.linalg.det(r)) == 0:
        return None
    g = np.linalg.solve(r, np.stack([cal.estimates[1], cal.estimates[2]]))
    out: dict[str, Any] = {}
    for i in (1, 2):
        e, w = np.asarray(cal.psf[i - 1], dtype=float), cal.weights[i]
        use = cal.rows & np.isfinite(e) & (w > 0)
        if not use.any() or np.std(e[use]) <= MIN_PSF_SPREAD:
            return None
        b = np.full(len(e), -1)
        b[use] = assign_bins(e[use], equal_population_edges(e[use], n_bins))
        entry: dict[str, list[Any]] = {"e_psf": [], "g": [], "g_err": [], "n": []}
        for k in range(int(b.max()) + 1):
            inside = b == k
            wk, gk = w[inside], g[i - 1][inside]
            total = wk.sum()
            mean = float(np.sum(wk * gk) / total)
            n_eff = total**2 / np.sum(wk * wk)
            scatter = np.sqrt(np.sum(wk * (gk - mean) ** 2) / total)
            entry["e_psf"].append(float(np.sum(wk * e[inside]) / total))
            entry["g"].append(mean)
            entry["g_err"].append(float(scatter / np.sqrt(n_eff)))
            entry["n"].append(int(inside.sum()))
        out[f"g{i}"] = entry
    return out


def object_index(columns: Mapping[str, np.ndarray]) -> np.ndarray:
    """Each row's object, numbered from 0: its ``id``, within its ``tile`` when the catalog
    has one (``megalut concat``)."""
    keys = [np.asarray(columns["id"])]
    if TILE_COLUMN in columns:
        keys.insert(0, np.asarray(columns[TILE_COLUMN]))
    return codes(np.stack([k.astype(np.int64) for k in keys], axis=1))


def codes(values: np.ndarray) -> np.ndarray:
    """Each row's value numbered from 0 in sorted order (rows of a 2-D array as keys)."""
    return np.unique(values, axis=0, return_inverse=True)[1].ravel()


def combine_epochs(rows: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One row per object (``id``) from the calibrated rows of its epochs: ``g1, g2`` and
    ``psf_g1, psf_g2`` averaged with each component's weights, the weights summed (so that
    averages over objects equal those over the epochs), ``n_epochs``; the other columns
    (positions, the bin and its responses) from the object's first epoch."""
    inverse = object_index(rows)
    first = np.unique(inverse, return_index=True)[1]
    n = len(first)

    def total(values: np.ndarray) -> np.ndarray:
        return np.bincount(inverse, weights=values, minlength=n)

    out = {c: np.asarray(v)[first] for c, v in rows.items() if c != "cutout"}
    w = {i: np.asarray(rows[f"weight_g{i}"], dtype=float) for i in (1, 2)}
    with np.errstate(invalid="ignore", divide="ignore"):
        for i in (1, 2):
            wi = total(w[i])
            for c in (f"g{i}", f"psf_g{i}"):
                if c in rows:
                    out[c] = np.where(wi > 0, total(w[i] * rows[c]) / wi, np.nan)
            out[f"weight_g{i}"] = wi
    out["weight"] = 0.5 * (out["weight_g1"] + out["weight_g2"])
    out["n_epochs"] = np.bincount(inverse, minlength=n).astype(np.int32)
    return out


def _pm(v: float | None, e: float | None) -> str:
    if v is None:
        return f"{'n/a':>19}"
    return f"{v:+.5f} ± {e:.5f}" if e is not None else f"{v:+.5f} ±     n/a"


def _label(entry: Mapping[str, Any], by: str | None) -> str:
    where = [f"{entry[c]:.4g}" for pair in POSITION_COLUMNS for c in pair if c in entry]
    if "value" in entry and by == PATCH_BY and where:
        return f"{by} {entry['value']} ({', '.join(where)})"
    if "value" in entry:
        return f"{by} = {entry['value']}"
    if "lo" in entry:
        return f"{entry['lo']:.4g} – {entry['hi']:.4g}"
    return "all"


def format_calibration(result: Mapping[str, Any]) -> str:
    """The text table of a calibration: one line for the whole catalog and one per bin
    (objects, calibrated g1, g2 with errors, R11, R22 of the total response, scheme; with
    PSF columns the leakage alpha), then a line saying where the errors come from."""
    by = (result.get("by") or {}).get("quantity")
    entries = [result["all"], *result.get("bins", [])]
    psf = result.get("psf_columns") is not None
    labels = [_label(e, by) for e in entries]
    width = max(12, *(len(x) for x in labels))
    head = f"{'bin':<{width}} {'n_objects':>9}  {'g1 ± err':>19}  {'g2 ± err':>19}"
    head += f"  {'R11':>7}  {'R22':>7}  scheme"
    if psf:
        head += f"  {'alpha1 ± err':>19}  {'alpha2 ± err':>19}"
    lines = [
        f"calibrated mean shear of {result['input']} ({result['calibration']} route"
        + (f", metacal step {result['metacal_step']:g}" if result.get("metacal_step") else "")
        + (f", by {by}" if by else "")
        + ")",
        head,
    ]
    for label, e in zip(labels, entries):
        total = _total_response(e)
        r11 = f"{total[0][0]:7.4f}" if total[0][0] is not None else f"{'n/a':>7}"
        r22 = f"{total[1][1]:7.4f}" if total[1][1] is not None else f"{'n/a':>7}"
        line = (
            f"{label:<{width}} {e['n_objects']:>9}  {_pm(e['g1'], e['g1_err'])}  "
            f"{_pm(e['g2'], e['g2_err'])}  {r11}  {r22}  {e['scheme']}"
        )
        if psf:
            a, ae = e["alpha"], e["alpha_err"]
            line += f"  {_pm(a[0], ae[0])}  {_pm(a[1], ae[1])}"
        lines.append(line)
    err = result["errors"]
    if err["method"] == JACKKNIFE and err.get("units"):
        lines.append(f"errors: jackknife over {err['patches']} values of {err['units']}")
    elif err["method"] == JACKKNIFE:
        lines.append(
            f"errors: jackknife over {err['patches']} patches of ({', '.join(err['positions'])})"
        )
    else:
        over = f"values of {err['units']}" if err.get("units") else "objects"
        lines.append(
            f"errors: bootstrap over {over} ({err['resamples']} resamples, seed {err['seed']})"
        )
    lines.append(f"frame: {FRAME_TEXT[result.get('frame', PIXEL_FRAME)]}")
    if result.get("epochs"):
        ep = result["epochs"]
        lines.append(
            f"rows: {ep['rows']} epochs of {ep['objects']} objects (measure --epochs), "
            "combined in the world frame"
        )
    if result["calibration"] == ROUTE_METADETECT:
        lines.append(
            "R = (<g>_jp - <g>_jm) / (2 step) over each version's own detections (metadetection)"
        )
    if result["calibration"] == ROUTE_METACAL and result.get("failures") == "selection":
        lines.append(
            "R = (<g>_jp - <g>_jm) / (2 step), each version's mean over its own measured "
            "objects (failures a selection)"
        )
    elif result["calibration"] == ROUTE_METACAL:
        lines.append("R = <R> + R_sel (mean and selection responses; --json has both)")
    return "\n".join(lines)


def _total_response(entry: Mapping[str, Any]) -> list[list[float | None]]:
    """``response + selection_response`` of a result entry (None where undetermined)."""
    mean, sel = entry["response"], entry["selection_response"]
    out: list[list[float | None]] = []
    for i in range(2):
        row: list[float | None] = []
        for j in range(2):
            m = mean[i][j]
            s = 0.0 if sel is None else sel[i][j]
            row.append(None if m is None or s is None else m + s)
        out.append(row)
    return out
