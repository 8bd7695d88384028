"""The subcommands of ``megalut`` in the order of the data flow: module and one-line help.

Import-free, so that ``megalut --version`` and ``megalut --help`` load no subcommand (each
is imported when it runs or its own help is asked for).
"""

from __future__ import annotations

#: name -> (module defining ``command``, the short help shown by ``megalut --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("megalut_cli.cli.simulate", "Simulate galaxy stamps with known shear."),
    "measure": (
        "megalut_cli.cli.measure",
        "Measure adaptive-moment features on a FITS image of stamps or a MEDS file.",
    ),
    "train-point": ("megalut_cli.cli.train_point", "Train point-estimate committees (MSB cost)."),
    "train-weight": (
        "megalut_cli.cli.train_weight",
        "Train weight committees (MSWB cost) for a point model.",
    ),
    "predict": (
        "megalut_cli.cli.predict",
        "Apply a trained model: add pre_g1, pre_g2 (and weights).",
    ),
    "evaluate": (
        "megalut_cli.cli.evaluate",
        "Measure shear biases m and c, overall and conditional.",
    ),
    "calibrate": (
        "megalut_cli.cli.calibrate",
        "Calibrated mean shear (and PSF leakage) of a catalog without truth.",
    ),
    "concat": (
        "megalut_cli.cli.concat",
        "Concatenate the catalogs of many tiles, their provenance checked.",
    ),
    "run": ("megalut_cli.cli.run", "Run a whole pipeline: simulate, train, predict, evaluate."),
    "draft": (
        "megalut_cli.cli.draft",
        "Draft a pipeline file whose PSF and noise come from your data.",
    ),
    "info": ("megalut_cli.cli.info", "Summarise a megalut catalog, stamp image or model file."),
}

_SIMULATE = "megalut_cli.sim.simulate"
_MEASURE = "megalut_cli.measure.measure"
_TRAIN = "megalut_cli.nn.train"
_PREDICT = "megalut_cli.shear.predict"
_NUMBA = "megalut_cli.warm_numba"

#: name -> the modules the command's local workers need (imported once, by
#: the server the workers are forked from: :func:`megalut_cli.parallel.start_worker_server`)
WORKER_MODULES: dict[str, tuple[str, ...]] = {
    "simulate": (_SIMULATE, _NUMBA),
    "measure": (_MEASURE, "megalut_cli.measure.meds", _NUMBA),
    "train-point": (_TRAIN,),
    "train-weight": (_TRAIN,),
    "predict": (_PREDICT,),
    "run": (_SIMULATE, _MEASURE, _TRAIN, _PREDICT, "megalut_cli.pipeline.steps", _NUMBA),
}


def short_help(name: str) -> str:
    """The one-line help of subcommand ``name``."""
    return COMMANDS[name][1]
