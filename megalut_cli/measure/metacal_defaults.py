"""Metacalibration constants, import-free (the options and the docs read them without GalSim)."""

#: The five versions of a stamp, in output order.
TYPES = ("noshear", "1p", "1m", "2p", "2m")
#: The applied shear of each version, for a step of 1.
SHEARS = {
    "noshear": (0.0, 0.0),
    "1p": (1.0, 0.0),
    "1m": (-1.0, 0.0),
    "2p": (0.0, 1.0),
    "2m": (0.0, -1.0),
}
#: The default shear step.
DEFAULT_STEP = 0.01
#: The step's range: above 0.1 the finite difference is no longer a first-order response.
MAX_STEP = 0.1
#: Header card of a catalog measured (or predicted) in metacal mode: the step.
STEP_CARD = "MCALSTEP"
#: Header card: the seed of the fixnoise fields.
SEED_CARD = "MCALSEED"
#: The features of the target PSF that a metacal catalog holds as ``psf_<X>_<type>``.
TARGET_PSF_COLUMNS = ("adamom_g1", "adamom_g2", "adamom_sigma", "adamom_rho4")
#: The metacal target PSF when none is named (:mod:`.metacal_targets`): the round Gaussian.
DEFAULT_TARGET = "gauss"
#: Header card of a catalog whose metacal target is not the default: the target's name.
TARGET_CARD = "MCALTARG"
#: The interpolant of the stamp and PSF images (ngmix's choice; lanczos15 keeps the
#: interpolation error of a sheared, deconvolved image at the 1e-4 level).
INTERPOLANT = "lanczos15"
#: Metadetection catalogs (``measure --metadetect``): the column naming each detection's
#: version, and the header card of the step.
MDET_COLUMN = "mdet_step"
MDET_STEP_CARD = "MDETSTEP"
