"""Concatenating the catalogs of many tiles into one (``megalut concat``), their provenance
checked: what makes them one catalog (format, model, metacal step and target, frame) must
agree; each row keeps the index of its tile."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from megalut_cli.catalog import catalog_info, catalog_writer, iter_catalog, read_cards
from megalut_cli.errors import ConfigError, InputError
from megalut_cli.measure.defaults import MDET_FORMAT
from megalut_cli.measure.metacal_defaults import MDET_STEP_CARD
from megalut_cli.provenance import sha256_file

log = logging.getLogger(__name__)

#: Header cards that must agree between the catalogs: the format, the model, the metacal
#: step (of stamps or of metadetection) and target PSF, the measuring engine and its retry,
#: and the frame.
MUST_AGREE: tuple[str, ...] = (
    "MLFORMAT",
    "MODELSHA",
    "MCALSTEP",
    MDET_STEP_CARD,
    "MCALTARG",
    "MENGINE",
    "HSMRETRY",
    "SHFRAME",
)
#: Formats that can be concatenated (a calibrated catalog's responses belong to its whole
#: catalog: calibrate the concatenated predictions instead).
CONCAT_FORMATS: tuple[str, ...] = ("megalut.features", "megalut.predictions", MDET_FORMAT)
#: The column holding each row's tile (its input's index, from 0).
TILE_COLUMN = "tile"
#: Rows read and written at a time.
CHUNK_ROWS = 200_000


@dataclass(frozen=True)
class Tile:
    """One input catalog: its path, rows, columns and header."""

    path: str
    rows: int
    columns: list[str]
    header: dict[str, Any]


def _text(value: Any) -> Any:
    return value.strip() if isinstance(value, str) else value


def check_tiles(paths: Sequence[str | os.PathLike]) -> list[Tile]:
    """The tiles of ``paths``, checked to make one catalog: a known format, the same columns
    and the cards of :data:`MUST_AGREE` equal (one missing where another has it differs);
    an :class:`InputError` names the card and the two files otherwise."""
    if len(paths) < 2:
        raise ConfigError("concat needs at least two catalogs")
    if len({os.path.abspath(p) for p in paths}) < len(paths):
        raise ConfigError("a catalog is given twice")
    tiles = []
    for p in paths:
        rows, cols, header = catalog_info(p)
        tiles.append(Tile(str(p), rows, cols, header))
    first = tiles[0]
    fmt = _text(first.header.get("MLFORMAT"))
    if fmt not in CONCAT_FORMATS:
        hint = (
            ": calibrate the concatenated predictions instead (the responses belong to the "
            "whole catalog)"
            if fmt == "megalut.calibrated"
            else ""
        )
        raise InputError(
            f"{first.path}: format {fmt or 'unknown'}; concat takes "
            f"{' or '.join(CONCAT_FORMATS)} catalogs{hint}"
        )
    if TILE_COLUMN in first.columns:
        raise InputError(f"{first.path}: already has a {TILE_COLUMN!r} column (a concatenation?)")
    for t in tiles[1:]:
        if set(t.columns) != set(first.columns):
            extra = sorted(set(t.columns) ^ set(first.columns))
            raise InputError(
                f"{t.path}: its columns differ from {first.path}'s ({', '.join(extra[:5])}"
                f"{', ...' if len(extra) > 5 else ''})"
            )
        for card in MUST_AGREE:
            a, b = _text(first.header.get(card)), _text(t.header.get(card))
            if a != b:
                raise InputError(
                    f"{t.path}: {card} = {b!r} differs from {first.path}'s {a!r}: not one catalog"
                )
    return tiles


def concat_catalogs(
    paths: Sequence[str | os.PathLike], output: str | os.PathLike, overwrite: bool = False
) -> int:
    """Write the rows of the catalogs ``paths`` (:func:`check_tiles`) one after the other
    into ``output``, with their :data:`TILE_COLUMN`; the cards all of them hold with one
    value are kept, ``NTILES`` is added, and one ``HISTORY`` line per tile names it with its
    rows and sha256, after the first tile's own history. Returns the rows written."""
    tiles = check_tiles(paths)
    carried = [read_cards(t.path) for t in tiles]
    common = {
        k: v
        for k, v in carried[0].items()
        if k != "COMMENT" and all(k in c and _text(c[k][0]) == _text(v[0]) for c in carried[1:])
    }
    dropped = sorted({k for c in carried for k in c} - set(common) - {"COMMENT"})
    if dropped:
        log.info("cards that differ between the tiles, left out: %s", ", ".join(dropped))
    common["NTILES"] = (len(tiles), "catalogs concatenated (column tile)")
    history = list(tiles[0].header.get("HISTORY") or [])
    history += [
        f"tile {k}: {os.path.basename(t.path)}, {t.rows} rows, sha256 {sha256_file(t.path)}"
        for k, t in enumerate(tiles)
    ]
    fmt = _text(tiles[0].header["MLFORMAT"])
    version = str(_text(tiles[0].header.get("MLFMTVER", "1.0")))
    total = 0
    with catalog_writer(
        output, fmt=fmt, fmt_version=version, overwrite=overwrite, cards=common, history=history
    ) as writer:
        for k, t in enumerate(tiles):
            for chunk in iter_catalog(t.path, CHUNK_ROWS, columns=tiles[0].columns):
                cols = {c: np.asarray(chunk[c]) for c in tiles[0].columns}
                cols[TILE_COLUMN] = np.full(len(chunk), k, dtype=np.int32)
                writer.append(cols)
                total += len(chunk)
    log.info("wrote %s: %d rows from %d catalogs", output, total, len(tiles))
    return total
