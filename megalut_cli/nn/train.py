"""Training one network: scipy BFGS / L-BFGS with the analytic gradient and mini-batches.

Paper Sect. 3.4: parameters start from N(0, 0.1) (or near-identity, or an earlier model);
a random "batch" of a fraction of the training cases (25 %) is optimised for a number of
iterations (30), then the next random batch, and so on. The cost on the validation set is
monitored after every iteration and the parameters with the lowest validation cost are
kept. Every random draw comes from the member's own seed, so a member trains identically in
any process.

``gradient="fd"`` replaces the analytic gradient by scipy's finite differences (what the
original implementation did); it exists for the benchmark only.
"""

from __future__ import annotations

import copy
import logging
import multiprocessing
import sys
import time
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from megalut_cli.engine import device_backend
from megalut_cli.errors import ConfigError
from megalut_cli.nn import costs
from megalut_cli.nn.data import CaseData, case_rows
from megalut_cli.nn.network import Network
from megalut_cli.nn.options import MEMBER_CHECKS, OPTION, POINT_OPTION, TrainSpec
from megalut_cli.seeding import rng_for

log = logging.getLogger(__name__)

#: Seconds between two progress lines of a member at info level (every mini-batch at debug).
REPORT_SECONDS = 30.0


@dataclass(frozen=True)
class TrainSettings:
    """How to train one member: the values of the training options it trains with (fields
    named as the options, defaults declared in :mod:`megalut_cli.nn.options`) and of the
    settings no option sets."""

    cost: str = POINT_OPTION["cost"].default
    iterations: int = OPTION["iterations"].default
    batch_fraction: float = OPTION["batch_fraction"].default
    batch_iterations: int = OPTION["batch_iterations"].default
    optimizer: str = OPTION["optimizer"].default
    gradient: str = "analytic"
    valid_every: int = 1
    max_stalls: int = 3
    precision: str = OPTION["precision"].default
    device: str = "cpu"  # "gpu": costs and gradients on the device (the backend's DeviceObjective)

    def __post_init__(self) -> None:
        """Check the settings: the ranges and choices of the declarations of
        :mod:`megalut_cli.nn.options` (a ``ValueError``: a programming error, not user input)."""
        if self.cost not in costs.COSTS:
            raise ValueError(f"unknown cost {self.cost!r}")
        if self.device not in ("cpu", "gpu"):
            raise ValueError(f"unknown device {self.device!r} (a resolved one: cpu or gpu)")
        if self.gradient not in ("analytic", "fd"):
            raise ValueError(f"unknown gradient {self.gradient!r}")
        if self.valid_every < 1:
            raise ValueError("valid_every must be >= 1")
        try:
            for f in fields(self):
                if f.name in MEMBER_CHECKS:
                    MEMBER_CHECKS[f.name].check(getattr(self, f.name), f.name)
        except ConfigError as err:
            raise ValueError(str(err)) from None

    @classmethod
    def of(cls, spec: TrainSpec, cost: str, device: str) -> TrainSettings:
        """How each member of the training ``spec`` trains: the spec's values of the fields
        named as its options, with ``cost`` on the resolved ``device``."""
        names = {o.name for o in spec.OPTIONS}
        values = {f.name: getattr(spec, f.name) for f in fields(cls) if f.name in names}
        return cls(**{**values, "cost": cost, "device": device})


def normalised_columns(
    x: np.ndarray, loc: np.ndarray, scale: np.ndarray, dtype: str, block: int = 16384
) -> np.ndarray:
    """``(x - loc) / scale`` (float64 arithmetic) transposed to the column layout
    (``features x rows``, C-contiguous) in ``dtype``; by blocks of rows that stay in the CPU
    cache (the numbers of ``np.ascontiguousarray(((x - loc) / scale).T, dtype)``)."""
    xt = np.empty((x.shape[1], x.shape[0]), dtype=dtype)
    for s in range(0, x.shape[0], block):
        xt[:, s : s + block] = ((x[s : s + block] - loc) / scale).T
    return xt


class Objective:
    """A cost of a network on a set of cases, as a function of the flat parameters.

    ``x`` are raw features, normalised here with ``in_loc``/``in_scale``; ``j`` picks the
    target (and point-estimate) column. The optimiser sees the cost divided by
    ``cost_scale**2`` (the targets' spread) so that its tolerances do not depend on units.
    """

    def __init__(
        self,
        net: Network,
        cost: str,
        data: CaseData,
        j: int,
        in_loc: np.ndarray,
        in_scale: np.ndarray,
        cost_scale: float = 1.0,
        dtype: str = "float64",
    ) -> None:
        self.net = net
        self.cost = cost
        self.xt = normalised_columns(data.x, in_loc, in_scale, dtype)
        self.groups = costs.Groups(data.case, data.n_cases)
        self.n = self.groups.n
        self.t = np.ascontiguousarray(data.targets[:, j])
        self.t_row = np.ascontiguousarray(data.row_targets[:, j])
        self.point = None if data.point is None else np.ascontiguousarray(data.point[:, j])
        if cost == "mswb" and self.point is None:
            raise ValueError("MSWB needs point estimates")
        self.norm = 1.0 / float(cost_scale) ** 2
        self.n_evals = 0
        self._work: list[list[np.ndarray]] | None = None

    def _cost(self, out: np.ndarray) -> tuple[float, np.ndarray]:
        if self.cost == "msb":
            return costs.msb(out, self.groups, self.n, self.t)
        if self.cost == "mse":
            return costs.mse(out, self.groups, self.n, self.t_row)
        return costs.mswb(out, self.point, self.groups, self.n, self.t)

    def batch(self, cases: np.ndarray) -> Objective:
        """The same cost on the cases ``cases`` of this objective's data, built from its
        normalised features (the numbers of ``Objective(..., data.subset(cases), ...)``
        without normalising the rows again)."""
        cases = np.asarray(cases, dtype=np.intp)
        counts = self.groups.counts
        rows = case_rows(counts, cases)
        new = copy.copy(self)
        new.xt = self.xt.take(rows, axis=1)  # C-contiguous (``xt[:, rows]`` would not be)
        new.groups = costs.Groups(np.repeat(np.arange(len(cases)), counts[cases]), len(cases))
        new.n = new.groups.n
        new.t = self.t[cases]
        new.t_row = self.t_row[rows]
        new.point = None if self.point is None else self.point[rows]
        new.n_evals = 0
        new._work = None
        return new

    def value(self, params: np.ndarray) -> float:
        """The cost (in the targets' units squared)."""
        self.n_evals += 1
        out = self.net.forward(params, self.xt)
        if self.cost == "msb":  # no derivative needed (validation passes)
            return costs.msb_value(out, self.groups, self.n, self.t)
        return self._cost(out)[0]

    def value_and_grad(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        """The cost and its analytic gradient (in the targets' units squared)."""
        self.n_evals += 1
        out, cache = self.net.forward_cached(params, self.xt, self._work)
        self._work = cache
        cost, g_out = self._cost(out)
        return cost, self.net.backward(params, out, cache, g_out)

    def scaled(self, params: np.ndarray) -> float:
        return self.value(params) * self.norm

    def scaled_with_grad(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        c, g = self.value_and_grad(params)
        return c * self.norm, g * self.norm


@dataclass
class MemberTask:
    """Everything needed to train one committee member (plain, picklable data)."""

    label: str
    net: Network
    settings: TrainSettings
    train: CaseData
    valid: CaseData | None  # None: monitor on the full training set
    j: int
    in_loc: np.ndarray
    in_scale: np.ndarray
    seed: int
    keys: tuple[int, ...]
    init_params: np.ndarray | None = None
    init_scheme: str = "normal"
    init_sigma: float = 0.1
    identity_feature: int = 0
    cost_scale: float = 1.0
    log_level: int = logging.INFO
    prior_history: np.ndarray | None = None


@dataclass
class MemberResult:
    """A trained member: parameters kept (lowest validation cost) and its record."""

    label: str
    params: np.ndarray
    seed: int
    keys: tuple[int, ...]
    train_cost: float
    valid_cost: float
    n_iter: int
    best_iter: int
    history: np.ndarray  # (n_iter_total, 2): batch training cost, validation cost
    times: np.ndarray = field(
        default_factory=lambda: np.zeros(0)
    )  # wall seconds since start, per iteration
    cpu_times: np.ndarray = field(default_factory=lambda: np.zeros(0))  # CPU seconds since start
    n_evals: int = 0
    elapsed: float = 0.0


def _ensure_worker_logging(level: int) -> None:
    """In a fresh local worker process, send progress lines to stderr like the parent does."""
    root = logging.getLogger()
    if multiprocessing.parent_process() is not None and not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("megalut: %(message)s"))
        root.addHandler(handler)
        root.setLevel(level)


def initial_params(task: MemberTask, rng: np.random.Generator) -> np.ndarray:
    if task.init_params is not None:
        return np.array(task.init_params, dtype=np.float64)
    if task.init_scheme == "identity":
        return task.net.init_identity(rng, task.identity_feature, task.in_loc, task.in_scale)
    return task.net.init_normal(rng, task.init_sigma)


class _Monitor:
    """Records the cost after every optimiser iteration and keeps the best-validation parameters."""

    def __init__(
        self,
        monitor: Objective,
        params: np.ndarray,
        settings: TrainSettings,
        t0: float,
        cpu0: float,
    ) -> None:
        self.monitor = monitor
        self.settings = settings
        self.t0 = t0
        self.best_valid = monitor.value(params)
        self.best_params = params.copy()
        self.best_iter = 0
        self.it = 0
        self.rows: list[tuple[float, float]] = []
        self.times: list[float] = []
        self.cpu_times: list[float] = []
        self.cpu0 = cpu0
        self.batch_norm = 1.0

    def __call__(self, intermediate_result: Any) -> None:  # scipy's callback protocol
        self.it += 1
        x = intermediate_result.x
        v = np.nan
        if self.it % self.settings.valid_every == 0 or self.it == self.settings.iterations:
            v = self.monitor.value(x)
            if v < self.best_valid or not np.isfinite(self.best_valid):
                self.best_valid, self.best_params, self.best_iter = (
                    v,
                    np.array(x, copy=True),
                    self.it,
                )
        self.rows.append((float(intermediate_result.fun) / self.batch_norm, v))
        self.times.append(time.perf_counter() - self.t0)
        self.cpu_times.append(time.process_time() - self.cpu0)


def train_member(task: MemberTask) -> MemberResult:
    """Train one network (a work unit: top-level, deterministic given its seed and keys)."""
    _ensure_worker_logging(task.log_level)
    s = task.settings
    rng = rng_for(task.seed, *task.keys)
    params = initial_params(task, rng)
    t0, cpu0 = time.perf_counter(), time.process_time()

    objective: Any = device_backend().DeviceObjective if s.device == "gpu" else Objective

    def make(data: CaseData) -> Objective:
        return objective(
            task.net, s.cost, data, task.j, task.in_loc, task.in_scale, task.cost_scale, s.precision
        )

    full = make(task.train)
    mon = _Monitor(full if task.valid is None else make(task.valid), params, s, t0, cpu0)
    n_cases = task.train.n_cases
    bsize = (
        n_cases
        if s.batch_fraction >= 1.0
        else min(n_cases, max(1, int(round(s.batch_fraction * n_cases))))
    )
    stalls = 0
    n_evals = 0
    last_report = t0
    from scipy.optimize import minimize  # here: importing it costs every command ~0.3 s

    if s.optimizer == "bfgs":
        method, opts = "BFGS", {"gtol": 1e-12}
    else:
        method, opts = "L-BFGS-B", {"gtol": 1e-12, "ftol": 1e-15}
    while mon.it < s.iterations:
        if bsize < n_cases:
            cases = np.sort(rng.choice(n_cases, size=bsize, replace=False))
            # On the CPU the batch's features are taken from the normalised training set.
            obj = (
                full.batch(cases) if isinstance(full, Objective) else make(task.train.subset(cases))
            )
        else:
            obj = full
        mon.batch_norm = obj.norm
        before_it, before_evals = mon.it, obj.n_evals
        fun, jac = (obj.scaled_with_grad, True) if s.gradient == "analytic" else (obj.scaled, None)
        res = minimize(
            fun,
            params,
            jac=jac,
            method=method,
            callback=mon,
            options={**opts, "maxiter": min(s.batch_iterations, s.iterations - mon.it)},
        )
        n_evals += obj.n_evals - before_evals
        if np.all(np.isfinite(res.x)):
            params = np.asarray(res.x, dtype=np.float64)
        last = mon.rows[-1] if mon.rows else (np.nan, np.nan)
        now = time.perf_counter()
        # One line per mini-batch only at debug level; at info, one every REPORT_SECONDS.
        level = logging.INFO if now - last_report >= REPORT_SECONDS else logging.DEBUG
        if level == logging.INFO:
            last_report = now
        log.log(
            level,
            "%s: iteration %d/%d, batch %s %.4e, valid %.4e (best %.4e at %d)",
            task.label,
            mon.it,
            s.iterations,
            s.cost,
            last[0],
            last[1],
            mon.best_valid,
            mon.best_iter,
        )
        if mon.it == before_it:
            stalls += 1
            if stalls >= s.max_stalls:
                log.info(
                    "%s: the optimiser made no progress on %d batches; stopping", task.label, stalls
                )
                break
        else:
            stalls = 0
    best_params, best_valid, best_iter, rows, times = (
        mon.best_params,
        mon.best_valid,
        mon.best_iter,
        mon.rows,
        mon.times,
    )
    train_cost = full.value(best_params)
    log.info(
        "%s: done, %d iterations in %.1f s, best validation %s %.4e at iteration %d",
        task.label,
        mon.it,
        time.perf_counter() - t0,
        s.cost,
        best_valid,
        best_iter,
    )
    history = np.asarray(rows, dtype=np.float64).reshape(-1, 2)
    if task.prior_history is not None and len(task.prior_history):
        history = np.vstack(
            [np.asarray(task.prior_history, dtype=np.float64).reshape(-1, 2), history]
        )
        offset = len(task.prior_history)
    else:
        offset = 0
    return MemberResult(
        label=task.label,
        params=best_params,
        seed=task.seed,
        keys=task.keys,
        train_cost=float(train_cost),
        valid_cost=float(best_valid),
        n_iter=len(history),
        best_iter=best_iter + offset,
        history=history,
        times=np.asarray(times),
        cpu_times=np.asarray(mon.cpu_times),
        n_evals=n_evals,
        elapsed=time.perf_counter() - t0,
    )
