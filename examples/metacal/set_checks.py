"""Checks of one CRN set's weighted metacal m (issue 39: why independent 10^6-stamp sets disagree).

For each component of a ``megalut predict`` catalog of a CRN set (``examples/fiducial/
vo-crn.toml`` in metacal mode), on the rows ``megalut evaluate`` uses (noshear measured,
every response finite), weighted by the networks' weights with their selection response:

* m from the cases' calibrated means (evaluate's estimator), and its delete-group jackknife
  error over 1000 groups of galaxy pairs (all shears of a pair in one group), the largest
  influence of one group and the kurtosis of the influences: is the bootstrap's error right,
  and is m carried by a few galaxies?
* m with a cubic term, <g> = (1 + m) g + c + beta g |g|^2, and the range of m when one case
  (shear) is left out: does the set's m depend on which shears were drawn?
* the cases' mean response against |g|^2.

With ``--matrix``: the whole 2x2 matrix of each set, ``<g_i> = (delta_ij + m_ij) g_j + c_i``,
as its isotropic part ``(m11 + m22) / 2``, its two spin-4 parts ``(m11 - m22) / 2`` and
``(m12 + m21) / 2`` and its rotation ``(m12 - m21) / 2``, with jackknife errors and each
part's chi^2 of the sets about their weighted mean.

With ``--swap A.fits B.fits X0.fits ... X19.fits``: the shears experiment. ``X*`` are set A's
stamps drawn again under set B's shears, one single-case run per shear, in B's case order
(``megalut simulate CONFIG --seed SEED_A --n-cases 1 shear.g1=G1 shear.g2=G2``, all of A's
realizations: the common-random-number galaxies, noise and fixnoise do not depend on the
case), predicted like A and B. The parts of A, of X and of B, and the paired differences
A - X (the same stamps, other shears: what the drawn shears do) with their jackknife over
the same galaxy groups, and X - B (the same shears, other galaxies and noise).

With ``--matrix --unweighted``: the same with every row alike (no selection response).

With ``--matrix --zero-shear [--line]``: the same at zero shear. A case's response depends on
its shear (metacal's step composes with the case's shear: the spin-4 parts of R go as -R0
(g1^2-g2^2) and -R0 2 g1 g2), so the mean response over a set's drawn shears, which calibrates
every case, depends on the draw. Here the cases' means are calibrated by the response at zero
shear (the intercept of a fit of each case's response against 1, g1, g2, abs(g)^2 and the
spin-4 pair) and the parts fitted beside every quadratic and cubic term of the shear (with
``--line``, a line alone, as ``megalut evaluate`` fits).

With ``--paired A.fits B.fits``: two catalogs of the same galaxies and noise (the same stamps
measured two ways, or one seed's galaxies under other shears, noise or metacal step),
weighted and unweighted (every row alike, no selection response), on evaluate's rows and on
the complete galaxies: m₁, m₂ and the isotropic part of each, and the difference A - B with
its jackknife over the same galaxy groups.

With ``--failures A.fits [B.fits ...]``: each set at zero shear (as ``--zero-shear``), on the
rows ``megalut evaluate`` uses (every version measured) and with the sheared versions'
failures as a selection (every row whose noshear version is measured; a row is selected on
a sheared version when that version is measured, and the selection response of those
selections corrects the rows that fail on one version and not another), weighted and not:
m1, m2 and the isotropic part, and the difference with its jackknife.

With ``--complete A.fits [B.fits ...]``: each set as ``megalut evaluate --response auto``
calibrates it (at zero shear with 10 cases or more, else by the mean response), on the rows
``evaluate`` uses and on the galaxies measured in every case only (a selection on the truth,
for diagnosis), weighted and not: m1, m2 and the isotropic part of a line, and the difference
with its jackknife. A galaxy measured under some shears and not others enters the cases'
means through a selection on the true shear, which no metacal response sees.

With ``--curvature A.fits [B.fits ...]`` (``vo-cross`` sets): m of the axis cases split into the
curvature of the mean estimate in the shear, p (the response along the shear against the
secant across the cases), and q (across it), on the complete galaxies: m is about
-(p + q) / 2, and a mean estimate curved in the shear puts 2 b g^2 into p (:func:`curvature`).

With ``--antithetic PLUS MINUS [REF_PLUS REF_MINUS]``: antithetic twins as two catalogs (one
seed's galaxies with noise and fixnoise n, f and -n, -f; docs/metacal.md, "Antithetic twins"),
each and pooled, on the galaxies measured in every case of both: m1, m2, the isotropic part,
c1, c2; with a low-noise pair of the same galaxies, the pools' paired difference (the noise
part). A single catalog of ``simulate`` with ``structure.antithetic = true`` (header
``ANTITHET = T``) needs no pooling: every mode keeps its twins in one jackknife group.

With ``--cut COLUMN LO HI`` before any mode: only the rows with LO <= COLUMN < HI (a truth
column that the shear does not change, e.g. ``tru_flux``: the same galaxies in every case).

With ``--twin 0`` (or ``1``) before any mode (after ``--cut``): in a set of antithetic twins,
only the first (second) twin of each galaxy, ``rea % 2``; the first twins are, bit for bit,
the plain set of half the size.

With ``--adamom`` before any mode (after ``--cut`` and ``--twin``): the adaptive moments' own
metacal in place of the networks' (``adamom_g`` of each version, weighted by
``1 / (0.3^2 + (2 / snr)^2)`` of that version's S/N).

With ``--by COLUMN`` (a truth column, e.g. ``tru_rad``, ``tru_sersicn``, ``tru_flux``): m of
each set in the quartiles of that column (edges from the first catalog; each bin calibrated by
its own response: the truth does not respond to the shear), its jackknife error, and each
bin's chi^2 of the sets about their weighted mean: where in the population the sets differ.

    python examples/metacal/set_checks.py vo-3901-a.fits [vo-3902-a.fits ...]
    python examples/metacal/set_checks.py --by tru_rad vo-3901-a.fits vo-3902-a.fits ...
    python examples/metacal/set_checks.py --matrix vo-3901-a.fits vo-3902-a.fits ...
    python examples/metacal/set_checks.py --matrix --zero-shear vo-3901-a.fits vo-3902-a.fits ...
    python examples/metacal/set_checks.py --matrix --zero-shear --line vo-3901-a.fits ...
    python examples/metacal/set_checks.py --paired fallback-3904-a.fits vo-3904-a.fits
    python examples/metacal/set_checks.py --failures vo-3901-a.fits vo-3902-a.fits ...
    python examples/metacal/set_checks.py --complete vo-3901-a.fits vo-cross-a.fits ...
    python examples/metacal/set_checks.py --curvature vx-4304-a.fits vx-4305-a.fits ...
    python examples/metacal/set_checks.py --cut tru_flux 344 inf --complete vx-4304-a.fits ...
    python examples/metacal/set_checks.py --adamom --complete vx-4304-a.fits ...
    python examples/metacal/set_checks.py --twin 0 --complete tw-4401-a.fits tw-4402-a.fits ...
    python examples/metacal/set_checks.py --swap vo-3901-a.fits vo-3902-a.fits x-{0..19}.fits
    python examples/metacal/set_checks.py --antithetic p-1.fits p--1.fits p-0.05.fits p--0.05.fits
"""

from __future__ import annotations

import sys

import fitsio
import numpy as np

from megalut_cli.shear.response import response_design

VERSIONS = ("noshear", "1p", "1m", "2p", "2m")
GROUPS = 1000


def used_rows(t: np.ndarray) -> np.ndarray:
    """The rows ``megalut evaluate`` uses: noshear measured, its estimates and every
    response finite."""
    return (
        (t["flags_noshear"] == 0)
        & np.isfinite(t["pre_g1_noshear"])
        & np.isfinite(t["pre_g2_noshear"])
        & np.all([np.isfinite(t[f"mcal_r{i}{j}"]) for i in (1, 2) for j in (1, 2)], axis=0)
    )


#: --antithetic: the realization offset of a pooled set's second twin (empty: no twins).
TWIN_PERIOD: list[int] = []


def galaxy_ids(t: np.ndarray) -> np.ndarray:
    """Each row's galaxy: its realization, or in a pooled antithetic set (:data:`TWIN_PERIOD`)
    the realization both twins share."""
    return t["rea"] % TWIN_PERIOD[0] if TWIN_PERIOD else t["rea"]


def complete_galaxies(t: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The rows of galaxies (realizations) that ``rows`` holds in every case (and in a pooled
    antithetic set, in both twins)."""
    n_cases = len(np.unique(t["case"])) * (2 if TWIN_PERIOD else 1)
    ids = galaxy_ids(t)
    counts = np.bincount(ids[rows], minlength=int(ids.max()) + 1)
    return counts[ids] == n_cases


#: Realizations per galaxy pair: 2, or 4 in a set of antithetic twins (header ANTITHET = T).
PAIR_REALIZATIONS = [2]


def pair_groups(t: np.ndarray, groups: int = GROUPS) -> np.ndarray:
    """Each row's jackknife group: galaxy pairs (every shear of a pair together, and both
    twins of an antithetic set or of a pooled one) spread over ``groups`` groups by a fixed
    permutation."""
    pair = galaxy_ids(t) // PAIR_REALIZATIONS[0]
    return np.random.default_rng(0).permutation(pair.max() + 1)[pair] % groups


def per_group_sums(
    t: np.ndarray,
    step: float,
    weighted: bool = True,
    failures: bool = False,
    complete: bool = False,
) -> tuple[dict, np.ndarray]:
    """Per (case, group) sums of the rows ``megalut evaluate`` uses (noshear measured, every
    response finite; weights finite and positive): weights, weighted estimates and responses,
    and the sheared versions' weights with the weighted noshear estimates; the cases' true
    shears ``(n_cases, 2)``. With ``failures``, the sheared versions' failures as a selection
    instead: every row whose noshear version is measured counts, the mean response is taken
    over those whose responses are finite, and a row is selected on a sheared version when
    that version is measured (its selection response corrects the failures). With
    ``complete``, only the galaxies whose rows are used in every case (a selection on the
    truth: a diagnostic of simulations, not an estimator for data)."""

    def col(name: str) -> np.ndarray:
        return np.asarray(t[name], dtype=float)

    every = used_rows(t)
    if failures:
        every = (
            (t["flags_noshear"] == 0)
            & np.isfinite(t["pre_g1_noshear"])
            & np.isfinite(t["pre_g2_noshear"])
        )
    if complete:
        every = every & complete_galaxies(t, every)
    cases, case = np.unique(t["case"], return_inverse=True)
    group = pair_groups(t)
    key = case * GROUPS + group

    def total(v: np.ndarray) -> np.ndarray:
        return np.bincount(key, weights=v, minlength=cases.size * GROUPS).reshape(cases.size, -1)

    def weight(kind: str, i: int) -> np.ndarray:
        seen = every & (t[f"flags_{kind}"] == 0) if failures else every
        if not weighted:  # every row alike: a selection response from failures alone
            return seen.astype(float)
        w = col(f"pre_g{i}_w_{kind}")
        return np.where(seen & np.isfinite(w) & (w > 0), w, 0.0)

    sums = {}
    for i in (1, 2):
        g = np.nan_to_num(col(f"pre_g{i}_noshear"))
        w = weight("noshear", i)
        sums[f"w{i}"], sums[f"wg{i}"] = total(w), total(w * g)
        responded = np.isfinite(col(f"mcal_r{i}1")) & np.isfinite(col(f"mcal_r{i}2"))
        sums[f"wn{i}"] = total(np.where(responded, w, 0.0))  # the mean response's rows
        for j in (1, 2):
            sums[f"wr{i}{j}"] = total(np.where(responded, w * col(f"mcal_r{i}{j}"), 0.0))
        for kind in VERSIONS[1:]:
            wk = weight(kind, i)
            sums[f"w{i}{kind}"], sums[f"wg{i}{kind}"] = total(wk), total(wk * g) / (2 * step)
    shears = np.array([[col(f"tru_g{i}")[case == c][0] for i in (1, 2)] for c in range(cases.size)])
    return sums, shears


def _totals(a: np.ndarray, drop: int | None) -> np.ndarray:
    """Per-case totals of per-(case, group) sums, group ``drop`` left out."""
    return a.sum(axis=1) - (a[:, drop] if drop is not None else 0.0)


def _responses(sums: dict, drop: int | None, per_case: bool) -> np.ndarray:
    """The mean response plus the weights' selection response, ``(2, 2)`` over all cases or
    ``(n_cases, 2, 2)`` each case's own, group ``drop`` left out."""

    def ratio(num: str, den: str) -> np.ndarray:
        a, b = _totals(sums[num], drop), _totals(sums[den], drop)
        return a / b if per_case else a.sum() / b.sum()

    parts = [
        [
            ratio(f"wr{i}{j}", f"wn{i}") + ratio(f"wg{i}{j}p", f"w{i}{j}p")
            - ratio(f"wg{i}{j}m", f"w{i}{j}m")
            for j in (1, 2)
        ]
        for i in (1, 2)
    ]  # fmt: skip
    resp = np.array(parts)  # (2, 2) or (2, 2, n_cases)
    return np.moveaxis(resp, -1, 0) if per_case else resp


def _case_means(sums: dict, drop: int | None) -> np.ndarray:
    """The cases' weighted mean estimates ``(n_cases, 2)``, group ``drop`` left out."""
    return np.stack(
        [_totals(sums[f"wg{i}"], drop) / _totals(sums[f"w{i}"], drop) for i in (1, 2)], axis=1
    )


def calibrated(sums: dict, drop: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The cases' calibrated means ``(n_cases, 2)`` by the mean response plus the weights'
    selection response, and the cases' mean responses ``R_ii``, group ``drop`` left out."""
    means = _case_means(sums, drop)
    cases_r = np.stack(
        [_totals(sums[f"wr{i}{i}"], drop) / _totals(sums[f"wn{i}"], drop) for i in (1, 2)], axis=1
    )
    return np.linalg.solve(_responses(sums, drop, False), means.T).T, cases_r


def case_responses(sums: dict, drop: int | None = None) -> np.ndarray:
    """Each case's own mean response ``(n_cases, 2, 2)``, the weights' selection response
    included, group ``drop`` left out."""
    return _responses(sums, drop, True)


def zero_shear_calibrated(
    sums: dict, shears: np.ndarray, drop: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The cases' means calibrated by the response at zero shear (the intercept of a fit of the
    cases' responses, :func:`response_design`) rather than by their mean over the drawn
    shears; and that response."""
    resp = case_responses(sums, drop).reshape(len(shears), 4)
    zero = np.linalg.lstsq(response_design(shears), resp, rcond=None)[0][0].reshape(2, 2)
    return np.linalg.solve(zero, _case_means(sums, drop).T).T, zero


def jackknife_sigma(jack: np.ndarray, groups: int = GROUPS) -> np.ndarray:
    """The delete-group jackknife error of the replicates ``jack`` (groups along axis 0)."""
    return np.sqrt((groups - 1) / groups * ((jack - jack.mean(axis=0)) ** 2).sum(axis=0))


TRUTH_CUT: list[tuple[str, float, float]] = []  # --cut COLUMN LO HI: (column, lo, hi)
ONE_TWIN: list[int] = []  # --twin 0|1: the realizations with rea % 2 of that value
ADAMOM: list[bool] = []  # --adamom: adaptive moments' own metacal instead of the networks


def _adamom_as_estimates(raw: np.ndarray, step: float, extra: tuple[str, ...]) -> np.ndarray:
    """The columns :func:`read_set` gives, from the adaptive moments of each version: ``pre_g``
    = ``adamom_g``, the weights ``1 / (0.3^2 + (2 / snr)^2)`` of that version's S/N, and the
    responses their finite differences."""
    names = ["case", "rea", "tru_g1", "tru_g2", *extra] + [f"flags_{k}" for k in VERSIONS]
    dtype = [(n, raw[n].dtype) for n in names]
    dtype += [(f"pre_g{c}{w}_{k}", "f8") for c in (1, 2) for w in ("", "_w") for k in VERSIONS]
    dtype += [(f"mcal_r{i}{j}", "f8") for i in (1, 2) for j in (1, 2)]
    t = np.zeros(len(raw), dtype=dtype)
    for n in names:
        t[n] = raw[n]
    for k in VERSIONS:
        measured = raw[f"flags_{k}"] == 0
        weight = 1.0 / (0.3**2 + (2.0 / raw[f"snr_{k}"]) ** 2)
        for c in (1, 2):
            t[f"pre_g{c}_{k}"] = np.where(measured, raw[f"adamom_g{c}_{k}"], np.nan)
            t[f"pre_g{c}_w_{k}"] = np.where(measured & np.isfinite(weight), weight, np.nan)
    for i in (1, 2):
        for j in (1, 2):
            t[f"mcal_r{i}{j}"] = (t[f"pre_g{i}_{j}p"] - t[f"pre_g{i}_{j}m"]) / (2 * step)
    return t


def read_set(path: str, extra: tuple[str, ...] = ()) -> tuple[np.ndarray, float]:
    """The columns the checks read (the rows within :data:`TRUTH_CUT`; with :data:`ADAMOM`, the
    adaptive moments' estimates in place of the networks'), and the set's metacal step."""
    header = fitsio.read_header(path, 1)
    step = float(header.get("MCALSTEP", 0.01))
    PAIR_REALIZATIONS[0] = 4 if header.get("ANTITHET", False) is True else 2
    names = ["case", "rea", "tru_g1", "tru_g2"] + [f"flags_{k}" for k in VERSIONS]
    if ADAMOM:
        names += [f"adamom_g{c}_{k}" for c in (1, 2) for k in VERSIONS]
        names += [f"snr_{k}" for k in VERSIONS]
    else:
        names += ["mcal_r11", "mcal_r12", "mcal_r21", "mcal_r22"]
        names += [f"pre_g{c}{w}_{k}" for c in (1, 2) for w in ("", "_w") for k in VERSIONS]
    extra = tuple(extra) + tuple(c for c, _, _ in TRUTH_CUT if c not in names + list(extra))
    t = fitsio.read(path, columns=names + list(extra))
    if ADAMOM:
        t = _adamom_as_estimates(t, step, extra)
    for column, lo, hi in TRUTH_CUT:
        t = t[(t[column] >= lo) & (t[column] < hi)]
    if ONE_TWIN:
        if PAIR_REALIZATIONS[0] != 4:
            sys.exit(f"{path}: --twin needs a set of antithetic twins (header ANTITHET = T)")
        t = t[t["rea"] % 2 == ONE_TWIN[0]]
    return t, step


def m_and_jackknife(t: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """m of both components and their delete-group jackknife errors."""
    sums, both = per_group_sums(t, step)
    cal = calibrated(sums)[0]
    jacks = [calibrated(sums, d)[0] for d in range(GROUPS)]
    m = np.array([np.polyfit(both[:, i], cal[:, i], 1)[0] - 1 for i in (0, 1)])
    jack = np.array([[np.polyfit(both[:, i], c[:, i], 1)[0] - 1 for i in (0, 1)] for c in jacks])
    return m, jackknife_sigma(jack)


MATRIX_PARTS = ("(m11 + m22) / 2", "(m11 - m22) / 2", "(m12 + m21) / 2", "(m12 - m21) / 2")


def matrix_parts(shears: np.ndarray, cal: np.ndarray, cubic: bool = False) -> np.ndarray:
    """The four parts (:data:`MATRIX_PARTS`) of the fitted 2x2 matrix ``m_ij``; with
    ``cubic``, fitted beside every quadratic and cubic term of (g1, g2): m at zero shear."""
    g1, g2 = shears[:, 0], shears[:, 1]
    terms = [g1, g2, np.ones(len(shears))]
    if cubic:
        terms += [g1 * g1, g1 * g2, g2 * g2, g1**3, g1 * g1 * g2, g1 * g2 * g2, g2**3]
    design = np.column_stack(terms)
    fit = np.linalg.lstsq(design, cal, rcond=None)[0]
    m = fit[:2].T - np.eye(2)
    return np.array(
        [
            (m[0, 0] + m[1, 1]) / 2,
            (m[0, 0] - m[1, 1]) / 2,
            (m[0, 1] + m[1, 0]) / 2,
            (m[0, 1] - m[1, 0]) / 2,
        ]
    )


def chi2_about_mean(values: np.ndarray, errors: np.ndarray) -> tuple[float, float, float]:
    """The weighted mean, its error and the chi^2 of ``values`` about it."""
    w = 1 / errors**2
    mean = float((w * values).sum() / w.sum())
    return mean, float(1 / np.sqrt(w.sum())), float((w * (values - mean) ** 2).sum())


def by_matrix(
    paths: list[str], zero_shear: bool = False, weighted: bool = True, cubic: bool = True
) -> None:
    """The parts of each set's 2x2 matrix, their jackknife errors and chi^2 across sets; with
    ``zero_shear``, at zero shear (:func:`zero_shear_calibrated`; the cubic terms fitted
    beside the line unless ``cubic`` is false, as in ``megalut evaluate``)."""

    def parts(sums: dict, shears: np.ndarray, drop: int | None = None) -> np.ndarray:
        if zero_shear:
            return matrix_parts(shears, zero_shear_calibrated(sums, shears, drop)[0], cubic)
        return matrix_parts(shears, calibrated(sums, drop)[0])

    values, errors = [], []
    for path in paths:
        t, step = read_set(path)
        sums, shears = per_group_sums(t, step, weighted)
        values.append(parts(sums, shears))
        jack = np.array([parts(sums, shears, d) for d in range(GROUPS)])
        errors.append(jackknife_sigma(jack))
    names = " | ".join(p.rsplit("/", 1)[-1] for p in paths)
    print(f"| part of m_ij (1e-3) | {names} | weighted mean | chi^2 |")
    print("|---|" + "---|" * (len(paths) + 2))
    for k, part in enumerate(MATRIX_PARTS):
        v = np.array([a[k] for a in values])
        e = np.array([a[k] for a in errors])
        mean, err, chi2 = chi2_about_mean(v, e)
        cells = " | ".join(f"{1e3 * a:+.2f} +- {1e3 * b:.2f}" for a, b in zip(v, e))
        print(f"| {part} | {cells} | {1e3 * mean:+.2f} +- {1e3 * err:.2f} | {chi2:.1f} |")


def read_cases(paths: list[str]) -> tuple[np.ndarray, float]:
    """Single-case catalogs of one common-random-number set as the cases of one set (``case``
    = the file's position), and the metacal step."""
    parts = []
    for k, path in enumerate(paths):
        t, step = read_set(path)
        t["case"] = k
        parts.append(t)
    return np.concatenate(parts), step


def swap(path_a: str, path_b: str, case_paths: list[str]) -> None:
    """The parts of sets A, X (A's stamps under B's shears) and B, and the differences A - X
    (jackknife over the same galaxy groups) and X - B."""
    parts = {}
    for name, (t, step) in (
        ("A", read_set(path_a)),
        ("X", read_cases(case_paths)),
        ("B", read_set(path_b)),
    ):
        sums, shears = per_group_sums(t, step)
        jack = np.array([matrix_parts(shears, calibrated(sums, d)[0]) for d in range(GROUPS)])
        parts[name] = matrix_parts(shears, calibrated(sums)[0]), jack
    print("| part of m_ij (1e-3) | A | X: A's stamps, B's shears | B | A - X | X - B |")
    print("|---|---|---|---|---|---|")
    errors = {n: jackknife_sigma(jack) for n, (_, jack) in parts.items()}
    diff_error = jackknife_sigma(parts["A"][1] - parts["X"][1])
    for k, part in enumerate(MATRIX_PARTS):
        cells = [f"{1e3 * parts[n][0][k]:+.2f} +- {1e3 * errors[n][k]:.2f}" for n in "AXB"]
        a_x = parts["A"][0][k] - parts["X"][0][k]
        x_b = parts["X"][0][k] - parts["B"][0][k]
        print(
            f"| {part} | {' | '.join(cells)} | {1e3 * a_x:+.2f} +- "
            f"{1e3 * diff_error[k]:.2f} | {1e3 * x_b:+.2f} |"
        )


def paired(path_a: str, path_b: str) -> None:
    """m of two sets of the same galaxies and noise (the same stamps measured two ways, or one
    seed's galaxies under other shears, noise level or metacal step), weighted and not, on the
    rows ``evaluate`` uses and on the galaxies measured in every case: each set's (evaluate's
    estimator, and the isotropic part of its matrix) and their difference A - B with its
    jackknife over the same galaxy groups."""
    sets = [read_set(p) for p in (path_a, path_b)]
    if not np.array_equal(sets[0][0]["rea"], sets[1][0]["rea"]):
        sys.exit("--paired: the two sets do not hold the same realizations row by row")
    print(f"A = {path_a}, B = {path_b}; rows used (noshear measured, every response finite):")
    for name, (t, _) in zip("AB", sets):
        print(f"  {name}: {used_rows(t).mean():.4f} of {len(t)}")
    print("| rows | estimator | quantity (1e-3) | A | B | A - B |")
    print("|---|---|---|---|---|---|")
    for complete in (False, True):
        rows = "complete galaxies" if complete else "evaluate's"
        for weighted in (True, False):
            values, jacks = [], []
            for t, step in sets:
                sums, shears = per_group_sums(t, step, weighted, complete=complete)

                def stats(cal: np.ndarray, shears: np.ndarray = shears) -> np.ndarray:
                    m = [np.polyfit(shears[:, i], cal[:, i], 1)[0] - 1 for i in (0, 1)]
                    return np.array([*m, matrix_parts(shears, cal)[0]])

                values.append(stats(calibrated(sums)[0]))
                jacks.append(np.array([stats(calibrated(sums, d)[0]) for d in range(GROUPS)]))
            errs = [jackknife_sigma(j) for j in jacks]
            diff = jackknife_sigma(jacks[0] - jacks[1])
            for k, q in enumerate(("m1", "m2", "(m11 + m22) / 2")):
                print(
                    f"| {rows} | {'weighted' if weighted else 'unweighted'} | {q} | "
                    f"{1e3 * values[0][k]:+.2f} +- {1e3 * errs[0][k]:.2f} | "
                    f"{1e3 * values[1][k]:+.2f} +- {1e3 * errs[1][k]:.2f} | "
                    f"{1e3 * (values[0][k] - values[1][k]):+.2f} +- {1e3 * diff[k]:.2f} |"
                )


ANTITHETIC_QUANTITIES = ("m1", "m2", "(m11 + m22) / 2", "c1", "c2")


def pooled_twins(plus: np.ndarray, minus: np.ndarray) -> np.ndarray:
    """One set of two antithetic twins (the same galaxies with noise and fixnoise n and -n):
    ``minus``'s realizations shifted by :data:`TWIN_PERIOD` (set here), so that each galaxy's
    twins count as one galaxy in :func:`complete_galaxies` and :func:`pair_groups`."""
    if not np.array_equal(plus["rea"], minus["rea"]) or plus.dtype != minus.dtype:
        sys.exit("--antithetic: the twins do not hold the same realizations row by row")
    period = int(plus["rea"].max()) + 1
    TWIN_PERIOD[:] = [period + period % 2]
    shifted = minus.copy()
    shifted["rea"] = shifted["rea"] + TWIN_PERIOD[0]
    return np.concatenate([plus, shifted])


def antithetic(paths: list[str]) -> None:
    """Antithetic twins: ``PLUS MINUS`` are one seed's galaxies with noise n and fixnoise f,
    and with -n and -f (``noise.override_sigma`` of both signs; the fixnoise sign from a patched
    tree: docs/metacal.md). Pooled, a galaxy's estimates lose every term odd in the noise, its
    noise bias (even) stays. On the complete galaxies (both twins measured in every case):
    m1, m2 and the isotropic part of each twin and of the pool, weighted and not, jackknife
    errors over galaxy pairs; with ``REF_PLUS REF_MINUS`` (the same galaxies at low noise),
    the pool's difference from the reference's pool with its paired jackknife: the noise
    part of m."""
    pools = []
    for a, b in zip(paths[::2], paths[1::2]):
        (ta, step), (tb, _) = read_set(a), read_set(b)
        TWIN_PERIOD.clear()
        singles = [(ta, step), (tb, step)]
        stats_single = [_complete_stats(t, st) for t, st in singles]
        pooled = pooled_twins(ta, tb)
        pools.append(_complete_stats(pooled, step))
        TWIN_PERIOD.clear()
        print(f"{a} | {b}: complete galaxies, m in 1e-3, c in 1e-4")
        print("| estimator | quantity | plus | minus | pooled |")
        print("|---|---|---|---|---|")
        for w, scheme in enumerate(("weighted", "unweighted")):
            for k, q in enumerate(ANTITHETIC_QUANTITIES):
                unit = 1e4 if q.startswith("c") else 1e3
                cells = [
                    f"{unit * v[w][0][k]:+.2f} +- {unit * jackknife_sigma(v[w][1])[k]:.2f}"
                    for v in (*stats_single, pools[-1])
                ]
                print(f"| {scheme} | {q} | {' | '.join(cells)} |")
    if len(pools) == 2:
        print(f"pooled difference, {paths[0]} pair - {paths[2]} pair (paired jackknife):")
        for w, scheme in enumerate(("weighted", "unweighted")):
            diff = pools[0][w][0] - pools[1][w][0]
            err = jackknife_sigma(pools[0][w][1] - pools[1][w][1])
            cells = [
                f"{q} {(1e4 if q.startswith('c') else 1e3) * d:+.2f} +- "
                f"{(1e4 if q.startswith('c') else 1e3) * e:.2f}"
                for q, d, e in zip(ANTITHETIC_QUANTITIES, diff, err)
            ]
            print(f"  {scheme}: {', '.join(cells)}")


def _complete_stats(t: np.ndarray, step: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """m1, m2 and the isotropic part on the complete galaxies, weighted and unweighted, each
    with its jackknife replicates over :func:`pair_groups`."""
    out = []
    for weighted in (True, False):
        sums, shears = per_group_sums(t, step, weighted, complete=True)

        def stats(cal: np.ndarray, shears: np.ndarray = shears) -> np.ndarray:
            lines = [np.polyfit(shears[:, i], cal[:, i], 1) for i in (0, 1)]
            m, c = [a - 1 for a, _ in lines], [b for _, b in lines]
            return np.array([*m, matrix_parts(shears, cal)[0], *c])

        jack = np.array([stats(calibrated(sums, d)[0]) for d in range(GROUPS)])
        out.append((stats(calibrated(sums)[0]), jack))
    return out


def _line_stats(sums: dict, shears: np.ndarray, drop: int | None, cubic: bool) -> np.ndarray:
    """m1, m2 (a line) and the isotropic part, calibrated as ``evaluate --response auto`` does
    (at zero shear with 10 cases or more, the isotropic part then with the cubic terms if
    ``cubic``; else by the mean response and a line)."""
    if len(shears) < 10:
        cal, cubic = calibrated(sums, drop)[0], False
    else:
        cal = zero_shear_calibrated(sums, shears, drop)[0]
    m = [np.polyfit(shears[:, i], cal[:, i], 1)[0] - 1 for i in (0, 1)]
    return np.array([*m, matrix_parts(shears, cal, cubic)[0]])


def compare_rows(paths: list[str], labels: tuple[str, str], variants: list[dict], cubic: bool):
    """Each set two ways on the same stamps (``variants``: the :func:`per_group_sums` keywords
    of each), weighted and not: m1, m2 and the isotropic part (:func:`_line_stats`), the
    difference with its jackknife over the same galaxy groups, and the sets' weighted means."""
    names = ("m1", "m2", "(m11 + m22) / 2")
    rows: dict[tuple[str, int], list[tuple[float, float, float, float, float, float]]] = {}
    print(f"| set | estimator | quantity (1e-3) | {labels[0]} | {labels[1]} | difference |")
    print("|---|---|---|---|---|---|")
    for path in paths:
        t, step = read_set(path)
        for weighted in (True, False):
            scheme = "weighted" if weighted else "unweighted"
            both = [per_group_sums(t, step, weighted, **kw) for kw in variants]
            values = [_line_stats(sums, shears, None, cubic) for sums, shears in both]
            jacks = [
                np.array([_line_stats(sums, shears, d, cubic) for d in range(GROUPS)])
                for sums, shears in both
            ]
            errs = [jackknife_sigma(j) for j in jacks]
            diff = jackknife_sigma(jacks[1] - jacks[0])
            for k, q in enumerate(names):
                a, b = values[0][k], values[1][k]
                rows.setdefault((scheme, k), []).append(
                    (a, errs[0][k], b, errs[1][k], b - a, diff[k])
                )
                print(
                    f"| {path.rsplit('/', 1)[-1]} | {scheme} | {q} | {1e3 * a:+.2f} +- "
                    f"{1e3 * errs[0][k]:.2f} | {1e3 * b:+.2f} +- {1e3 * errs[1][k]:.2f} | "
                    f"{1e3 * (b - a):+.2f} +- {1e3 * diff[k]:.2f} |"
                )
    print("| all sets: weighted mean, chi^2 | | | | | |")
    for (scheme, k), vals in rows.items():
        v = np.array(vals)
        cells = []
        for col in (0, 2, 4):
            mean, err, chi2 = chi2_about_mean(v[:, col], v[:, col + 1])
            cells.append(f"{1e3 * mean:+.2f} +- {1e3 * err:.2f} ({chi2:.1f})")
        print(f"| {len(paths)} sets | {scheme} | {names[k]} | {' | '.join(cells)} |")


def failures_check(paths: list[str]) -> None:
    """:func:`compare_rows`: as ``evaluate`` takes its rows (every version measured) against
    the sheared versions' failures as a selection (:func:`per_group_sums` ``failures``); the
    isotropic part with the cubic terms at zero shear."""
    labels = ("every version measured", "failures as a selection")
    compare_rows(paths, labels, [{"failures": False}, {"failures": True}], cubic=True)


def complete_check(paths: list[str]) -> None:
    """:func:`compare_rows`: as ``evaluate`` takes its rows against only the galaxies measured
    in every case (:func:`per_group_sums` ``complete``), a line throughout. A galaxy measured
    under some shears and not others enters the cases' means through a selection on the true
    shear, which no metacal response sees."""
    labels = ("evaluate's rows", "complete galaxies")
    compare_rows(paths, labels, [{"complete": False}, {"complete": True}], cubic=False)


CURVATURE = ("m", "p = 2 b g^2", "q")
CURVATURE_GROUPS = 200


def _version_sums(
    t: np.ndarray, rows: np.ndarray, group: np.ndarray, weighted: bool, c: int, kind: str
) -> tuple[np.ndarray, np.ndarray]:
    """Per-group sums of the weights and weighted estimates of component ``c`` of version
    ``kind`` on ``rows`` (every row alike unless ``weighted``)."""
    e = np.nan_to_num(np.asarray(t[f"pre_g{c}_{kind}"], dtype=float))
    w = np.nan_to_num(np.asarray(t[f"pre_g{c}_w_{kind}"], dtype=float)) if weighted else 1.0
    w = np.where(rows, w, 0.0)
    return (
        np.bincount(group, w * e, CURVATURE_GROUPS),
        np.bincount(group, w, CURVATURE_GROUPS),
    )


def _curvature_stats(table: dict, i: int, g: float, step: float, drop: int | None) -> np.ndarray:
    """m, p and q (:func:`curvature`) of axis ``i`` from the per-group sums ``table``, group
    ``drop`` left out."""

    def mean(key: tuple[int, int, str]) -> float:
        a, b = (x.sum() - (x[drop] if drop is not None else 0.0) for x in table[key])
        return a / b

    s = (mean((1, i, "noshear")) - mean((-1, i, "noshear"))) / (2 * g)
    r_par, r_perp = (
        np.mean([mean((sign, c, f"{c}p")) - mean((sign, c, f"{c}m")) for sign in (1, -1)])
        / (2 * step)
        for c in (i, 3 - i)
    )
    m = 2 * s / (r_par + r_perp) - 1
    return np.array([m, r_par / (1 - g * g) / s - 1, r_perp / (1 + g * g) / s - 1])


def axis_curvature(
    t: np.ndarray, every: np.ndarray, group: np.ndarray, step: float, weighted: bool, i: int
) -> tuple[float, np.ndarray, np.ndarray]:
    """abs(g) of the axis cases of component ``i``, and m, p, q (:func:`curvature`) on the rows
    ``every`` with their jackknife errors over the galaxy-pair groups ``group``."""
    j = 3 - i
    along, across = np.asarray(t[f"tru_g{i}"]), np.asarray(t[f"tru_g{j}"])
    g = float(np.abs(along[np.isclose(across, 0) & (np.abs(along) > 0)]).max())
    table = {}
    for sign in (1, -1):
        rows = every & np.isclose(along, sign * g) & np.isclose(across, 0)
        for c, kind in [(i, "noshear"), (i, f"{i}p"), (i, f"{i}m"), (j, f"{j}p"), (j, f"{j}m")]:
            table[(sign, c, kind)] = _version_sums(t, rows, group, weighted, c, kind)
    value = _curvature_stats(table, i, g, step, None)
    jack = np.array([_curvature_stats(table, i, g, step, d) for d in range(CURVATURE_GROUPS)])
    return g, value, jackknife_sigma(jack, CURVATURE_GROUPS)


def curvature(paths: list[str]) -> None:
    """m of a ``vo-cross`` set's axis cases split by the curvature of the mean estimate in the
    shear. On the complete galaxies (every version measured in every case), each version with
    its own weights: the secant ``s`` of the noshear means across the cases (+g, 0) and (-g, 0),
    and the metacal responses along the shear, ``R_par = (<e_i>_ip - <e_i>_im) / 2 step``, and
    across it, ``R_perp`` from the other component's versions, averaged over the two cases.
    For ``<e> = A g (1 + b abs(g)^2)`` the composition of shears gives ``R_par = A (1 + 3 b
    g^2)(1 - g^2)`` and ``R_perp = A (1 + b g^2)(1 + g^2)``, so with ``p = R_par / (1 - g^2) /
    s - 1`` (= 2 b g^2) and ``q = R_perp / (1 + g^2) / s - 1`` (0 for an equivariant
    estimator), ``m = s / ((R_par + R_perp) / 2) - 1`` is about ``-(p + q) / 2``: the
    curvature's part of m goes as g^2 and vanishes at zero shear."""
    found: dict[bool, list[tuple[np.ndarray, np.ndarray]]] = {True: [], False: []}
    print("| set | estimator | axis | abs(g) | " + " | ".join(CURVATURE) + " |")
    print("|---|---|---|---|---|---|---|")
    for path in paths:
        t, step = read_set(path)
        every = used_rows(t) & np.all([t[f"flags_{k}"] == 0 for k in VERSIONS], axis=0)
        every &= complete_galaxies(t, every)
        group = pair_groups(t, CURVATURE_GROUPS)
        for weighted in (True, False):
            scheme = "weighted" if weighted else "unweighted"
            for i in (1, 2):
                g, value, error = axis_curvature(t, every, group, step, weighted, i)
                found[weighted].append((value, error))
                cells = " | ".join(f"{1e3 * a:+.2f} +- {1e3 * b:.2f}" for a, b in zip(value, error))
                print(f"| {path.rsplit('/', 1)[-1]} | {scheme} | g{i} | {g:.4g} | {cells} |")
    print("| all sets and axes: weighted mean (chi^2) | | | | | | |")
    for weighted, both in found.items():
        values, errors = np.array([v for v, _ in both]), np.array([e for _, e in both])
        cells = []
        for k in range(len(CURVATURE)):
            mean, err, chi2 = chi2_about_mean(values[:, k], errors[:, k])
            cells.append(f"{1e3 * mean:+.2f} +- {1e3 * err:.2f} ({chi2:.1f})")
        scheme = "weighted" if weighted else "unweighted"
        print(f"| {len(both)} axes | {scheme} | | | {' | '.join(cells)} |")


def by_column(column: str, paths: list[str], bins: int = 4) -> None:
    """m of each set in the quantile bins of a truth ``column``, and each bin's chi^2."""
    edges = None
    results = []
    for path in paths:
        t, step = read_set(path, (column,))
        if edges is None:
            edges = np.quantile(t[column], np.linspace(0, 1, bins + 1))
            edges[-1] = np.inf
        which = np.digitize(t[column], edges[1:-1])
        results.append([m_and_jackknife(t[which == b], step) for b in range(bins)])
    names = " | ".join(p.rsplit("/", 1)[-1] for p in paths)
    print(f"| {column} bin | comp. | {names} | chi^2 |")
    print("|---|---|" + "---|" * (len(paths) + 1))
    for b in range(bins):
        for i in (0, 1):
            m = np.array([r[b][0][i] for r in results])
            err = np.array([r[b][1][i] for r in results])
            chi2 = chi2_about_mean(m, err)[2]
            cells = " | ".join(f"{1e3 * a:+.1f} +- {1e3 * e:.1f}" for a, e in zip(m, err))
            print(f"| {edges[b]:.3g} to {edges[b + 1]:.3g} | g{i + 1} | {cells} | {chi2:.1f} |")


def main(paths: list[str]) -> None:
    print(
        "| catalog | comp. | m | jackknife | largest influence; kurtosis | m, cubic fit | beta "
        "| m, one case left out | R against abs(g)^2 |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for path in paths:
        t, step = read_set(path)
        sums, both = per_group_sums(t, step)
        abs2 = (both**2).sum(axis=1)
        cal_all, resp_all = calibrated(sums)
        jacks = [calibrated(sums, d)[0] for d in range(GROUPS)]
        for i in (1, 2):
            shears, cal, resp = both[:, i - 1], cal_all[:, i - 1], resp_all[:, i - 1]
            m = np.polyfit(shears, cal, 1)[0] - 1
            jack = np.array([np.polyfit(shears, c[:, i - 1], 1)[0] - 1 for c in jacks])
            influence = (GROUPS - 1) * (jack - jack.mean())
            sigma = jackknife_sigma(jack)
            kurt = ((influence - influence.mean()) ** 4).mean() / influence.var() ** 2
            design = np.vstack([shears, np.ones_like(shears), shears * abs2]).T
            cubic = np.linalg.lstsq(design, cal, rcond=None)[0]
            keep = np.ones(len(shears), bool)
            loo = []
            for c in range(len(shears)):
                keep[:] = True
                keep[c] = False
                loo.append(np.polyfit(shears[keep], cal[keep], 1)[0] - 1)
            slope = np.polyfit(abs2, resp, 1)
            print(
                f"| {path.rsplit('/', 1)[-1]} | g{i} | {1e3 * m:+.2f}e-3 | {1e3 * sigma:.2f}e-3 | "
                f"{1e3 * np.abs(influence).max():.0f}e-3; {kurt:.1f} | "
                f"{1e3 * (cubic[0] - 1):+.2f}e-3 | "
                f"{cubic[2]:+.2f} | {1e3 * min(loo):+.2f} to {1e3 * max(loo):+.2f}e-3 | "
                f"{slope[1]:.4f} {slope[0]:+.3f} abs(g)^2 |"
            )


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0 if len(sys.argv) > 1 else 2)
    if len(sys.argv) > 4 and sys.argv[1] == "--cut":  # a truth cut before any mode
        TRUTH_CUT.append((sys.argv[2], float(sys.argv[3]), float(sys.argv[4])))
        del sys.argv[1:5]
    if len(sys.argv) > 1 and sys.argv[1] == "--twin":
        if len(sys.argv) < 3 or sys.argv[2] not in ("0", "1"):
            print(
                "--twin takes 0 (the first twin of each galaxy) or 1 (the second)", file=sys.stderr
            )
            sys.exit(2)
        ONE_TWIN.append(int(sys.argv[2]))
        del sys.argv[1:3]
    if len(sys.argv) > 1 and sys.argv[1] == "--adamom":  # adaptive moments' own metacal
        ADAMOM.append(True)
        del sys.argv[1]
    if len(sys.argv) > 2 and sys.argv[1] == "--by":
        by_column(sys.argv[2], sys.argv[3:])
    elif len(sys.argv) > 2 and sys.argv[1] == "--failures":
        failures_check(sys.argv[2:])
    elif len(sys.argv) > 2 and sys.argv[1] == "--curvature":
        curvature(sys.argv[2:])
    elif len(sys.argv) > 2 and sys.argv[1] == "--complete":
        complete_check(sys.argv[2:])
    elif len(sys.argv) in (4, 6) and sys.argv[1] == "--antithetic":
        antithetic(sys.argv[2:])
    elif len(sys.argv) == 4 and sys.argv[1] == "--paired":
        paired(sys.argv[2], sys.argv[3])
    elif len(sys.argv) > 4 and sys.argv[1] == "--swap":
        swap(sys.argv[2], sys.argv[3], sys.argv[4:])
    elif len(sys.argv) > 1 and sys.argv[1] == "--matrix":
        flags = {"--zero-shear", "--unweighted", "--line"}
        by_matrix(
            [a for a in sys.argv[2:] if a not in flags],
            zero_shear="--zero-shear" in sys.argv,
            weighted="--unweighted" not in sys.argv,
            cubic="--line" not in sys.argv,
        )
    else:
        main(sys.argv[1:])
