"""The compiled kernels of :mod:`.adamom` (numba): GalSim's ``FindAdaptiveMomView``,
``find_ellipmom_2`` and ``find_ellipmom_1`` on stacks of stamps, and the status codes they
return. :func:`megalut_cli.measure.adamom.adaptive_moments` checks the arguments and calls
:func:`adaptive_moments_stack`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import uint64

from megalut_cli.jit import njit

#: Status codes of :func:`megalut_cli.measure.adamom.adaptive_moments` (0 is success), one per
#: failure of GalSim.
SUCCESS = 0
ALL_ZERO = 1
NOT_POSITIVE_DEFINITE = 2
BAD_BOUNDS = 3
NO_ROW_SOLUTION = 4
WEIGHT_NOT_POSITIVE_DEFINITE = 5
OUT_OF_RANGE = 6
SINGULAR = 7
TOO_MANY_ITERATIONS = 8
NAN = 9

#: The failures of the iteration itself, which a damped retry may cure (``retry_step``).
RETRIED = (OUT_OF_RANGE, TOO_MANY_ITERATIONS, NAN)


@njit(cache=True, inline="always")
def _cpp_max(a: float, b: float) -> float:
    """``std::max(a, b)``, NaN handling included: ``a`` unless ``a < b``."""
    return b if a < b else a


@njit(cache=True, inline="always")
def _clip(v: float, bound: float) -> float:
    """GalSim's step limit: ``v`` into ``[-bound, bound]`` (NaN passes through)."""
    if v > bound:
        v = bound
    if v < -bound:
        v = -bound
    return v


@njit(cache=True, error_model="numpy")
def _nonzero_bounds(image: np.ndarray) -> tuple[int, int, int, int]:
    """GalSim's ``nonZeroBounds``: 1-based ``(xmin, xmax, ymin, ymax)``; xmin > xmax if none."""
    ny, nx = image.shape
    xmin, xmax, ymin, ymax = nx + 1, 0, ny + 1, 0
    for j in range(ny):
        for i in range(nx):
            if image[j, i] != 0.0:
                if i + 1 < xmin:
                    xmin = i + 1
                if i + 1 > xmax:
                    xmax = i + 1
                if j + 1 < ymin:
                    ymin = j + 1
                if j + 1 > ymax:
                    ymax = j + 1
    return xmin, xmax, ymin, ymax


#: Largest |exponent| of a factor of the weight in the factorised sums (exp(600) ~ 1e260).
_MAX_EXPONENT = 600.0


@njit(cache=True, error_model="numpy", fastmath={"reassoc"})
def _window_sums(
    image: np.ndarray,
    iy1: int,
    iy2: int,
    y0: float,
    segments: np.ndarray,
    xb1: int,
    xb2: int,
    cross: np.ndarray,
    step: np.ndarray,
    tables: np.ndarray,
    row_weight: float,
    row_ratio: float,
    row_ratio_step: float,
    minv_xx: float,
    minv_yy: float,
    two_minv_xy: float,
    sums: np.ndarray,
) -> None:
    """The factorised sums of :func:`_ellipmom_1` over rows ``iy1..iy2`` into ``sums``.

    Row ``y`` sums the 0-based columns ``segments[:, y - 1]``; per pixel,
    ``cross[x] image[y, x] tables[k, x]`` for the powers k = 0..4 of ``x'``, which give the
    moments once multiplied by the row factor. Unsigned indices (no negative-index test)
    and reassociated sums let LLVM vectorise the pixel loops.
    """
    a_sum = bx = by = cxx = cxy = cyy = rho4w = 0.0
    box_lo = uint64(xb1 - 1)
    box_hi = uint64(xb2)
    for y in range(iy1, iy2 + 1):
        r = uint64(y - 1)
        first = segments[0, r]
        last = segments[1, r]
        if first <= last:
            s0 = s1 = s2 = s3 = s4 = 0.0
            for x in range(uint64(first), uint64(last + 1)):
                u = cross[x] * image[r, x]
                s0 += u * tables[0, x]
                s1 += u * tables[1, x]
                s2 += u * tables[2, x]
                s3 += u * tables[3, x]
                s4 += u * tables[4, x]
            y_y0 = y - y0
            b = two_minv_xy * y_y0
            cy = minv_yy * y_y0 * y_y0
            s0 *= row_weight
            s1 *= row_weight
            s2 *= row_weight
            s3 *= row_weight
            s4 *= row_weight
            a_sum += s0
            bx += s1
            by += s0 * y_y0
            cxx += s2
            cxy += s1 * y_y0
            cyy += s0 * y_y0 * y_y0
            # rho^2 = cy + b x' + minv_xx x'^2, squared and summed over the row
            rho4w += (
                cy * cy * s0
                + 2.0 * cy * b * s1
                + (b * b + 2.0 * minv_xx * cy) * s2
                + 2.0 * minv_xx * b * s3
                + minv_xx * minv_xx * s4
            )
        for x in range(box_lo, box_hi):
            cross[x] *= step[x]
        row_weight *= row_ratio
        row_ratio *= row_ratio_step
    sums[0] = a_sum
    sums[1] = bx
    sums[2] = by
    sums[3] = cxx
    sums[4] = cxy
    sums[5] = cyy
    sums[6] = rho4w


@njit(cache=True, error_model="numpy")
def _ellipmom_1(
    image: np.ndarray,
    xmin: int,
    xmax: int,
    ymin: int,
    ymax: int,
    x0: float,
    y0: float,
    mxx: float,
    mxy: float,
    myy: float,
    nsig2: float,
    tables: np.ndarray,
    cross: np.ndarray,
    step: np.ndarray,
    segments: np.ndarray,
    sums: np.ndarray,
    exact_exp: bool,
) -> int:
    """``find_ellipmom_1``: weighted sums ``A, Bx, By, Cxx, Cxy, Cyy, rho4w`` into ``sums``.

    The pixels summed are GalSim's (rows and, per row, the x range where
    ``rho^2 < nsig2``). Unless ``exact_exp``, the weight is factorised as
    ``exp(-minv_yy y'^2 / 2) exp(-minv_xx x'^2 / 2) exp(-minv_xy x' y')``: a factor per row,
    tables per column (times ``x'^k`` for the moments), and the cross term per column,
    multiplied by ``exp(-minv_xy x')`` from row to row, so that no ``exp`` is evaluated per
    pixel. Where a factor could leave the double range (very elongated or tiny weights),
    ``exp`` is evaluated per pixel as in GalSim.
    """
    det = mxx * myy - mxy * mxy
    if det <= 0 or mxx <= 0 or myy <= 0:
        return NOT_POSITIVE_DEFINITE
    minv_xx = myy / det
    two_minv_xy = -mxy / det * 2.0
    minv_yy = mxx / det
    inv2_minv_xx = 0.5 / minv_xx

    y2 = math.sqrt(nsig2 * myy)
    y1 = -y2 + y0
    y2 += y0
    iy1 = max(int(math.ceil(y1)), ymin)
    iy2 = min(int(math.floor(y2)), ymax)
    if iy1 > iy2:
        return BAD_BOUNDS

    # Columns that can be inside the window (GalSim's x ranges lie within, up to rounding).
    half_width = math.sqrt(nsig2 * mxx)
    xb1 = max(int(math.ceil(x0 - half_width)) - 1, xmin)
    xb2 = min(int(math.floor(x0 + half_width)) + 1, xmax)
    dx_max = max(abs(xb1 - x0), abs(xb2 - x0))
    dy_max = max(abs(iy1 - y0), abs(iy2 - y0))
    # Every factor and every ratio of neighbouring factors below stays within exp(+-600).
    factorised = (
        not exact_exp
        and minv_xx * (0.5 * dx_max * dx_max + dx_max + 1.0) < _MAX_EXPONENT
        and minv_yy * (0.5 * dy_max * dy_max + dy_max + 1.0) < _MAX_EXPONENT
        and abs(two_minv_xy) * (dx_max * dy_max + dx_max + dy_max + 1.0) < _MAX_EXPONENT
    )
    if factorised:
        # Along x: exp(-minv_xx x'^2 / 2) by ratios of neighbours (the ratios themselves
        # change by exp(-minv_xx)); exp(-minv_xy x' y') at the first row and its change
        # from one row to the next, exp(-minv_xy x'), each a geometric sequence in x.
        xp = xb1 - x0
        dy1 = iy1 - y0
        weight = math.exp(-0.5 * minv_xx * xp * xp)
        ratio = math.exp(-0.5 * minv_xx * (2.0 * xp + 1.0))
        ratio_step = math.exp(-minv_xx)
        cross_x = math.exp(-0.5 * two_minv_xy * xp * dy1)
        cross_x_step = math.exp(-0.5 * two_minv_xy * dy1)
        row_step = math.exp(-0.5 * two_minv_xy * xp)
        row_step_step = math.exp(-0.5 * two_minv_xy)
        for x in range(xb1 - 1, xb2):
            tables[0, x] = weight
            tables[1, x] = weight * xp
            tables[2, x] = weight * xp * xp
            tables[3, x] = weight * xp * xp * xp
            tables[4, x] = weight * xp * xp * xp * xp
            cross[x] = cross_x
            step[x] = row_step
            xp += 1.0
            weight *= ratio
            ratio *= ratio_step
            cross_x *= cross_x_step
            row_step *= row_step_step
        # Along y: exp(-minv_yy y'^2 / 2) the same way as along x.
        row_weight = math.exp(-0.5 * minv_yy * dy1 * dy1)
        row_ratio = math.exp(-0.5 * minv_yy * (2.0 * dy1 + 1.0))
        row_ratio_step = math.exp(-minv_yy)
    else:
        for x in range(xmin, xmax + 1):
            tables[0, x - 1] = minv_xx * (x - x0) * (x - x0)
        row_weight = row_ratio = row_ratio_step = 0.0

    # GalSim's x range of each row (rho^2 < nsig2: a quadratic in x - x0), 0-based
    for y in range(iy1, iy2 + 1):
        y_y0 = y - y0
        b = two_minv_xy * y_y0
        c = minv_yy * y_y0 * y_y0 - nsig2
        d = b * b - 4.0 * minv_xx * c
        if d < 0.0:
            return NO_ROW_SOLUTION
        sqrtd = math.sqrt(d)
        ix1 = max(int(math.ceil(inv2_minv_xx * (-b - sqrtd) + x0)), xmin)
        ix2 = min(int(math.floor(inv2_minv_xx * (-b + sqrtd) + x0)), xmax)
        if factorised:
            ix1 = max(ix1, xb1)
            ix2 = min(ix2, xb2)
        segments[0, y - 1] = ix1 - 1
        segments[1, y - 1] = ix2 - 1
    if factorised:
        _window_sums(
            image,
            iy1,
            iy2,
            y0,
            segments,
            xb1,
            xb2,
            cross,
            step,
            tables,
            row_weight,
            row_ratio,
            row_ratio_step,
            minv_xx,
            minv_yy,
            two_minv_xy,
            sums,
        )
        return SUCCESS

    # GalSim's sums, in its order
    a_sum = bx = by = cxx = cxy = cyy = rho4w = 0.0
    for y in range(iy1, iy2 + 1):
        row = y - 1
        ix1 = segments[0, row] + 1
        ix2 = segments[1, row] + 1
        if ix1 > ix2:
            continue
        y_y0 = y - y0
        two_minv_xy_y = two_minv_xy * y_y0
        minv_yy_y2 = minv_yy * y_y0 * y_y0
        x_x0 = ix1 - x0
        for x in range(ix1, ix2 + 1):
            rho2 = minv_yy_y2 + two_minv_xy_y * x_x0 + tables[0, x - xmin]
            intensity = math.exp(-0.5 * rho2) * image[row, x - 1]
            ix = intensity * x_x0
            iy = intensity * y_y0
            a_sum += intensity
            bx += ix
            by += iy
            cxx += ix * x_x0
            cxy += ix * y_y0
            cyy += iy * y_y0
            rho4w += intensity * rho2 * rho2
            x_x0 += 1.0
    sums[0] = a_sum
    sums[1] = bx
    sums[2] = by
    sums[3] = cxx
    sums[4] = cxy
    sums[5] = cyy
    sums[6] = rho4w
    return SUCCESS


@njit(cache=True, error_model="numpy")
def adaptive_moments_one(
    image: np.ndarray,
    guess_sigma: float,
    x_guess: float,
    y_guess: float,
    precision: float,
    nsig2: float,
    bound: float,
    max_amoment: float,
    max_ashift: float,
    max_iter: int,
    exact_exp: bool,
    step_factor: float,
    tables: np.ndarray,
    cross: np.ndarray,
    step: np.ndarray,
    segments: np.ndarray,
    sums: np.ndarray,
    result: np.ndarray,
) -> tuple[int, int]:
    """``FindAdaptiveMomView`` + ``find_ellipmom_2`` on one stamp: ``(status, n_iter)``.

    ``step_factor`` scales every update of the centroid and moments: 1 is GalSim's iteration
    (bit for bit: the product by 1.0 is exact); below 1 a damped one, whose fixed points are
    the same. On success ``result`` holds ``amp, g1, g2, sigma, rho4, x, y``.
    """
    xmin, xmax, ymin, ymax = _nonzero_bounds(image)
    if xmin > xmax:
        return ALL_ZERO, 0
    x0 = x_guess
    y0 = y_guess
    mxx = guess_sigma * guess_sigma
    myy = mxx
    mxy = 0.0
    x00 = x0
    y00 = y0
    convergence = 1.0
    shiftscale0 = 0.0
    amp = -1000.0
    rho4 = 0.0
    n_iter = 0
    while convergence > precision:
        status = _ellipmom_1(
            image,
            xmin,
            xmax,
            ymin,
            ymax,
            x0,
            y0,
            mxx,
            mxy,
            myy,
            nsig2,
            tables,
            cross,
            step,
            segments,
            sums,
            exact_exp,
        )
        if status != SUCCESS:
            return status, n_iter
        amp = sums[0]
        rho4 = sums[6]
        two_psi = math.atan2(2 * mxy, mxx - myy)
        semi_a2 = 0.5 * ((mxx + myy) + (mxx - myy) * math.cos(two_psi)) + mxy * math.sin(two_psi)
        semi_b2 = mxx + myy - semi_a2
        if semi_b2 <= 0:
            return WEIGHT_NOT_POSITIVE_DEFINITE, n_iter
        shiftscale = math.sqrt(semi_b2)
        if n_iter == 0:
            shiftscale0 = shiftscale
        dx = _clip(2.0 * sums[1] / (amp * shiftscale), bound)
        dy = _clip(2.0 * sums[2] / (amp * shiftscale), bound)
        dxx = _clip(4.0 * (sums[3] / amp - 0.5 * mxx) / semi_b2, bound)
        dxy = _clip(4.0 * (sums[4] / amp - 0.5 * mxy) / semi_b2, bound)
        dyy = _clip(4.0 * (sums[5] / amp - 0.5 * myy) / semi_b2, bound)
        convergence = _cpp_max(abs(dx), abs(dy))
        convergence = _cpp_max(abs(dxx), convergence)
        convergence = _cpp_max(abs(dxy), convergence)
        convergence = _cpp_max(abs(dyy), convergence)
        if shiftscale < shiftscale0:
            convergence *= shiftscale0 / shiftscale
        x0 += step_factor * dx * shiftscale
        y0 += step_factor * dy * shiftscale
        mxx += step_factor * dxx * semi_b2
        mxy += step_factor * dxy * semi_b2
        myy += step_factor * dyy * semi_b2
        if (
            abs(mxx) > max_amoment
            or abs(mxy) > max_amoment
            or abs(myy) > max_amoment
            or abs(x0 - x00) > max_ashift
            or abs(y0 - y00) > max_ashift
        ):
            return OUT_OF_RANGE, n_iter
        det = mxx * myy - mxy * mxy
        if abs(mxx) < 1.0e-8 or abs(myy) < 1.0e-8 or det < 1.0e-8:
            return SINGULAR, n_iter
        n_iter += 1
        if n_iter > max_iter:
            return TOO_MANY_ITERATIONS, n_iter
        if (
            math.isnan(convergence)
            or math.isnan(mxx)
            or math.isnan(myy)
            or math.isnan(mxy)
            or math.isnan(x0)
            or math.isnan(y0)
        ):
            return NAN, n_iter
    # FindAdaptiveMomView's outputs, stored as float32 in GalSim's C++ ShapeData (e1, e2,
    # sigma, amp), then galsim.Shear(e1=, e2=).g1, .g2 in double precision
    e1 = np.float64(np.float32((mxx - myy) / (mxx + myy)))
    e2 = np.float64(np.float32(2.0 * mxy / (mxx + myy)))
    abs_e2 = e1 * e1 + e2 * e2
    if abs_e2 > 1.0e-4:
        e2g = 1.0 / (1.0 + math.sqrt(1.0 - abs_e2))
    else:
        e2g = 0.5 + abs_e2 * (0.125 + abs_e2 * (0.0625 + abs_e2 * 0.0390625))
    result[0] = np.float64(np.float32(2.0 * amp))
    result[1] = e1 * e2g
    result[2] = e2 * e2g
    result[3] = np.float64(np.float32((mxx * myy - mxy * mxy) ** 0.25))
    result[4] = rho4 / amp
    result[5] = x0
    result[6] = y0
    return SUCCESS, n_iter


@njit(cache=True, error_model="numpy")
def moments_workspace(ny: int, nx: int) -> tuple:
    """The buffers :func:`adaptive_moments_one` works in, for stamps of ``ny x nx`` pixels:
    ``tables, cross, step, segments, sums``."""
    return (
        np.empty((5, nx)),
        np.empty(nx),
        np.empty(nx),
        np.empty((2, ny), dtype=np.int64),
        np.empty(7),
    )


@njit(cache=True, error_model="numpy")
def measure_into(
    image: np.ndarray,
    k: int,
    guess_sigma: np.ndarray,
    settings: tuple,
    work: tuple,
    status: np.ndarray,
    n_iter: np.ndarray,
    results: np.ndarray,
) -> None:
    """:func:`adaptive_moments_one` of ``image`` from ``guess_sigma[k]``, into row ``k`` of
    ``status``, ``n_iter`` and ``results``. ``settings``: the scalar arguments (``x_guess`` to
    ``exact_exp``, then ``retry_step``, :func:`megalut_cli.measure.adamom.kernel_settings`);
    ``work``: :func:`moments_workspace`. When ``retry_step`` > 0 a stamp whose iteration
    fails (:data:`RETRIED`) is measured again from the same start with its updates scaled by
    ``retry_step``; ``n_iter`` then counts both runs."""
    scalars, retry_step = settings[:9], settings[9]  # x_guess ... exact_exp, retry_step
    factor, done = 1.0, 0
    while True:
        status[k], n = adaptive_moments_one(
            image, guess_sigma[k], *scalars, factor, *work, results[k]
        )
        n_iter[k] = done + n
        # the iteration's own failures (RETRIED)
        failed = status[k] == OUT_OF_RANGE or status[k] == TOO_MANY_ITERATIONS or status[k] == NAN
        if factor != 1.0 or retry_step <= 0 or not failed:
            return
        factor, done = retry_step, n_iter[k]


@njit(cache=True, error_model="numpy")
def adaptive_moments_stack(
    stamps: np.ndarray,
    guess_sigma: np.ndarray,
    settings: tuple,
    status: np.ndarray,
    n_iter: np.ndarray,
    results: np.ndarray,
) -> None:
    """Runs :func:`adaptive_moments_one` on every stamp of ``stamps`` (:func:`measure_into`)."""
    work = moments_workspace(stamps.shape[1], stamps.shape[2])
    for k in range(stamps.shape[0]):
        measure_into(stamps[k], k, guess_sigma, settings, work, status, n_iter, results)
