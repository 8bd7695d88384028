"""Detection with sep (as megalut calls it) against photutils, on scenes with truth.

    megalut simulate examples/scenes/metadetect.toml -o truth.fits --scene scenes.fits \\
        scene.n_fields=50 scene.pairs=false --seed 11 -j 1
    python examples/metadetect/detectors.py scenes.fits truth.fits [--images N]
        [--match-radius 1.5] [--detect-thresh 5] [--detect-minarea 4] [--deblend-nthresh 32]
        [--deblend-cont 0.005] [--noise-cells 50] [--repeats 3] [--json OUT.json]

The images are the scene's cells as they are (``SCI``, bad pixels of ``WGT``/``MSK`` set to 0
and masked, as ``measure --detect`` sees them; no metacal version), the noise of each cell
``1 / sqrt(median WGT)`` (megalut's ``cell_noise``). Every detector gets the same settings
(megalut's ``--metadetect`` defaults unless given):

- sep (megalut's call): megalut's own ``megalut_cli.measure.cell_detect.detect`` (``sep.extract``
  with ``err`` = the noise, sep's default 3x3 kernel, ``minarea``, ``deblend_nthresh``,
  ``deblend_cont``, sep's cleaning on by default), positions sep's barycentres ``x``, ``y``.
- sep, cleaning off: the same call replicated here with ``clean=False`` (what makes sep's
  footprints differ from photutils', which has no cleaning step).
- photutils: the cell convolved with the same normalized 3x3 kernel [[1,2,1],[2,4,2],[1,2,1]]
  (zero outside the cell, as sep), ``detect_threshold`` (thresh x noise, background 0),
  ``detect_sources`` (``n_pixels`` = minarea, 8-connected), ``deblend_sources`` (``n_levels`` =
  nthresh, ``contrast`` = cont, exponential levels, as Source Extractor), positions the
  ``SourceCatalog`` centroids on the convolved cell (sep's barycentres are those of the
  filtered pixels too). Not megalut dependencies: ``pip install photutils scikit-image``
(photutils' deblending needs scikit-image).

Per detector (truth positions are FITS 1-based, detections 0-based + 1): completeness (truth
galaxies matched one-to-one, nearest first, within --match-radius px), unmatched detections
per cell (spurious or a blend's merged or misplaced detection), false detections per cell on
--noise-cells pure white-noise cells of the scene's noise, close truth pairs (two galaxies of
one cell closer than the sum of their half-light radii, ``tru_rad``, i.e. two radii for
equal sizes; and in bins of pixel separation) resolved: both matched (strict), or each
one's nearest detection within max(separation, match radius) and the two distinct (two
detections); the rms of the matched positions' offsets (radial, px) on every match and on the
galaxies every detector matches; the CPU time per cell (``time.process_time`` of the whole set
of cells, best of --repeats, one thread). A check of the settings: the footprints (the union of
sep's segmentation map, against photutils' ``detect_sources`` before deblending) are
compared pixel by pixel, sep's cleaning on and off.
"""

from __future__ import annotations

import os

for _v in (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from types import ModuleType  # noqa: E402

import fitsio  # noqa: E402
import numpy as np  # noqa: E402
import sep  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from megalut_cli.measure.cell_detect import cell_noise, cleaned_cell, detect  # noqa: E402
from megalut_cli.measure.cells import read_cell  # noqa: E402
from megalut_cli.measure.defaults import (  # noqa: E402
    DEBLEND_CONT,
    DEBLEND_NTHRESH,
    DETECT_MINAREA,
    DETECT_THRESH,
)
from megalut_cli.measure.source_registry import DetectSettings  # noqa: E402

#: sep's default filter (Source Extractor's default.conv), normalized as sep applies it.
KERNEL = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]]) / 16.0
PAIR_BINS = (0.0, 4.0, 8.0, 12.0, 16.0)  # pixel separations of the close-pair bins

Cell = tuple[np.ndarray, float, np.ndarray]  # image (bad pixels 0), noise sigma, bad mask
Detector = Callable[[np.ndarray, float, DetectSettings, np.ndarray], np.ndarray]


def photutils_module() -> ModuleType:
    """photutils, imported lazily (with scikit-image, which its deblending needs); one line
    and exit 1 when either is not installed."""
    try:
        import photutils
        import photutils.segmentation  # noqa: F401
        import skimage.segmentation  # noqa: F401
    except ImportError as e:
        sys.exit(f"detectors.py: {e.name} is missing: pip install photutils scikit-image")
    from photutils.utils.exceptions import NoDetectionsWarning

    warnings.simplefilter("ignore", NoDetectionsWarning)  # an empty pure-noise cell
    return photutils


def sep_positions(
    image: np.ndarray, noise: float, settings: DetectSettings, bad: np.ndarray
) -> np.ndarray:
    """megalut's detection (sep) of one cell: the 0-based positions, shape (n, 2)."""
    found = detect(image, noise, settings, bad)
    return np.c_[found.x, found.y]


def photutils_segments(
    image: np.ndarray, noise: float, settings: DetectSettings, bad: np.ndarray
) -> tuple[np.ndarray, object]:
    """photutils' footprints of one cell before deblending: the convolved cell and the
    segmentation image (None when nothing is detected)."""
    from astropy.convolution import convolve
    from photutils.segmentation import detect_sources, detect_threshold

    conv = convolve(image, KERNEL, boundary="fill", fill_value=0.0, normalize_kernel=False)
    mask = bad if bad.any() else None
    threshold = detect_threshold(image, settings.thresh, background=0.0, error=noise, mask=mask)
    segm = detect_sources(conv, threshold, settings.minarea, connectivity=8, mask=mask)
    return conv, segm


def photutils_positions(
    image: np.ndarray, noise: float, settings: DetectSettings, bad: np.ndarray
) -> np.ndarray:
    """photutils' detection of one cell (footprints, deblending, centroids on the convolved
    cell): the 0-based positions, shape (n, 2)."""
    conv, segm = photutils_segments(image, noise, settings, bad)
    if segm is None:
        return np.zeros((0, 2))
    return photutils_centroids(image, conv, photutils_deblend(conv, segm, settings), bad)


def photutils_deblend(conv: np.ndarray, segm: object, settings: DetectSettings) -> object:
    """photutils' deblending of the footprints ``segm`` of the convolved cell ``conv``."""
    from photutils.segmentation import deblend_sources

    return deblend_sources(
        conv,
        segm,
        settings.minarea,
        n_levels=settings.nthresh,
        contrast=settings.cont,
        mode="exponential",
        connectivity=8,
        progress_bar=False,
    )


def photutils_centroids(
    image: np.ndarray, conv: np.ndarray, segm: object, bad: np.ndarray
) -> np.ndarray:
    """The ``SourceCatalog`` centroids (on the convolved cell) of the sources ``segm``."""
    from photutils.segmentation import SourceCatalog

    cat = SourceCatalog(image, segm, convolved_data=conv, mask=bad if bad.any() else None)
    return np.c_[np.asarray(cat.x_centroid, float), np.asarray(cat.y_centroid, float)]


def sep_extract(
    image: np.ndarray, noise: float, settings: DetectSettings, bad: np.ndarray, clean: bool
) -> tuple[np.ndarray, np.ndarray]:
    """megalut's ``sep.extract`` call (``cell_detect.detect``) replicated, with sep's cleaning on
    or off: its objects and segmentation map."""
    return sep.extract(
        np.ascontiguousarray(image, dtype=np.float64),
        settings.thresh,
        err=noise,
        mask=np.ascontiguousarray(bad, dtype=np.uint8) if bad.any() else None,
        minarea=settings.minarea,
        deblend_nthresh=settings.nthresh,
        deblend_cont=settings.cont,
        clean=clean,
        segmentation_map=True,
    )


def sep_noclean_positions(
    image: np.ndarray, noise: float, settings: DetectSettings, bad: np.ndarray
) -> np.ndarray:
    """sep as megalut calls it but with its cleaning off: the 0-based positions (n, 2)."""
    objects, _ = sep_extract(image, noise, settings, bad, clean=False)
    return np.c_[objects["x"], objects["y"]]


def read_cells(path: str, n: int | None) -> tuple[list[Cell], np.ndarray]:
    """The first ``n`` (None: all) cells of a scenes file as megalut reads them, and their
    image indices."""
    with fitsio.FITS(path) as f:
        n_all = f["SCI"].get_dims()[0]
    index = np.arange(n_all if n is None else min(n, n_all))
    cells = []
    for i in index:
        c = read_cell(path, int(i))
        image, bad = cleaned_cell(c["image"], c["bad"])
        cells.append((image, cell_noise(c["weight"], bad), bad))
    return cells, index


def match(truth: np.ndarray, det: np.ndarray, radius: float) -> np.ndarray:
    """One-to-one matching, nearest pairs first, within ``radius``: for each truth position
    the index of its detection, else -1."""
    out = np.full(len(truth), -1)
    if len(truth) == 0 or len(det) == 0:
        return out
    dist = cKDTree(truth).sparse_distance_matrix(cKDTree(det), radius, output_type="ndarray")
    used = np.zeros(len(det), bool)
    for k in np.argsort(dist["v"], kind="stable"):
        i, j = dist["i"][k], dist["j"][k]
        if out[i] < 0 and not used[j]:
            out[i], used[j] = j, True
    return out


def close_pairs(pos: np.ndarray, rad: np.ndarray, max_sep: float) -> tuple[np.ndarray, ...]:
    """Truth pairs of one cell closer than ``max_sep`` px: indices ``i``, ``j``, their
    separation and whether it is below the sum of their half-light radii."""
    pairs = np.array(sorted(cKDTree(pos).query_pairs(max_sep)), dtype=np.int64).reshape(-1, 2)
    i, j = pairs[:, 0], pairs[:, 1]
    sep_px = np.hypot(*(pos[i] - pos[j]).T)
    return i, j, sep_px, sep_px < rad[i] + rad[j]


def evaluate(
    name: str,
    positions: list[np.ndarray],
    truth: dict[int, np.ndarray],
    rads: dict[int, np.ndarray],
    radius: float,
) -> dict:
    """The detection counts of one detector on every cell against the truth."""
    n_truth = n_det = n_match = 0
    offsets, matched_ids = [], []
    pairs: list[tuple[float, bool, bool, bool]] = []  # separation, 2-hlr pair, strict, two
    max_sep = max(PAIR_BINS[-1], 2.0 * max(float(r.max()) for r in rads.values() if len(r)))
    for cell, det in enumerate(positions):
        tru = truth.get(cell, np.zeros((0, 2)))
        m = match(tru, det, radius)
        n_truth, n_det, n_match = n_truth + len(tru), n_det + len(det), n_match + (m >= 0).sum()
        off = det[m[m >= 0]] - tru[m >= 0]
        offsets.append(off)
        matched_ids.append(np.c_[np.full((m >= 0).sum(), cell), np.flatnonzero(m >= 0)])
        if len(tru) < 2:
            continue
        i, j, sep_px, by_rad = close_pairs(tru, rads[cell], max_sep)
        if len(det):
            dist, near = cKDTree(det).query(tru)
        else:
            dist, near = np.full(len(tru), np.inf), np.full(len(tru), -1)
        for a, b, s, r in zip(i, j, sep_px, by_rad):
            lim = max(s, radius)
            two = dist[a] <= lim and dist[b] <= lim and near[a] != near[b]
            pairs.append((float(s), bool(r), bool(m[a] >= 0 and m[b] >= 0), bool(two)))
    off = np.concatenate(offsets) if offsets else np.zeros((0, 2))
    return {
        "name": name,
        "n_truth": int(n_truth),
        "n_det": int(n_det),
        "n_match": int(n_match),
        "offsets": off,
        "matched": np.concatenate(matched_ids) if matched_ids else np.zeros((0, 2), int),
        "pairs": np.array(pairs, dtype=float).reshape(-1, 4),
    }


def cpu_per_cell(fn: Detector, cells: list[Cell], settings: DetectSettings, repeats: int) -> float:
    """CPU seconds per cell of ``fn`` over all ``cells``: the best of ``repeats`` passes."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.process_time()
        for image, noise, bad in cells:
            fn(image, noise, settings, bad)
        best = min(best, time.process_time() - t0)
    return best / len(cells)


def photutils_stages(cells: list[Cell], settings: DetectSettings, repeats: int) -> list[float]:
    """CPU seconds per cell of photutils' three stages (footprints: convolution, threshold,
    detect_sources; deblend_sources; SourceCatalog centroids), best of ``repeats``."""
    best = [np.inf] * 3
    for _ in range(repeats):
        spent = [0.0] * 3
        for image, noise, bad in cells:
            t0 = time.process_time()
            conv, segm = photutils_segments(image, noise, settings, bad)
            t1 = time.process_time()
            spent[0] += t1 - t0
            if segm is None:
                continue
            segm = photutils_deblend(conv, segm, settings)
            t2 = time.process_time()
            photutils_centroids(image, conv, segm, bad)
            spent[1] += t2 - t1
            spent[2] += time.process_time() - t2
        best = [min(b, t) for b, t in zip(best, spent)]
    return [b / len(cells) for b in best]


def fraction(k: float, n: float) -> str:
    """``k/n`` as a percentage with its binomial error, or a dash."""
    if n == 0:
        return "-"
    p = k / n
    return f"{100 * p:.1f} ± {100 * np.sqrt(p * (1 - p) / n):.1f} % ({int(k)}/{int(n)})"


def rms(off: np.ndarray) -> float:
    """The radial rms of offsets (n, 2), px."""
    return float(np.sqrt(np.mean(np.sum(off**2, axis=1)))) if len(off) else float("nan")


def main(argv: list[str] | None = None) -> int:
    """Run both detectors on the cells of a scene file and print the comparison."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenes", help="megalut simulate --scene file (format megalut.scenes)")
    p.add_argument("truth", help="its truth table (megalut.scene_truth)")
    p.add_argument("--images", type=int, default=None, help="the first N images only")
    p.add_argument("--match-radius", type=float, default=1.5, help="px (default 1.5)")
    p.add_argument("--detect-thresh", type=float, default=DETECT_THRESH)
    p.add_argument("--detect-minarea", type=int, default=DETECT_MINAREA)
    p.add_argument("--deblend-nthresh", type=int, default=DEBLEND_NTHRESH)
    p.add_argument("--deblend-cont", type=float, default=DEBLEND_CONT)
    p.add_argument("--noise-cells", type=int, default=50, help="pure-noise cells (default 50)")
    p.add_argument("--seed", type=int, default=1, help="of the pure-noise cells")
    p.add_argument("--repeats", type=int, default=3, help="timing passes, best kept")
    p.add_argument("--json", default=None, help="write the numbers to this file")
    args = p.parse_args(argv)
    photutils = photutils_module()

    settings = DetectSettings(
        args.detect_thresh, args.detect_minarea, args.deblend_nthresh, args.deblend_cont
    )
    cells, index = read_cells(args.scenes, args.images)
    rows = fitsio.read(args.truth)
    truth, rads = {}, {}
    for cell, image in enumerate(index):
        sel = rows["image"] == image
        truth[cell] = np.c_[rows["x"][sel] - 1.0, rows["y"][sel] - 1.0]  # 0-based
        rads[cell] = np.asarray(rows["tru_rad"][sel], float)
    size = cells[0][0].shape[0]
    sigma = float(np.median([c[1] for c in cells]))

    detectors: dict[str, Detector] = {
        "sep (megalut's call)": sep_positions,
        "sep, cleaning off": sep_noclean_positions,
        "photutils": photutils_positions,
    }
    results, cpu, noise_false = {}, {}, {}
    rng = np.random.default_rng(args.seed)
    noise_cells = [
        (rng.normal(0.0, sigma, (size, size)), sigma, np.zeros((size, size), bool))
        for _ in range(args.noise_cells)
    ]
    for name, fn in detectors.items():
        positions = [fn(image, noise, settings, bad) for image, noise, bad in cells]
        results[name] = evaluate(name, positions, truth, rads, args.match_radius)
        noise_false[name] = sum(len(fn(im, nz, settings, bd)) for im, nz, bd in noise_cells)
        cpu[name] = cpu_per_cell(fn, cells, settings, args.repeats)

    stages = photutils_stages(cells, settings, args.repeats)
    same = {True: 0, False: 0}  # sep's cleaning on, off
    for image, noise, bad in cells:
        _, segm = photutils_segments(image, noise, settings, bad)
        phot = np.zeros(image.shape, bool) if segm is None else segm.data > 0
        for clean in same:
            seg = sep_extract(image, noise, settings, bad, clean)[1]
            same[clean] += bool(np.array_equal(seg > 0, phot))

    both = set.intersection(*({tuple(m) for m in r["matched"]} for r in results.values()))
    n_cells = len(cells)
    n_truth = sum(len(r) for r in rads.values())
    print(
        f"{args.scenes}: {n_cells} cells of {size} px (images {index[0]} to {index[-1]}), "
        f"{n_truth} truth galaxies, noise {sigma:.3g}; thresh {settings.thresh:g} x noise, "
        f"minarea {settings.minarea}, nthresh {settings.nthresh}, cont {settings.cont:g}; "
        f"match within {args.match_radius:g} px; sep {sep.__version__}, photutils "
        f"{photutils.__version__}, numpy {np.__version__}"
    )
    print(
        "footprints (sep's segmentation map against photutils' detect_sources) identical in "
        f"{same[False]}/{n_cells} cells with sep's cleaning off, {same[True]} with it on"
    )
    print(f"galaxies matched by every detector: {len(both)}")
    print(
        "photutils CPU per cell (ms): footprints {:.2f}, deblending {:.2f}, centroids "
        "{:.2f}".format(*(1e3 * t for t in stages))
    )
    print()
    print("| | " + " | ".join(results) + " |")
    print("|---" * (len(results) + 1) + "|")
    line: dict[str, list[str]] = {}
    out: dict[str, dict] = {}
    for name, r in results.items():
        pairs = r["pairs"]
        common = np.array([tuple(m) in both for m in r["matched"]], bool)
        cells_lines = [
            fraction(r["n_match"], r["n_truth"]),
            f"{r['n_det'] / n_cells:.2f}",
            f"{(r['n_det'] - r['n_match']) / n_cells:.2f}",
            f"{noise_false[name] / max(args.noise_cells, 1):.2f}",
        ]
        by_rad = pairs[pairs[:, 1] > 0] if len(pairs) else pairs
        cells_lines += [
            fraction(by_rad[:, 2].sum(), len(by_rad)),
            fraction(by_rad[:, 3].sum(), len(by_rad)),
        ]
        bins = []
        for lo, hi in zip(PAIR_BINS[:-1], PAIR_BINS[1:]):
            inb = pairs[(pairs[:, 0] >= lo) & (pairs[:, 0] < hi)] if len(pairs) else pairs
            bins.append(fraction(inb[:, 3].sum(), len(inb)))
            cells_lines.append(bins[-1])
        cells_lines += [
            f"{rms(r['offsets']):.3f}",
            f"{rms(r['offsets'][common]):.3f}",
            f"{1e3 * cpu[name]:.2f}",
        ]
        line[name] = cells_lines
        out[name] = {
            "n_truth": r["n_truth"],
            "n_det": r["n_det"],
            "n_match": r["n_match"],
            "noise_false": noise_false[name],
            "rms": rms(r["offsets"]),
            "rms_common": rms(r["offsets"][common]),
            "cpu_per_cell_s": cpu[name],
            "pairs_2hlr": [len(by_rad), int(by_rad[:, 2].sum()), int(by_rad[:, 3].sum())],
        }
    labels = [
        "completeness",
        "detections per cell",
        "unmatched detections per cell",
        f"false detections per pure-noise cell ({args.noise_cells} cells)",
        "close pairs (< sum of half-light radii) resolved: both matched",
        "close pairs (< sum of half-light radii) resolved: two detections",
    ]
    labels += [
        f"pairs {lo:g}–{hi:g} px apart: two detections"
        for lo, hi in zip(PAIR_BINS[:-1], PAIR_BINS[1:])
    ]
    labels += [
        "rms position error, every match (px)",
        "rms position error, galaxies every detector matches (px)",
        f"CPU per {size}-px cell (ms, best of {args.repeats})",
    ]
    for k, label in enumerate(labels):
        print(f"| {label} | " + " | ".join(v[k] for v in line.values()) + " |")
    if args.json:
        meta = {
            "scenes": args.scenes,
            "cells": n_cells,
            "footprints_identical_clean_on_off": [same[True], same[False]],
            "matched_by_every_detector": len(both),
            "photutils_stages_s": stages,
            "sep": sep.__version__,
            "photutils": photutils.__version__,
            "settings": vars(args),
        }
        with open(args.json, "w") as f:
            json.dump({"meta": meta, **out}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
