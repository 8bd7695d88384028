"""Benchmark of the training engine against a finite-difference BFGS baseline.

1. One cost (MSB) + gradient evaluation of a 5-5-1 network on 500 cases x 2000
   realizations x 5 features (10^6 rows): forward pass alone, analytic cost + gradient
   (float64 and float32), and the 2-point finite-difference gradient that the original
   implementation used (one forward pass per parameter, 66 parameters).
2. Time to train committee members to a given validation MSB: each member is trained with
   scipy BFGS on mini-batches (25 % of the cases x 30 iterations, paper settings) once
   with finite-difference gradients (the baseline) and once with analytic gradients, from
   the same initial parameters and with the same mini-batch sequence. The target of each
   member is the best validation MSB its baseline run reached; we compare the wall time
   at which each run first reached it. Both runs use the same vectorised forward pass, so
   the baseline is, if anything, faster than the original code (which ran on masked numpy
   arrays); the validation cost is evaluated after every iteration in both.
3. (``--cli``) The whole command against the same baseline: the training set of 2. and its
   validation set are written as FITS catalogs; ``megalut train-point`` trains one member
   (one target, the baseline's iterations, batches and validation catalog, ``-j 1``) as a
   separate process, timed from its start to its exit (start-up, reading, normalisation,
   training, writing the model), and the finite-difference baseline trains the same member
   (the same initial parameters and mini-batches: the CLI member's seed and keys) in this
   process, timed to its best validation MSB. The command is given the iterations it needs
   to reach that MSB (the first hit of an in-process analytic run of the same member; at
   most 10x the baseline's). Runs alternate; medians are reported, and the command's member
   must reach the baseline's best validation MSB (read from the model file). The floor: a
   process importing only numpy, SciPy's BFGS and h5py, plus the in-process training loop's
   time to the MSB, is the least any command could take.

Run from the repository root (single process; results go to stdout):

    python benchmarks/bench_training.py            # defaults as recorded in training.md
    python benchmarks/bench_training.py --quick    # a smaller run, for a smoke test
    python benchmarks/bench_training.py --cli      # 3. only (the whole command)
"""

from __future__ import annotations

import os

# One BLAS thread, as in the worker processes of ``-j N``: timings per core.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from bench_startup import FLOORS  # noqa: E402  (this folder, first on the path of a script)

from megalut_cli.nn import normalization  # noqa: E402
from megalut_cli.nn.data import build_cases, valid_rows  # noqa: E402
from megalut_cli.nn.network import Network  # noqa: E402
from megalut_cli.nn.toy import shear_like_columns  # noqa: E402
from megalut_cli.nn.train import MemberTask, Objective, TrainSettings, train_member  # noqa: E402

MAX_FACTOR = 10  # analytic runs may use up to this many times the baseline's iterations
FEATURES = ["adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4"]


def _cases(n_cases: int, n_rea: int, seed: int):
    cols = shear_like_columns(n_cases, n_rea, seed)
    ok = valid_rows(cols, FEATURES, len(cols["case"]))
    return build_cases(cols, FEATURES, ["tru_g1"], ok, where="synthetic")


def _best_of(f, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t)
    return best


def _original_style_msb(layers, x3, mask3, targets) -> float:
    """MSB as the original implementation computed it, for comparison only: a forward pass
    on padded (realization, feature, case) arrays with ``np.dot`` per layer, then the mean
    over realizations of a numpy masked array."""
    a = x3
    for i, (w, b) in enumerate(layers):
        z = np.rollaxis(np.dot(w.T, a) + b.reshape(-1, 1, 1), 1)
        a = np.tanh(z) if i < len(layers) - 1 else z
    pred = np.ma.array(a, mask=mask3)
    return float(np.mean(np.square(np.mean(pred, axis=0) - targets)))


def bench_evaluation(n_cases: int, n_rea: int, repeat: int) -> dict[str, float]:
    data = _cases(n_cases, n_rea, seed=1)
    loc, scale = normalization.fit(data.x)
    spread = float(data.targets.std())
    net = Network(5, (5, 5), "identity", float(data.targets.mean()), spread)
    p = net.init_normal(np.random.default_rng(0))
    o64 = Objective(net, "msb", data, 0, loc, scale, spread, "float64")
    o32 = Objective(net, "msb", data, 0, loc, scale, spread, "float32")
    o64.value_and_grad(p)
    o32.value_and_grad(p)  # allocate the work buffers once
    res = {
        "rows": data.n_rows,
        "params": net.n_params,
        "forward64": _best_of(lambda: o64.value(p), repeat),
        "grad64": _best_of(lambda: o64.value_and_grad(p), repeat),
        "grad32": _best_of(lambda: o32.value_and_grad(p), repeat),
    }
    from scipy.optimize import approx_fprime

    # approx_fprime: one evaluation at p plus one per parameter, like scipy's BFGS without jac
    res["fd_grad"] = _best_of(lambda: approx_fprime(p, o64.value, 1.4901161193847656e-08), 1)
    # the original style of evaluation (padded arrays, masked-array mean), 2 % of rows masked
    x3, mask, _ = data.padded()
    x3 = np.ascontiguousarray(np.transpose((x3 - loc) / scale, (1, 2, 0)))  # (rea, feature, case)
    mask = np.random.default_rng(1).random(mask.shape) < 0.02
    mask3 = np.broadcast_to(mask.T[:, None, :], (x3.shape[0], 1, x3.shape[2]))
    layers = net.unpack(p)
    res["original_style"] = _best_of(
        lambda: _original_style_msb(layers, x3, mask3, data.targets[:, 0]), 2
    )
    g_fd = approx_fprime(p, o64.value, 1.4901161193847656e-08)
    g_an = o64.value_and_grad(p)[1]
    res["fd_rel_err"] = float(np.max(np.abs(g_fd - g_an)) / np.max(np.abs(g_an)))
    return res


def _time_to(result, target: float, cpu: bool = False) -> float:
    """Wall (or CPU) seconds until the validation cost first reached ``target``."""
    valid = result.history[:, 1]
    hit = np.flatnonzero(valid <= target * (1 + 1e-12))
    times = result.cpu_times if cpu else result.times
    return float(times[hit[0]]) if len(hit) else np.nan


def bench_training(
    n_cases: int, n_rea: int, members: int, fd_iterations: int, max_factor: int
) -> list[dict]:
    train = _cases(n_cases, n_rea, seed=2)
    valid = _cases(max(2, n_cases // 5), n_rea, seed=3)
    loc, scale = normalization.fit(train.x)
    spread = float(train.targets.std())
    net = Network(5, (5, 5), "identity", float(train.targets.mean()), spread)
    rows = []
    for k in range(members):

        def task(gradient: str, iterations: int, dtype: str = "float64", k: int = k) -> MemberTask:
            settings = TrainSettings(
                cost="msb", iterations=iterations, gradient=gradient, precision=dtype
            )
            return MemberTask(
                f"member {k}",
                net,
                settings,
                train,
                valid,
                0,
                loc,
                scale,
                seed=1,
                keys=(2, 0, k),
                cost_scale=spread,
                log_level=30,
            )

        fd = train_member(task("fd", fd_iterations))
        target = fd.valid_cost
        t_fd = _time_to(fd, target)
        row = {
            "member": k,
            "target": target,
            "fd_iter": fd.best_iter,
            "t_fd": t_fd,
            "cpu_fd": _time_to(fd, target, cpu=True),
            "fd_evals": fd.n_evals,
        }
        for dtype in ("float64", "float32"):
            an = train_member(task("analytic", fd_iterations * max_factor, dtype))
            t_an = _time_to(an, target)
            hit = np.flatnonzero(an.history[:, 1] <= target * (1 + 1e-12))
            row[f"t_{dtype}"] = t_an
            row[f"cpu_{dtype}"] = _time_to(an, target, cpu=True)
            row[f"iter_{dtype}"] = int(hit[0]) + 1 if len(hit) else -1
            row[f"final_{dtype}"] = an.valid_cost
        rows.append(row)
        print(
            f"  member {k}: target MSB {target:.4e} (FD best at iteration {fd.best_iter}, "
            f"{t_fd:.2f} s); analytic float64 reached it at iteration {row['iter_float64']} in "
            f"{row['t_float64']:.3f} s, float32 at {row['iter_float32']} in "
            f"{row['t_float32']:.3f} s",
            flush=True,
        )
    return rows


def _child_cpu() -> float:
    """CPU seconds (user + system) of the waited-for child processes so far."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


#: The floor of a training command (bench_startup.py's): a process that only imports what
#: training cannot do without (numpy, SciPy's BFGS, h5py for the model file) and leaves
#: without Python's teardown, as ``megalut`` does.
FLOOR = FLOORS["bfgs+h5py"]


def _run_cli(
    tp: Path, vp: Path, out: Path, iterations: int, precision: str | None, tree: str | None = None
) -> tuple[float, float]:
    """Wall and CPU seconds of one ``megalut train-point`` process training one member
    (``tree``: the megalut_cli of that source tree, e.g. a git worktree of an older commit)."""
    env = dict(os.environ, PYTHONPATH=tree) if tree else None
    # ``python -m`` puts the working folder first on the path: run in the folder of the code
    cwd = tree or str(Path(__file__).resolve().parent.parent)
    cmd = [
        sys.executable,
        "-m",
        "megalut_cli",
        "train-point",
        str(tp),
        "-o",
        str(out),
        "--overwrite",
        "--targets",
        "tru_g1",
        "--members",
        "1",
        "--valid",
        str(vp),
        "--iterations",
        str(iterations),
        "--seed",
        "1",
        "-j",
        "1",
    ]
    if precision:
        cmd += ["--precision", precision]
    cpu, t = _child_cpu(), time.perf_counter()
    subprocess.run(
        cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=cwd
    )
    return time.perf_counter() - t, _child_cpu() - cpu


def bench_cli(
    n_cases: int, n_rea: int, fd_iterations: int, repeat: int, tree: str | None = None
) -> None:
    """Section 3: the whole ``train-point`` command (one member) against the FD baseline;
    ``tree``: also the command of that source tree, in the same alternation."""
    from megalut_cli.catalog import write_catalog
    from megalut_cli.nn.committee import member_keys
    from megalut_cli.nn.model import ShearModel

    train_cols = shear_like_columns(n_cases, n_rea, 2)
    valid_cols = shear_like_columns(max(2, n_cases // 5), n_rea, 3)
    # The baseline's member: the data, normalisation and network the command builds, and
    # the seed and keys of its first tru_g1 member (same initial parameters and batches).
    train = build_cases(
        train_cols, FEATURES, ["tru_g1"], valid_rows(train_cols, FEATURES, len(train_cols["case"]))
    )
    valid = build_cases(
        valid_cols, FEATURES, ["tru_g1"], valid_rows(valid_cols, FEATURES, len(valid_cols["case"]))
    )
    loc, scale = normalization.fit(train.x)
    spread = float(np.std(train.targets[:, 0]))
    net = Network(5, (5, 5), "identity", float(np.mean(train.targets[:, 0])), spread)
    settings = TrainSettings(cost="msb", iterations=fd_iterations, gradient="fd")
    fd_task = MemberTask(
        "fd",
        net,
        settings,
        train,
        valid,
        0,
        loc,
        scale,
        seed=1,
        keys=member_keys("point", "tru_g1", 0),
        cost_scale=spread,
        log_level=30,
    )
    precisions = (None, "float32")  # the command's default (float64), then --precision float32
    fd = train_member(fd_task)
    target = fd.valid_cost
    # Iterations the command needs to reach the target: the first hit of an in-process analytic
    # run of the same member (the command's member follows the same trajectory).
    needed: dict[str | None, int] = {}
    train_time: dict[str | None, float] = {}  # the analytic run's seconds to the target
    for p in precisions:
        an_settings = TrainSettings(
            cost="msb", iterations=fd_iterations * MAX_FACTOR, precision=p or "float64"
        )
        an = train_member(
            MemberTask(
                "an",
                net,
                an_settings,
                train,
                valid,
                0,
                loc,
                scale,
                seed=1,
                keys=fd_task.keys,
                cost_scale=spread,
                log_level=30,
            )
        )
        hit = np.flatnonzero(an.history[:, 1] <= target * (1 + 1e-12))
        needed[p] = int(hit[0]) + 1 if len(hit) else fd_iterations * MAX_FACTOR
        train_time[p] = _time_to(an, target)
    print(
        f"  FD baseline: best validation MSB {target:.4e} at iteration {fd.best_iter}; "
        "the command reaches it at "
        + ", ".join(f"iteration {needed[p]} ({p or 'float64, default'})" for p in precisions),
        flush=True,
    )
    with tempfile.TemporaryDirectory() as tmp:
        tp, vp = Path(tmp) / "tp.fits", Path(tmp) / "vp.fits"
        write_catalog(tp, train_cols, fmt="megalut.toy")
        write_catalog(vp, valid_cols, fmt="megalut.toy")
        t_fd, cpu_fd, t_floor = [], [], []
        trees = {"": None, **({f" [{tree}]": tree} if tree else {})}
        runs = [(p, t) for t in trees for p in precisions]
        cli: dict[tuple[str | None, str], list[tuple[float, float, float]]] = {k: [] for k in runs}
        for r in range(repeat):
            if r:
                fd = train_member(fd_task)
            t_fd.append(
                _time_to(fd, target) if fd.best_iter else 0.0
            )  # 0: no iteration improved on the start
            cpu_fd.append(_time_to(fd, target, cpu=True) if fd.best_iter else 0.0)
            t = time.perf_counter()
            subprocess.run([sys.executable, "-c", FLOOR], check=True)
            t_floor.append(time.perf_counter() - t)
            line = f"  run {r + 1}: FD {t_fd[-1]:.2f} s (CPU {cpu_fd[-1]:.2f} s)"
            for p, t in runs:
                out = Path(tmp) / f"m-{p}.h5"
                wall, cpu = _run_cli(tp, vp, out, needed[p], p, trees[t])
                reached = ShearModel.load(out).point["tru_g1"].members[0].valid_cost
                cli[p, t].append((wall, cpu, reached))
                line += (
                    f"; CLI{t} {p or 'float64'} {wall:.2f} s "
                    f"(CPU {cpu:.2f} s, valid MSB {reached:.4e})"
                )
            print(line, flush=True)
    med_fd, med_cpu_fd = float(np.median(t_fd)), float(np.median(cpu_fd))
    print(
        "  FD baseline to its best validation MSB (in-process, training loop only): "
        f"wall {med_fd:.2f} s, CPU {med_cpu_fd:.2f} s (medians of {repeat})"
    )
    for p, t in runs:
        wall = float(np.median([c[0] for c in cli[p, t]]))
        cpu = float(np.median([c[1] for c in cli[p, t]]))
        reached = max(c[2] for c in cli[p, t])
        ok = (
            "reached"
            if reached <= target * (1 + 1e-12)
            else f"NOT reached ({reached / target - 1:+.1%})"
        )
        print(
            f"  train-point{t} --iterations {needed[p]}, precision {p or 'float64 (default)'}: "
            f"whole process wall {wall:.2f} s, CPU {cpu:.2f} s -> {med_fd / wall:.1f}x (wall), "
            f"{med_cpu_fd / cpu:.1f}x (CPU); baseline's validation MSB {ok}"
        )
    floor = float(np.median(t_floor))
    for p in precisions:
        least = floor + train_time[p]
        print(
            f"  the least a command could take, {p or 'float64'}: the floor process "
            f"({FLOOR!r}) {floor:.2f} s + the training loop to the MSB (in-process) "
            f"{train_time[p]:.2f} s = {least:.2f} s -> at most {med_fd / least:.1f}x"
        )


def bench_predict(n_rows: int, repeat: int) -> float:
    """Rows per second of Committee.predict for two 8-member (4 selected) 5-5-1 committees."""
    from megalut_cli.nn.model import Committee, Member

    rng = np.random.default_rng(0)
    net = Network(5, (5, 5), "identity", 0.0, 0.05)
    comms = []
    for target in ("tru_g1", "tru_g2"):
        members = [
            Member(
                layers=[(w.copy(), b.copy()) for w, b in net.unpack(net.init_normal(rng, 0.5))],
                selected=i < 4,
            )
            for i in range(8)
        ]
        comms.append(
            Committee(
                "point", target, FEATURES, (5, 5), np.zeros(5), np.ones(5), members, 0.0, 0.05
            )
        )
    x = rng.normal(size=(n_rows, 5))
    t = _best_of(lambda: [c.predict(x) for c in comms], repeat)
    return n_rows / t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    ap.add_argument("--members", type=int, default=4)
    ap.add_argument("--fd-iterations", type=int, default=60)
    ap.add_argument(
        "--cli",
        action="store_true",
        help="only 3.: the whole train-point command against the baseline",
    )
    ap.add_argument("--repeat", type=int, default=3, help="alternating runs of 3.")
    ap.add_argument(
        "--tree",
        default=None,
        metavar="DIR",
        help="3. also runs the command of this source tree (e.g. a git worktree of HEAD), "
        "alternating",
    )
    args = ap.parse_args()
    ev_cases, ev_rea, repeat = (50, 2000, 3) if args.quick else (500, 2000, 7)
    tr_cases, tr_rea = (100, 400) if args.quick else (500, 1000)
    members = 2 if args.quick else args.members
    fd_iter = 15 if args.quick else args.fd_iterations

    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, numpy {np.__version__}, "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}"
    )
    if args.cli:
        print(
            f"\n3. the whole train-point command, one member, {tr_cases} cases x {tr_rea} "
            f"realizations (validation catalog {max(2, tr_cases // 5)} cases), "
            f"batches 25% x 30 iterations, {fd_iter} iterations (CLI and FD baseline)"
        )
        bench_cli(tr_cases, tr_rea, fd_iter, args.repeat, args.tree)
        return
    print(
        f"\n1. one MSB evaluation, 5-5-1 network, {ev_cases} cases x {ev_rea} realizations "
        "x 5 features"
    )
    ev = bench_evaluation(ev_cases, ev_rea, repeat)
    print(f"  rows {ev['rows']}, parameters {ev['params']} (best of {repeat})")
    print(f"  forward pass + cost (float64):         {ev['forward64'] * 1e3:8.1f} ms")
    print(f"  cost + analytic gradient (float64):    {ev['grad64'] * 1e3:8.1f} ms")
    print(f"  cost + analytic gradient (float32):    {ev['grad32'] * 1e3:8.1f} ms")
    print(
        f"  cost + finite-difference gradient:     {ev['fd_grad'] * 1e3:8.1f} ms "
        f"({ev['fd_grad'] / ev['grad64']:.0f}x float64, "
        f"{ev['fd_grad'] / ev['grad32']:.0f}x float32)"
    )
    print(f"  max |FD - analytic| / max |analytic|:  {ev['fd_rel_err']:.1e}")
    orig_fd = ev["original_style"] * (ev["params"] + 1)
    print(
        f"  original-style cost (masked 3-D arrays): {ev['original_style'] * 1e3:6.1f} ms; "
        f"its FD gradient would take ~{orig_fd:.1f} s ({orig_fd / ev['grad64']:.0f}x float64, "
        f"{orig_fd / ev['grad32']:.0f}x float32)"
    )

    rate = bench_predict(1_000_000, repeat)
    print(
        "\n  Committee.predict, two 8-member (4 kept) 5-5-1 committees: "
        f"{rate / 1e6:.2f} million rows/s (one core)"
    )

    print(
        f"\n2. training to a validation MSB: {members} members, {tr_cases} cases x {tr_rea} "
        f"realizations (validation {max(2, tr_cases // 5)} cases), batches 25% x 30 iterations, "
        f"FD baseline {fd_iter} iterations per member"
    )
    rows = bench_training(tr_cases, tr_rea, members, fd_iter, max_factor=MAX_FACTOR)
    t_fd = sum(r["t_fd"] for r in rows)
    cpu_fd = sum(r["cpu_fd"] for r in rows)
    for dtype in ("float64", "float32"):
        reached = all(np.isfinite(r[f"t_{dtype}"]) for r in rows)
        t_an = sum(r[f"t_{dtype}"] for r in rows)
        cpu_an = sum(r[f"cpu_{dtype}"] for r in rows)
        if reached:
            print(
                f"  committee ({dtype}): wall FD baseline {t_fd:.1f} s, "
                f"analytic {t_an:.2f} s -> {t_fd / t_an:.0f}x faster; "
                f"CPU {cpu_fd:.1f} s vs {cpu_an:.2f} s -> {cpu_fd / cpu_an:.0f}x"
            )
        else:
            print(
                f"  committee ({dtype}): not every member reached its target within {MAX_FACTOR}x "
                "the iterations"
            )


if __name__ == "__main__":
    main()
