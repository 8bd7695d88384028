"""HSM adaptive moments of a batch of stamps on the device, iterated together.

The iteration of :mod:`megalut_cli.measure.adamom` (GalSim's ``FindAdaptiveMomView`` with
``find_ellipmom_2``/``find_ellipmom_1``): same start, pixel window (rows, and per row GalSim's
x range of ``rho^2 < nsig2`` inside the bounding box of non-zero pixels), step limits,
convergence test, iteration limit, the same failures in the same order and GalSim's float32
storage of ``amp``, ``sigma``, ``e1, e2``. Every stamp of the batch takes one step per loop
iteration (masked once it has converged or failed); the weighted sums run over the whole
stamp with the window as a mask, the weight as ``exp(-rho^2 / 2)`` per pixel (GalSim's own
form), accumulated in float64.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from megalut_cli.measure import adamom as ref
from megalut_cli.measure.defaults import MAD_TO_SIGMA

jax.config.update("jax_enable_x64", True)

#: Columns of :func:`measure_batch`'s result.
RESULT_COLUMNS = (
    "amp",
    "g1",
    "g2",
    "sigma",
    "rho4",
    "x",
    "y",
    "status",
    "n_iter",
    "skymad",
    "finite",
)


def _cpp_max(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    return jnp.where(a < b, b, a)


def _clip(v: jnp.ndarray, bound: float) -> jnp.ndarray:
    v = jnp.where(v > bound, bound, v)
    return jnp.where(v < -bound, -bound, v)


#: Steps every stamp of a batch takes together; the few stamps still iterating then go on in
#: a smaller batch (a stamp that never converges would otherwise hold the whole batch for
#: ``max_mom2_iter`` = 400 steps).
FIRST_STEPS = 48


def _start(img: jnp.ndarray, guess: jnp.ndarray) -> tuple[jnp.ndarray, ...]:
    """Bounds of the non-zero pixels and the start of the iteration (GalSim's)."""
    m, ny, nx = img.shape
    xs = jnp.arange(1, nx + 1, dtype=jnp.float64)
    ys = jnp.arange(1, ny + 1, dtype=jnp.float64)
    nz = img != 0.0
    cols, rows = nz.any(axis=1), nz.any(axis=2)
    big = 1.0e9
    bounds = jnp.stack(
        [
            jnp.min(jnp.where(cols, xs, big), axis=1),
            jnp.max(jnp.where(cols, xs, -big), axis=1),
            jnp.min(jnp.where(rows, ys, big), axis=1),
            jnp.max(jnp.where(rows, ys, -big), axis=1),
        ],
        axis=1,
    )
    all_zero = ~cols.any(axis=1)
    zeros = jnp.zeros(m)
    status0 = jnp.where(all_zero, ref.ALL_ZERO, ref.SUCCESS).astype(jnp.int32)
    # state: x0, y0, mxx, mxy, myy, shiftscale0, amp, rho4, n_iter, status, active
    state = (
        jnp.full(m, (nx + 1) / 2.0),
        jnp.full(m, (ny + 1) / 2.0),
        guess * guess,
        zeros,
        guess * guess,
        zeros,
        zeros,
        zeros,
        jnp.zeros(m, jnp.int32),
        status0,
        ~all_zero,
    )
    return bounds, state


@functools.partial(jax.jit, static_argnames=("precision", "params", "max_steps"))
def iterate_moments(
    img: jnp.ndarray,
    bounds: jnp.ndarray,
    state: tuple[jnp.ndarray, ...],
    precision: float,
    params: ref.HSMParams,
    max_steps: int,
) -> tuple[jnp.ndarray, ...]:
    """At most ``max_steps`` steps of the iteration of every active stamp."""
    m, ny, nx = img.shape
    nsig2 = -2.0 * math.log(params.convergence_threshold / 10.0)
    bound = float(params.bound_correct_wt)
    xs = jnp.arange(1, nx + 1, dtype=jnp.float64)
    ys = jnp.arange(1, ny + 1, dtype=jnp.float64)
    xmin, xmax, ymin, ymax = bounds.T
    x00 = jnp.full(m, (nx + 1) / 2.0)
    y00 = jnp.full(m, (ny + 1) / 2.0)

    def cond(carry):
        return jnp.any(carry[1][-1]) & (carry[0] < max_steps)

    def body(loop):
        steps, carry = loop
        x0, y0, mxx, mxy, myy, ss0, amp, rho4, n_iter, status, active = carry
        det = mxx * myy - mxy * mxy
        npd = (det <= 0) | (mxx <= 0) | (myy <= 0)
        minv_xx = myy / det
        two_minv_xy = -mxy / det * 2.0
        minv_yy = mxx / det
        inv2 = 0.5 / minv_xx
        y2 = jnp.sqrt(nsig2 * myy)
        iy1 = jnp.maximum(jnp.ceil(-y2 + y0), ymin)
        iy2 = jnp.minimum(jnp.floor(y2 + y0), ymax)
        bad_bounds = iy1 > iy2
        y_y0 = ys[None, :] - y0[:, None]  # (m, ny)
        in_rows = (ys[None, :] >= iy1[:, None]) & (ys[None, :] <= iy2[:, None])
        b = two_minv_xy[:, None] * y_y0
        c = minv_yy[:, None] * y_y0 * y_y0 - nsig2
        d = b * b - 4.0 * minv_xx[:, None] * c
        no_row = jnp.any(in_rows & (d < 0.0), axis=1)
        sqrtd = jnp.sqrt(jnp.maximum(d, 0.0))
        ix1 = jnp.maximum(jnp.ceil(inv2[:, None] * (-b - sqrtd) + x0[:, None]), xmin[:, None])
        ix2 = jnp.minimum(jnp.floor(inv2[:, None] * (-b + sqrtd) + x0[:, None]), xmax[:, None])
        x_x0 = xs[None, :] - x0[:, None]  # (m, nx)
        inside = (
            in_rows[:, :, None]
            & (xs[None, None, :] >= ix1[:, :, None])
            & (xs[None, None, :] <= ix2[:, :, None])
        )
        rho2 = (
            minv_yy[:, None, None] * (y_y0 * y_y0)[:, :, None]
            + (two_minv_xy[:, None] * y_y0)[:, :, None] * x_x0[:, None, :]
            + minv_xx[:, None, None] * (x_x0 * x_x0)[:, None, :]
        )
        inten = jnp.where(inside, jnp.exp(-0.5 * jnp.where(inside, rho2, 0.0)) * img, 0.0)
        row_sum = inten.sum(axis=2)  # (m, ny)
        row_x = (inten * x_x0[:, None, :]).sum(axis=2)
        row_xx = (inten * (x_x0 * x_x0)[:, None, :]).sum(axis=2)
        a_sum = row_sum.sum(axis=1)
        bx = row_x.sum(axis=1)
        by = (row_sum * y_y0).sum(axis=1)
        cxx = row_xx.sum(axis=1)
        cxy = (row_x * y_y0).sum(axis=1)
        cyy = (row_sum * y_y0 * y_y0).sum(axis=1)
        rho4w = (inten * rho2 * rho2).sum(axis=(1, 2))
        two_psi = jnp.arctan2(2 * mxy, mxx - myy)
        semi_a2 = 0.5 * ((mxx + myy) + (mxx - myy) * jnp.cos(two_psi)) + mxy * jnp.sin(two_psi)
        semi_b2 = mxx + myy - semi_a2
        wnpd = semi_b2 <= 0
        shiftscale = jnp.sqrt(jnp.where(wnpd, 1.0, semi_b2))
        ss0 = jnp.where(n_iter == 0, shiftscale, ss0)
        dx = _clip(2.0 * bx / (a_sum * shiftscale), bound)
        dy = _clip(2.0 * by / (a_sum * shiftscale), bound)
        dxx = _clip(4.0 * (cxx / a_sum - 0.5 * mxx) / semi_b2, bound)
        dxy = _clip(4.0 * (cxy / a_sum - 0.5 * mxy) / semi_b2, bound)
        dyy = _clip(4.0 * (cyy / a_sum - 0.5 * myy) / semi_b2, bound)
        conv = _cpp_max(jnp.abs(dx), jnp.abs(dy))
        conv = _cpp_max(jnp.abs(dxx), conv)
        conv = _cpp_max(jnp.abs(dxy), conv)
        conv = _cpp_max(jnp.abs(dyy), conv)
        conv = jnp.where(shiftscale < ss0, conv * (ss0 / shiftscale), conv)
        nx0 = x0 + dx * shiftscale
        ny0 = y0 + dy * shiftscale
        nmxx = mxx + dxx * semi_b2
        nmxy = mxy + dxy * semi_b2
        nmyy = myy + dyy * semi_b2
        out_of_range = (
            (jnp.abs(nmxx) > params.max_amoment)
            | (jnp.abs(nmxy) > params.max_amoment)
            | (jnp.abs(nmyy) > params.max_amoment)
            | (jnp.abs(nx0 - x00) > params.max_ashift)
            | (jnp.abs(ny0 - y00) > params.max_ashift)
        )
        ndet = nmxx * nmyy - nmxy * nmxy
        singular = (jnp.abs(nmxx) < 1.0e-8) | (jnp.abs(nmyy) < 1.0e-8) | (ndet < 1.0e-8)
        it = n_iter + 1
        too_many = it > params.max_mom2_iter
        nan = (
            jnp.isnan(conv)
            | jnp.isnan(nmxx)
            | jnp.isnan(nmyy)
            | jnp.isnan(nmxy)
            | jnp.isnan(nx0)
            | jnp.isnan(ny0)
        )
        failure = jnp.select(
            [npd, bad_bounds, no_row, wnpd, out_of_range, singular, too_many, nan],
            [
                ref.NOT_POSITIVE_DEFINITE,
                ref.BAD_BOUNDS,
                ref.NO_ROW_SOLUTION,
                ref.WEIGHT_NOT_POSITIVE_DEFINITE,
                ref.OUT_OF_RANGE,
                ref.SINGULAR,
                ref.TOO_MANY_ITERATIONS,
                ref.NAN,
            ],
            ref.SUCCESS,
        ).astype(jnp.int32)
        counted = (
            (failure == ref.TOO_MANY_ITERATIONS) | (failure == ref.NAN) | (failure == ref.SUCCESS)
        )
        failed = active & (failure != ref.SUCCESS)
        step = active & (failure == ref.SUCCESS)
        keep = lambda new, old: jnp.where(step, new, old)  # noqa: E731
        return steps + 1, (
            keep(nx0, x0),
            keep(ny0, y0),
            keep(nmxx, mxx),
            keep(nmxy, mxy),
            keep(nmyy, myy),
            jnp.where(active, ss0, carry[5]),
            keep(a_sum, amp),
            keep(rho4w, rho4),
            jnp.where(active & counted, it, n_iter),
            jnp.where(failed, failure, status),
            step & (conv > precision),
        )

    return jax.lax.while_loop(cond, body, (0, state))[1]


@jax.jit
def _results(state: tuple[jnp.ndarray, ...]) -> jnp.ndarray:
    """(m, 7) ``amp, g1, g2, sigma, rho4, x, y`` from the final state, GalSim's roundings."""
    x0, y0, mxx, mxy, myy, _, amp, rho4, n_iter, status, _ = state
    e1 = ((mxx - myy) / (mxx + myy)).astype(jnp.float32).astype(jnp.float64)
    e2 = (2.0 * mxy / (mxx + myy)).astype(jnp.float32).astype(jnp.float64)
    abs_e2 = e1 * e1 + e2 * e2
    e2g = jnp.where(
        abs_e2 > 1.0e-4,
        1.0 / (1.0 + jnp.sqrt(jnp.maximum(1.0 - abs_e2, 0.0))),
        0.5 + abs_e2 * (0.125 + abs_e2 * (0.0625 + abs_e2 * 0.0390625)),
    )
    det = mxx * myy - mxy * mxy
    results = jnp.stack(
        [
            (2.0 * amp).astype(jnp.float32).astype(jnp.float64),
            e1 * e2g,
            e2 * e2g,
            jnp.power(jnp.maximum(det, 0.0), 0.25).astype(jnp.float32).astype(jnp.float64),
            rho4 / amp,
            x0,
            y0,
        ],
        axis=1,
    )
    return jnp.where((status == ref.SUCCESS)[:, None], results, jnp.nan)


def adaptive_moments(
    stamps: jnp.ndarray,
    guess_sigma: float | jnp.ndarray,
    precision: float = 1.0e-6,
    params: ref.HSMParams | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """``(status, n_iter, results)`` of every stamp of ``stamps`` (m, S, S): ``results``
    (m, 7) holds ``amp, g1, g2, sigma, rho4, x, y`` as
    :func:`megalut_cli.measure.adamom.adaptive_moments` returns them (NaN where
    ``status != 0``). All stamps take :data:`FIRST_STEPS` steps together; those still
    iterating go on alone (gathered into a batch of a power-of-two size)."""
    params = ref.HSMParams() if params is None else params
    img = jnp.asarray(stamps).astype(jnp.float64)
    m = img.shape[0]
    guess = jnp.broadcast_to(jnp.asarray(guess_sigma, jnp.float64), (m,))
    bounds, state = _start(img, guess)
    state = iterate_moments(img, bounds, state, float(precision), params, FIRST_STEPS)
    left = np.flatnonzero(np.asarray(state[-1]))
    if len(left):
        size = 1 << int(math.ceil(math.log2(len(left))))
        # padded to a power of two: gathered as copies of the first, scattered nowhere (m)
        take = jnp.asarray(np.concatenate([left, np.full(size - len(left), left[0])]))
        put = jnp.asarray(np.concatenate([left, np.full(size - len(left), m)]))
        sub_img, sub_bounds, sub = _gather(img, bounds, state, take)
        sub = iterate_moments(sub_img, sub_bounds, sub, float(precision), params, 1 << 30)
        state = _scatter(state, sub, put)
    return state[9], state[8], _results(state)


@jax.jit
def _gather(img, bounds, state, take):
    """The stamps ``take`` of a batch: one compiled kernel per (batch, sub-batch) shape."""
    return img[take], bounds[take], tuple(v[take] for v in state)


@jax.jit
def _scatter(state, sub, put):
    """``state`` with rows ``put`` replaced by ``sub`` (rows at index m, the padding, dropped)."""
    return tuple(v.at[put].set(w, mode="drop") for v, w in zip(state, sub))


def sky_mad(stamps: jnp.ndarray) -> jnp.ndarray:
    """:func:`megalut_cli.measure.features.sky_mad` on the device."""
    s = stamps.astype(jnp.float64)
    edges = jnp.concatenate([s[:, 0, :], s[:, -1, :], s[:, 1:-1, 0], s[:, 1:-1, -1]], axis=1)
    med = jnp.median(edges, axis=1, keepdims=True)
    return MAD_TO_SIGMA * jnp.median(jnp.abs(edges - med), axis=1)


def measure_batch(stamps: jnp.ndarray, guess_sigma: float) -> jnp.ndarray:
    """What :func:`megalut_cli.measure.features.measure_stamps` needs of the pixels, as one
    (m, 11) float64 array (columns :data:`RESULT_COLUMNS`): the moments (NaN rows where HSM
    fails or a pixel is not finite), status, iterations, sky MAD, whether all pixels are finite."""
    finite = jnp.isfinite(stamps).all(axis=(1, 2))
    safe = jnp.where(finite[:, None, None], stamps, 0.0)
    status, n_iter, results = adaptive_moments(safe, float(guess_sigma))
    return _pack(finite, status, n_iter, results, stamps)


@jax.jit
def _pack(finite, status, n_iter, results, stamps) -> jnp.ndarray:
    results = jnp.where(finite[:, None], results, jnp.nan)
    return jnp.concatenate(
        [
            results,
            status[:, None].astype(jnp.float64),
            n_iter[:, None].astype(jnp.float64),
            sky_mad(stamps)[:, None],
            finite[:, None].astype(jnp.float64),
        ],
        axis=1,
    )
