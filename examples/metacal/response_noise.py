"""Where the noise of a CRN set's unweighted metacal m comes from (issue 39).

For each component of a ``megalut predict`` catalog of a common-random-number set in metacal
mode (``examples/fiducial/vo-crn.toml``), on the galaxies whose noshear version is measured
with a finite estimate and response in every case:

* per galaxy, the slope of its estimate ``pre_gi_noshear`` against the cases' true shears
  (a least-squares fit of 1, g1, g2 over the cases: the response to a true shear) and its
  metacal response ``mcal_rii`` averaged over the cases;
* m = <slope> / <R> - 1 over the galaxies (unweighted), and its error from the scatter of
  ``slope - (1 + m) R`` between 90-degree pairs of galaxies (a pair is one unit), beside the
  errors the slope alone and the response alone would give;
* the response's variance split into a part between galaxies and a part between the cases of
  one galaxy (the part that more cases per galaxy average away);
* the share of the variance of ``slope - R`` in each decile of the galaxies' S/N (their median
  ``snr_noshear`` over the cases) and in the 1 % of galaxies farthest from the mean;
* the variance per stamp, n_stamps * sigma_m^2: the figure that compares designs (cases per
  galaxy) at equal cost.

With ``--average OUT.fits A.fits B.fits ...``: catalogs of the same stamps measured with other
fixnoise seeds (``megalut measure ... --metacal --seed S``, then ``megalut predict``): the
correlation of each row's response and estimate between the first two, then OUT.fits with
every row's estimates and responses averaged over the catalogs (the estimator averaged over
several fixnoise fields; a row is kept where it is measured in all), and its report.

    python examples/metacal/response_noise.py vo-3901-a.fits [vo-3902-a.fits ...]
    python examples/metacal/response_noise.py --average p12.fits p1.fits p2.fits
"""

from __future__ import annotations

import sys

import numpy as np
from astropy.io import fits

COLUMNS = ("case", "rea", "tru_g1", "tru_g2", "flags_noshear", "snr_noshear")


def read(path: str) -> dict[str, np.ndarray]:
    """The columns this script needs, component by component."""
    with fits.open(path, memmap=True) as hdul:
        data = hdul[1].data
        out = {name: np.asarray(data[name]) for name in COLUMNS}
        for i in (1, 2):
            out[f"g{i}"] = np.asarray(data[f"pre_g{i}_noshear"], dtype=np.float64)
            out[f"r{i}"] = np.asarray(data[f"mcal_r{i}{i}"], dtype=np.float64)
    return out


def grid(values: np.ndarray, case: np.ndarray, rea: np.ndarray, shape: tuple[int, int]):
    """``values`` as a (cases, realizations) array, NaN where a row is missing."""
    out = np.full(shape, np.nan)
    out[case, rea] = values
    return out


def pair_error(x: np.ndarray, units: np.ndarray) -> float:
    """The error of the mean of ``x`` (one value per galaxy) from the scatter of its pairs'
    means (``units``: each galaxy's pair)."""
    present = np.unique(units)
    per_pair = np.bincount(units, weights=x)[present] / np.bincount(units)[present]
    return float(per_pair.std(ddof=1) / np.sqrt(len(present)))


def report(path: str) -> None:
    t = read(path)
    case, rea = t["case"].astype(int), t["rea"].astype(int)
    shape = (case.max() + 1, rea.max() + 1)
    n_cases = shape[0]
    shears = np.zeros((n_cases, 2))
    shears[case, 0], shears[case, 1] = t["tru_g1"], t["tru_g2"]
    design = np.column_stack([np.ones(n_cases), shears])
    snr = grid(t["snr_noshear"], case, rea, shape)
    print(f"{path}: {n_cases} cases x {shape[1]} realizations, {len(case)} rows")
    for i in (1, 2):
        ok = (t["flags_noshear"] == 0) & np.isfinite(t[f"g{i}"]) & np.isfinite(t[f"r{i}"])
        est = grid(np.where(ok, t[f"g{i}"], np.nan), case, rea, shape)
        resp = grid(np.where(ok, t[f"r{i}"], np.nan), case, rea, shape)
        complete = np.all(np.isfinite(est), axis=0)
        # the two galaxies of a 90-degree pair must both be complete: a pair is one unit
        pair = np.arange(shape[1]) // 2
        both = np.bincount(pair, weights=complete, minlength=pair.max() + 1) == 2
        keep = both[pair]
        coef = np.linalg.lstsq(design, est[:, keep], rcond=None)[0]
        slope, r_mean = coef[i], resp[:, keep].mean(axis=0)
        m = slope.mean() / r_mean.mean() - 1.0
        units = pair[keep]
        n_units = len(np.unique(units))

        diff = slope - (1.0 + m) * r_mean
        sigma_m = pair_error(diff, units) / r_mean.mean()
        n_stamps = int(keep.sum()) * n_cases
        within = float(np.mean(resp[:, keep].var(axis=0, ddof=1)))
        between = float(r_mean.var(ddof=1) - within / n_cases)
        print(
            f"  g{i}: {keep.sum()} galaxies ({keep.mean():.1%}) in {n_units} pairs; "
            f"m = {m:+.2e} +- {sigma_m:.1e} (pairs' scatter); the slope alone "
            f"+-{pair_error(slope, units) / r_mean.mean():.1e}, the response alone "
            f"+-{pair_error(r_mean, units) / r_mean.mean():.1e}"
        )
        print(
            f"      per galaxy: std of the slope {slope.std():.3f}, of the mean response "
            f"{r_mean.std():.3f}, of slope - R {diff.std():.3f}; the response's variance per "
            f"row {between:.3f} between galaxies + {within:.3f} between one galaxy's cases"
        )
        print(f"      variance per stamp, n_stamps sigma_m^2 = {n_stamps * sigma_m**2:.1f}")
        med_snr = np.nanmedian(snr[:, keep], axis=0)
        dev2 = (diff - diff.mean()) ** 2
        edges = np.quantile(med_snr, np.linspace(0, 1, 11))
        decile = np.clip(np.searchsorted(edges, med_snr, side="right") - 1, 0, 9)
        shares = np.bincount(decile, weights=dev2, minlength=10) / dev2.sum()
        top = dev2 > np.quantile(dev2, 0.99)
        print(
            "      share of var(slope - R) by S/N decile (low to high): "
            + " ".join(f"{s:.3f}" for s in shares)
        )
        print(
            f"      the 1 % farthest galaxies: {dev2[top].sum() / dev2.sum():.2f} of it, "
            f"median S/N {np.median(med_snr[top]):.1f} (all: {np.median(med_snr):.1f})"
        )


def average(out_path: str, paths: list[str]) -> None:
    """Write the catalogs' rows with their estimates and responses averaged (see the module
    docstring) and print the rows' correlations between the first two."""
    tables = [read(p) for p in paths]
    first = tables[0]
    for p, t in zip(paths[1:], tables[1:]):
        if not (
            np.array_equal(t["case"], first["case"]) and np.array_equal(t["rea"], first["rea"])
        ):
            sys.exit(f"{p}: not the rows of {paths[0]} (case, rea differ)")
    flags = np.max([t["flags_noshear"] for t in tables], axis=0)
    ok = flags == 0
    for i in (1, 2):
        for kind in ("r", "g"):
            a, b = tables[0][f"{kind}{i}"], tables[1][f"{kind}{i}"]
            both = ok & np.isfinite(a) & np.isfinite(b)
            what = f"mcal_r{i}{i}" if kind == "r" else f"pre_g{i}_noshear"
            print(
                f"{what}: correlation of a row's value between the first two catalogs "
                f"{np.corrcoef(a[both], b[both])[0, 1]:.3f} ({both.sum()} rows)"
            )
    columns = [fits.Column(name=n, format="K", array=first[n]) for n in ("case", "rea")]
    columns += [fits.Column(name=n, format="D", array=first[n]) for n in ("tru_g1", "tru_g2")]
    columns += [
        fits.Column(name="flags_noshear", format="K", array=flags),
        fits.Column(name="snr_noshear", format="D", array=first["snr_noshear"]),
    ]
    for i in (1, 2):
        for kind, name in (("g", f"pre_g{i}_noshear"), ("r", f"mcal_r{i}{i}")):
            mean = np.mean([t[f"{kind}{i}"] for t in tables], axis=0)
            columns.append(fits.Column(name=name, format="D", array=mean))
    fits.BinTableHDU.from_columns(columns).writeto(out_path)
    report(out_path)


def main(args: list[str]) -> None:
    if not args:
        sys.exit(__doc__.split("\n\n")[-1].strip())
    if args[0] == "--average":
        if len(args) < 4:
            sys.exit("--average needs OUT.fits and at least two catalogs")
        average(args[1], args[2:])
        return
    for path in args:
        report(path)


if __name__ == "__main__":
    main(sys.argv[1:])
