"""Features of host stamps measured on the device (``measure --device gpu``)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from megalut_cli.gpu import jax_device
from megalut_cli.gpu.adamom import measure_batch

#: Most stamps per device batch (memory: ~0.3 MB per 64 x 64 stamp in the moment iteration).
BATCH_STAMPS = 4096
#: Fewest stamps of a padded batch.
MIN_BATCH = 8


def padded_size(n: int, batch: int | None = None) -> int:
    """Batch shape for ``n`` stamps: the next power of two (at least :data:`MIN_BATCH`, at
    most ``batch``, default :data:`BATCH_STAMPS`), so that few shapes are compiled."""
    batch = BATCH_STAMPS if batch is None else batch
    return min(batch, max(MIN_BATCH, 1 << math.ceil(math.log2(max(n, 1)))))


def split_measurements(res: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(moments (n, 7), skymad, finite)`` from :func:`megalut_cli.gpu.adamom.measure_batch`
    rows."""
    return res[:, :7], res[:, 9], res[:, 10] > 0


def measure_on_device(stamps: jnp.ndarray, guess_sigma: float) -> np.ndarray:
    """:func:`measure_batch` of device stamps (any count), padded into fixed-shape batches;
    only the (n, 11) results come back to the host."""
    n = stamps.shape[0]
    out = []
    for a in range(0, n, BATCH_STAMPS):
        block = stamps[a : a + BATCH_STAMPS]
        size = padded_size(len(block))
        if size > len(block):
            block = jnp.concatenate(
                [block, jnp.zeros((size - len(block), *block.shape[1:]), block.dtype)]
            )
        out.append(np.asarray(measure_batch(block, guess_sigma))[: min(BATCH_STAMPS, n - a)])
    return np.concatenate(out) if out else np.zeros((0, 11))


def pixel_measurements(
    stamps: np.ndarray, guess_sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(moments, skymad, finite)`` of host ``stamps`` (n, S, S), measured on the device,
    as :func:`megalut_cli.measure.features.measure_stamps` measures them on the CPU."""
    dev = jax_device()
    dtype = np.float64 if np.asarray(stamps).dtype == np.float64 else np.float32
    res = []
    for a in range(0, len(stamps), BATCH_STAMPS):
        block = jax.device_put(np.asarray(stamps[a : a + BATCH_STAMPS], dtype=dtype), dev)
        res.append(measure_on_device(block, guess_sigma))
    return split_measurements(np.concatenate(res))
