"""The ``[catalog]`` table of a simulation config: the input catalog whose rows ``catalog``
parameters sample (read, selected, scaled)."""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from megalut_cli.errors import ConfigError
from megalut_cli.expr import columns_used, evaluate_rows
from megalut_cli.schema import check_table, resolve_beside
from megalut_cli.sim.distributions import CatalogColumn

log = logging.getLogger(__name__)


_CATALOG_KEYS = {"path", "select", "hdu"}


def _catalog_dists(parts: Mapping[str, Mapping[str, Any]]) -> list[tuple[str, str, CatalogColumn]]:
    found = []
    for part, dists in parts.items():
        for name, d in dists.items():
            if isinstance(d, CatalogColumn):
                found.append((part, name, d))
    return found


def _element_columns(expr_cols: Sequence[str], table: Any) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {}
    for name in expr_cols:
        if name in table.colnames:
            arr = np.asarray(table[name])
            if arr.ndim != 1:
                raise ConfigError(
                    f"catalog.select: {name!r} is an array column; use {name}_0, {name}_1, ..."
                )
            cols[name] = arr
            continue
        m = re.fullmatch(r"(.+)_(\d+)", name)
        if m and m.group(1) in table.colnames:
            arr = np.asarray(table[m.group(1)])
            i = int(m.group(2))
            if arr.ndim == 2 and i < arr.shape[1]:
                cols[name] = arr[:, i]
                continue
        raise ConfigError(f"catalog.select: unknown column {name!r}")
    return cols


def load_catalog_columns(
    raw: Mapping[str, Any], config_path: str, parts: dict[str, dict[str, Any]]
) -> tuple[int, str | None]:
    """Read the [catalog] columns used by ``catalog`` distributions; attach their data."""
    from megalut_cli.catalog import catalog_info, read_catalog  # fitsio: not needed for --help

    t = check_table(raw.get("catalog"), "catalog", _CATALOG_KEYS)
    found = _catalog_dists(parts)
    if not found:
        if t:
            log.warning("[catalog] given but no parameter has type = 'catalog'; ignored")
        return 0, None
    if not t:
        raise ConfigError(f"{found[0][2].key}: type 'catalog' needs a [catalog] table with a path")
    if "hdu" in t:
        log.warning("catalog.hdu is ignored: the first table extension is read")
    path = resolve_beside(t.get("path"), "catalog.path", config_path)
    select = t.get("select")
    expr_cols: list[str] = []
    if select is not None:
        if not isinstance(select, str):
            raise ConfigError("catalog.select: expected an expression string")
        expr_cols = columns_used(select)
    _, names, _ = catalog_info(path)
    needed = {d.column for _, _, d in found}
    for name in expr_cols:
        m = re.fullmatch(r"(.+)_(\d+)", name)
        needed.add(m.group(1) if (m and name not in names and m.group(1) in names) else name)
    for _, _, d in found:
        if d.column not in names:
            raise ConfigError(f"{d.key}.column: no column {d.column!r} in {path}")
    unknown = sorted(n for n in needed if n not in names)
    if unknown:
        raise ConfigError(f"catalog.select: unknown column {unknown[0]!r}")
    table = read_catalog(path, columns=sorted(needed))
    n = len(table)
    mask = np.ones(n, dtype=bool)
    if select is not None:
        mask = np.asarray(evaluate_rows(select, _element_columns(expr_cols, table), n), dtype=bool)
    values: dict[tuple[str, str], np.ndarray] = {}
    for part, name, d in found:
        arr = np.asarray(table[d.column])
        if arr.dtype.kind not in "fiu":
            raise ConfigError(f"{d.key}.column: {d.column!r} is not numeric")
        if arr.ndim == 2:
            if d.element is None:
                raise ConfigError(
                    f"{d.key}.element: {d.column!r} is an array column of {arr.shape[1]} values; "
                    "give element = INDEX (0-based)"
                )
            if d.element >= arr.shape[1]:
                raise ConfigError(
                    f"{d.key}.element: {d.element} out of range for {d.column!r} "
                    f"({arr.shape[1]} values)"
                )
            arr = arr[:, d.element]
        elif arr.ndim != 1:
            raise ConfigError(f"{d.key}.column: {d.column!r} has an unsupported shape")
        elif d.element is not None:
            raise ConfigError(f"{d.key}.element: {d.column!r} is not an array column")
        values[(part, name)] = arr.astype(float) * d.scale + d.offset
    finite = np.all([np.isfinite(v) for v in values.values()], axis=0)
    bad = int(np.sum(mask & ~finite))
    if bad:
        log.warning("%s: %d selected row(s) with non-finite values skipped", path, bad)
    mask &= finite
    if not mask.any():
        raise ConfigError(f"catalog.select: no usable row left in {path}")
    for part, name, d in found:
        parts[part][name] = d.with_data(values[(part, name)][mask])
    log.info("catalog %s: sampling from %d of %d rows", path, int(mask.sum()), n)
    return int(mask.sum()), str(path)
