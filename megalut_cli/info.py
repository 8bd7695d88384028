"""What is inside a megalut file (``megalut info``): catalogs, stamp images, models.

:func:`describe_file` returns a JSON-ready dict; :func:`format_info` renders it as text,
as ``fitsinfo`` and ``rio info`` do for their files.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import fitsio
import numpy as np

from megalut_cli import flags as fl
from megalut_cli.catalog import header_dict, history_steps
from megalut_cli.errors import InputError
from megalut_cli.provenance import sha256_file

_FITS_MAGIC = b"SIMPLE  ="
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: Cards shown under "provenance" rather than with the other cards.
_PROVENANCE_CARDS = {"DATE", "CREATOR", "MLFORMAT", "MLFMTVER", "HISTORY", "MODEL", "MODELSHA",
                     "CFGFILE", "CFGSHA", "CFGOVR", "SEED"}
#: Rows read at a time when counting flags.
_CHUNK_ROWS = 1_000_000


def describe_file(path: str | os.PathLike) -> dict[str, Any]:
    """Describe a megalut FITS catalog or stamp image, or an HDF5 model file.

    Raises :class:`InputError` (one line) for anything else.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    with open(p, "rb") as f:
        magic = f.read(8)
    if magic == _FITS_MAGIC[:8]:
        return _describe_fits(p)
    if magic == _HDF5_MAGIC:
        return _describe_model(p)
    raise InputError(f"{p}: not a FITS catalog, FITS image or HDF5 model file")


# --------------------------------------------------------------------------- FITS
def _columns(hdu: Any) -> list[dict[str, Any]]:
    hdr = hdu.read_header()
    dtype = hdu.get_rec_dtype()[0]
    out = []
    for i, name in enumerate(hdu.get_colnames(), start=1):
        unit = hdr.get(f"TUNIT{i}")
        comment = hdr.get(f"TCOMM{i}")
        out.append({
            "name": name,
            "type": dtype[name].base.name if dtype[name].kind != "S" else f"str{dtype[name].itemsize}",
            "unit": None if unit is None else str(unit).strip(),
            "description": None if comment is None else str(comment).strip(),
        })
    return out


def _flag_counts(hdu: Any, n_rows: int) -> dict[str, Any]:
    """Rows flagged, and rows per bit (names from the file's FLAGBITn cards, else flags.py)."""
    hdr = hdu.read_header()
    names = {1 << b: str(hdr.get(f"FLAGBIT{b}", fl.FLAG_NAMES.get(1 << b, f"BIT{b}"))).strip() for b in range(63)}
    total = 0
    per_bit = np.zeros(63, dtype=np.int64)
    view = hdu["flags"]
    for start in range(0, n_rows, _CHUNK_ROWS):
        v = np.asarray(view[start : min(start + _CHUNK_ROWS, n_rows)]).astype(np.int64)
        total += int(np.count_nonzero(v))
        for b in range(63):
            per_bit[b] += int(np.count_nonzero((v >> b) & 1))
    bits = {names[1 << b]: {"value": 1 << b, "rows": int(per_bit[b])} for b in range(63) if per_bit[b]}
    return {"rows_flagged": total, "rows_good": n_rows - total, "bits": bits}


def _provenance_from_header(header: dict[str, Any]) -> dict[str, Any]:
    prov: dict[str, Any] = {
        "created": header.get("DATE"),
        "creator": header.get("CREATOR"),
        "steps": history_steps(header.get("HISTORY", [])),
    }
    for key, card in (("seed", "SEED"), ("config_file", "CFGFILE"), ("config_sha256", "CFGSHA"),
                      ("config_overrides", "CFGOVR"), ("model", "MODEL"), ("model_sha256", "MODELSHA")):
        if card in header:
            prov[key] = header[card]
    return prov


def _describe_fits(p: Path) -> dict[str, Any]:
    if p.stat().st_size % 2880:
        raise InputError(f"{p}: not a readable FITS file (truncated or not FITS)")
    try:
        with fitsio.FITS(str(p)) as f:
            hdus = [(i, h.get_exttype(), h.get_extname()) for i, h in enumerate(f)]
            table = next((i for i, t, _ in hdus if t in ("BINARY_TBL", "ASCII_TBL")), None)
            image = next((i for i, t, _ in hdus if t == "IMAGE_HDU" and f[i].has_data()), None)
            if table is not None:
                hdu = f[table]
                header = header_dict(hdu.read_header())
                n_rows = hdu.get_nrows()
                out: dict[str, Any] = {"kind": "catalog", "rows": n_rows, "columns": _columns(hdu)}
                if "flags" in hdu.get_colnames():
                    out["flags"] = _flag_counts(hdu, n_rows)
                out["extensions"] = [e for i, _, e in hdus if i != table and e]
                if "CONFIG" in f:
                    out["config"] = _config_summary(f["CONFIG"].read())
            elif image is not None:
                hdu = f[image]
                header = header_dict(hdu.read_header())
                dims = [int(d) for d in hdu.get_dims()]
                out = {"kind": "image", "shape": dims, "type": _image_dtype(hdu).name}
                size = header.get("STAMPSZ")
                if isinstance(size, int) and size > 0 and len(dims) == 2:
                    out["stamp_size"] = size
                    out["grid"] = [dims[1] // size, dims[0] // size]
                    out["stamps"] = header.get("NSTAMPS", (dims[1] // size) * (dims[0] // size))
            else:
                raise InputError(f"{p}: a FITS file without a table or an image")
    except InputError:
        raise
    except (OSError, ValueError):
        raise InputError(f"{p}: not a readable FITS file (truncated or not FITS)") from None
    fmt = header.get("MLFORMAT")
    return {
        "path": str(p),
        "format": fmt if fmt is not None else f"FITS {out['kind']} (not written by megalut)",
        "format_version": header.get("MLFMTVER"),
        **out,
        "cards": {k: v for k, v in header.items() if k not in _PROVENANCE_CARDS and k != "EXTNAME"},
        "provenance": _provenance_from_header(header),
    }


def _image_dtype(hdu: Any) -> np.dtype:
    bitpix = {8: np.uint8, 16: np.int16, 32: np.int32, 64: np.int64, -32: np.float32, -64: np.float64}
    return np.dtype(bitpix.get(int(hdu.read_header().get("BITPIX", -32)), np.float32))


def _text(value: Any) -> str:
    return value.decode("ascii", "replace") if isinstance(value, bytes) else str(value)


def _config_summary(arr: np.ndarray) -> dict[str, Any]:
    """Sections and sha256 of the effective configuration stored in a CONFIG HDU."""
    out: dict[str, Any] = {}
    if arr.dtype.names and "config_json" in arr.dtype.names and len(arr):
        try:
            cfg = json.loads(_text(arr["config_json"][0]))
        except (ValueError, UnicodeDecodeError):
            cfg = None
        if isinstance(cfg, dict):
            out["sections"] = sorted(cfg)
    if arr.dtype.names and "config_sha256" in arr.dtype.names and len(arr):
        out["sha256"] = _text(arr["config_sha256"][0])
    return out


# --------------------------------------------------------------------------- models
def _describe_model(p: Path) -> dict[str, Any]:
    from megalut_cli.nn.model import ShearModel, prediction_column

    model = ShearModel.load(p)
    committees = []
    for comm in [*model.point.values(), *model.weight.values()]:
        valid = [m.valid_cost for m in comm.selected]
        committees.append({
            "kind": comm.kind,
            "target": comm.target,
            "output": prediction_column(comm.target, comm.kind),
            "features": comm.features,
            "hidden": list(comm.hidden),
            "cost": comm.cost,
            "members": len(comm.members),
            "selected": comm.n_selected,
            "valid_cost": [float(np.min(valid)), float(np.max(valid))] if valid else None,
            "iterations": int(max(m.n_iter for m in comm.members)),
            "normalization": {
                "method": comm.normalization,
                "in_loc": comm.in_loc.tolist(),
                "in_scale": comm.in_scale.tolist(),
                "out_loc": comm.out_loc,
                "out_scale": comm.out_scale,
            },
            "training": comm.training,
        })
    return {
        "path": str(p),
        "format": "megalut.model",
        "format_version": model.format_version,
        "kind": "model",
        "sha256": sha256_file(p),
        "uuid": model.uuid,
        "targets": model.targets,
        "features": model.features,
        "shear_mode": model.shear_mode,
        "committees": committees,
        "provenance": {"created": model.created, **model.provenance},
    }


# --------------------------------------------------------------------------- text
def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def _model_chain(prov: dict[str, Any]) -> list[str]:
    """One line per training step, the oldest first (``parent`` links)."""
    lines = []
    while isinstance(prov, dict) and prov:
        inputs = prov.get("inputs") or {}
        used = ", ".join(
            f"{role} {v.get('path', '?')} (sha256 {str(v.get('sha256', '?'))[:12]})"
            for role, v in inputs.items() if isinstance(v, dict)
        )
        lines.append(f"{prov.get('argv') or prov.get('command', '?')}" + (f"\n      inputs: {used}" if used else ""))
        prov = prov.get("parent")
    return lines[::-1]


def format_info(info: dict[str, Any]) -> str:
    """Human-readable summary of :func:`describe_file`'s dict."""
    lines = []
    kind = info["kind"]
    fmt = info["format"] + (f" {info['format_version']}" if info.get("format_version") else "")
    if kind == "catalog":
        lines.append(f"{info['path']}: {fmt}, {info['rows']} rows, {len(info['columns'])} columns")
        lines.append("columns:")
        width = max([len(c["name"]) for c in info["columns"]] + [4])
        for c in info["columns"]:
            unit = "?" if c["unit"] is None else (c["unit"] or "-")
            lines.append(f"  {c['name']:<{width}}  {c['type']:<8} {unit:<13} {c['description'] or ''}".rstrip())
        if "flags" in info:
            fl_info = info["flags"]
            lines.append(f"flags: {fl_info['rows_flagged']} of {info['rows']} rows flagged")
            for name, b in fl_info["bits"].items():
                lines.append(f"  {name:<16} {b['value']:>4}  {b['rows']} rows")
        if info.get("extensions"):
            lines.append(f"extensions: {', '.join(info['extensions'])}")
        if info.get("config"):
            cfg = info["config"]
            lines.append(f"config: sections {', '.join(cfg.get('sections', []))}; sha256 {cfg.get('sha256', '?')}")
    elif kind == "image":
        shape = "x".join(str(d) for d in info["shape"][::-1])
        lines.append(f"{info['path']}: {fmt}, image {shape} pixels ({info['type']})")
        if "stamp_size" in info:
            gx, gy = info["grid"]
            lines.append(f"stamps: {info['stamps']} of {info['stamp_size']}x{info['stamp_size']} pixels "
                         f"in a {gx}x{gy} grid")
    else:
        lines.append(f"{info['path']}: {fmt}, targets {', '.join(info['targets'])}")
        mode = info.get("shear_mode", "simulation")
        lines.append("mode: " + ("metacal (for catalogs of measure --metacal: features X_noshear..., calibrated by "
                                 "the response; docs/metacal.md)" if mode == "metacal" else
                                 "simulation-calibrated (for catalogs measured without --metacal)"))
        lines.append(f"features: {', '.join(info['features'])}")
        lines.append("committees:")
        for c in info["committees"]:
            vc = c["valid_cost"]
            cost = f", validation cost {vc[0]:.4g} to {vc[1]:.4g}" if vc else ""
            lines.append(f"  {c['kind']:<6} {c['target']} -> {c['output']}: {c['selected']} of {c['members']} "
                         f"networks selected, hidden {c['hidden']}, cost {c['cost']}, "
                         f"{c['iterations']} iterations{cost}")
            nrm = c["normalization"]
            lines.append(f"         features {', '.join(c['features'])}; normalization {nrm['method']}")
            if c["training"]:
                lines.append("         training: " + ", ".join(
                    f"{k}={_fmt_value(v)}" for k, v in sorted(c["training"].items())))
        lines.append(f"sha256: {info['sha256']}")
        lines.append(f"uuid: {info['uuid']}")
    if kind != "model":
        if info["cards"]:
            lines.append("cards: " + ", ".join(f"{k}={_fmt_value(v)}" for k, v in info["cards"].items()))
        prov = info["provenance"]
        lines.append(f"created: {prov.get('created') or '?'} by {prov.get('creator') or '?'}")
        extra = [f"{k} {_fmt_value(v)}" for k, v in prov.items() if k not in ("created", "creator", "steps")]
        if extra:
            lines.append("origin: " + ", ".join(extra))
        if prov["steps"]:
            lines.append("provenance:")
            lines += [f"  {i}. {s}" for i, s in enumerate(prov["steps"], start=1)]
    else:
        prov = info["provenance"]
        lines.append(f"created: {prov.get('created') or '?'}")
        versions = prov.get("versions")
        if isinstance(versions, dict):
            lines.append("versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()))
        chain = _model_chain(prov)
        if chain:
            lines.append("provenance:")
            lines += [f"  {i}. {s}" for i, s in enumerate(chain, start=1)]
    return "\n".join(lines)
