"""The options of ``megalut simulate``, declared once: its click options, the defaults of
:func:`megalut_cli.sim.simulate.simulate` and the table of ``docs/config.md``.

``--morphology`` (every optional feature set, :mod:`megalut_cli.measure.feature_sets`) is
declared by its set (simulate measures as ``megalut measure`` does);
``--n-cases``/``--n-realizations`` are the ``[structure]`` keys of
:mod:`megalut_cli.sim.config`; ``--engine``, ``--device``, ``--seed``, ``-j``,
``--scheduler`` and ``--overwrite`` are the shared declarations.
"""

from __future__ import annotations

from dataclasses import replace

from megalut_cli.atomic import OVERWRITE_OPTION
from megalut_cli.engine import DEVICE_OPTION, ENGINE_OPTION
from megalut_cli.measure.feature_sets import set_options
from megalut_cli.measure.options import MEASURE
from megalut_cli.parallel import NPROC_OPTION, SCHEDULER_OPTION
from megalut_cli.schema import Option
from megalut_cli.seeding import SEED_OPTION
from megalut_cli.sim.config import STRUCTURE


def _after_measure(option: Option) -> Option:
    """A measure option as simulate has it: with ``--measure`` only."""
    return replace(option, help=f"With --measure: {option.help[0].lower()}{option.help[1:]}")


#: The options of ``megalut simulate`` with a value (files aside), in the order of ``--help``.
SIMULATE_OPTIONS: tuple[Option, ...] = (
    Option(
        "measure",
        "bool",
        False,
        "Measure the features right after drawing (no image kept): the way to "
        "make large training sets.",
    ),
    *(_after_measure(o) for o in set_options()),  # --morphology, every optional feature set
    replace(
        MEASURE["metacal"],
        help="With --measure: also the features of the five metacalibration versions of "
        "each stamp, deconvolved by the PSF it was drawn with (X_noshear, X_1p, X_1m, X_2p, X_2m "
        "for every feature X; docs/metacal.md); the fixnoise fields come from --seed.",
    ),
    _after_measure(MEASURE["metacal_step"]),
    _after_measure(MEASURE["moments_retry"]),
    replace(STRUCTURE["n_cases"], help="Override structure.n_cases.", default_text=None),
    replace(
        STRUCTURE["n_realizations"], help="Override structure.n_realizations.", default_text=None
    ),
    Option(
        "pairs",
        "bool",
        False,
        "With --scene: draw every field at +g and -g with the same galaxies and the same "
        "noise (scene.pairs = true; docs/scenes.md).",
    ),
    Option(
        "dry_run",
        "bool",
        False,
        "Check the config and the outputs, say what would be simulated and how long "
        "it would take (from a tiny calibration draw), and stop.",
    ),
    replace(
        SEED_OPTION,
        help="Seed of every random draw; the output is identical for any -j or cluster.",
    ),
)
SIMULATE = {o.name: o for o in SIMULATE_OPTIONS}

#: Every option of ``megalut simulate`` with a value, for the docs table.
ALL_SIMULATE_OPTIONS: tuple[Option, ...] = (
    *SIMULATE_OPTIONS,
    ENGINE_OPTION,
    DEVICE_OPTION,
    NPROC_OPTION,
    SCHEDULER_OPTION,
    OVERWRITE_OPTION,
)
