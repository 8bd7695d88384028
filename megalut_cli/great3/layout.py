"""The GREAT3 branch layout: file names, galaxy IDs, catalogs, star fields, submissions, truth.

A GREAT3 branch folder holds, per subfield ``SSS`` (000-199) and epoch ``E`` (0 for
single-epoch branches):

``image-SSS-E.fits``
    a grid of ``n_x`` x ``n_y`` (100 x 100) galaxy stamps of ``S`` x ``S`` pixels (48
    ground, 96 space), stamp ``(column, row)`` covering 0-indexed pixels
    ``[column S, (column + 1) S)`` in x and ``[row S, (row + 1) S)`` in y;
``galaxy_catalog-SSS.fits`` and ``galaxy_catalog-SSS.txt``
    columns ``x, y, ID``: the 0-indexed stamp centres as GREAT3 writes them,
    ``x = column S + (S - 1) // 2`` (the true centre ``column S + (S - 1) / 2`` rounded
    down, e.g. 23, 71, ... for ``S = 48``), and ``ID = 1e6 subfield + 1e3 column + row``;
    the text file has one ``# name`` header line per column, then one row per galaxy
    (GREAT3 writes every value with ``numpy.savetxt``'s ``%.18e``, IDs included);
    variable-PSF branches add ``x_tile_index, y_tile_index, tile_x_pos_deg,
    tile_y_pos_deg, x_field_true_deg, y_field_true_deg``;
``starfield_image-SSS-E.fits``
    a 3 x 3 grid of noiseless PSF stamps of the same size, the lower-left one exactly
    centred (at the true centre of its stamp), the others offset by up to a pixel;
``star_catalog-SSS.fits`` / ``.txt``
    their 0-indexed centres ``x, y``.

The truth of a constant-shear branch (a separate folder with the same structure in
GREAT3, ``truth/`` inside branches written by megalut) holds ``shear_params-SSS.txt``
(and ``.yaml``) with the subfield's ``g1, g2`` and ``starshape_parameters-SSS-E.txt``
(``.yaml``) with the PSF ellipticity ``psf_g1, psf_g2`` that defines the PSF frame. Text
dictionaries follow GREAT3's ``writeDict``: a ``# key key ...`` line, then the values.

A constant-shear *submission* is a text file with one line ``subfield g1 g2`` per
subfield, in ascending subfield order (200 lines for a full branch): what GREAT3's
``presubmission.py`` writes and its ``evaluate.py`` reads with ``numpy.loadtxt``.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table

from megalut_cli.atomic import atomic_output
from megalut_cli.errors import InputError, MegalutError
from megalut_cli.shear.bias import calibrate_by_response, case_means

#: Stamp sizes (pixels) of single-epoch GREAT3 branches.
STAMP_SIZES = {"ground": 48, "space": 96}
#: Stamps per row and per column of a GREAT3 subfield image.
GRID_SIZE = 100
#: Stars per row and per column of a constant-PSF star field.
STARFIELD_GRID = 3
#: Subfields of a full GREAT3 branch.
N_SUBFIELDS = 200
#: Largest subfield index and grid size the ID scheme (1e6 s + 1e3 c + r) can encode.
MAX_SUBFIELD = 999
MAX_GRID = 1000

#: megalut file formats of the FITS files written here.
IMAGE_FORMAT = "great3.image"
STARFIELD_FORMAT = "great3.starfield"
CATALOG_FORMAT = "great3.catalog"


# --------------------------------------------------------------------------- names


def image_name(subfield: int, epoch: int = 0) -> str:
    return f"image-{int(subfield):03d}-{int(epoch):d}.fits"


def starfield_name(subfield: int, epoch: int = 0) -> str:
    return f"starfield_image-{int(subfield):03d}-{int(epoch):d}.fits"


def galaxy_catalog_name(subfield: int, ext: str = "txt") -> str:
    return f"galaxy_catalog-{int(subfield):03d}.{ext}"


def star_catalog_name(subfield: int, ext: str = "txt") -> str:
    return f"star_catalog-{int(subfield):03d}.{ext}"


def shear_params_name(subfield: int, ext: str = "txt") -> str:
    return f"shear_params-{int(subfield):03d}.{ext}"


def starshape_name(subfield: int, epoch: int = 0, ext: str = "txt") -> str:
    return f"starshape_parameters-{int(subfield):03d}-{int(epoch):d}.{ext}"


_SUBFIELD_FILE = re.compile(r"^image-(\d{3,})-(\d)\.fits$")


def find_subfields(branch_dir: str | os.PathLike, epoch: int = 0) -> list[int]:
    """Sorted subfield indices of the ``image-SSS-E.fits`` files of a branch folder."""
    d = Path(branch_dir)
    if not d.is_dir():
        raise InputError(f"{d}: no such branch folder")
    found = []
    for p in d.iterdir():
        m = _SUBFIELD_FILE.match(p.name)
        if m and int(m.group(2)) == epoch:
            found.append(int(m.group(1)))
    return sorted(found)


def subfield_files(branch_dir: str | os.PathLike, subfield: int, epoch: int = 0) -> dict[str, Path]:
    """Paths of a subfield's ``image``, ``catalog`` (text, else FITS) and ``starfield``;
    an :class:`InputError` naming every missing file."""
    d = Path(branch_dir)
    files = {
        "image": d / image_name(subfield, epoch),
        "catalog": d / galaxy_catalog_name(subfield, "txt"),
        "starfield": d / starfield_name(subfield, epoch),
    }
    if not files["catalog"].is_file() and (d / galaxy_catalog_name(subfield, "fits")).is_file():
        files["catalog"] = d / galaxy_catalog_name(subfield, "fits")
    missing = [p.name for p in files.values() if not p.is_file()]
    if missing:
        raise InputError(f"{d}: subfield {subfield}: missing {', '.join(missing)}")
    return files


def catalog_stamp_size(x: np.ndarray, image_width: int) -> int:
    """The stamp size of a GREAT3 grid: ``image width / number of distinct x centres``."""
    n = np.unique(np.round(np.asarray(x, dtype=float), 6)).size
    if n < 1 or image_width % n:
        raise InputError(
            f"cannot infer the stamp size: {n} distinct x centres on a {image_width}-pixel-wide "
            "image"
        )
    return image_width // n


# --------------------------------------------------------------------------- IDs and grids


def galaxy_ids(subfield: int | np.ndarray, column: np.ndarray, row: np.ndarray) -> np.ndarray:
    """GREAT3 galaxy IDs ``1e6 subfield + 1e3 column + row`` (int64)."""
    return (
        np.asarray(subfield, dtype=np.int64) * 1_000_000
        + np.asarray(column, dtype=np.int64) * 1000
        + np.asarray(row, dtype=np.int64)
    )


def split_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(subfield, column, row)`` of GREAT3 galaxy IDs."""
    ids = np.asarray(ids, dtype=np.int64)
    return ids // 1_000_000, (ids // 1000) % 1000, ids % 1000


def grid_centres(n_x: int, n_y: int, stamp_size: int) -> dict[str, np.ndarray]:
    """Stamp ``column, row`` and GREAT3 0-indexed integer centres ``x, y`` in grid order.

    Stamp ``k`` is at column ``k mod n_x`` and row ``k div n_x``;
    ``x = column S + (S - 1) // 2`` as GREAT3's builder computes it.
    """
    k = np.arange(n_x * n_y, dtype=np.int64)
    col, row = k % n_x, k // n_x
    half = (int(stamp_size) - 1) // 2
    return {"column": col, "row": row, "x": col * stamp_size + half, "y": row * stamp_size + half}


def galaxy_catalog(subfield: int, n_x: int, n_y: int, stamp_size: int) -> dict[str, np.ndarray]:
    """The GREAT3 galaxy catalog (``x, y, ID``) of a subfield grid, in grid order."""
    if not 0 <= subfield <= MAX_SUBFIELD:
        raise MegalutError(f"subfield {subfield}: GREAT3 IDs encode subfields 0 to {MAX_SUBFIELD}")
    if max(n_x, n_y) > MAX_GRID:
        raise MegalutError(
            f"a {n_x}x{n_y} grid is too large for GREAT3 IDs (at most {MAX_GRID} per side)"
        )
    g = grid_centres(n_x, n_y, stamp_size)
    return {"x": g["x"], "y": g["y"], "ID": galaxy_ids(subfield, g["column"], g["row"])}


def read_galaxy_catalog(path: str | os.PathLike) -> Table:
    """A GREAT3 galaxy catalog (FITS or text) with numeric columns ``x, y, ID``."""
    # fitsio: not for checking a branch pipeline
    from megalut_cli.catalog import read_any_catalog, require_columns

    t = read_any_catalog(path)
    require_columns(t.colnames, ["x", "y", "ID"], path)
    if len(t) == 0:
        raise InputError(f"{path}: the galaxy catalog has no rows (empty subfield)")
    for c in ("x", "y", "ID"):
        a = np.asarray(t[c])
        if a.dtype.kind not in "iuf" or not np.all(np.isfinite(a)):
            raise InputError(f"{path}: column {c} must hold finite numbers")
    t["ID"] = np.asarray(t["ID"]).astype(np.int64)
    return t


# --------------------------------------------------------------------------- star fields


def read_starfield(path: str | os.PathLike, stamp_size: int) -> np.ndarray:
    """The star stamps ``(n, S, S)`` of a star field image, in grid order from the lower-left.

    Raises :class:`InputError` naming the file when the stamp size does not divide the
    image, pixels are NaN or infinite, or no stamp holds a star (positive flux).
    """
    # fitsio: not for checking a branch pipeline
    from megalut_cli.measure.stamps import check_grid, image_info, read_rows

    info = image_info(path)
    n_y, n_x = check_grid(info, stamp_size)
    data = read_rows(info, 0, info.shape[0])
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: the star field has NaN or infinite pixels")
    s = int(stamp_size)
    stars = data.reshape(n_y, s, n_x, s).transpose(0, 2, 1, 3).reshape(n_y * n_x, s, s)
    if not np.any(stars.sum(axis=(1, 2)) > 0):
        raise InputError(f"{path}: no star in the star field (every stamp is empty)")
    return np.ascontiguousarray(stars)


# --------------------------------------------------------------------------- submissions


def write_submission(
    path: str | os.PathLike,
    subfield: Sequence[int] | np.ndarray,
    g1: Sequence[float] | np.ndarray,
    g2: Sequence[float] | np.ndarray,
    overwrite: bool = False,
) -> Path:
    """Write a constant-shear submission: one ``subfield g1 g2`` line per subfield, ascending.

    Refuses duplicate or negative subfields and non-finite shears (naming the subfields).
    """
    s = np.asarray(subfield)
    if s.dtype.kind not in "iu":
        if s.dtype.kind == "f" and np.all(np.isfinite(s)) and np.all(s == np.round(s)):
            s = s.astype(np.int64)
        else:
            raise MegalutError("submission: subfield indices must be integers")
    s = s.astype(np.int64)
    a1, a2 = np.asarray(g1, dtype=float), np.asarray(g2, dtype=float)
    if not (s.shape == a1.shape == a2.shape) or s.ndim != 1:
        raise MegalutError("submission: subfield, g1 and g2 must be 1-d arrays of one length")
    if s.size == 0:
        raise MegalutError("submission: no subfield to write")
    if np.any(s < 0):
        raise MegalutError("submission: negative subfield index")
    uniq, counts = np.unique(s, return_counts=True)
    if np.any(counts > 1):
        raise MegalutError(
            f"submission: duplicate subfield(s) {', '.join(map(str, uniq[counts > 1][:10]))}"
        )
    bad = ~(np.isfinite(a1) & np.isfinite(a2))
    if np.any(bad):
        raise MegalutError(
            f"submission: no shear estimate for subfield(s) {', '.join(map(str, s[bad][:10]))}"
            + (" ..." if bad.sum() > 10 else "")
        )
    order = np.argsort(s)
    lines = [f"{int(s[i])} {float(a1[i])!r} {float(a2[i])!r}" for i in order]
    with atomic_output(path, overwrite) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    return Path(path)


def read_submission(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(subfield, g1, g2)`` of a constant-shear submission (``#`` comments allowed)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    rows = []
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise InputError(f"{p}: not a text submission file (subfield g1 g2 per line)") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.split("#", 1)[0].split()
        if not s:
            continue
        if len(s) < 3:
            raise InputError(f"{p}: line {lineno}: expected 'subfield g1 g2', got {line.strip()!r}")
        try:
            rows.append([float(v) for v in s[:3]])
        except ValueError:
            raise InputError(f"{p}: line {lineno}: not a number in {line.strip()!r}") from None
    if not rows:
        raise InputError(f"{p}: the submission has no 'subfield g1 g2' line")
    a = np.array(rows)
    sub = a[:, 0]
    if not np.all(sub == np.round(sub)) or np.any(sub < 0):
        raise InputError(f"{p}: the first column must hold subfield indices (integers >= 0)")
    sub = sub.astype(np.int64)
    uniq, counts = np.unique(sub, return_counts=True)
    if np.any(counts > 1):
        raise InputError(f"{p}: duplicate subfield(s) {', '.join(map(str, uniq[counts > 1][:10]))}")
    if not np.all(np.isfinite(a[:, 1:])):
        raise InputError(f"{p}: non-finite shear estimates")
    return sub, a[:, 1], a[:, 2]


def subfield_column(table: Any, where: str = "catalog") -> np.ndarray:
    """The subfield of every row: column ``subfield``, else ``ID // 1e6`` (GREAT3 IDs)."""
    names = list(table.colnames) if hasattr(table, "colnames") else list(table)
    if "subfield" in names:
        s = np.asarray(table["subfield"])
    elif "ID" in names:
        s = split_ids(np.asarray(table["ID"]).astype(np.int64))[0]
    else:
        raise InputError(
            f"{where}: no 'subfield' or GREAT3 'ID' column to group galaxies by subfield"
        )
    if s.dtype.kind not in "iu":
        if s.dtype.kind == "f" and np.all(np.isfinite(s)) and np.all(s == np.round(s)):
            s = s.astype(np.int64)
        else:
            raise InputError(f"{where}: column subfield must hold integers")
    return s.astype(np.int64)


def submission_from_catalog(
    table: Any, weighted: bool = False, where: str = "catalog"
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-subfield mean shears ``(subfield, g1, g2, n_used)`` of a predictions catalog.

    Rows with ``flags != 0`` or non-finite ``pre_g1, pre_g2`` do not count; ``weighted``
    averages with ``pre_g1_w, pre_g2_w``. A subfield without usable rows gets NaN. A metacal
    catalog (``mcal_r11`` ... columns) gives each subfield's mean noshear estimate times the
    inverse of its mean response (rows need finite responses).
    """
    from megalut_cli.catalog import require_columns  # fitsio: not for checking a branch pipeline

    names = list(table.colnames) if hasattr(table, "colnames") else list(table)
    if "mcal_r11" in names:
        return _metacal_subfield_means(table, names, weighted, where)
    need = ["pre_g1", "pre_g2"] + (["pre_g1_w", "pre_g2_w"] if weighted else [])
    require_columns(names, need, where)
    sub = subfield_column(table, where)
    ok = np.ones(len(sub), dtype=bool)
    if "flags" in names:
        ok &= np.asarray(table["flags"]) == 0
    out = []
    n_used = None
    for comp in ("g1", "g2"):
        v = np.where(ok, np.asarray(table[f"pre_{comp}"], dtype=float), np.nan)
        w = np.asarray(table[f"pre_{comp}_w"], dtype=float) if weighted else None
        ids, means, _, nrows = case_means(sub, v, w)
        out.append(means)
        n_used = nrows if n_used is None else np.minimum(n_used, nrows)
    return ids, out[0], out[1], n_used


def _metacal_subfield_means(
    table: Any, names: list[str], weighted: bool, where: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`submission_from_catalog` of a metacal catalog: ``<R>^-1 <g_noshear>`` per subfield."""
    from megalut_cli.catalog import require_columns  # fitsio: not for checking a branch pipeline

    resp = [f"mcal_r{i}{j}" for i in "12" for j in "12"]
    require_columns(
        names,
        ["pre_g1_noshear", "pre_g2_noshear", *resp]
        + (["pre_g1_w_noshear", "pre_g2_w_noshear"] if weighted else []),
        where,
    )
    sub = subfield_column(table, where)
    ok = (
        np.asarray(table["flags_noshear"]) == 0
        if "flags_noshear" in names
        else np.ones(len(sub), dtype=bool)
    )
    for c in resp:
        ok &= np.isfinite(np.asarray(table[c], dtype=float))
    mean: dict[str, np.ndarray] = {}
    n_used = None
    for i in "12":
        w = np.asarray(table[f"pre_g{i}_w_noshear"], dtype=float) if weighted else None
        g = np.where(ok, np.asarray(table[f"pre_g{i}_noshear"], dtype=float), np.nan)
        ids, mean[f"g{i}"], _, nrows = case_means(sub, g, w)
        n_used = nrows if n_used is None else np.minimum(n_used, nrows)
        for j in "12":  # the response of the same rows, with the same weights
            r = np.where(np.isfinite(g), np.asarray(table[f"mcal_r{i}{j}"], dtype=float), np.nan)
            mean[f"r{i}{j}"] = case_means(sub, r, w)[1]
    g1, g2 = calibrate_by_response(
        mean["r11"], mean["r12"], mean["r21"], mean["r22"], mean["g1"], mean["g2"]
    )
    return ids, g1, g2, n_used


# --------------------------------------------------------------------------- truth


def _dict_text(values: Mapping[str, float]) -> str:
    """GREAT3's ``writeDict(type='txt')``: ``# k1 k2 `` then ``v1 v2 ``."""
    keys = sorted(values)
    return (
        "# "
        + "".join(f"{k} " for k in keys)
        + "\n"
        + "".join(f"{float(values[k])!r} " for k in keys)
        + "\n"
    )


def _dict_yaml(values: Mapping[str, float]) -> str:
    return "".join(f"{k}: {float(values[k])!r}\n" for k in sorted(values))


def write_truth(
    truth_dir: str | os.PathLike,
    subfield: Sequence[int] | np.ndarray,
    g1: np.ndarray,
    g2: np.ndarray,
    psf_g1: np.ndarray,
    psf_g2: np.ndarray,
    overwrite: bool = False,
) -> list[Path]:
    """Write ``shear_params-SSS`` and ``starshape_parameters-SSS-0`` (``.txt`` and ``.yaml``)."""
    d = Path(truth_dir)
    d.mkdir(parents=True, exist_ok=True)
    written = []
    for s, a, b, pa, pb in zip(subfield, g1, g2, psf_g1, psf_g2):
        for name, values in (
            (shear_params_name, {"g1": a, "g2": b}),
            (lambda k, ext: starshape_name(k, 0, ext), {"psf_g1": pa, "psf_g2": pb}),
        ):
            for ext, text in (("txt", _dict_text(values)), ("yaml", _dict_yaml(values))):
                path = d / name(int(s), ext)
                with atomic_output(path, overwrite) as tmp:
                    Path(tmp).write_text(text)
                written.append(path)
    return written


_YAML_ITEM = re.compile(
    r"([A-Za-z_][A-Za-z0-9_]*)\s*:\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?\.?(?:nan|inf)\b)",
    re.I,
)


def read_dict_file(path: str | os.PathLike) -> dict[str, float]:
    """A GREAT3 parameter file: ``.txt`` (``writeDict``: a ``# key key ...`` line, one line
    of values) or simple ``.yaml`` (block or flow style); errors name the file."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise InputError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError):
        raise InputError(f"{p}: not a readable text parameter file") from None
    if p.suffix == ".yaml":
        out = {
            k: float(v.replace(".nan", "nan").replace(".inf", "inf"))
            for k, v in _YAML_ITEM.findall(text)
        }
        if not out:
            raise InputError(f"{p}: no 'key: value' entries")
        return out
    lines = [ln for ln in text.splitlines() if ln.strip()]
    keys = [ln[1:].split() for ln in lines if ln.lstrip().startswith("#")]
    vals = [ln.split() for ln in lines if not ln.lstrip().startswith("#")]
    if len(keys) != 1 or len(vals) != 1 or len(keys[0]) != len(vals[0]):
        raise InputError(f"{p}: expected a '# key ...' line and one line of values")
    try:
        return {k: float(v) for k, v in zip(keys[0], vals[0])}
    except ValueError:
        raise InputError(f"{p}: not a number among {' '.join(vals[0])!r}") from None


def _truth_file(d: Path, name_txt: str, name_yaml: str) -> Path | None:
    for n in (name_txt, name_yaml):
        if (d / n).is_file():
            return d / n
    return None


def read_truth(
    truth_dir: str | os.PathLike, subfields: Sequence[int] | None = None
) -> dict[str, np.ndarray]:
    """Truth of a constant-shear branch: ``subfield, g1, g2, psf_g1, psf_g2`` arrays.

    Reads ``shear_params-SSS`` and ``starshape_parameters-SSS-0`` (``.txt`` or ``.yaml``)
    for ``subfields`` (default: every ``shear_params`` file found). A missing starshape
    file, or GREAT3's failure value -10, gives NaN PSF ellipticities (no PSF frame for
    that subfield).
    """
    d = Path(truth_dir)
    if not d.is_dir():
        raise InputError(f"{d}: no such truth folder")
    if subfields is None:
        found = set()
        for p in d.iterdir():
            m = re.match(r"^shear_params-(\d{3,})\.(txt|yaml)$", p.name)
            if m:
                found.add(int(m.group(1)))
        if not found:
            raise InputError(f"{d}: no shear_params-SSS.txt (or .yaml) truth file")
        subfields = sorted(found)
    out: dict[str, list[float]] = {k: [] for k in ("g1", "g2", "psf_g1", "psf_g2")}
    for s in subfields:
        sp = _truth_file(d, shear_params_name(s, "txt"), shear_params_name(s, "yaml"))
        if sp is None:
            raise InputError(
                f"{d}: no truth for subfield {s} ({shear_params_name(s, 'txt')} missing)"
            )
        vals = read_dict_file(sp)
        missing = [k for k in ("g1", "g2") if k not in vals]
        if missing:
            raise InputError(f"{sp}: missing {', '.join(missing)}")
        out["g1"].append(vals["g1"])
        out["g2"].append(vals["g2"])
        ss = _truth_file(d, starshape_name(s, 0, "txt"), starshape_name(s, 0, "yaml"))
        pg = read_dict_file(ss) if ss is not None else {}
        p1, p2 = pg.get("psf_g1", math.nan), pg.get("psf_g2", math.nan)
        if p1 <= -9.9 or p2 <= -9.9:  # GREAT3's flag for a failed PSF measurement
            p1 = p2 = math.nan
        out["psf_g1"].append(p1)
        out["psf_g2"].append(p2)
    res = {k: np.asarray(v, dtype=float) for k, v in out.items()}
    res["subfield"] = np.asarray(list(subfields), dtype=np.int64)
    return res
