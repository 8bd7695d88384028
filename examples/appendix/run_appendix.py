"""The inverse regression of the paper's Appendix A, at the paper's size, through megalut.

theta ~ U(0.25, 2), d = sqrt(1 + theta^2) + n, n ~ N(0, 0.1): an estimator of theta from
one noisy d. Three committees of networks with one hidden layer of 5 nodes are trained
with the generic engine (feature ``d``, target ``tru_theta``, prediction ``pre_theta``):

- MSE on the noisy training set (1000 cases x 1000 realizations),
- MSE on noise-free data ("trained on averages", one realization per case),
- MSB on the noisy training set.

Their bias <theta_hat> - theta is measured on validation cases (a grid of theta, 20 000
realizations each, noise drawn in +/- pairs) and plotted with the estimators themselves.

    python examples/appendix/run_appendix.py [--out examples/appendix] [-j 2]

Writes appendix_bias.png and results.json in --out (a few minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from megalut_cli.catalog import write_catalog
from megalut_cli.nn.fit import train_point
from megalut_cli.nn.model import ShearModel, prediction_column
from megalut_cli.nn.options import PointSpec
from megalut_cli.nn.toy import appendix_columns


def main() -> None:
    ap = argparse.ArgumentParser(description="Appendix A of Tewes et al. (2019) with megalut")
    ap.add_argument("--out", default=str(Path(__file__).parent))
    ap.add_argument("-j", "--nproc", type=int, default=1)
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--rea", type=int, default=1000)
    ap.add_argument("--members", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    theta = rng.uniform(0.25, 2.0, args.cases)
    noisy = appendix_columns(theta, args.rea, rng, antithetic=False)
    avg = appendix_columns(theta, 1, rng, sigma=0.0)
    grid = np.linspace(0.25, 2.0, 36)
    val = appendix_columns(grid, 20000, np.random.default_rng(args.seed + 1))
    results: dict[str, dict] = {}
    curves = {}
    dd = np.linspace(0.7, 2.5, 300)
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        write_catalog(t / "noisy.fits", noisy, fmt="megalut.toy")
        write_catalog(t / "avg.fits", avg, fmt="megalut.toy")
        runs = {
            "MSE": ("noisy.fits", "mse"),
            "trained on averages": ("avg.fits", "mse"),
            "MSB": ("noisy.fits", "msb"),
        }
        for label, (cat, cost) in runs.items():
            t0 = time.perf_counter()
            model_path = t / f"{cost}_{cat}.h5"
            spec = PointSpec(
                features=["d"],
                targets=["tru_theta"],
                hidden=[5],
                cost=cost,
                members=args.members,
                iterations=args.iterations,
                seed=args.seed,
            )
            train_point(t / cat, model_path, spec, nproc=args.nproc)
            comm = ShearModel.load(model_path).point["tru_theta"]
            pre = comm.predict(val["d"][:, None])  # the pre_theta column of `megalut predict`
            bias = pre.reshape(len(grid), -1).mean(axis=1) - grid
            err = pre.reshape(len(grid), -1).std(axis=1) / np.sqrt(20000) / np.sqrt(2)  # +/- pairs
            curves[label] = (comm.predict(dd[:, None]), bias, err)
            results[label] = {
                "column": prediction_column("tru_theta"),
                "max_abs_bias": float(np.abs(bias).max()),
                "bias_at_theta_0.25": float(bias[0]),
                "bias_at_theta_0.5": float(bias[np.argmin(np.abs(grid - 0.5))]),
                "bias_at_theta_2": float(bias[-1]),
                "max_abs_bias_theta_ge_0.3": float(np.abs(bias[grid >= 0.3]).max()),
                "train_seconds": round(time.perf_counter() - t0, 1),
            }
            print(label, json.dumps(results[label]), flush=True)
    settings = {k: v for k, v in vars(args).items() if k != "out"}
    (out / "results.json").write_text(
        json.dumps({"settings": settings, "results": results}, indent=2) + "\n"
    )
    _plot(out / "appendix_bias.png", noisy, dd, grid, curves)


def _plot(path: Path, noisy: dict, dd: np.ndarray, grid: np.ndarray, curves: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    sel = np.random.default_rng(0).choice(len(noisy["d"]), 400, replace=False)
    ax1.plot(
        noisy["d"][sel], noisy["tru_theta"][sel], ".", color="0.6", ms=3, label="training samples"
    )
    colors = {"MSE": "tab:green", "trained on averages": "tab:orange", "MSB": "tab:purple"}
    for label, (curve, bias, err) in curves.items():
        ax1.plot(dd, curve, color=colors[label], label=label)
        ax2.errorbar(grid, bias, yerr=err, fmt="o-", ms=3, color=colors[label], label=label)
    ax1.set_xlabel("observation d")
    ax1.set_ylabel(r"$\hat\theta$ (estimator) / true $\theta$ (samples)")
    ax1.set_xlim(0.7, 2.5)
    ax1.set_ylim(-0.5, 2.5)
    ax1.legend(loc="upper left", fontsize=8)
    ax2.axhline(0, color="k", lw=0.8)
    ax2.axhspan(-0.01, 0.01, color="0.9", label=r"$\pm 0.01$")
    ax2.set_xlabel(r"true $\theta$")
    ax2.set_ylabel(r"bias $\langle\hat\theta\rangle - \theta$")
    ax2.legend(fontsize=8)
    fig.suptitle(
        "Appendix A of Tewes et al. (2019) reproduced with megalut (1-5-1 networks, "
        "committees of 8)"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
