"""Committees (paper Sect. 3.4): N members trained independently, the best half kept.

Every member of every committee is one work unit mapped with
:func:`megalut_cli.parallel.map_units` (in this process, on local worker processes, or on
a Dask cluster). Each member draws its random numbers from the user's seed and its own keys
(the committee's kind and target, and the member index), so the trained committees do not
depend on the number of workers or the engine.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from megalut_cli.nn.data import CaseData
from megalut_cli.nn.model import Committee, Member
from megalut_cli.nn.network import Network
from megalut_cli.nn.train import MemberResult, MemberTask, TrainSettings, train_member
from megalut_cli.parallel import map_units
from megalut_cli.seeding import STREAM_TRAIN

log = logging.getLogger(__name__)


def member_keys(kind: str, target: str, member: int) -> tuple[int, int, int]:
    """Seed keys of a member: stream, a stable hash of the committee, the member index."""
    return (STREAM_TRAIN, zlib.crc32(f"{kind}:{target}".encode()), int(member))


@dataclass
class CommitteeSpec:
    """What to train for one target."""

    kind: str  # "point" or "weight"
    target: str
    j: int  # column of the target in the CaseData
    net: Network
    in_loc: np.ndarray
    in_scale: np.ndarray
    train: CaseData
    valid: CaseData | None
    members: int
    normalization: str  # of the inputs (megalut_cli.nn.normalization.METHODS)
    keep: int | None = None  # members kept; default: the best half
    cost_scale: float = 1.0
    init_scheme: str = "normal"
    identity_feature: int = 0
    init_members: Sequence[Member] | None = None  # start from these (--init-from)
    training: dict[str, Any] = field(default_factory=dict)


def _tasks(
    spec: CommitteeSpec, settings: TrainSettings, seed: int, log_level: int
) -> list[MemberTask]:
    tasks = []
    for k in range(spec.members):
        init = prior = None
        if spec.init_members:
            src = spec.init_members[k % len(spec.init_members)]
            init = spec.net.pack(src.layers)
            prior = src.history
        tasks.append(
            MemberTask(
                label=f"{spec.kind} {spec.target} member {k + 1}/{spec.members}",
                net=spec.net,
                settings=settings,
                train=spec.train,
                valid=spec.valid,
                j=spec.j,
                in_loc=spec.in_loc,
                in_scale=spec.in_scale,
                seed=seed,
                keys=member_keys(spec.kind, spec.target, k),
                init_params=init,
                init_scheme=spec.init_scheme,
                identity_feature=spec.identity_feature,
                cost_scale=spec.cost_scale,
                log_level=log_level,
                prior_history=prior,
            )
        )
    return tasks


def select_best(valid_costs: Sequence[float], keep: int) -> np.ndarray:
    """Boolean mask of the ``keep`` members with the lowest validation cost (NaN last, ties by
    index)."""
    costs = np.array([c if np.isfinite(c) else np.inf for c in valid_costs])
    order = np.argsort(costs, kind="stable")
    mask = np.zeros(len(costs), bool)
    mask[order[:keep]] = True
    return mask


def train_committees(
    specs: Sequence[CommitteeSpec],
    settings: TrainSettings,
    seed: int,
    pool: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Committee]:
    """Train all members of all committees as independent work units; keep the best half of each."""
    level = log.getEffectiveLevel()
    tasks: list[MemberTask] = []
    for spec in specs:
        tasks += _tasks(spec, settings, seed, level)
    results: list[MemberResult] = map_units(train_member, tasks, pool, progress)
    out: dict[str, Committee] = {}
    i = 0
    for spec in specs:
        res = results[i : i + spec.members]
        i += spec.members
        keep = spec.keep if spec.keep else max(1, spec.members // 2)
        chosen = select_best([r.valid_cost for r in res], min(keep, spec.members))
        members = [
            Member(
                layers=[(w.copy(), b.copy()) for w, b in spec.net.unpack(r.params)],
                seed=r.seed,
                keys=r.keys,
                train_cost=r.train_cost,
                valid_cost=r.valid_cost,
                n_iter=r.n_iter,
                best_iter=r.best_iter,
                selected=bool(sel),
                history=r.history,
            )
            for r, sel in zip(res, chosen)
        ]
        kept = [f"{r.valid_cost:.4g}" for r, s in zip(res, chosen) if s]
        log.info(
            "%s %s: kept %d/%d members, validation %s %s",
            spec.kind,
            spec.target,
            int(chosen.sum()),
            spec.members,
            settings.cost,
            ", ".join(kept),
        )
        out[spec.target] = Committee(
            kind=spec.kind,
            target=spec.target,
            features=spec.train.features,
            hidden=spec.net.hidden,
            in_loc=spec.in_loc,
            in_scale=spec.in_scale,
            out_loc=spec.net.out_loc,
            out_scale=spec.net.out_scale,
            members=members,
            cost=settings.cost,
            normalization=spec.normalization,
            training=spec.training,
        )
    return out
