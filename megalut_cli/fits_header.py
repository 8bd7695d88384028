"""FITS header helpers below every reader: the image HDU of a file and a header's user-level
cards."""

from __future__ import annotations

import os
import re
from typing import Any

import fitsio

from megalut_cli.errors import InputError

#: Structural keywords of a FITS header (and the flag-bit cards every writer makes afresh).
STRUCTURAL_KEYWORDS = re.compile(
    r"^(XTENSION|SIMPLE|EXTEND|BITPIX|NAXIS\d*|PCOUNT|GCOUNT|TFIELDS|BZERO|BSCALE|T(TYPE|FORM|UNIT|COMM|DIM|NULL|SCAL|ZERO)\d+"
    r"|FLAGBIT\d+)$"
)


def header_dict(hdr: fitsio.FITSHDR) -> dict[str, Any]:
    """Header as a dict of user-level cards (structural keywords left out)."""
    out: dict[str, Any] = {}
    for rec in hdr.records():
        name = rec.get("name")
        if not name or name in ("COMMENT", "CONTINUE") or STRUCTURAL_KEYWORDS.match(name):
            continue
        if name == "HISTORY":
            out.setdefault("HISTORY", []).append(str(rec.get("value", "")))
        else:
            out[name] = rec.get("value")
    return out


def image_ext(fits: fitsio.FITS, path: str | os.PathLike, ext: int | None = None) -> int:
    """``ext``, or else the index of the first image HDU of ``fits`` that holds data."""
    if ext is not None:
        return ext
    found = next(
        (i for i, h in enumerate(fits) if h.get_exttype() == "IMAGE_HDU" and h.has_data()), None
    )
    if found is None:
        raise InputError(f"{path}: no image in this FITS file")
    return found
