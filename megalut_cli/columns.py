"""Units and descriptions of catalog columns, written as ``TUNITn``/``TCOMMn`` cards.

One table for every writer: exact names in :data:`COLUMNS`, families by pattern
(``pre_X`` takes the unit of ``tru_X``, ``psf_adamom_X`` that of ``adamom_X``). A column
not known here gets no unit rather than a wrong one. Units follow the FITS standard
(``pixel``, ``adu``, ``deg``, ``mag``); an empty unit means a dimensionless quantity.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

from megalut_cli import flags
from megalut_cli.measure.feature_sets import column_descriptions
from megalut_cli.measure.metacal_defaults import TYPES

#: (unit, comment) of the columns megalut writes, the feature sets' declared with them.
COLUMNS: dict[str, tuple[str, str]] = {
    "case": ("", "case index (one galaxy/shear per case)"),
    "rea": ("", "realization index within the case"),
    "x": ("pixel", "stamp centre x in the image (1-based unless XYORIGIN = 0)"),
    "y": ("pixel", "stamp centre y in the image (1-based unless XYORIGIN = 0)"),
    "subfield": ("", "GREAT3 subfield"),
    "ID": ("", "GREAT3 galaxy ID"),
    "star": ("", "star index in the star field"),
    "id": ("", "object id (MEDS object_data id)"),
    "number": ("", "object number in the segmentation maps (MEDS)"),
    "box_size": ("pixel", "MEDS cutout size of the object"),
    "ncutout": ("", "MEDS cutouts of the object (coadd and epochs)"),
    "ra": ("deg", "right ascension"),
    "dec": ("deg", "declination"),
    "orig_row": ("pixel", "MEDS object row in the measured cutout's image (0-based)"),
    "orig_col": ("pixel", "MEDS object column in the measured cutout's image (0-based)"),
    **{
        f"d{w}d{p}": (
            "",
            f"Jacobian d{w}/d{p} of the measured stamp (world units per pixel; u west, v north)",
        )
        for w in "uv"
        for p in ("col", "row")
    },
    "psf_g1": ("", "PSF ellipticity g1 at the object, in the frame of g1, g2 (SHFRAME)"),
    "psf_g2": ("", "PSF ellipticity g2 at the object, in the frame of g1, g2 (SHFRAME)"),
    "n_epochs": ("", "epochs combined into the row (calibrate -o of measure --epochs)"),
    "cutout": ("", "MEDS cutout index of the row (measure --epochs: one row per epoch)"),
    "noise_weight": ("adu", "pixel noise from the weight map: 1/sqrt(median weight)"),
    "n_masked": ("", "masked pixels of the stamp (bmask != 0 or weight 0; -1: no cutout)"),
    "g1": ("", "calibrated shear estimate g1 (megalut calibrate; for averages, not one object)"),
    "g2": ("", "calibrated shear estimate g2 (megalut calibrate; for averages, not one object)"),
    "weight": ("", "weight of the object: mean of weight_g1 and weight_g2"),
    "weight_g1": ("", "weight of g1 (pre_g1_w, or 1 unweighted)"),
    "weight_g2": ("", "weight of g2 (pre_g2_w, or 1 unweighted)"),
    "bin": ("", "calibration bin of the object (megalut calibrate --by; -1: none)"),
    **{
        f"R{i}{j}": ("", f"total response R{i}{j} of the object's bin (mean + selection)")
        for i in "12"
        for j in "12"
    },
    "tru_g1": ("", "true reduced shear g1"),
    "tru_g2": ("", "true reduced shear g2"),
    "tru_e1": ("", "true intrinsic ellipticity e1"),
    "tru_e2": ("", "true intrinsic ellipticity e2"),
    "tru_ell": ("", "true intrinsic ellipticity modulus |e|"),
    "tru_theta": ("deg", "true position angle of the galaxy, in [0, 180)"),
    "tru_flux": ("adu", "true total flux of the galaxy"),
    "tru_rad": ("pixel", "true half-light radius"),
    "tru_sersicn": ("", "true Sersic index"),
    "tru_sb": ("adu / pixel2", "true mean surface brightness, flux / (pi rad^2)"),
    "tru_mag": ("mag", "true magnitude"),
    "tru_sky_sigma": ("adu", "true sky noise standard deviation"),
    "tru_dx": ("pixel", "true sub-pixel offset of the galaxy in x"),
    "tru_dy": ("pixel", "true sub-pixel offset of the galaxy in y"),
    "tru_psf_g1": ("", "true PSF reduced shear g1"),
    "tru_psf_g2": ("", "true PSF reduced shear g2"),
    "tru_psf_sigma": ("pixel", "true PSF size sigma"),
    "tru_field_x": ("", "true field position x (field units, 0 to 1)"),
    "tru_field_y": ("", "true field position y (field units, 0 to 1)"),
    "tru_real_index": ("", "index of the real galaxy in its catalog"),
    "tru_flux_drawn": ("adu", "flux of the galaxy on the field's pixels (scenes)"),
    "image": ("", "image index in the scene cubes (fields x signs)"),
    "field": ("", "scene field index (one shear per field)"),
    "pair_sign": ("", "sign of the field's shear in this image (+1, -1 with pairs)"),
    "galaxy": ("", "galaxy index within its scene field"),
    "n_gal": ("", "number of galaxies in the scene field"),
    "mdet_step": ("", "metadetect version the row was detected on (noshear, 1p, 1m, 2p, 2m)"),
    "inner": ("", "1: the detection lies in its cell's inner region (metadetect)"),
    "mask_dist": (
        "pixel",
        "distance to the nearest masked pixel of the cell (from the unsheared detection) or "
        "of the stamp (MEDS); inf: none",
    ),
    "cell": ("", "metadetection of a coadd: the cell the row was detected in (row by row)"),
    "tru_hst_noise_var": ("adu2", "variance of the HST noise left in the stamp"),
    "tru_twin": ("", "1: the real galaxy's Sersic twin was drawn, 0: the real galaxy"),
    "tru_twin_rad": ("pixel", "half-light radius of the real galaxy's Sersic fit"),
    "tru_twin_sersicn": ("", "Sersic index of the real galaxy's Sersic fit"),
    "tru_twin_g1": ("", "intrinsic shape g1 of the Sersic fit (HST frame)"),
    "tru_twin_g2": ("", "intrinsic shape g2 of the Sersic fit (HST frame)"),
    **column_descriptions(),
}

_METACAL = re.compile(rf"^(?P<base>.+)_(?P<kind>{'|'.join(TYPES)})$")
_RESPONSE = re.compile(r"^mcal_r(?P<i>[12])(?P<j>[12])$")
_PRE_WEIGHT = re.compile(r"^pre_(?P<base>.+)_w$")
_PRE = re.compile(r"^pre_(?P<base>.+)$")
_PSF = re.compile(r"^psf_(?P<base>adamom_.+)$")


def describe(name: str) -> tuple[str, str] | None:
    """``(unit, comment)`` of column ``name``, or None when megalut does not know it."""
    if name in COLUMNS:
        return COLUMNS[name]
    if m := _RESPONSE.match(name):
        return ("", f"metacal response dpre_g{m['i']}/dg{m['j']} (finite difference)")
    if m := _METACAL.match(name):
        base = describe(m["base"])
        return None if base is None else (base[0], f"metacal {m['kind']}: {base[1]}"[:68])
    if name.startswith("flags_") and name[len("flags_") :] in TYPES:
        return ("", f"flags of the metacal {name[len('flags_') :]} version")
    if m := _PSF.match(name):
        base = describe(m["base"])
        return None if base is None else (base[0], f"PSF: {base[1]}"[:68])
    if m := _PRE_WEIGHT.match(name):
        return ("", f"weight of pre_{m['base']}, in (0, 1)")
    if m := _PRE.match(name):
        truth = describe(f"tru_{m['base']}")
        unit = truth[0] if truth is not None else None
        if unit is None:
            return None
        return (unit, f"estimate of tru_{m['base']}")
    return None


def column_units(names: Sequence[str]) -> list[str]:
    """FITS units of ``names`` (empty for dimensionless and unknown columns)."""
    return [(describe(n) or ("", ""))[0] for n in names]


def column_cards(names: Sequence[str]) -> list[dict[str, Any]]:
    """``TCOMMn`` (and empty ``TUNITn``) records for each known column of ``names``.

    Units go through fitsio's ``units=`` argument (:func:`column_units`), which places
    ``TUNITn`` next to ``TTYPEn``; a known dimensionless column gets ``TUNITn = ''``
    here, an unknown column no card. ``flags`` adds the ``FLAGBITn`` cards.
    """
    recs: list[dict[str, Any]] = []
    for i, name in enumerate(names, start=1):
        desc = describe(name)
        if desc is None:
            continue
        if not desc[0]:
            recs.append({"name": f"TUNIT{i}", "value": "", "comment": "dimensionless"})
        recs.append({"name": f"TCOMM{i}", "value": desc[1][:68], "comment": ""})
    if "flags" in names:
        recs.extend(flag_cards())
    return recs


def flag_cards() -> list[dict[str, Any]]:
    """``FLAGBITn = NAME / value: description`` for every bit of :mod:`megalut_cli.flags`."""
    recs = []
    for value, name in sorted(flags.FLAG_NAMES.items()):
        bit = value.bit_length() - 1
        recs.append(
            {
                "name": f"FLAGBIT{bit}",
                "value": name,
                "comment": f"{value}: {flags.FLAG_DESCRIPTIONS[value]}"[:46],
            }
        )
    return recs
