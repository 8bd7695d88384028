"""The first N members of each point committee of a model, all selected, as a new model.

    python benchmarks/first_members.py point.h5 2 first2.h5

Member seeds do not depend on the committee size (``megalut_cli.nn.committee.member_keys``),
so these are the members ``train-point --members N --keep N`` with the same settings and
seed would train: used to compare float32 with float64 training at the paper's size without
retraining the float32 committee (benchmarks/training.md).
"""

from __future__ import annotations

import dataclasses
import sys

from megalut_cli.nn.model import Committee, ShearModel


def first_members(committee: Committee, n: int) -> Committee:
    """A copy of ``committee`` with its first ``n`` members, all selected."""
    members = [dataclasses.replace(m, selected=True) for m in committee.members[:n]]
    return Committee(
        committee.kind,
        committee.target,
        committee.features,
        committee.hidden,
        committee.in_loc,
        committee.in_scale,
        members,
        committee.out_loc,
        committee.out_scale,
        committee.cost,
        committee.normalization,
        committee.training,
    )


def main(model_path: str, n: str, output: str) -> None:
    model = ShearModel.load(model_path)
    point = {t: first_members(c, int(n)) for t, c in model.point.items()}
    out = ShearModel(point, {}, model.provenance)
    out.save(output, overwrite=True)
    for t, c in point.items():
        print(t, "validation costs:", [f"{m.valid_cost:.4e}" for m in c.members])


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit("usage: first_members.py MODEL.h5 N OUTPUT.h5")
    main(*sys.argv[1:])
