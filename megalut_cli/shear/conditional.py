"""Equal-population bins for conditional biases (paper Sect. 5.3, Figs. 12 and 15).

A conditional bias is ``m`` and ``c`` measured on the rows whose value of some column
(a true parameter such as ``tru_rad``, or a measured one such as ``snr``) falls in a bin:
rows are binned, the estimates of each case are averaged within the bin, and the line is
fitted over those cases (:mod:`megalut_cli.shear.evaluate` does the bookkeeping). Binning
on measured columns mixes in selection effects (paper Sect. 2.2); that is often the point.
"""

from __future__ import annotations

import logging

import numpy as np

from megalut_cli.errors import ConfigError

log = logging.getLogger(__name__)


def equal_population_edges(
    values: np.ndarray, n_bins: int, name: str = "column", key: str = "by"
) -> np.ndarray:
    """Bin edges holding about the same number of (finite) ``values`` in each bin.

    Edges are quantiles; ties (e.g. a true parameter shared by all rows of a case, or a
    column with few distinct values) can merge bins, in which case fewer than ``n_bins``
    bins come back and a note is logged. Raises :class:`ConfigError` when no finite value
    exists. Messages name the column ``name`` after the caller's ``key``.
    """
    if n_bins < 1:
        raise ConfigError(f"number of bins must be positive, got {n_bins}")
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise ConfigError(f"{key} {name}: no finite values among the rows used")
    edges = np.unique(np.quantile(v, np.linspace(0.0, 1.0, n_bins + 1)))
    if edges.size == 1:  # a single value: one bin of zero width
        edges = np.array([edges[0], edges[0]])
    if edges.size - 1 < n_bins:
        log.info("%s %s: only %d distinct bin(s) (tied values)", key, name, edges.size - 1)
    return edges


def assign_bins(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin index of each value: ``edges[k] <= v < edges[k+1]`` (last bin closed); -1 outside or
    NaN."""
    v = np.asarray(values, dtype=float)
    n_bins = edges.size - 1
    idx = np.searchsorted(edges, v, side="right") - 1
    idx[v == edges[-1]] = n_bins - 1
    idx[~np.isfinite(v) | (v < edges[0]) | (v > edges[-1])] = -1
    return idx.astype(np.int64)
