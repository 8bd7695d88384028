"""Where the CPU time of one ``megalut train-point`` member goes (issue 26; benchmarks/training.md).

Writes the catalogs of ``bench_training.py --cli`` (500 cases x 1000 realizations, seed 2;
validation 100 cases, seed 3) and runs, in fresh processes, the command it times
(``--targets tru_g1 --members 1 --valid vp.fits --seed 1 -j 1``; float32 with 60 iterations,
the default float64 with 72) through ``megalut_cli.cli.main`` in-process, with a timer
around the imports and around each function of the path (reading, cases, normalisation,
objectives, cost + gradient, validation passes, the optimiser, provenance, writing). Prints
the median CPU milliseconds of each part over ``--repeat`` processes. ``--tree DIR`` also
runs the command of another source tree (e.g. ``git archive 5126f68 | tar -x -C DIR``),
alternating with this one. Run from the repository root::

    PYTHONPATH=. python benchmarks/profile_train_point.py [--repeat 5] [--tree DIR]

The interpreter's own start (``python -c pass``, ~20 ms) is not in the timers.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

#: (precision option or None for the default, iterations): the benchmark's two commands.
COMMANDS = (("float32", 60), (None, 72))


class Timers:
    """CPU seconds and calls per part."""

    def __init__(self) -> None:
        self.parts: dict[str, list[float]] = {}

    def add(self, part: str, seconds: float) -> None:
        entry = self.parts.setdefault(part, [0.0, 0])
        entry[0] += seconds
        entry[1] += 1

    def wrap(self, owner: Any, name: str, part: str) -> None:
        """Replace ``owner.name`` by a timed call of it."""
        function: Callable[..., Any] = getattr(owner, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.add(part, time.process_time() - start)

        setattr(owner, name, timed)


def child(data: Path, precision: str | None, iterations: int) -> None:
    """One command in this process; prints ``{part: [cpu seconds, calls]}`` as JSON."""
    timers = Timers()
    start = time.process_time()
    import numpy  # noqa: F401

    timers.add("import numpy", time.process_time() - start)
    start = time.process_time()
    import megalut_cli.cli.train_point  # noqa: F401
    from megalut_cli.cli import main

    timers.add("import click, the command group, its options", time.process_time() - start)
    start = time.process_time()
    from megalut_cli.nn import fit, model, train

    timers.add("import the training modules", time.process_time() - start)
    start = time.process_time()
    import scipy.optimize  # what train_member imports where it is used

    timers.add("import scipy's BFGS", time.process_time() - start)
    timers.wrap(scipy.optimize, "minimize", "optimiser (with its evaluations)")
    timers.wrap(fit, "training_columns", "opening the catalogs")
    timers.wrap(fit, "_load_cases", "reading, cases, domain")
    timers.wrap(fit.norm, "fit", "normalisation")
    timers.wrap(train, "normalised_columns", "objectives (normalised, transposed)")
    timers.wrap(train.Objective, "batch", "mini-batches")
    timers.wrap(train.Objective, "value_and_grad", "cost + gradient")
    timers.wrap(train.Objective, "value", "validation passes, final training cost")
    timers.wrap(fit, "_run", "training (all)")
    timers.wrap(fit, "software_versions", "provenance: versions")
    timers.wrap(fit, "_input", "provenance: sha256 of the inputs")
    timers.wrap(model.ShearModel, "save", "writing the model")
    args = ["train-point", str(data / "tp.fits"), "-o", str(data / "m.h5"), "--overwrite"]
    args += ["--targets", "tru_g1", "--members", "1", "--valid", str(data / "vp.fits")]
    args += ["--iterations", str(iterations), "--seed", "1", "-j", "1"]
    if precision:
        args += ["--precision", precision]
    start = time.process_time()
    main.main(args, standalone_mode=False)
    timers.add("the command (all)", time.process_time() - start)
    print(json.dumps(timers.parts))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="processes per command")
    parser.add_argument(
        "--tree", action="append", metavar="DIR", help="another source tree (repeatable)"
    )
    parser.add_argument("--child", nargs=3, metavar=("DATA", "PRECISION", "ITERATIONS"))
    args = parser.parse_args()
    if args.child:
        data, precision, iterations = args.child
        child(Path(data), None if precision == "default" else precision, int(iterations))
        return
    from megalut_cli.catalog import write_catalog
    from megalut_cli.nn.toy import shear_like_columns

    here = str(Path(__file__).resolve().parent.parent)
    trees = [here] + [str(Path(t).resolve()) for t in args.tree or []]
    runs: dict[tuple[str, str | None], list[dict[str, list[float]]]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        write_catalog(data / "tp.fits", shear_like_columns(500, 1000, 2), fmt="megalut.toy")
        write_catalog(data / "vp.fits", shear_like_columns(100, 1000, 3), fmt="megalut.toy")
        for _ in range(args.repeat):  # trees and commands alternate
            for tree in trees:
                for precision, iterations in COMMANDS:
                    done = subprocess.run(
                        [sys.executable, __file__, "--child", tmp, precision or "default"]
                        + [str(iterations)],
                        env=dict(os.environ, PYTHONPATH=tree),
                        cwd=tree,
                        capture_output=True,
                        text=True,
                        check=True,
                    )
                    parts = json.loads(done.stdout.strip().splitlines()[-1])
                    runs.setdefault((tree, precision), []).append(parts)
    for (tree, precision), found in runs.items():
        iterations = dict(COMMANDS)[precision]
        print(
            f"{precision or 'float64 (default)'}, {iterations} iterations, {tree} "
            f"(CPU ms, medians of {args.repeat} processes; calls)"
        )
        for part in found[0]:
            ms = statistics.median(r[part][0] * 1e3 for r in found if part in r)
            print(f"  {part:46s} {ms:8.1f}  x{int(found[0][part][1])}")


if __name__ == "__main__":
    main()
