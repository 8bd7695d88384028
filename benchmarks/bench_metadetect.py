"""Cost of metadetection per detected object, where it goes, and memory on a large coadd.

One core (BLAS and numba on one thread), CPU seconds, on the scenes of
``examples/scenes/metadetect.toml`` (250-px cells, about 17 galaxies each):

* per cell, in this process, for the cell engine (the default, :mod:`megalut_cli.measure.
  cell_metacal`) and GalSim's reference (``--engine galsim``) on the same cells: the metacal
  operation on the cell with its fixnoise (the white field moved with each version; for
  GalSim apart), sep's detection on the five versions, the features of the stamps around
  the detections; and the networks (``predict`` with ``fiducial-metacal``) per row;
* coadds of ``--coadd-sizes`` pixels (the scenes' galaxies at the same density, written as
  one image with its weight map) measured with ``-j 2``: the peak memory of the command and
  of its workers, against the image's size;
* with ``--psf-model-size N``, a coadd of N pixels measured with ``-j 1`` with one PSF image
  (``--psf``) and with the PSFEx model of ``tests/data`` drawn at each cell's centre
  (``--psf-model``), alternated ``--repeat`` times: CPU per cell and per detection of each,
  with each tree of ``--trees`` (default this one; e.g. an export of an earlier commit).

Run::

    PYTHONPATH=. python benchmarks/bench_metadetect.py [--cells 20] [--coadd-sizes 1000 3000]
    PYTHONPATH=. python benchmarks/bench_metadetect.py --cells 0 --coadd-sizes \
        --psf-model-size 1500 --repeat 3 --trees . /tmp/before
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import fitsio  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "examples" / "scenes" / "metadetect.toml"


def run(args: list[str]) -> None:
    subprocess.run([sys.executable, "-m", "megalut_cli", *args], check=True, cwd=ROOT)


def cells_profile(path: Path, n: int, engine: str) -> dict[str, float]:
    """CPU per cell of each stage of :func:`metadetect_cell` with ``engine`` (stages timed
    by wrapping; ``operation`` holds ``fixnoise``)."""
    from megalut_cli.measure import cell_detect, cell_fixnoise, cells
    from megalut_cli.measure.measurer import Measurer, MeasureSettings, MetacalSettings
    from megalut_cli.measure.source_registry import DetectSettings

    spent = {"operation": 0.0, "fixnoise": 0.0, "detection": 0.0, "features": 0.0}

    def timed(fn, key):
        def wrapper(*a, **k):
            t = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                spent[key] += time.process_time() - t

        return wrapper

    originals = (
        cell_detect.detect,
        Measurer.measure,
        cell_detect.cell_operation,
        cell_fixnoise.moving_fixnoise,
    )
    cell_fixnoise.moving_fixnoise = timed(cell_fixnoise.moving_fixnoise, "fixnoise")
    cell_detect.detect = timed(cell_detect.detect, "detection")
    Measurer.measure = timed(Measurer.measure, "features")
    cell_detect.cell_operation = timed(cell_detect.cell_operation, "operation")
    settings = MeasureSettings(engine=engine, metacal=MetacalSettings(0.01, 1))
    detection = DetectSettings(5.0, 4, 32, 0.005)
    cell = cells.read_cell(str(path), 0)
    cell_detect.metadetect_cell(  # first call: caches, numba
        cell["image"],
        cell["psf"],
        cell_detect.CellNoise(1.0, 0),
        settings,
        detection,
        48,
        cell["bad"],
    )
    spent.update({k: 0.0 for k in spent})
    rows, t0 = 0, time.process_time()
    for i in range(1, n + 1):
        cell = cells.read_cell(str(path), i)
        noise = cell_detect.cell_noise(cell["weight"], cell["bad"])
        out = cell_detect.metadetect_cell(
            cell["image"],
            cell["psf"],
            cell_detect.CellNoise(noise, i),
            settings,
            detection,
            48,
            cell["bad"],
        )
        rows += len(out["x"])
    total = time.process_time() - t0
    (
        cell_detect.detect,
        Measurer.measure,
        cell_detect.cell_operation,
        cell_fixnoise.moving_fixnoise,
    ) = originals
    return {"cells": n, "rows": rows, "total": total, **spent}


def predict_per_row(det: Path, tmp: Path) -> float:
    """CPU per row of ``predict --model fiducial-metacal`` (fixed start-up removed: two
    sizes)."""
    times = []
    rows = fitsio.read(str(det))
    for k, n in enumerate((len(rows) // 4, len(rows))):
        part = tmp / f"part{k}.fits"
        fitsio.write(str(part), rows[:n], header=fitsio.read_header(str(det), 1), clobber=True)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        run(
            [
                "predict",
                str(part),
                "--model",
                "fiducial-metacal",
                "-o",
                str(tmp / "p.fits"),
                "--overwrite",
                "-q",
            ]
        )
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        times.append((after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, n))
    (t0, n0), (t1, n1) = times
    return (t1 - t0) / (n1 - n0)


def write_coadd(size: int, tmp: Path, header: dict | None = None) -> int:
    """One unpaired scene field of ``size`` pixels written as a coadd: ``img.fits``,
    ``wgt.fits`` (with ``header``) and its PSF image ``psf.fits`` in ``tmp``; the image's
    bytes."""
    scenes = tmp / "big.fits"
    run(
        [
            "simulate",
            str(CONFIG),
            "-o",
            str(tmp / "bt.fits"),
            "--scene",
            str(scenes),
            "scene.n_fields=1",
            "scene.pairs=false",
            f"scene.size={size}",
            "--overwrite",
            "-q",
        ]
    )
    sci = fitsio.read(str(scenes), ext="SCI")[0]
    fitsio.write(str(tmp / "img.fits"), sci, header=header, clobber=True)
    wgt = fitsio.read(str(scenes), ext="WGT")[0]
    fitsio.write(str(tmp / "wgt.fits"), wgt, header=header, clobber=True)
    fitsio.write(str(tmp / "psf.fits"), fitsio.read(str(scenes), ext="PSF")[0], clobber=True)
    return sci.nbytes


def coadd_memory(size: int, tmp: Path) -> dict[str, float]:
    """Peak RSS (MB) of ``measure --metadetect`` on a coadd of ``size`` pixels with -j 2."""
    image_bytes = write_coadd(size, tmp)
    cmd = [
        "/usr/bin/time",
        "-v",
        sys.executable,
        "-m",
        "megalut_cli",
        "measure",
        str(tmp / "img.fits"),
        "--weight",
        str(tmp / "wgt.fits"),
        "--psf",
        str(tmp / "psf.fits"),
        "--metadetect",
        "-o",
        str(tmp / "bdet.fits"),
        "-j",
        "2",
        "--overwrite",
        "-q",
    ]
    t = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t
    peak = next(
        float(line.split(":")[1]) / 1024.0
        for line in res.stderr.splitlines()
        if "Maximum resident set size" in line
    )
    return {
        "image_mb": image_bytes * 3 / 1e6,
        "peak_mb": peak,
        "wall": wall,
        "rows": len(fitsio.read(str(tmp / "bdet.fits"), columns=["x"])),
    }


def cell_costs(tmp: Path, n_cells: int) -> None:
    """The cell route's stages per detected object with both engines, and the networks'
    cost per row, on ``n_cells`` cells of the scenes."""
    scenes = tmp / "scenes.fits"
    run(
        [
            "simulate",
            str(CONFIG),
            "-o",
            str(tmp / "t.fits"),
            "--scene",
            str(scenes),
            f"scene.n_fields={(n_cells + 2) // 2}",
            "--overwrite",
            "-q",
        ]
    )
    for engine in ("fast", "galsim"):
        p = cells_profile(scenes, n_cells, engine)
        objects = p["rows"] / 5.0
        print(
            f"engine {engine}: {p['cells']} cells, {p['rows']} rows ({objects:.0f} objects "
            f"x 5 versions); CPU per detected object, whole cell route: "
            f"{1e3 * p['total'] / objects:.2f} ms"
        )
        for k in ("operation", "fixnoise", "detection", "features"):
            share = 100 * p[k] / p["total"]
            print(f"  {k:10s} {1e3 * p[k] / objects:6.2f} ms  ({share:.0f} %)")
    det = tmp / "det.fits"
    run(["measure", str(scenes), "--metadetect", "-o", str(det), "-j", "1", "-q"])
    per_row = predict_per_row(det, tmp)
    print(
        f"predict (fiducial-metacal), per row: {1e3 * per_row:.3f} ms; per object "
        f"(5 rows): {5e3 * per_row:.2f} ms"
    )


def psf_model_coadd(size: int, tmp: Path, trees: list[Path], repeat: int) -> None:
    """CPU of ``measure --metadetect -j 1`` on a coadd of ``size`` pixels with one PSF image
    and with a PSFEx model, each tree in turn, ``repeat`` times; prints the medians."""
    scale = 0.263 / 3600.0  # the PSFEx model's native pixel scale (DECam), in degrees
    header = {"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "CRVAL1": 150.0, "CRVAL2": 2.0}
    header.update({"CRPIX1": size / 2, "CRPIX2": size / 2, "CD1_1": -scale, "CD2_2": scale})
    header.update({"CD1_2": 0.0, "CD2_1": 0.0})
    write_coadd(size, tmp, header)
    model = ROOT / "tests" / "data" / "DECam_00154912_12_psfcat.psf"
    spent: dict[tuple[str, str], list[float]] = {}
    rows = {}
    for _ in range(repeat):
        for tree in trees:
            for label, psf in (
                ("--psf", ["--psf", str(tmp / "psf.fits")]),
                ("--psf-model", ["--psf-model", str(model)]),
            ):
                args = [
                    "measure",
                    str(tmp / "img.fits"),
                    "--weight",
                    str(tmp / "wgt.fits"),
                    *psf,
                    "--metadetect",
                    "-o",
                    str(tmp / "pdet.fits"),
                    "-j",
                    "1",
                    "--overwrite",
                    "-q",
                ]
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                subprocess.run(
                    [sys.executable, "-m", "megalut_cli", *args],
                    check=True,
                    cwd=tree,
                    env={**os.environ, "PYTHONPATH": str(tree)},
                )
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
                spent.setdefault((str(tree), label), []).append(cpu)
                rows[label] = len(fitsio.read(str(tmp / "pdet.fits"), columns=["x"]))
    cells = int(fitsio.read_header(str(tmp / "pdet.fits"), 1).get("NCELLS", 0)) or None
    for (tree, label), times in spent.items():
        med = statistics.median(times)
        per = f", {1e3 * med / cells:.1f} ms per cell" if cells else ""
        print(
            f"coadd {size}^2, {label:12s} tree {tree}: CPU median {med:.2f} s (of "
            f"{', '.join(f'{t:.2f}' for t in times)}){per}, {rows[label]} rows, "
            f"{5e3 * med / rows[label]:.2f} ms per detection"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20)
    parser.add_argument("--coadd-sizes", type=int, nargs="*", default=[1000, 3000])
    parser.add_argument("--psf-model-size", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--trees", type=Path, nargs="+", default=[ROOT])
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if args.cells:
            cell_costs(tmp, args.cells)
        if args.psf_model_size:
            psf_model_coadd(
                args.psf_model_size, tmp, [t.resolve() for t in args.trees], args.repeat
            )
        for size in args.coadd_sizes:
            m = coadd_memory(size, tmp)
            print(
                f"coadd {size}^2 px (image, weight, PSF: {m['image_mb']:.0f} MB as float32): "
                f"peak RSS {m['peak_mb']:.0f} MB with -j 2, {m['rows']} rows, "
                f"{m['wall']:.0f} s wall"
            )


if __name__ == "__main__":
    main()
