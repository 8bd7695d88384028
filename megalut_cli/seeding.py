"""Seeds per work unit, so that results never depend on the engine or worker count.

Every random draw of megalut comes from a generator built here from the user's seed and
a tuple of integer keys naming the unit (a stream id, a case index, a member index...).
"""

from __future__ import annotations

import numpy as np

from megalut_cli.schema import Option

#: Stream ids keep independent uses of one user seed apart.
STREAM_SIMULATE = 1
STREAM_TRAIN = 2
STREAM_SPLIT = 3
#: Per-subfield seeds of a GREAT3 branch pipeline (``megalut run`` on a ``[branch]`` file).
STREAM_SUBFIELD = 4
#: Per-realization draws shared by all cases of a common-random-number set (``structure.common``).
STREAM_COMMON = 5
#: Bootstrap resampling of ``megalut evaluate`` (also its paired ``--twin`` bootstrap).
STREAM_BOOTSTRAP = 6
#: The fixnoise fields of metacalibration (``measure --metacal``), one per stamp.
STREAM_METACAL = 7
#: The bootstrap over objects of ``megalut calibrate``.
STREAM_CALIBRATE = 8
#: The fields of ``megalut simulate --scene`` (counts, galaxies, positions, noise; per field).
STREAM_SCENE = 9

#: The ``--seed`` of the commands (each gives its own default and help).
SEED_OPTION = Option("seed", "int", 1, "Seed of every random draw of this step.")


def rng_for(seed: int, *keys: int) -> np.random.Generator:
    """A numpy Generator for the unit named by ``keys`` under the user's ``seed``."""
    return np.random.default_rng(
        np.random.SeedSequence(entropy=int(seed), spawn_key=tuple(int(k) for k in keys))
    )


def int_seed_for(seed: int, *keys: int) -> int:
    """A 31-bit positive integer seed (e.g. for ``galsim.BaseDeviate``) for the unit ``keys``."""
    state = np.random.SeedSequence(entropy=int(seed), spawn_key=tuple(int(k) for k in keys))
    return int(state.generate_state(1, dtype=np.uint32)[0] >> 1) + 1
