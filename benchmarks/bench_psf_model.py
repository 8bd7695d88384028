"""Cost of one PSF of a PSF model (``measure --psf-model``), side by side in one run.

On the real DECam PSFEx model of ``tests/data`` at random positions over its chip:

* ``psfex``: :meth:`megalut_cli.measure.psf_model.PsfModel.draw` (basis resampled once per
  stamp size, one polynomial combination per position, vectorised);
* ``galsim``: ``DES_PSFEx.getPSF(pos).drawImage(method='no_pixel')``, one object per position
  (what the vectorised drawing reproduces);
* ``hsm``: measuring the drawn PSF stamp (``measure_stamps``, fast engine), for scale;
* ``piff``: ``PsfModel.draw`` of a Piff model, with ``--piff FILE`` (one ``PSF.draw`` per position).

Best of ``--repeat`` wall-clock times per PSF, one process (the machine may be busy). Run::

    PYTHONPATH=. python benchmarks/bench_psf_model.py [--n 2000] [--size 48] [--piff MODEL.piff]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

DECAM = Path(__file__).resolve().parents[1] / "tests" / "data" / "DECam_00154912_12_psfcat.psf"


def best(f: Callable[[], object], repeat: int) -> float:
    """The shortest of ``repeat`` wall-clock times of ``f()`` (seconds)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    import galsim
    import galsim.des

    from megalut_cli.measure.features import measure_stamps
    from megalut_cli.measure.psf_model import load_psf_model

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="positions (GalSim and Piff: min(n, 300))")
    ap.add_argument("--size", type=int, default=48, help="stamp size in pixels")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--piff", default=None, help="a single-chip Piff model to time as well")
    args = ap.parse_args()
    n, size, k = args.n, args.size, min(args.n, 300)
    rng = np.random.default_rng(1)
    x, y = rng.uniform(1, 2048, n), rng.uniform(1, 4096, n)
    model = load_psf_model(DECAM)
    model.draw(x[:10], y[:10], size)  # the basis resampled for this size
    ref = galsim.des.DES_PSFEx(str(DECAM))
    stamps = model.draw(x, y, size)
    measure_stamps(stamps[:10])  # compiled
    rows = {
        "psfex": best(lambda: model.draw(x, y, size), args.repeat) / n,
        "galsim": best(
            lambda: [
                ref.getPSF(galsim.PositionD(x[i], y[i])).drawImage(
                    nx=size, ny=size, scale=1.0, method="no_pixel"
                )
                for i in range(k)
            ],
            args.repeat,
        )
        / k,
        "hsm": best(lambda: measure_stamps(stamps), args.repeat) / n,
    }
    if args.piff:
        piff = load_psf_model(args.piff)
        x0, x1, y0, y1 = piff.bounds or (1.0, 1000.0, 1.0, 1000.0)
        px, py = rng.uniform(x0, x1, k), rng.uniform(y0, y1, k)
        piff.draw(px[:3], py[:3], size)
        rows["piff"] = best(lambda: piff.draw(px, py, size), args.repeat) / k
    print(f"{size}-px PSF stamps, best of {args.repeat}, microseconds per PSF:")
    for name, seconds in rows.items():
        print(f"  {name:7s} {seconds * 1e6:8.0f}")


if __name__ == "__main__":
    main()
