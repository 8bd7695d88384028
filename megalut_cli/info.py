"""What is inside a megalut file (``megalut info``): catalogs, stamp images, models,
evaluations (``evaluate --json``), run manifests (``manifest.json``) and text catalogs
(GREAT3's ``# name`` catalogs).

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
from megalut_cli.catalog import history_steps, read_text_catalog
from megalut_cli.errors import InputError
from megalut_cli.fits_header import header_dict
from megalut_cli.measure.meds import extra_columns, meds_extensions, read_meds
from megalut_cli.nn.domain import domain_summary, model_domain
from megalut_cli.nn.model import ShearModel, prediction_column
from megalut_cli.nn.population import domain_line, population_lines, population_summary
from megalut_cli.nn.shipped import SHIPPED_MODELS, shipped_model
from megalut_cli.pipeline.steps import MANIFEST_FORMAT
from megalut_cli.provenance import sha256_file, shown_command, shown_path
from megalut_cli.shear.frame import (
    FRAME_CARD,
    FRAME_TEXT,
    JACOBIAN_COLUMNS,
    PIXEL_FRAME,
    WORLD_FRAME,
    has_jacobian,
    jacobian_frames,
    usable_jacobians,
)
from megalut_cli.shear.options import JSON_FORMAT as EVALUATION_FORMAT

_FITS_MAGIC = b"SIMPLE  ="
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: Cards shown under "provenance" rather than with the other cards.
_PROVENANCE_CARDS = {
    "DATE",
    "CREATOR",
    "MLFORMAT",
    "MLFMTVER",
    "HISTORY",
    "MODEL",
    "MODELSHA",
    "CFGFILE",
    "CFGSHA",
    "CFGOVR",
    "SEED",
}
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
        if meds_extensions(p):  # a MEDS file (or an incomplete one: read_meds says why)
            return _describe_meds(p)
        return _describe_fits(p)
    if magic == _HDF5_MAGIC:
        return _describe_model(p)
    if magic.lstrip()[:1] == b"{":
        return _describe_json(p)
    try:
        return _describe_text_catalog(p)
    except InputError:
        pass
    raise InputError(
        f"{p}: not a FITS catalog or image, HDF5 model, megalut JSON file (evaluation, "
        "manifest) or text catalog"
    )


# --------------------------------------------------------------------------- JSON and text files
def _describe_json(p: Path) -> dict[str, Any]:
    """evaluate --json files and run manifests (their writers' format names)."""
    try:
        data = json.loads(p.read_text())
    except (UnicodeDecodeError, ValueError):
        raise InputError(f"{p}: not a readable JSON file") from None
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt == EVALUATION_FORMAT:
        return _describe_evaluation(p, data)
    if fmt == MANIFEST_FORMAT:
        return _describe_manifest(p, data)
    raise InputError(
        f"{p}: a JSON file megalut does not describe (format {fmt!r}; known: "
        f"{EVALUATION_FORMAT}, {MANIFEST_FORMAT})"
    )


def _describe_evaluation(p: Path, data: dict[str, Any]) -> dict[str, Any]:
    fits = {s: data[s] for s in ("unweighted", "weighted") if isinstance(data.get(s), dict)}
    prov = data.get("provenance") if isinstance(data.get("provenance"), dict) else {}
    return {
        "path": str(p),
        "format": data["format"],
        "format_version": data.get("format_version"),
        "kind": "evaluation",
        "input": data.get("input"),
        "rows": data.get("n_rows"),
        "rows_usable": data.get("n_valid"),
        "error": data.get("error"),
        "fits": fits,
        "requirement": data.get("requirement"),
        "conditional": sorted(data.get("conditional") or {}),
        "provenance": {k: prov.get(k) for k in ("created", "creator", "command") if k in prov},
    }


def _describe_manifest(p: Path, data: dict[str, Any]) -> dict[str, Any]:
    pipe = data.get("pipeline") if isinstance(data.get("pipeline"), dict) else {}
    steps = data.get("steps") if isinstance(data.get("steps"), dict) else {}
    return {
        "path": str(p),
        "format": data["format"],
        "format_version": data.get("format_version"),
        "kind": "manifest",
        "megalut": data.get("megalut"),
        "pipeline": {k: pipe.get(k) for k in ("path", "sha256", "overrides")},
        "pipelines": sorted(data.get("pipelines") or {}),
        "steps": {
            name: {
                "seconds": rec.get("seconds"),
                "finished": rec.get("finished"),
                "outputs": sorted(rec.get("outputs") or {}),
                "copied_from": rec.get("copied_from"),
            }
            for name, rec in steps.items()
            if isinstance(rec, dict)
        },
        "failed": data.get("failed") or {},
    }


def _describe_text_catalog(p: Path) -> dict[str, Any]:
    try:
        with open(p, "rb") as f:
            head = f.read(4096)
        if b"\0" in head or not head.lstrip().startswith(b"#"):
            raise InputError(f"{p}: not a text catalog")
        table = read_text_catalog(p)
    except (OSError, ValueError):
        raise InputError(f"{p}: not a text catalog") from None
    names = list(table.colnames)
    n = len(table)
    out: dict[str, Any] = {
        "path": str(p),
        "format": "text catalog",
        "format_version": None,
        "kind": "text_catalog",
        "rows": n,
        "columns": [{"name": c, "type": np.asarray(table[c]).dtype.name} for c in names],
    }
    great3 = _great3_kind(p.name, names)
    if great3:
        out["format"] = f"GREAT3 {great3} (text)"
    if "ID" in names and n:
        ids = np.asarray(table["ID"]).astype(np.int64)
        out["subfields"] = sorted({int(i) for i in ids // 1_000_000})[:20]
    for c in ("x", "y"):
        if c in names and n:
            v = np.asarray(table[c], dtype=float)
            out[f"{c}_range"] = [float(np.nanmin(v)), float(np.nanmax(v))]
    return out


def _great3_kind(name: str, columns: list[str]) -> str | None:
    """GREAT3's name of a text catalog, from its file name and columns (docs/great3.md)."""
    for prefix, what in (
        ("galaxy_catalog-", "galaxy catalog"),
        ("star_catalog-", "star catalog"),
        ("shear_params-", "shear parameters"),
        ("starshape_parameters-", "star shape parameters"),
        ("subfield_offset-", "subfield offset"),
        ("epoch_dither-", "epoch dither"),
    ):
        if name.startswith(prefix):
            return what
    if {"x", "y", "ID"} <= set(columns):
        return "galaxy catalog"
    return None


# --------------------------------------------------------------------------- FITS
def _columns(hdu: Any) -> list[dict[str, Any]]:
    hdr = hdu.read_header()
    dtype = hdu.get_rec_dtype()[0]
    out = []
    for i, name in enumerate(hdu.get_colnames(), start=1):
        unit = hdr.get(f"TUNIT{i}")
        comment = hdr.get(f"TCOMM{i}")
        out.append(
            {
                "name": name,
                "type": dtype[name].base.name
                if dtype[name].kind != "S"
                else f"str{dtype[name].itemsize}",
                "unit": None if unit is None else str(unit).strip(),
                "description": None if comment is None else str(comment).strip(),
            }
        )
    return out


def _flag_counts(hdu: Any, n_rows: int) -> dict[str, Any]:
    """Rows flagged, and rows per bit (names from the file's FLAGBITn cards, else flags.py)."""
    hdr = hdu.read_header()
    names = {
        1 << b: str(hdr.get(f"FLAGBIT{b}", fl.FLAG_NAMES.get(1 << b, f"BIT{b}"))).strip()
        for b in range(63)
    }
    total = 0
    per_bit = np.zeros(63, dtype=np.int64)
    view = hdu["flags"]
    for start in range(0, n_rows, _CHUNK_ROWS):
        v = np.asarray(view[start : min(start + _CHUNK_ROWS, n_rows)]).astype(np.int64)
        total += int(np.count_nonzero(v))
        for b in range(63):
            per_bit[b] += int(np.count_nonzero((v >> b) & 1))
    bits = {
        names[1 << b]: {"value": 1 << b, "rows": int(per_bit[b])} for b in range(63) if per_bit[b]
    }
    return {"rows_flagged": total, "rows_good": n_rows - total, "bits": bits}


def _provenance_from_header(header: dict[str, Any]) -> dict[str, Any]:
    prov: dict[str, Any] = {
        "created": header.get("DATE"),
        "creator": header.get("CREATOR"),
        "steps": history_steps(header.get("HISTORY", [])),
    }
    for key, card in (
        ("seed", "SEED"),
        ("config_file", "CFGFILE"),
        ("config_sha256", "CFGSHA"),
        ("config_overrides", "CFGOVR"),
        ("model", "MODEL"),
        ("model_sha256", "MODELSHA"),
    ):
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
                frame = _shear_frame(hdu.get_colnames(), header)
                if frame is not None:
                    out["frame"] = frame
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


#: Columns that make a catalog's shapes or shears worth naming a frame for.
_SPIN2_COLUMNS = ("adamom_g1", "adamom_g1_noshear", "pre_g1", "pre_g1_noshear", "g1")


def _shear_frame(colnames: list[str], header: dict[str, Any]) -> str | None:
    """What frame a catalog's shapes and shears are in (None for a catalog without any)."""
    frame = str(header.get(FRAME_CARD, "")).strip()
    if frame in FRAME_TEXT:
        return frame
    if not any(c in colnames for c in _SPIN2_COLUMNS):
        return None
    if has_jacobian(colnames):
        return f"{PIXEL_FRAME}, with per-object Jacobians (calibrate gives the {WORLD_FRAME} frame)"
    return PIXEL_FRAME


def _describe_meds(p: Path) -> dict[str, Any]:
    """A MEDS file, checked as ``measure`` reads it (:func:`megalut_cli.measure.meds.read_meds`:
    required columns, every cutout inside its extensions): objects, cutouts, box and PSF
    sizes, the maps it holds and what its Jacobians say about the frame."""
    meds = read_meds(p)
    obj = meds.objects
    ncut = np.asarray(obj["ncutout"], dtype=np.int64)
    used = np.arange(meds.n_max)[None, :] < ncut[:, None]
    out: dict[str, Any] = {
        "path": str(p),
        "format": "MEDS cutout file",
        "format_version": None,
        "kind": "meds",
        "objects": len(meds),
        "cutouts": int(ncut.sum()),
        "cutouts_per_object": {str(k): int(np.sum(ncut == k)) for k in np.unique(ncut)},
        "first_is_coadd": meds.first_is_coadd(),
        "box_sizes": {
            str(int(b)): int(np.sum(obj["box_size"] == b)) for b in np.unique(obj["box_size"])
        },
        "maps": [k for k in ("weight", "bmask", "seg", "psf") if meds.has(k)],
        "passed_columns": extra_columns(meds),
        "cards": {},
        "provenance": {"steps": []},
    }
    if meds.has("psf"):
        shapes = np.stack([meds.psf_shapes(k) for k in range(meds.n_max)], axis=1)[used]
        out["psf_sizes"] = sorted({f"{int(r)}x{int(c)}" for r, c in shapes})
    if all(c in obj for c in JACOBIAN_COLUMNS):
        jac = [np.asarray(obj[c], dtype=float)[used] for c in JACOBIAN_COLUMNS]
        ok = usable_jacobians(*jac)
        frames = jacobian_frames(*(j[ok] for j in jac)) if ok.any() else None
        out["jacobians"] = {
            "usable": int(ok.sum()),
            "of": int(used.sum()),
            **(
                {
                    "scale": [float(frames.scale.min()), float(frames.scale.max())],
                    "turned": int(np.sum(np.abs(np.sin(frames.angle)) > 1e-6)),
                    "flipped": int(np.sum(frames.parity < 0)),
                    "max_distortion": float(np.hypot(*frames.distortion.T).max()),
                }
                if frames is not None
                else {}
            ),
        }
    return out


def _meds_lines(info: dict[str, Any], fmt: str) -> list[str]:
    per = ", ".join(f"{n} with {k}" for k, n in info["cutouts_per_object"].items())
    boxes = ", ".join(f"{n} of {b} px" for b, n in info["box_sizes"].items())
    lines = [
        f"{info['path']}: {fmt}, {info['objects']} objects, {info['cutouts']} cutouts ({per})",
        "cutout 0: " + ("the coadd" if info["first_is_coadd"] else "a single epoch (no coadd)"),
        f"boxes: {boxes}",
        f"maps: {', '.join(info['maps']) or 'images only'}"
        + (f"; PSF cutouts {', '.join(info['psf_sizes'])}" if info.get("psf_sizes") else ""),
    ]
    jac = info.get("jacobians")
    if jac is None:
        lines.append("frame: no Jacobian columns: shears stay in the cutouts' pixel frame")
    elif not jac["usable"]:
        lines.append(f"frame: none of the {jac['of']} Jacobians is usable: pixel frame")
    else:
        lines.append(
            f"frame: {jac['usable']} of {jac['of']} cutouts with a usable Jacobian "
            f"(scale {jac['scale'][0]:.4g}–{jac['scale'][1]:.4g} per pixel, {jac['turned']} "
            f"turned, {jac['flipped']} flipped, residual shear up to "
            f"{jac['max_distortion']:.3g}): calibrate gives world-frame shears"
        )
    if info["passed_columns"]:
        lines.append(f"passed through by measure: {', '.join(info['passed_columns'])}")
    lines.append("valid: measure reads every cutout of it")
    return lines


def _image_dtype(hdu: Any) -> np.dtype:
    bitpix = {
        8: np.uint8,
        16: np.int16,
        32: np.int32,
        64: np.int64,
        -32: np.float32,
        -64: np.float64,
    }
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
    model = ShearModel.load(p)
    committees = []
    for comm in [*model.point.values(), *model.weight.values()]:
        valid = [m.valid_cost for m in comm.selected]
        committees.append(
            {
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
            }
        )
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
        "symmetry": model.symmetry,
        "committees": committees,
        "training_sets": _training_sets(model.provenance),
        "domain": model_domain(model.provenance),
        "provenance": {"created": model.created, **model.provenance},
    }


def _training_sets(prov: dict[str, Any]) -> list[dict[str, Any]]:
    """What each training step (the newest first) recorded of its set: the committees it
    trained, the catalog, the population (with its one-line summary) and the setup."""
    out = []
    while isinstance(prov, dict) and prov:
        if prov.get("command"):
            pop = prov.get("population") if isinstance(prov.get("population"), dict) else None
            train = (prov.get("inputs") or {}).get("train")
            catalog = (
                (train.get("name") or shown_path(train.get("path", "?")))
                if isinstance(train, dict)
                else None
            )
            out.append(
                {
                    "committees": "point estimates"
                    if prov.get("command") == "train-point"
                    else "weights",
                    "catalog": catalog or (pop or {}).get("config"),
                    "summary": (pop.get("summary") or population_summary(pop)) if pop else None,
                    "population": pop,
                    "setup": prov.get("setup") if isinstance(prov.get("setup"), dict) else None,
                }
            )
        prov = prov.get("parent")
    return out


def describe_shipped_models() -> list[dict[str, Any]]:
    """The models shipped with megalut (:data:`megalut_cli.nn.shipped.SHIPPED_MODELS`), one
    dict each: name, file, shear mode, what they were trained on (from the model files)."""
    out = []
    for name in SHIPPED_MODELS:
        path = shipped_model(name)
        model = ShearModel.load(path)
        sets = _training_sets(model.provenance)
        domain = model_domain(model.provenance)
        setup = next((t["setup"] for t in sets if t["setup"]), None) or {}
        out.append(
            {
                "name": name,
                "file": str(path),
                "shear_mode": model.shear_mode,
                "symmetry": model.symmetry,
                "trained_on": next((t["summary"] for t in sets if t["summary"]), None),
                "stamp_size": (domain or {}).get("stamp_size") or setup.get("stamp_size"),
                "domain": domain_summary(domain) if domain else None,
            }
        )
    return out


def format_shipped_models(models: list[dict[str, Any]]) -> str:
    """One line per shipped model: name, mode (and symmetry), training population and stamp
    size, file."""
    width = max(len(m["name"]) for m in models)
    modes = []
    for m in models:
        mode = str(m["shear_mode"])  # "simulation" or "metacal", as the docs name them
        if m.get("symmetry", "none") != "none":
            mode += f"+{m['symmetry']}"
        modes.append(mode)
    mode_width = max(len(x) for x in modes)
    lines = []
    for m, mode in zip(models, modes):
        stamp = f", stamp {m['stamp_size']} px" if m.get("stamp_size") else ""
        lines.append(
            f"{m['name']:<{width}}  {mode:<{mode_width}}  "
            f"{m['trained_on'] or 'training population not recorded'}{stamp}  ({m['file']})"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------- text
def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def _model_chain(prov: dict[str, Any]) -> list[str]:
    """One line per training step, the oldest first (``parent`` links); files by their
    recorded names (absolute paths of older records by their file names)."""
    lines = []
    while isinstance(prov, dict) and prov:
        inputs = prov.get("inputs") or {}
        used = ", ".join(
            f"{role} {v.get('name') or shown_path(v.get('path', '?'))} "
            f"(sha256 {str(v.get('sha256', '?'))[:12]})"
            for role, v in inputs.items()
            if isinstance(v, dict)
        )
        command = shown_command(prov["argv"]) if prov.get("argv") else prov.get("command", "?")
        lines.append(f"{command}" + (f"\n      inputs: {used}" if used else ""))
        prov = prov.get("parent")
    return lines[::-1]


def _training_lines(info: dict[str, Any]) -> list[str]:
    """The training population of every step in plain words, and the domain."""
    lines = []
    sets = info.get("training_sets") or []
    if sets:
        lines.append("trained on:")
    previous = None
    for t in sets:
        where = f" ({t['catalog']})" if t.get("catalog") else ""
        if t["population"] is None:
            lines.append(f"  {t['committees']}{where}: population not recorded")
            continue
        if (
            previous is not None
            and t["population"].get("summary") == previous.get("summary")
            and {k: t["population"].get(k) for k in ("galaxy", "psf", "noise")}
            == {k: previous.get(k) for k in ("galaxy", "psf", "noise")}
        ):
            lines.append(f"  {t['committees']}{where}: the same population")
            continue
        lines.append(f"  {t['committees']}{where}: {t['summary']}")
        setup = t.get("setup") or {"stamp_size": (info.get("domain") or {}).get("stamp_size")}
        lines += [f"    {line}" for line in population_lines(t["population"], setup)]
        previous = t["population"]
    domain = info.get("domain")
    lines.append(
        f"domain: {domain_line(domain)}"
        if domain
        else "domain: not recorded (predict compares only the recorded setup)"
    )
    return lines


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
            lines.append(
                (
                    f"  {c['name']:<{width}}  {c['type']:<8} {unit:<13} {c['description'] or ''}"
                ).rstrip()
            )
        if "flags" in info:
            fl_info = info["flags"]
            lines.append(f"flags: {fl_info['rows_flagged']} of {info['rows']} rows flagged")
            for name, b in fl_info["bits"].items():
                lines.append(f"  {name:<16} {b['value']:>4}  {b['rows']} rows")
        if info.get("frame"):
            frame = info["frame"]
            lines.append(f"frame: {frame}: {FRAME_TEXT[frame.split(',')[0]]}")
        if info.get("extensions"):
            lines.append(f"extensions: {', '.join(info['extensions'])}")
        if info.get("config"):
            cfg = info["config"]
            lines.append(
                f"config: sections {', '.join(cfg.get('sections', []))}; "
                f"sha256 {cfg.get('sha256', '?')}"
            )
    elif kind == "image":
        shape = "x".join(str(d) for d in info["shape"][::-1])
        lines.append(f"{info['path']}: {fmt}, image {shape} pixels ({info['type']})")
        if "stamp_size" in info:
            gx, gy = info["grid"]
            lines.append(
                f"stamps: {info['stamps']} of {info['stamp_size']}x{info['stamp_size']} pixels "
                f"in a {gx}x{gy} grid"
            )
    elif kind in _OTHER_FORMATS:
        lines += _OTHER_FORMATS[kind](info, fmt)
        return "\n".join(lines)
    else:
        lines.append(f"{info['path']}: {fmt}, targets {', '.join(info['targets'])}")
        mode = info.get("shear_mode", "simulation")
        lines.append(
            "mode: "
            + (
                "metacal (for catalogs of measure --metacal: features X_noshear..., calibrated by "
                "the response; docs/metacal.md)"
                if mode == "metacal"
                else "simulation-calibrated (for catalogs measured without --metacal)"
            )
        )
        lines.append(
            "symmetry: "
            + (
                "d4 (the networks averaged over the stamp's 90-degree rotations and reflections: "
                "no additive bias of their own; docs/metacal.md)"
                if info.get("symmetry") == "d4"
                else "none (the networks as trained)"
            )
        )
        lines.append(f"features: {', '.join(info['features'])}")
        lines.append("committees:")
        for c in info["committees"]:
            vc = c["valid_cost"]
            cost = f", validation cost {vc[0]:.4g} to {vc[1]:.4g}" if vc else ""
            lines.append(
                f"  {c['kind']:<6} {c['target']} -> {c['output']}: "
                f"{c['selected']} of {c['members']} "
                f"networks selected, hidden {c['hidden']}, cost {c['cost']}, "
                f"{c['iterations']} iterations{cost}"
            )
            nrm = c["normalization"]
            lines.append(
                f"         features {', '.join(c['features'])}; normalization {nrm['method']}"
            )
            if c["training"]:
                lines.append(
                    "         training: "
                    + ", ".join(f"{k}={_fmt_value(v)}" for k, v in sorted(c["training"].items()))
                )
        lines += _training_lines(info)
        lines.append(f"sha256: {info['sha256']}")
        lines.append(f"uuid: {info['uuid']}")
    if kind != "model":
        if info["cards"]:
            lines.append(
                "cards: " + ", ".join(f"{k}={_fmt_value(v)}" for k, v in info["cards"].items())
            )
        prov = info["provenance"]
        lines.append(f"created: {prov.get('created') or '?'} by {prov.get('creator') or '?'}")
        extra = [
            f"{k} {_fmt_value(v)}"
            for k, v in prov.items()
            if k not in ("created", "creator", "steps")
        ]
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


def _pm(v: Any, e: Any) -> str:
    if v is None:
        return "undetermined"
    return f"{v:+.2e} ± " + (f"{e:.1e}" if e is not None else "n/a")


def _evaluation_lines(info: dict[str, Any], fmt: str) -> list[str]:
    lines = [
        f"{info['path']}: {fmt}, the biases of {info.get('input') or '?'} "
        f"({info.get('rows_usable', '?')} of {info.get('rows', '?')} rows usable)"
    ]
    lines.append(
        f"""errors: {
            "bootstrap over galaxies"
            if info.get("error") == "bootstrap-galaxies"
            else "from the fit"
        }"""
    )
    for scheme, comps in info["fits"].items():
        for comp, f in comps.items():
            lines.append(
                f"  {scheme:<10} {comp:<5} m = {_pm(f.get('m'), f.get('m_err')):<21} "
                f"c = {_pm(f.get('c'), f.get('c_err')):<21} {f.get('n_cases', '?')} cases"
            )
    req = info.get("requirement")
    if isinstance(req, dict):
        lines.append(
            f"Stage IV requirement on {req.get('applies_to', '?')} results: "
            + ("met" if req.get("met") else "NOT met")
        )
    if info.get("conditional"):
        lines.append(f"conditional biases by: {', '.join(info['conditional'])}")
    prov = info["provenance"]
    lines.append(f"created: {prov.get('created') or '?'} by {prov.get('creator') or '?'}")
    if prov.get("command"):
        lines.append(f"command: {prov['command']}")
    return lines


def _manifest_lines(info: dict[str, Any], fmt: str) -> list[str]:
    pipe = info["pipeline"]
    sha = str(pipe.get("sha256") or "?")[:12]
    lines = [
        f"{info['path']}: {fmt}, a megalut run's work folder record "
        f"(megalut {info.get('megalut') or '?'})",
        f"pipeline: {pipe.get('path') or '?'} (sha256 {sha}), overrides: "
        + (" ".join(pipe.get("overrides") or []) or "none"),
    ]
    if len(info["pipelines"]) > 1:
        lines.append(
            f"pipelines run here: {', '.join(n or '(unnamed)' for n in info['pipelines'])}"
        )
    steps = info["steps"]
    lines.append(f"steps: {len(steps)} finished")
    width = max([len(n) for n in steps] + [4])
    for name, st in steps.items():
        secs = st.get("seconds")
        took = f"{secs:.1f} s" if isinstance(secs, (int, float)) else "?"
        copied = f" (copied from {st['copied_from']})" if st.get("copied_from") else ""
        lines.append(
            f"  {name:<{width}}  {took:>9}  {st.get('finished') or '?':<19}  "
            f"{', '.join(st['outputs'])}{copied}".rstrip()
        )
    for unit, error in info["failed"].items():
        lines.append(f"  failed: {unit}: {error}")
    return lines


def _text_catalog_lines(info: dict[str, Any], fmt: str) -> list[str]:
    lines = [
        f"{info['path']}: {fmt}, {info['rows']} rows, {len(info['columns'])} columns: "
        + ", ".join(c["name"] for c in info["columns"])
    ]
    if "subfields" in info:
        lines.append(f"subfields (ID // 10^6): {', '.join(map(str, info['subfields']))}")
    for c in ("x", "y"):
        if f"{c}_range" in info:
            lo, hi = info[f"{c}_range"]
            lines.append(f"{c}: {lo:g} to {hi:g}")
    return lines


_OTHER_FORMATS = {
    "meds": _meds_lines,
    "evaluation": _evaluation_lines,
    "manifest": _manifest_lines,
    "text_catalog": _text_catalog_lines,
}
