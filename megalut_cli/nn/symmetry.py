"""Estimators that cannot create an additive bias: networks averaged over the symmetries of
the pixel grid (docs/metacal.md, "The networks' additive bias").

Rotating a stamp by 90 degrees or reflecting it maps a spin-2 quantity (a shape, a shear)
``(a, b)`` to ``(-a, -b)``, ``(a, -b)`` or ``(-a, b)`` and leaves sizes, fluxes and noise
levels unchanged. A network trained on the features need not respect this; its mean over a
ring of orientations is then not zero, which metacal's multiplicative response does not
remove. With ``symmetry = "d4"`` a model's estimate is the mean of the network over the four
actions, each mapped back: ``g1 = (f1(x) - f1(-x) + f1(x*) - f1(-x*)) / 4`` (``x*`` the
reflected features), likewise ``g2``, and the weights are averaged. It is then odd under a
90-degree rotation and equivariant under reflections, by construction.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from megalut_cli.errors import InputError

#: ``symmetry`` of a model: its networks as trained, or averaged over the pixel grid's symmetries.
SYMMETRIES = ("none", "d4")

#: Feature pairs that transform as a shear (first and second component).
SPIN2_PAIRS = (("adamom_g1", "adamom_g2"), ("psf_adamom_g1", "psf_adamom_g2"))

#: Features that a rotation by a multiple of 90 degrees or a reflection of the stamp leaves
#: unchanged.
INVARIANT = frozenset(
    {
        "adamom_flux",
        "adamom_logflux",
        "adamom_sigma",
        "adamom_rho4",
        "psf_adamom_flux",
        "psf_adamom_sigma",
        "psf_adamom_rho4",
        "skymad",
        "snr",
        "morph_conc",
        "morph_conc_inner",
        "morph_size_ratio",
    }
)

#: The action of the pixel grid's symmetries (dihedral group D4) on spin-2 quantities: signs of
#: the first and second components. Identity (and 180 degrees), 90 degrees (and 270), the
#: reflections about the axes, those about the diagonals.
ACTIONS = ((1.0, 1.0), (-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0))


def feature_signs(features: Sequence[str]) -> np.ndarray:
    """``(len(ACTIONS), len(features))``: how each action multiplies each feature.

    :class:`InputError` for a feature whose transformation is not known (a centroid, a
    column of the user's)."""
    signs = np.ones((len(ACTIONS), len(features)))
    component = {name: i for pair in SPIN2_PAIRS for i, name in enumerate(pair)}
    unknown = [f for f in features if f not in component and f not in INVARIANT]
    if unknown:
        raise InputError(
            f"symmetry d4: how a rotation of the stamp changes feature(s) {', '.join(unknown)} "
            "is not known; use symmetry none"
        )
    for j, f in enumerate(features):
        if f in component:
            signs[:, j] = [a[component[f]] for a in ACTIONS]
    return signs


def output_signs(target: str, kind: str) -> np.ndarray:
    """How each action multiplies a committee's output: a shear component's sign, or 1 for a
    weight."""
    if kind == "weight":
        return np.ones(len(ACTIONS))
    comp = {"tru_g1": 0, "tru_g2": 1}.get(target)
    if comp is None:
        raise InputError(f"symmetry d4: target {target!r} is not a shear component")
    return np.array([a[comp] for a in ACTIONS])


def predict_with_symmetry(
    symmetry: str,
    predict: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    features: Sequence[str],
    target: str,
    kind: str,
) -> np.ndarray:
    """``predict`` on the rows ``x`` (columns ``features``): as it is for ``"none"``, or for
    ``"d4"`` its mean over the actions of :data:`ACTIONS`, each output mapped back."""
    if symmetry == SYMMETRIES[0]:
        return np.asarray(predict(np.ascontiguousarray(x)), dtype=np.float64)
    fsign = feature_signs(features)
    osign = output_signs(target, kind)
    total = np.zeros(x.shape[0])
    for a in range(len(ACTIONS)):
        xa = x * fsign[a] if np.any(fsign[a] != 1.0) else x
        total += osign[a] * np.asarray(predict(np.ascontiguousarray(xa)), dtype=np.float64)
    return total / len(ACTIONS)
