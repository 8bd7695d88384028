"""A tiny pipeline shared by the `megalut run` tests (small stamps, few networks: seconds)."""

from __future__ import annotations

from pathlib import Path

TINY_PIPELINE = """
description = "tiny test pipeline"

[simulation.structure]
stamp_size = 24

[simulation.shear]
g1 = {type = "uniform", min = -0.1, max = 0.1}
g2 = {type = "uniform", min = -0.1, max = 0.1}

[simulation.galaxy]
profile = "gaussian"
rad = {type = "uniform", min = 1.5, max = 3.0}
flux = {type = "uniform", min = 150.0, max = 500.0}
ellipticity = {type = "rayleigh", mode = 0.2, min = 0.0, max = 0.6}

[simulation.psf]
type = "gaussian"
sigma = 1.5

[simulation.noise]
type = "gaussian"
sigma = 1.0

[sets.tp]
n_cases = 24
n_realizations = 8
seed = 1
simulation = {structure = {per_realization = ["angle"], snc = "ring"}}

[sets.tw]
n_cases = 8
n_realizations = 30
seed = 2
simulation = {structure = {per_realization = ["galaxy"], snc = "pairs"}}

[sets.vo]
n_cases = 8
n_realizations = 30
seed = 3
simulation = {structure = {per_realization = ["galaxy"], snc = "pairs"}}

[train_point]
members = 2
iterations = 15
seed = 11

[train_weight]
members = 2
iterations = 10
seed = 12

[evaluate]
plot = false
"""

#: Appended to TINY_PIPELINE: a low-noise, unsheared pretraining set (Fig. 6 structure) and a
#: VP set (Fig. 4 structure), for the pipelines of the paper's Sects. 6 and 7.
PRETRAIN_VP = (
    """
[sets.pretrain]
n_cases = 40
n_realizations = 2
seed = 4
simulation = {structure = {per_realization = [], snc = "none"}, noise = {sigma = 0.1}, """
    """shear = {g1 = {type = "constant", value = 0.0}, g2 = {type = "constant", value = 0.0}}}

[sets.vp]  # as TP, more realizations per case
simulation = {structure = {per_realization = ["angle"], snc = "ring"}}
seed = 5
n_cases = 10
n_realizations = 16

[evaluate_vp]
by = ["tru_rad"]
bins = 2
plot = false

[pretrain]
members = 2
iterations = 15
seed = 10
"""
)


def write_pipeline(folder: Path, text: str = TINY_PIPELINE, name: str = "pipeline.toml") -> Path:
    path = Path(folder) / name
    path.write_text(text)
    return path
