"""How much of the error on m of a common-random-number set comes from the draw of its shears.

    python examples/fiducial/crn_shear_draws.py [WORKDIR]

Simulates one CRN set (examples/fiducial/vo-crn.toml) of 40 shears x 20 000 galaxies (10 000
pairs, 8 x 10^5 stamps, seed 1001), predicts with models/fiducial.h5, and evaluates m on the
10 disjoint groups of 4 shears: the same galaxies, offsets and noise in every group, only the
shears differ. The scatter of m over the groups is then what the draw of 4 shears adds; the
bootstrap over galaxies, which holds the shears fixed, does not see it. About 3 minutes on
2 cores; the recorded run is in models/README.md.
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

from megalut_cli.shear.evaluate import evaluate_catalog
from megalut_cli.shear.predict import predict_catalog
from megalut_cli.sim.config import load_config
from megalut_cli.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[2]
N_GROUPS, GROUP, N_REA, SEED = 10, 4, 20_000, 1001


def main(workdir: Path) -> None:
    config = load_config(
        ROOT / "examples" / "fiducial" / "vo-crn.toml",
        n_cases=N_GROUPS * GROUP,
        n_realizations=N_REA,
    )
    vo, shears = workdir / "vo.fits", workdir / "shears.fits"
    simulate(config, vo, measure=True, seed=SEED, nproc=2, overwrite=True)
    predict_catalog(vo, ROOT / "models" / "fiducial.h5", shears, nproc=2, overwrite=True)
    groups = [
        evaluate_catalog(
            shears, seed=SEED, select=f"(case >= {GROUP * g}) & (case < {GROUP * (g + 1)})"
        )
        for g in range(N_GROUPS)
    ]
    whole = evaluate_catalog(shears, seed=SEED)
    for scheme in ("unweighted", "weighted"):
        fits = [[r[scheme][c] for c in ("g1", "g2")] for r in groups]

        def col(key: str, i: int, fits=fits) -> np.ndarray:
            return np.array([f[i][key] if f[i][key] is not None else np.nan for f in fits])

        for i, comp in enumerate(("g1", "g2")):
            m = col("m", i)
            w = whole[scheme][comp]
            print(
                f"{scheme:10s} {comp}: m over {N_GROUPS} draws of {GROUP} shears "
                f"{' '.join(f'{v:+.2e}' for v in m)}"
            )
            # The draws share their galaxies: their scatter is the drawn shears' part alone.
            print(
                f"{'':10s} {comp}: scatter {m.std(ddof=1):.1e}; mean error: shears' part "
                f"{np.nanmean(col('m_err_shears', i)):.1e} (rms "
                f"{np.sqrt(np.nanmean(col('m_err_shears', i) ** 2)):.1e}), galaxies' "
                f"{col('m_err_galaxies', i).mean():.1e}, total {col('m_err', i).mean():.1e}; "
                f"all {N_GROUPS * GROUP} shears: m = {w['m']:+.2e} ± {w['m_err']:.1e} "
                f"(galaxies {w['m_err_galaxies']:.1e}, shears {w['m_err_shears']:.1e})"
            )


if __name__ == "__main__":  # worker processes are spawned: they import this file
    if len(sys.argv) > 1:
        main(Path(sys.argv[1]))
    else:
        with tempfile.TemporaryDirectory() as tmp:
            main(Path(tmp))
