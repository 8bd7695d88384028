"""Small simulation configs shared by the simulate tests (tiny stamps, fast)."""

from __future__ import annotations

from pathlib import Path

COSMOS = (
    Path(__file__).resolve().parents[1]
    / "examples"
    / "data"
    / "cosmos"
    / "real_galaxy_catalog_23.5_example_fits.fits"
)
#: GalSim's COSMOS noise correlation function (getCOSMOSNoise).
CF_FILE = COSMOS.parent / "acs_I_unrot_sci_20_cf.fits"

TINY = """
description = "tiny test set"

[structure]
n_cases = 3
n_realizations = 4
per_realization = ["angle"]
snc = "ring"
stamp_size = 24
offset = 0.5

[shear]
g1 = {type = "uniform", min = -0.1, max = 0.1}
g2 = {type = "uniform", min = -0.1, max = 0.1}

[galaxy]
profile = "sersic"
sersicn = {type = "grid", min = 1.0, max = 2.0, step = 0.5}
rad = {type = "uniform", min = 1.5, max = 3.0}
sb = {type = "uniform", min = 5.0, max = 15.0}
ellipticity = {type = "rayleigh", mode = 0.2, min = 0.0, max = 0.6}
angle = {type = "uniform", min = 0.0, max = 180.0}

[psf]
type = "gaussian"
sigma = 1.5

[noise]
type = "gaussian"
sigma = 1.0
"""


# Galaxy models (tests/test_sim_models.py) and correlated noise (tests/test_sim_noise.py).
BULGEDISK = """
[structure]
n_cases = 3
n_realizations = 4
per_realization = ["angle"]
snc = "ring"
stamp_size = 32

[shear]
g1 = {type = "uniform", min = -0.05, max = 0.05}

[galaxy]
profile = "bulgedisk"
rad = {type = "uniform", min = 2.0, max = 4.0}
flux = 500.0
ellipticity = {type = "rayleigh", mode = 0.25, min = 0.0, max = 0.7}
bulge_fraction = {type = "uniform", min = 0.1, max = 0.5}
bulge_rad_ratio = 0.4
knots = 12
knots_fraction = 0.2

[psf]
type = "gaussian"
sigma = 1.5

[noise]
type = "gaussian"
sigma = 1.0
"""

COSMOSFIT = f"""
[structure]
n_cases = 3
n_realizations = 4
per_realization = ["angle"]
snc = "ring"
stamp_size = 32

[galaxy]
profile = "cosmos_fit"
fit = "auto"
pixel_scale = 0.1
mag = {{type = "catalog", column = "mag_auto"}}

[catalog]
path = "{COSMOS}"
select = "mag_auto < 23"

[instrument]
zeropoint = 24.6
exptime = 1695.0
gain = 3.1

[psf]
type = "gaussian"
sigma = 1.5

[noise]
type = "gaussian"
sigma = 1.0
"""

NOISE_ONLY = """
[structure]
n_cases = 2
n_realizations = 3
per_realization = ["galaxy"]
stamp_size = 32

[galaxy]
profile = "gaussian"
rad = 2.0
flux = 0.0

[psf]
type = "gaussian"
sigma = 1.5

[noise]
type = "correlated"
SOURCE
"""


def write(
    tmp_path: Path, text: str = TINY, name: str = "sim.toml", replace: dict[str, str] | None = None
) -> Path:
    """Write a config (with optional plain-text replacements) and return its path."""
    for old, new in (replace or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    p = tmp_path / name
    p.write_text(text)
    return p
