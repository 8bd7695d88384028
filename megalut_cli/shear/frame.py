"""Shears in the world frame: each object's local Jacobian turns pixel-frame estimates,
responses and PSF ellipticities into the sky's (u, v) frame.

The Jacobian maps pixel offsets to the tangent plane, ``u = dudcol dx + dudrow dy`` and
``v = dvdcol dx + dvdrow dy`` (x the column, y the row: MEDS ``object_data``, GalSim's
``wcs.jacobian``), with GalSim's and ngmix's (u, v): v towards north, u towards west
(decreasing RA). It is split into a conformal part (scale, rotation, and a flip where
the determinant is negative) and a residual shear ``eta`` of the pixel grid. A galaxy of
world shear g has in its cutout the shear ``Q^T g - eta`` to first order in ``eta``
(Q the spin-2 rotation, with a conjugation for a flip), so the world-frame estimate is
``Q (g_pix + R eta)`` with the pixel-frame response R, and the world-frame response
``Q R Q^T``. docs/your-data.md ("The frame of the shears") has the derivation.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from megalut_cli.errors import InputError

#: The per-object Jacobian columns, as MEDS ``object_data`` names them.
JACOBIAN_COLUMNS: tuple[str, str, str, str] = ("dudcol", "dudrow", "dvdcol", "dvdrow")
#: Header card naming the frame of a catalog's calibrated shears.
FRAME_CARD = "SHFRAME"
PIXEL_FRAME, WORLD_FRAME = "pixel", "world"
#: What each frame means, for headers, tables and ``megalut info``.
FRAME_TEXT: dict[str, str] = {
    PIXEL_FRAME: "pixel frame of each stamp (g1 > 0 along x, the columns)",
    WORLD_FRAME: "world frame (u, v): g1 > 0 along u (west), g2 > 0 along u = v (north-west)",
}
#: Smallest |det J| / (sum of J's squared entries) accepted: below, the Jacobian is degenerate.
MIN_DETERMINANT = 1e-6
#: The meds package's fill of unset ``object_data`` entries.
MEDS_FILL = -9999.0


@dataclass(frozen=True)
class Frames:
    """Per-object maps from pixel-frame spin-2 quantities to the world frame:
    ``rotation`` ``(n, 2, 2)`` (Q), ``distortion`` ``(n, 2)`` (eta, the Jacobian's residual
    shear on the pixel axes), ``parity`` (+1, or -1 for a flip), ``angle`` (radians, from
    the x axis to the u axis) and ``scale`` (world units per pixel, the conformal part's)."""

    rotation: np.ndarray
    distortion: np.ndarray
    parity: np.ndarray
    angle: np.ndarray
    scale: np.ndarray

    def __len__(self) -> int:
        return len(self.parity)


def jacobian_frames(
    dudcol: np.ndarray, dudrow: np.ndarray, dvdcol: np.ndarray, dvdrow: np.ndarray
) -> Frames:
    """The :class:`Frames` of per-object Jacobians (arrays of one length; NaN entries give
    NaN maps). A degenerate Jacobian (determinant near 0) is an :class:`InputError`."""
    j00, j01, j10, j11 = (np.asarray(a, dtype=float) for a in (dudcol, dudrow, dvdcol, dvdrow))
    finite = np.isfinite(j00) & np.isfinite(j01) & np.isfinite(j10) & np.isfinite(j11)
    bad = finite & ~usable_jacobians(j00, j01, j10, j11)
    if np.any(bad):
        raise InputError(
            f"{int(bad.sum())} object(s) with a degenerate Jacobian (dudcol dvdrow - dudrow "
            "dvdcol near 0): no world frame"
        )
    # J = A + B: A = [[a, -b], [b, a]] conformal, B = [[c, e], [e, -c]] anti-conformal
    a, b = 0.5 * (j00 + j11), 0.5 * (j10 - j01)
    c, e = 0.5 * (j00 - j11), 0.5 * (j01 + j10)
    conformal, anti = a * a + b * b, c * c + e * e
    flip = j00 * j11 - j01 * j10 < 0
    # the conformal part C (A, or B for a flip) and eta = C^-1 (J - C) = [[p, q], [q, -p]]
    x, y = np.where(flip, c, a), np.where(flip, e, b)
    u, w = np.where(flip, a, c), np.where(flip, b, e)
    norm = np.where(flip, anti, conformal)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = (x * u + y * w) / norm
        q = np.where(flip, y * u - x * w, x * w - y * u) / norm
    angle = np.arctan2(y, x)
    c2, s2 = np.cos(2 * angle), np.sin(2 * angle)
    rotation = np.empty((len(angle), 2, 2))
    rotation[:, 0, 0] = c2
    rotation[:, 1, 0] = s2
    rotation[:, 0, 1] = np.where(flip, s2, -s2)
    rotation[:, 1, 1] = np.where(flip, -c2, c2)
    return Frames(
        rotation,
        np.stack([p, q], axis=1),
        np.where(flip, -1, 1).astype(np.int8),
        angle,
        np.sqrt(norm),
    )


def usable_jacobians(
    dudcol: np.ndarray, dudrow: np.ndarray, dvdcol: np.ndarray, dvdrow: np.ndarray
) -> np.ndarray:
    """Which Jacobians are usable: finite, not the meds package's fill, and not degenerate
    (|det J| above :data:`MIN_DETERMINANT` times the sum of its squared entries)."""
    j = [np.asarray(a, dtype=float) for a in (dudcol, dudrow, dvdcol, dvdrow)]
    with np.errstate(invalid="ignore"):
        det = j[0] * j[3] - j[1] * j[2]
        ok = np.abs(det) > MIN_DETERMINANT * sum(x * x for x in j)
        for x in j:
            ok &= np.isfinite(x) & (x > MEDS_FILL)
    return ok


def has_jacobian(colnames: object) -> bool:
    """Whether a catalog's column names include every :data:`JACOBIAN_COLUMNS`."""
    have = set(colnames)  # type: ignore[call-overload]
    return all(c in have for c in JACOBIAN_COLUMNS)


def catalog_frames(columns: Mapping[str, np.ndarray]) -> Frames:
    """The :class:`Frames` of a catalog's :data:`JACOBIAN_COLUMNS`."""
    return jacobian_frames(*(np.asarray(columns[c], dtype=float) for c in JACOBIAN_COLUMNS))


def spin2_to_world(
    frames: Frames, g1: np.ndarray, g2: np.ndarray, offset: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-frame spin-2 values ``(g1, g2)`` plus ``offset`` ``(n, 2)`` (default: the
    distortion eta, right for a shear or a PSF ellipticity; ``R eta`` for a metacal estimate
    of response R) rotated to the world frame."""
    d = frames.distortion if offset is None else offset
    x1, x2 = np.asarray(g1, dtype=float) + d[:, 0], np.asarray(g2, dtype=float) + d[:, 1]
    q = frames.rotation
    return q[:, 0, 0] * x1 + q[:, 0, 1] * x2, q[:, 1, 0] * x1 + q[:, 1, 1] * x2


def response_offset(frames: Frames, response: Mapping[tuple[int, int], np.ndarray]) -> np.ndarray:
    """``R eta`` per object ``(n, 2)``: what a response ``R`` makes of the pixel grid's
    residual shear, added to a pixel-frame metacal estimate before its rotation."""
    d = frames.distortion
    return np.stack(
        [response[(i, 1)] * d[:, 0] + response[(i, 2)] * d[:, 1] for i in (1, 2)], axis=1
    )


def response_to_world(
    frames: Frames, response: Mapping[tuple[int, int], np.ndarray]
) -> dict[tuple[int, int], np.ndarray]:
    """The world-frame response ``Q R Q^T`` of per-object pixel-frame responses
    ``response[(i, j)]``."""
    q = frames.rotation
    r = np.empty((len(frames), 2, 2))
    for (i, j), values in response.items():
        r[:, i - 1, j - 1] = values
    world = np.einsum("nik,nkl,njl->nij", q, r, q)
    return {(i, j): world[:, i - 1, j - 1] for i in (1, 2) for j in (1, 2)}


def weights_to_world(frames: Frames, weights: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Per-component weights for the world components: ``W_i = sum_l Q_il^2 w_l`` (the
    weight of the pixel component each world component comes from; exact under rotations
    by multiples of 45 degrees and flips)."""
    q2 = frames.rotation**2
    return {i: q2[:, i - 1, 0] * weights[1] + q2[:, i - 1, 1] * weights[2] for i in (1, 2)}


def versions_to_world(
    frames: Frames, by_version: Mapping[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """Per-object values under each sheared version (``1p, 1m, 2p, 2m``: the pixel-frame
    shears) turned into their values under world-frame shears of the same step, to first
    order in the step: ``x(jp), x(jm) = xbar_j +- sum_k Q_jk (x(kp) - x(km)) / 2`` with
    ``xbar_j = sum_k Q_jk^2 (x(kp) + x(km)) / 2``. Exact for an identity frame, rotations by
    multiples of 45 degrees and flips, where world versions are pixel ones."""
    q = frames.rotation
    half_diff = {k: 0.5 * (by_version[f"{k}p"] - by_version[f"{k}m"]) for k in (1, 2)}
    half_sum = {k: 0.5 * (by_version[f"{k}p"] + by_version[f"{k}m"]) for k in (1, 2)}
    out = {}
    for j in (1, 2):
        mean = sum(q[:, j - 1, k - 1] ** 2 * half_sum[k] for k in (1, 2))
        slope = sum(q[:, j - 1, k - 1] * half_diff[k] for k in (1, 2))
        out[f"{j}p"], out[f"{j}m"] = mean + slope, mean - slope
    return out


def is_celestial(header: Mapping[str, object]) -> bool:
    """Whether an image header holds a celestial WCS (``CTYPE1``/``CTYPE2`` RA and DEC)."""
    c1, c2 = (str(header.get(k, "")).strip().upper() for k in ("CTYPE1", "CTYPE2"))
    return c1.startswith("RA") and c2.startswith("DEC")


def celestial_jacobians(
    header: Mapping[str, object], x: np.ndarray, y: np.ndarray
) -> dict[str, np.ndarray]:
    """The sky position (``ra``, ``dec``, degrees) and the local Jacobian
    (:data:`JACOBIAN_COLUMNS`, arcsec per pixel; u west, v north) of an image with a
    celestial WCS (GalSim's reading of the header: TAN, TPV, SIP...) at its 1-based pixel
    positions ``x, y``, by central differences of half a pixel."""
    import galsim  # imported here: measuring without a WCS does not need it

    try:
        wcs = galsim.FitsWCS(header=galsim.FitsHeader(header=dict(header)))
    except (galsim.GalSimError, ValueError, TypeError, KeyError) as err:
        raise InputError(f"cannot read the image's WCS: {str(err).splitlines()[0][:80]}") from None
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    ra, dec = (np.asarray(a, dtype=float) for a in wcs.xyToradec(x, y, units="deg"))
    cos_dec = np.cos(np.deg2rad(dec))
    h = 0.5
    out = {"ra": ra, "dec": dec}
    for name, dx, dy in (("col", h, 0.0), ("row", 0.0, h)):
        ra_p, dec_p = wcs.xyToradec(x + dx, y + dy, units="deg")
        ra_m, dec_m = wcs.xyToradec(x - dx, y - dy, units="deg")
        dra = (np.asarray(ra_p) - np.asarray(ra_m) + 180.0) % 360.0 - 180.0
        out[f"dud{name}"] = -dra * cos_dec * 3600.0 / (2 * h)  # u towards decreasing RA
        out[f"dvd{name}"] = (np.asarray(dec_p) - np.asarray(dec_m)) * 3600.0 / (2 * h)
    return out
