"""The whole method in memory, from Python: no file is written.

    python examples/in_memory.py

Simulates small TP, TW and VO sets of the fiducial configs (arrays of columns), trains
the point and weight committees (``ShearModel`` objects), predicts on VO and evaluates m
and c: the library calls behind ``megalut simulate``, ``train-point``, ``train-weight``,
``predict`` and ``evaluate`` (docs/architecture.md). At this size (2x10^4 TP stamps,
2 members) the biases are of several per cent; `megalut run` does it at a useful size.
"""

from pathlib import Path

from megalut_cli.nn.fit import fit_point, fit_weight
from megalut_cli.nn.options import PointSpec, WeightSpec
from megalut_cli.shear.evaluate import evaluate_columns
from megalut_cli.shear.predict import predict_columns
from megalut_cli.sim import load_config
from megalut_cli.sim.simulate import simulate_table


def main() -> None:
    ex = str(Path(__file__).resolve().parent / "fiducial") + "/"
    tp, _ = simulate_table(
        load_config(ex + "tp.toml", n_cases=200, n_realizations=100), 1, measure=True, nproc=2
    )
    tw, _ = simulate_table(
        load_config(ex + "tw.toml", n_cases=40, n_realizations=500), 2, measure=True, nproc=2
    )
    vo, _ = simulate_table(
        load_config(ex + "vo.toml", n_cases=40, n_realizations=500), 3, measure=True, nproc=2
    )
    point_spec = PointSpec(select_cases="mean(snr) > 10", members=2, iterations=300)
    point = fit_point(tp, point_spec, nproc=2)
    model = fit_weight(tw, point, WeightSpec(members=2, iterations=200), nproc=2)
    vo.update(predict_columns(model, vo))
    result = evaluate_columns(vo)
    for scheme in ("unweighted", "weighted"):
        for comp in ("g1", "g2"):
            fit = result[scheme][comp]
            print(
                f"{scheme:10s} {comp}: m = {fit['m']:+.2e} ± {fit['m_err']:.1e}, "
                f"c = {fit['c']:+.2e} ± {fit['c_err']:.1e}"
            )


if __name__ == "__main__":  # worker processes are spawned: they import this file
    main()
