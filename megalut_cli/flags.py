"""The ``flags`` bitmask of megalut catalogs: bit names, values and an explainer.

A row with ``flags != 0`` has NaN features (and, after ``predict``, NaN estimates and
zero weights). Bits combine, e.g. 1 | 16 = 17.
"""

from __future__ import annotations

#: HSM FindAdaptiveMom did not converge (or raised).
HSM_FAILED = 1 << 0
#: Adaptive-moment centroid more than the allowed distance from the stamp centre.
CENTROID_SHIFT = 1 << 1
#: Adaptive-moment flux (amplitude) is not positive.
NEGATIVE_FLUX = 1 << 2
#: The stamp does not lie entirely inside the image.
STAMP_OFF_IMAGE = 1 << 3
#: The stamp contains NaN or infinite pixels.
BAD_PIXELS = 1 << 4
#: The sky noise estimate (``skymad``) is not finite (zero is allowed: noiseless images).
BAD_SKY = 1 << 5
#: The PSF stamp could not be measured.
PSF_FAILED = 1 << 6
#: ``predict``: an input feature of the model is missing or not finite on this row.
BAD_FEATURES = 1 << 7
#: MEDS input: the object has no cutout of the index measured (``ncutout`` too small).
NO_CUTOUT = 1 << 8
#: MEDS input: too many masked pixels (bad-mask bits or zero weight) for usable moments:
#: more than ``meds.MAX_MASKED_FRACTION`` (25 %) of the stamp, or one within
#: ``meds.CENTRAL_MASK_RADIUS`` (2 pixels) of the object's position.
MASKED_PIXELS = 1 << 9
#: A masked pixel within ``--mask-margin`` pixels of the object: of its cell, from the
#: detection's unsheared position (metadetection: the same place in every version), or of
#: its stamp (MEDS input).
NEAR_MASK = 1 << 10
#: Detections (``--metadetect``, ``--detect``): the adaptive-moment centroid lies within
#: ``--duplicate-radius`` of another detection's of the same image and version, the same
#: light measured twice (a galaxy split by the deblending, or a neighbour's light taken
#: over); the detection nearest that centroid keeps it.
DUPLICATE = 1 << 11

FLAG_NAMES: dict[int, str] = {
    HSM_FAILED: "HSM_FAILED",
    CENTROID_SHIFT: "CENTROID_SHIFT",
    NEGATIVE_FLUX: "NEGATIVE_FLUX",
    STAMP_OFF_IMAGE: "STAMP_OFF_IMAGE",
    BAD_PIXELS: "BAD_PIXELS",
    BAD_SKY: "BAD_SKY",
    PSF_FAILED: "PSF_FAILED",
    BAD_FEATURES: "BAD_FEATURES",
    NO_CUTOUT: "NO_CUTOUT",
    MASKED_PIXELS: "MASKED_PIXELS",
    NEAR_MASK: "NEAR_MASK",
    DUPLICATE: "DUPLICATE",
}

FLAG_DESCRIPTIONS: dict[int, str] = {
    HSM_FAILED: "HSM adaptive moments failed",
    CENTROID_SHIFT: "adaptive-moment centroid too far from the stamp centre",
    NEGATIVE_FLUX: "adaptive-moment flux not positive",
    STAMP_OFF_IMAGE: "stamp not entirely inside the image",
    BAD_PIXELS: "NaN or infinite pixels in the stamp",
    BAD_SKY: "sky noise (skymad) not finite",
    PSF_FAILED: "PSF stamp could not be measured",
    BAD_FEATURES: "model input features missing or not finite",
    NO_CUTOUT: "MEDS object without the cutout measured",
    MASKED_PIXELS: "masked pixels: over 25 % of the stamp, or within 2 px of the centre",
    NEAR_MASK: "a masked pixel of the cell or stamp within --mask-margin of the object",
    DUPLICATE: "centroid within --duplicate-radius of another detection's: the same light",
}


def explain(value: int) -> list[str]:
    """Names of the bits set in ``value`` (unknown bits as ``BIT<n>``)."""
    value = int(value)
    names = []
    bit = 0
    while value >> bit:
        if (value >> bit) & 1:
            names.append(FLAG_NAMES.get(1 << bit, f"BIT{bit}"))
        bit += 1
    return names
