"""Throughput of ``megalut predict``: the network part and the whole command, side by side.

An 8-member committee of 5-5-1 networks (5 features, two hidden layers of 5 tanh nodes)
for each of g1 and g2, as in the paper (Sect. 5.3). Measured on ONE core (BLAS limited to
one thread before numpy is imported):

* ``network``: ``Committee.predict`` for both components on an in-memory feature matrix;
* ``predict_arrays``: the same plus failed-row masking and flag handling;
* ``end-to-end``: ``predict_catalog`` on a FITS catalog (read in chunks, predict, append
  to the output FITS, rename), serial.

Rates are rows per second, each row getting both components. Run::

    python benchmarks/bench_predict.py [--rows 2000000] [--repeat 3]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import fitsio  # noqa: E402
import numpy as np  # noqa: E402

from megalut_cli.catalog import iter_catalog, write_catalog  # noqa: E402
from megalut_cli.nn.model import Committee, Member, ShearModel  # noqa: E402
from megalut_cli.shear.predict import predict_arrays, predict_catalog  # noqa: E402

FEATURES = ["adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4"]


def committee(
    target: str, seed: int, n_members: int = 8, hidden: tuple[int, ...] = (5, 5)
) -> Committee:
    rng = np.random.default_rng(seed)
    sizes = [len(FEATURES), *hidden, 1]
    members = [
        Member(
            layers=[
                (rng.normal(0, 0.5, (i, o)), rng.normal(0, 0.1, o))
                for i, o in zip(sizes[:-1], sizes[1:])
            ]
        )
        for _ in range(n_members)
    ]
    return Committee("point", target, FEATURES, hidden, np.zeros(5), np.ones(5), members)


def best_of(func, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        func()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--chunk-rows", type=int, default=250_000)
    args = ap.parse_args()
    n = args.rows
    rng = np.random.default_rng(0)
    x = np.column_stack(
        [
            rng.normal(0, 0.3, n),
            rng.normal(0, 0.3, n),
            rng.uniform(1, 5, n),
            rng.uniform(10, 1000, n),
            rng.uniform(1.8, 2.5, n),
        ]
    )
    model = ShearModel({t: committee(t, i) for i, t in enumerate(("tru_g1", "tru_g2"))})
    model.sha256 = "benchmark"
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, "
        f"numpy {np.__version__}, 1 BLAS thread, {n} rows, best of {args.repeat}"
    )

    def network() -> None:
        for c in model.point.values():
            c.predict(x)

    t_net = best_of(network, args.repeat)
    t_arr = best_of(lambda: predict_arrays(model, x), args.repeat)
    print(f"network (Committee.predict x2)   {n / t_net:12.3e} rows/s  ({t_net:.3f} s)")
    print(f"predict_arrays (masking, flags)  {n / t_arr:12.3e} rows/s  ({t_arr:.3f} s)")

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        model_path = tmp / "model.h5"
        model.save(model_path)
        src = tmp / "features.fits"
        cols = {
            "case": np.arange(n) // 100,
            **{f: x[:, i] for i, f in enumerate(FEATURES)},
            "flags": np.zeros(n, dtype=np.int32),
        }
        write_catalog(src, cols, fmt="megalut.features")
        out = tmp / "shears.fits"

        def end_to_end() -> None:
            predict_catalog(src, model_path, out, overwrite=True, chunk_rows=args.chunk_rows)

        t_e2e = best_of(end_to_end, args.repeat)
        size = src.stat().st_size + out.stat().st_size

        def read_only() -> None:
            for _ in iter_catalog(src, args.chunk_rows):
                pass

        t_read = best_of(read_only, args.repeat)
        shears = fitsio.read(out)
        t_write = best_of(
            lambda: fitsio.write(str(tmp / "w.fits"), shears, clobber=True), args.repeat
        )
    print(
        f"end-to-end predict_catalog       {n / t_e2e:12.3e} rows/s  ({t_e2e:.3f} s, "
        f"{size / 1e6:.0f} MB read+written, chunks of {args.chunk_rows})"
    )
    print(
        f"  of which: network {t_net:.3f} s ({t_net / t_e2e:.0%}), reading the input in chunks "
        f"{t_read:.3f} s ({t_read / t_e2e:.0%}), fitsio writing the output {t_write:.3f} s "
        f"({t_write / t_e2e:.0%})"
    )


if __name__ == "__main__":
    main()
