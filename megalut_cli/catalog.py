"""FITS catalogs and images: fast bulk I/O (fitsio), provenance header cards, safe writes.

Catalogs are handled in memory as :class:`astropy.table.Table` objects (one row per
stamp/galaxy). Every file written here carries ``DATE``, ``CREATOR``, a format name and
version (``MLFORMAT``/``MLFMTVER``), any extra cards (seeds, model hash, ...) and the
``HISTORY`` of the processing chain, one card per step with its command line.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import fitsio
import numpy as np

from megalut_cli.atomic import atomic_output
from megalut_cli.columns import column_cards, column_units
from megalut_cli.errors import InputError
from megalut_cli.fits_header import STRUCTURAL_KEYWORDS, header_dict, image_ext
from megalut_cli.provenance import CREATOR, command_line, utc_now

if TYPE_CHECKING:  # astropy.table costs ~0.4 s to import: loaded where a Table is made
    from astropy.table import Table

#: Header keywords managed here and never copied from an input header.
_MANAGED = {"DATE", "CREATOR", "MLFORMAT", "MLFMTVER", "HISTORY", "EXTNAME"}
#: Extra table HDUs carried from an input catalog to the catalogs made from it.
CARRIED_HDUS = ("CONFIG",)
_HISTORY_WIDTH = 70


def _open_error(path: str | os.PathLike, err: Exception) -> InputError:
    del err  # cfitsio's own messages are long and cryptic
    return InputError(f"{path}: not a readable FITS file (truncated or not FITS)")


def _check_exists(path: str | os.PathLike) -> None:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such file")
    if p.stat().st_size % 2880:  # FITS files are made of 2880-byte blocks
        raise InputError(f"{path}: not a readable FITS file (truncated or not FITS)")


def _table_ext(fits: fitsio.FITS, path: str | os.PathLike) -> int:
    for i, hdu in enumerate(fits):
        if hdu.get_exttype() in ("BINARY_TBL", "ASCII_TBL"):
            return i
    raise InputError(f"{path}: no table extension (is this a catalog?)")


def _native(arr: np.ndarray) -> np.ndarray:
    """Convert a (big-endian) structured array read from FITS to native byte order."""
    if arr.dtype.names is None:
        return arr.astype(arr.dtype.newbyteorder("="), copy=False)
    dt = np.dtype([(n, arr.dtype[n].newbyteorder("=")) for n in arr.dtype.names])
    return arr.astype(dt, copy=False)


def catalog_info(path: str | os.PathLike) -> tuple[int, list[str], dict[str, Any]]:
    """Return ``(n_rows, column_names, header)`` of a catalog without reading its rows."""
    _check_exists(path)
    try:
        with fitsio.FITS(str(path)) as f:
            ext = _table_ext(f, path)
            hdu = f[ext]
            return hdu.get_nrows(), list(hdu.get_colnames()), header_dict(hdu.read_header())
    except InputError:
        raise
    except (OSError, ValueError) as err:
        raise _open_error(path, err) from None


def read_cards(path: str | os.PathLike, ext: int | None = None) -> dict[str, Any]:
    """User-level cards of a catalog's table header (or of HDU ``ext``, e.g. a stamp image)
    as ``(value, comment)`` pairs, to carry into a catalog made from it; ``COMMENT`` cards
    as a list under ``"COMMENT"``.

    Cards written afresh by every writer (dates, format, history, columns, flag bits) and
    structural ones are left out.
    """
    _check_exists(path)
    try:
        with fitsio.FITS(str(path)) as f:
            hdr = f[_table_ext(f, path) if ext is None else ext].read_header()
    except InputError:
        raise
    except (OSError, ValueError) as err:
        raise _open_error(path, err) from None
    out: dict[str, Any] = {}
    for rec in hdr.records():
        name = rec.get("name")
        if not name or name in _MANAGED or name == "CONTINUE" or STRUCTURAL_KEYWORDS.match(name):
            continue
        if name == "COMMENT":
            out.setdefault("COMMENT", []).append(str(rec.get("value", "")))
        else:
            out[name] = (rec.get("value"), rec.get("comment") or "")
    return out


def read_carried_hdus(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The extra table HDUs of ``path`` named in :data:`CARRIED_HDUS` (e.g. ``CONFIG``)."""
    _check_exists(path)
    out: dict[str, np.ndarray] = {}
    try:
        with fitsio.FITS(str(path)) as f:
            for name in CARRIED_HDUS:
                if name in f:
                    out[name] = f[name].read()
    except (OSError, ValueError) as err:
        raise _open_error(path, err) from None
    return out


def read_catalog(
    path: str | os.PathLike,
    columns: Sequence[str] | None = None,
    rows: slice | None = None,
) -> Table:
    """Read a FITS catalog (first table extension) as an astropy Table.

    ``table.meta`` holds the header as a dict (``HISTORY`` as a list of strings).
    Missing ``columns`` are reported all at once.
    """
    from astropy.table import Table

    data, header = read_catalog_columns(path, columns, rows)
    table = Table(data, copy=False)
    table.meta.update(header)
    return table


def read_catalog_columns(
    path: str | os.PathLike, columns: Sequence[str] | None = None, rows: slice | None = None
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """What :func:`read_catalog` reads, without an astropy Table (whose import costs ~0.4 s):
    ``(columns, header)``, the columns (all, or ``columns``; native byte order; all rows, or
    ``rows``) in the file's order and the header as ``table.meta`` would hold it."""
    _check_exists(path)
    try:
        with fitsio.FITS(str(path)) as f:
            hdu = f[_table_ext(f, path)]
            if columns is not None:
                require_columns(hdu.get_colnames(), columns, path)
            names = hdu.get_colnames() if columns is None else list(columns)
            n_rows = hdu.get_nrows()
            kwargs: dict[str, Any] = {}
            if columns is not None:
                kwargs["columns"] = names
            if rows is not None:
                start, stop, _ = rows.indices(n_rows)
                kwargs["rows"] = np.arange(start, stop)
            if n_rows:
                data = hdu.read(**kwargs)
            else:
                dtype = hdu.get_rec_dtype()[0]
                data = np.zeros(0, dtype=[(n, dtype[n]) for n in names])
            header = header_dict(hdu.read_header())
    except InputError:
        raise
    except (OSError, ValueError) as err:
        raise _open_error(path, err) from None
    data = _native(data)
    return {name: data[name] for name in data.dtype.names}, header


#: Bytes of rows :func:`read_columns_by_rows` reads at once (all columns of a block of rows).
ROW_BLOCK_BYTES = 4 << 20


def read_columns_by_rows(path: str | os.PathLike, columns: Sequence[str]) -> dict[str, np.ndarray]:
    """The arrays of ``read_catalog_columns(path, columns)[0]``, read in one pass over the
    rows: whole rows by blocks of :data:`ROW_BLOCK_BYTES`, the columns copied out (fitsio reads
    a subset of columns one column at a time, each a pass over the file: 8 of a 500 000-row
    catalog take 6 times as long)."""
    _check_exists(path)
    try:
        with fitsio.FITS(str(path)) as f:
            hdu = f[_table_ext(f, path)]
            require_columns(hdu.get_colnames(), columns, path)
            n_rows = hdu.get_nrows()
            if not n_rows:
                return read_catalog_columns(path, columns)[0]
            step = max(1, ROW_BLOCK_BYTES // max(1, hdu.get_rec_dtype()[0].itemsize))
            out: dict[str, np.ndarray] = {}
            for start in range(0, n_rows, step):
                block = hdu[start : min(start + step, n_rows)]
                if not out:
                    out = {
                        name: np.empty(
                            (n_rows, *block.dtype[name].shape),
                            block.dtype[name].base.newbyteorder("="),
                        )
                        for name in columns
                    }
                for name in columns:
                    out[name][start : start + len(block)] = block[name]
    except InputError:
        raise
    except (OSError, ValueError) as err:
        raise _open_error(path, err) from None
    return out


def iter_catalog(
    path: str | os.PathLike, chunk_rows: int, columns: Sequence[str] | None = None
) -> Iterator[Table]:
    """Yield successive row chunks of a catalog (memory bounded by ``chunk_rows``).

    The file is opened and its header read once; each chunk is a contiguous row slice.
    """
    from astropy.table import Table

    _check_exists(path)
    try:
        with fitsio.FITS(str(path)) as f:
            hdu = f[_table_ext(f, path)]
            if columns is not None:
                require_columns(hdu.get_colnames(), columns, path)
            n = hdu.get_nrows()
            header = header_dict(hdu.read_header())
            if n == 0:
                yield read_catalog(path, columns=columns)
                return
            view = hdu[list(columns)] if columns is not None else hdu
            for start in range(0, n, chunk_rows):
                table = Table(_native(view[start : min(start + chunk_rows, n)]), copy=False)
                table.meta.update(header)
                yield table
    except InputError:
        raise
    except (OSError, ValueError) as err:
        raise _open_error(path, err) from None


class CatalogColumns(Mapping[str, np.ndarray]):
    """The columns of a FITS catalog as a mapping, each read from the file when first asked for."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = path
        self.names: list[str] = catalog_info(path)[1]
        self._read: dict[str, np.ndarray] = {}

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._read:
            if name not in self.names:
                raise KeyError(name)
            self._read[name] = read_catalog_columns(self.path, [name])[0][name]
        return self._read[name]

    def load(self, names: Iterable[str]) -> None:
        """Read the columns ``names`` of the catalog not read yet, in one pass over the file
        (:func:`read_columns_by_rows`; a name the catalog lacks is left for ``[]`` to report)."""
        wanted = [n for n in dict.fromkeys(names) if n in self.names and n not in self._read]
        if len(wanted) > 1:
            self._read.update(read_columns_by_rows(self.path, wanted))

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)


class VersionColumns(Mapping[str, np.ndarray]):
    """The columns of a metacal catalog as one version sees them: ``X`` reads ``X_<version>``
    where that exists (features, flags), else ``X`` (truth, structure)."""

    def __init__(self, columns: Mapping[str, np.ndarray], version: str = "noshear") -> None:
        self.columns = columns
        self.version = version
        self._names = set(getattr(columns, "names", None) or list(columns))

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[self.own_name(name)]

    def own_name(self, name: str) -> str:
        """The column that ``name`` reads: ``name_<version>`` where that exists, else ``name``."""
        own = f"{name}_{self.version}"
        return own if own in self._names else name

    def load(self, names: Iterable[str]) -> None:
        """Read the columns ``names`` in one pass, when the columns are a
        :class:`CatalogColumns` (other mappings hold theirs already)."""
        if isinstance(self.columns, CatalogColumns):
            self.columns.load(self.own_name(n) for n in names)

    def __iter__(self) -> Iterator[str]:
        return iter(self.columns)

    def __len__(self) -> int:
        return len(self.columns)


def require_columns(
    available: Iterable[str], needed: Iterable[str], where: str | os.PathLike = "catalog"
) -> None:
    """Raise one :class:`InputError` naming every column of ``needed`` not in ``available``."""
    have = set(available)
    missing = [c for c in needed if c not in have]
    if missing:
        raise InputError(f"{where}: missing column(s) {', '.join(missing)}")


def _history_cards(lines: Iterable[str]) -> list[dict[str, Any]]:
    """One step per line, cut into cards; a continuation card starts with one space
    (FITS readers strip trailing blanks, so a cut never leaves one at a card's end)."""
    cards = []
    for line in lines:
        rest, prefix = str(line), ""
        while True:
            width = _HISTORY_WIDTH - len(prefix)
            chunk = rest[:width]
            if len(rest) > width:
                chunk = chunk.rstrip(" ") or chunk
            cards.append({"name": "HISTORY", "value": prefix + chunk})
            rest, prefix = rest[len(chunk) :], " "
            if not rest:
                break
    return cards


def history_steps(lines: Iterable[str]) -> list[str]:
    """The processing steps recorded in ``HISTORY`` cards, continuation cards joined."""
    steps: list[str] = []
    for line in lines:
        line = str(line)
        if line.startswith(" ") and steps:
            steps[-1] += line[1:]
        else:
            steps.append(line)
    return steps


def header_cards(
    fmt: str,
    fmt_version: str = "1.0",
    cards: Mapping[str, Any] | None = None,
    history: Sequence[str] | None = None,
    command: str | None = None,
    columns: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """Header records: DATE, CREATOR, format, extra ``cards`` and HISTORY (+ this command).

    ``cards`` values may be ``(value, comment)`` pairs; a ``COMMENT`` entry is a list of
    comment lines. ``history`` holds earlier steps (e.g. an input's ``meta['HISTORY']``);
    the current command line is appended. With the table's ``columns``, the column
    descriptions and flag bits of :func:`megalut_cli.columns.column_cards` are added.
    """
    recs: list[dict[str, Any]] = [
        {"name": "DATE", "value": utc_now(), "comment": "UTC date of file creation"},
        {"name": "CREATOR", "value": CREATOR, "comment": "software that wrote this file"},
        {"name": "MLFORMAT", "value": fmt, "comment": "megalut file format"},
        {"name": "MLFMTVER", "value": fmt_version, "comment": "megalut file format version"},
    ]
    comments: list[str] = []
    for key, val in (cards or {}).items():
        key = key.upper()
        if key in _MANAGED or STRUCTURAL_KEYWORDS.match(key):
            continue
        if key == "COMMENT":
            comments.extend(str(v) for v in ([val] if isinstance(val, str) else val))
            continue
        comment = ""
        if isinstance(val, tuple):
            val, comment = val
        if isinstance(val, (np.integer, np.floating, np.bool_)):
            val = val.item()
        if val is None:
            continue
        if isinstance(val, str) and len(val) > 68:
            val = val[:68]
        recs.append({"name": key[:8], "value": val, "comment": comment})
    recs.extend({"name": "COMMENT", "value": line} for line in comments)
    if columns is not None:
        recs.extend(column_cards(columns))
    steps = list(history or []) + [command if command is not None else command_line()]
    recs.extend(_history_cards(steps))
    return recs


def to_structured(table: Table | Mapping[str, np.ndarray]) -> np.ndarray:
    """A table (an astropy Table or a mapping of equal-length columns) as a structured array
    fitsio writes (text columns as ASCII bytes)."""
    if hasattr(table, "colnames"):  # an astropy Table
        cols = {name: np.asarray(table[name]) for name in table.colnames}
    else:
        cols = {name: np.asarray(v) for name, v in table.items()}
    lengths = {len(v) for v in cols.values()}
    if len(lengths) > 1:
        raise ValueError(f"columns of unequal length: {sorted(lengths)}")
    n = lengths.pop() if lengths else 0
    dtype = []
    for name, v in cols.items():
        if v.dtype.kind == "U":
            v = np.char.encode(v, "ascii")
            cols[name] = v
        if v.dtype.kind == "b":
            v = v.astype(np.int16)  # FITS logical columns are awkward for most readers
            cols[name] = v
        dtype.append((name, v.dtype, v.shape[1:]) if v.ndim > 1 else (name, v.dtype))
    arr = np.empty(n, dtype=dtype)
    for name, v in cols.items():
        arr[name] = v
    return arr


def write_catalog(
    path: str | os.PathLike,
    table: Table | Mapping[str, np.ndarray],
    *,
    fmt: str,
    fmt_version: str = "1.0",
    overwrite: bool = False,
    cards: Mapping[str, Any] | None = None,
    history: Sequence[str] | None = None,
    extname: str = "CATALOG",
    extra_hdus: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Write a catalog atomically as a FITS binary table with provenance cards, column
    units and descriptions; ``extra_hdus`` (EXTNAME -> structured array, e.g. the
    ``CONFIG`` of :func:`read_carried_hdus`) follow as further table HDUs."""
    arr = to_structured(table)
    with catalog_writer(
        path,
        fmt=fmt,
        fmt_version=fmt_version,
        overwrite=overwrite,
        cards=cards,
        history=history,
        extname=extname,
        extra_hdus=extra_hdus,
    ) as writer:
        writer.append(arr)
    return Path(path)


class CatalogWriter:
    """A catalog table written chunk by chunk into an open FITS file (:func:`catalog_writer`):
    the first chunk fixes the columns and the header, later ones are appended in order, in
    blocks of about :attr:`BLOCK_BYTES` (each append of a FITS table costs ~2 ms whatever its
    size; :meth:`flush` writes what is held)."""

    #: Rows held before they are appended to the file, in bytes.
    BLOCK_BYTES = 1 << 20

    def __init__(self, fits: fitsio.FITS, header: Any, extname: str) -> None:
        self._fits = fits
        self._header = header
        self._extname = extname
        self._dtype: np.dtype | None = None
        self._held: list[np.ndarray] = []
        self._held_bytes = 0
        self.n_rows = 0

    def append(self, table: Table | Mapping[str, np.ndarray] | np.ndarray) -> None:
        """Append the rows of ``table`` (columns as in the first chunk, in any order)."""
        arr = table if isinstance(table, np.ndarray) and table.dtype.names else to_structured(table)
        if self._dtype is None:
            self._dtype = arr.dtype
            write_table_hdu(self._fits, arr, self._header(arr.dtype.names), self._extname)
        else:
            if set(arr.dtype.names) != set(self._dtype.names):
                raise ValueError(f"chunk columns {arr.dtype.names} differ from {self._dtype.names}")
            if arr.dtype != self._dtype:
                cast = np.zeros(len(arr), dtype=self._dtype)
                for name in self._dtype.names:
                    cast[name] = arr[name]
                arr = cast
            self._held.append(arr)
            self._held_bytes += arr.nbytes
            if self._held_bytes >= self.BLOCK_BYTES:
                self.flush()
        self.n_rows += len(arr)

    def flush(self) -> None:
        """Append the rows held to the file."""
        if self._held:
            block = self._held[0] if len(self._held) == 1 else np.concatenate(self._held)
            self._fits[self._extname].append(block)
            self._held = []
            self._held_bytes = 0

    @property
    def started(self) -> bool:
        """Whether the table exists (a first chunk, possibly empty, was appended)."""
        return self._dtype is not None


@contextlib.contextmanager
def catalog_writer(
    path: str | os.PathLike,
    *,
    fmt: str,
    fmt_version: str = "1.0",
    overwrite: bool = False,
    cards: Mapping[str, Any] | None = None,
    history: Sequence[str] | None = None,
    extname: str = "CATALOG",
    extra_hdus: Mapping[str, np.ndarray] | None = None,
) -> Iterator[CatalogWriter]:
    """Stream a catalog to ``path``: a :class:`CatalogWriter` whose chunks go to a temporary
    file, renamed to ``path`` when the block ends without error (header as
    :func:`write_catalog`'s; ``extra_hdus`` follow the table)."""
    with atomic_output(path, overwrite) as tmp, fitsio.FITS(str(tmp), "rw", clobber=True) as fits:
        writer = CatalogWriter(
            fits,
            lambda columns: header_cards(fmt, fmt_version, cards, history, columns=columns),
            extname,
        )
        yield writer
        writer.flush()
        if not writer.started:
            raise ValueError("a catalog needs at least one (possibly empty) chunk")
        for name, extra in (extra_hdus or {}).items():
            fits.write(extra, extname=name)


def write_table_hdu(
    fits: fitsio.FITS, arr: np.ndarray, recs: Sequence[Mapping[str, Any]], extname: str = "CATALOG"
) -> None:
    """Append the table ``arr`` to an open ``fits`` with header ``recs`` and column units."""
    fits.write(arr, header=list(recs), extname=extname, units=column_units(arr.dtype.names))


def read_image(
    path: str | os.PathLike, ext: int | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a FITS image (the first HDU holding one unless ``ext`` is given) and its header."""
    _check_exists(path)
    try:
        with fitsio.FITS(str(path)) as f:
            hdu = f[image_ext(f, path, ext)]
            data = hdu.read()
            header = header_dict(hdu.read_header())
    except InputError:
        raise
    except (OSError, ValueError, IndexError) as err:
        raise _open_error(path, err) from None
    if data is None or data.ndim != 2:
        raise InputError(f"{path}: expected a 2-D image")
    return _native(data), header


def write_image(
    path: str | os.PathLike,
    image: np.ndarray,
    *,
    fmt: str,
    fmt_version: str = "1.0",
    overwrite: bool = False,
    cards: Mapping[str, Any] | None = None,
    history: Sequence[str] | None = None,
) -> Path:
    """Write a 2-D image atomically with provenance cards."""
    recs = header_cards(fmt, fmt_version, cards, history)
    with atomic_output(path, overwrite) as tmp:
        fitsio.write(str(tmp), np.ascontiguousarray(image), header=recs, clobber=True)
    return Path(path)


#: What a catalog records of how its stamps were made, compared between a model's training
#: catalog and the catalog it predicts on: header card -> name in the setup record.
SETUP_CARDS = {"STAMPSZ": "stamp_size", "NOISE": "noise_type", "GAIN": "gain"}
#: Sections of the simulation config (``CONFIG`` HDU) that describe the observing setup.
SETUP_CONFIG_KEYS = ("psf", "noise")


def read_setup(path: str | os.PathLike) -> dict[str, Any]:
    """The observing setup a catalog records: stamp size, noise, gain (header cards) and, for a
    simulated catalog, the PSF and noise sections of its ``CONFIG`` HDU. Empty if none."""
    import json

    _, _, header = catalog_info(path)
    setup: dict[str, Any] = {
        name: header[card] for card, name in SETUP_CARDS.items() if card in header
    }
    try:
        with fitsio.FITS(str(path)) as f:
            if "CONFIG" in f:
                text = f["CONFIG"].read(columns=["config_json"])[0]["config_json"]
                config = json.loads(text.decode("ascii") if isinstance(text, bytes) else str(text))
                setup.update({key: config[key] for key in SETUP_CONFIG_KEYS if key in config})
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        pass  # no readable CONFIG: the header cards are what is recorded
    return setup


#: Setup keys whose values are file paths: the same file may be named from another folder.
SETUP_PATH_KEYS = frozenset({"path", "image", "correlation", "psf_path"})


def _same_setup_value(a: Any, b: Any, key: str = "") -> bool:
    """Equal, where sections (dicts) are compared on the keys both give (a key one of them
    leaves to its default is not a difference) and paths by their file names."""
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return all(_same_setup_value(a[k], b[k], k) for k in a.keys() & b.keys())
    if key in SETUP_PATH_KEYS and isinstance(a, str) and isinstance(b, str):
        return Path(a).name == Path(b).name
    return a == b


def setup_differences(trained: Mapping[str, Any], applied: Mapping[str, Any]) -> list[str]:
    """``name: trained vs applied`` for every setup item both record and that differ."""
    return [
        f"{name} {trained[name]} vs {applied[name]}"
        for name in trained
        if name in applied and not _same_setup_value(trained[name], applied[name])
    ]


# --------------------------------------------------------------------------- text catalogs

_FITS_MAGIC = b"SIMPLE  ="


def is_fits_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` starts like a FITS file (else it is read as a text catalog)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(_FITS_MAGIC)) == _FITS_MAGIC
    except OSError:
        raise InputError(f"{path}: no such file") from None


#: Columns read as integers from text catalogs (when their values are integral): GREAT3
#: writes every column with numpy.savetxt's default ``%.18e``, IDs and tile indices too.
INTEGER_COLUMNS = ("ID", "id", "subfield", "case", "rea", "flags", "x_tile_index", "y_tile_index")


def read_text_catalog(path: str | os.PathLike) -> Table:
    """Read a whitespace-separated text catalog whose column names are in ``#`` lines.

    Names come from one ``# name`` line per column (GREAT3's catalogs) or from a single
    ``# name name ...`` line. Every value must be a number; ``ID``-like columns
    (:data:`INTEGER_COLUMNS`) with integral values become int64, the others float64.
    Errors name the file (and the line).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise InputError(f"{p}: neither a FITS file nor a text catalog") from None
    header: list[list[str]] = []
    rows: list[list[str]] = []
    first_data = None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            if first_data is None:
                header.append(s[1:].split())
            continue
        if first_data is None:
            first_data = lineno
        rows.append([lineno, *s.split()])  # type: ignore[list-item]
    header = [h for h in header if h]
    if not header:
        raise InputError(f"{p}: no '# name' header lines giving the column names")
    if rows:
        ncol = len(rows[0]) - 1
    else:
        ncol = len(header) if all(len(h) == 1 for h in header) else len(header[-1])
    last = header[-ncol:] if 0 < ncol <= len(header) else []
    if last and all(len(h) == 1 for h in last):
        names = [h[0] for h in last]  # one '# name' line per column (GREAT3)
    elif len(header[-1]) == ncol:
        names = header[-1]  # one '# name name ...' line
    else:
        raise InputError(
            f"{p}: the '#' header lines do not name the {ncol} column(s) "
            "(expected one '# name' line per column, or one '# name name ...' line)"
        )
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"{p}: duplicate column name(s) {', '.join(dup)}")
    values = np.empty((len(rows), ncol), dtype=np.float64)
    for i, r in enumerate(rows):
        lineno, fields = r[0], r[1:]
        if len(fields) != ncol:
            raise InputError(f"{p}: line {lineno}: {len(fields)} value(s), expected {ncol}")
        try:
            values[i] = [float(v) for v in fields]
        except ValueError:
            raise InputError(f"{p}: line {lineno}: not a number in {' '.join(fields)!r}") from None
    from astropy.table import Table

    table = Table()
    for j, name in enumerate(names):
        col = values[:, j]
        if name in INTEGER_COLUMNS and np.all(np.isfinite(col)) and np.all(col == np.round(col)):
            table[name] = col.astype(np.int64)
        else:
            table[name] = col
    table.meta["TEXTCAT"] = p.name
    return table


def _format_value(v: Any) -> str:
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    f = float(v)
    return str(int(f)) if f.is_integer() and abs(f) < 2**53 else repr(f)


def text_catalog_lines(columns: Mapping[str, np.ndarray]) -> list[str]:
    """Lines of a GREAT3-style text catalog: ``# name`` per column, then the rows."""
    names = list(columns)
    arrays = [np.asarray(columns[n]) for n in names]
    lines = [f"# {n}" for n in names]
    for i in range(len(arrays[0]) if arrays else 0):
        lines.append(" ".join(_format_value(a[i]) for a in arrays))
    return lines


def write_text_catalog(
    path: str | os.PathLike, columns: Mapping[str, np.ndarray], overwrite: bool = False
) -> Path:
    """Write ``columns`` as a GREAT3-style text catalog, atomically."""
    with atomic_output(path, overwrite) as tmp:
        Path(tmp).write_text("\n".join(text_catalog_lines(columns)) + "\n")
    return Path(path)


def read_any_catalog(path: str | os.PathLike) -> Table:
    """A FITS catalog (first table) or a text catalog with ``# name`` header lines."""
    if is_fits_file(path):
        return read_catalog(path)
    return read_text_catalog(path)
