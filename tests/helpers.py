"""Helpers shared by several test modules: synthetic models, catalogs and predictions, and
the checks of a command's result (exit status, one error line) of the command-line tests."""

from __future__ import annotations

import struct

import numpy as np

from megalut_cli.nn.data import CaseData
from megalut_cli.nn.model import Committee, Member, ShearModel
from megalut_cli.nn.network import Network
from megalut_cli.nn.toy import appendix_columns
from megalut_cli.nn.train import MemberTask, TrainSettings

FEATURES = ["adamom_g1", "adamom_g2", "adamom_sigma", "adamom_flux", "adamom_rho4"]


def make_committee(
    kind: str, target: str, features: list[str], hidden=(5, 5), n_members=3, seed=0
) -> Committee:
    rng = np.random.default_rng(seed)
    sizes = [len(features), *hidden, 1]
    members = [
        Member(
            layers=[
                (rng.normal(0, 0.7, (i, o)), rng.normal(0, 0.2, o))
                for i, o in zip(sizes[:-1], sizes[1:])
            ]
        )
        for _ in range(n_members)
    ]
    return Committee(
        kind,
        target,
        features,
        hidden,
        in_loc=rng.normal(0, 0.5, len(features)),
        in_scale=rng.uniform(0.5, 2.0, len(features)),
        members=members,
        out_loc=0.01,
        out_scale=0.3,
    )


def make_model(path, weights: bool = True, seed: int = 0) -> ShearModel:
    point = {
        t: make_committee("point", t, FEATURES, seed=seed + i)
        for i, t in enumerate(("tru_g1", "tru_g2"))
    }
    weight = {}
    if weights:  # weight committees may use other features: the model needs their union
        wf = [*FEATURES[2:], "snr"]
        weight = {
            t: make_committee("weight", t, wf, hidden=(4,), seed=seed + 10 + i)
            for i, t in enumerate(("tru_g1", "tru_g2"))
        }
    model = ShearModel(point, weight)
    model.save(path)
    return model


def manual_predict(c: Committee, x: np.ndarray) -> np.ndarray:
    """Independent forward pass: mean over members of the plain layer-by-layer formula."""
    outs = []
    for mem in c.members:
        a = (x - c.in_loc) / c.in_scale
        for w, b in mem.layers[:-1]:
            a = np.tanh(a @ w + b)
        z = a @ mem.layers[-1][0][:, 0] + mem.layers[-1][1][0]
        outs.append(
            c.out_loc + c.out_scale * z if c.kind == "point" else 1.0 / (1.0 + np.exp(-4.0 * z))
        )
    return np.mean(outs, axis=0)


def features_catalog(n: int = 1000, seed: int = 1) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = {
        "case": np.arange(n) // 10,
        "adamom_g1": rng.normal(0, 0.2, n),
        "adamom_g2": rng.normal(0, 0.2, n),
        "adamom_sigma": rng.uniform(1, 4, n),
        "adamom_flux": rng.uniform(10, 100, n),
        "adamom_rho4": rng.uniform(1.8, 2.4, n),
        "snr": rng.uniform(5, 50, n),
        "name": np.array([f"g{i % 7}" for i in range(n)]),
        "vec": rng.normal(size=(n, 3)),
        "flags": np.zeros(n, dtype=np.int32),
    }
    return d


def synthetic(
    seed: int = 0,
    n_cases: int = 100,
    n_rea: int = 100,
    m: tuple[float, float] = (0.0, 0.0),
    c: tuple[float, float] = (0.0, 0.0),
    sigma: float = 0.2,
    weights: bool = False,
    psf: bool = False,
) -> dict[str, np.ndarray]:
    """Rows ``pre = (1 + m) g + c + noise`` for cases with uniform true shears (no simulation)."""
    rng = np.random.default_rng(seed)
    case = np.repeat(np.arange(n_cases), n_rea) + 1000  # ids need not start at 0
    g = rng.uniform(-0.1, 0.1, (2, n_cases))
    t1, t2 = g[0][case - 1000], g[1][case - 1000]
    d = {
        "case": case,
        "rea": np.tile(np.arange(n_rea), n_cases),
        "tru_g1": t1,
        "tru_g2": t2,
        "pre_g1": (1 + m[0]) * t1 + c[0] + rng.normal(0, sigma, case.size),
        "pre_g2": (1 + m[1]) * t2 + c[1] + rng.normal(0, sigma, case.size),
        "flags": np.zeros(case.size, dtype=np.int32),
        "tru_rad": rng.uniform(1.0, 5.0, n_cases)[case - 1000],
        "snr": rng.uniform(5.0, 50.0, case.size),
    }
    if weights:
        d["pre_g1_w"] = rng.uniform(0.1, 1.0, case.size)
        d["pre_g2_w"] = rng.uniform(0.1, 1.0, case.size)
    if psf:
        d["tru_psf_g1"] = rng.uniform(-0.1, 0.1, n_cases)[case - 1000]
        d["tru_psf_g2"] = rng.uniform(-0.1, 0.1, n_cases)[case - 1000]
    return d


def metacal_predictions(
    n: int = 4000,
    g: tuple[float, float] = (0.02, -0.01),
    seed: int = 1,
    step: float = 0.01,
    weights: bool = False,
    sigma_e: float = 0.25,
    positions: bool = True,
    ring: int = 2,
    jacobians: bool = False,
) -> dict[str, np.ndarray]:
    """A synthetic metacal prediction catalog (the columns of ``megalut predict`` on a metacal
    catalog) under the constant shear ``g``: each object's estimate under the shear ``s`` is
    ``e + R s`` (a per-object response ``R``; the intrinsic ``e`` in rings of ``ring``
    orientations sharing everything else, 2: 90-degree pairs), the sheared versions at
    ``g +- step``; ``size_<type> = u + |estimate|^2`` (``u`` uniform) is a measured column
    whose cut (``size > 0.5``) has a selection response; ``weights``:
    ``pre_g*_w_<type> = 1 / (0.1 + |estimate|^2)`` (a weight response too). With
    ``jacobians``, ``g`` is a world-frame shear seen through a random Jacobian per ring
    (any angle, a flip for half, a residual shear eta of 0.02 rms; columns ``dudcol`` ..
    ``dvdrow``): each object's estimates are those of its pixel-frame shear ``Q^T g - eta``."""
    rng = np.random.default_rng(seed)
    m = n // ring
    n = m * ring
    e0 = rng.normal(0.0, sigma_e, (2, m))
    angle = np.repeat(2.0 * np.pi * np.arange(ring) / ring, m)  # spin-2 angle of each member
    e0 = np.tile(e0, ring)
    cos, sin = np.cos(angle), np.sin(angle)
    e = np.array([cos * e0[0] - sin * e0[1], sin * e0[0] + cos * e0[1]])
    r = np.empty((2, 2, m))
    r[0, 0] = rng.uniform(0.6, 1.0, m)
    r[1, 1] = rng.uniform(0.6, 1.0, m)
    r[0, 1] = rng.normal(0.0, 0.05, m)
    r[1, 0] = rng.normal(0.0, 0.05, m)
    r = np.tile(r, ring)
    u = np.tile(rng.uniform(0.0, 1.0, m), ring)
    pixel_g = np.repeat(np.asarray(g, dtype=float)[:, None], n, axis=1)
    out: dict[str, np.ndarray] = {"id": np.arange(n, dtype=np.int64)}
    if jacobians:
        phi = np.tile(rng.uniform(0.0, 2.0 * np.pi, m), ring)
        flip = np.tile(rng.random(m) < 0.5, ring)
        eta = np.tile(rng.normal(0.0, 0.02, (2, m)), ring)
        c, s_ = np.cos(phi), np.sin(phi)
        rot = np.array([[c, -s_], [s_, c]])  # (2, 2, n)
        par = np.array([[np.ones(n), np.zeros(n)], [np.zeros(n), np.where(flip, -1.0, 1.0)]])
        dist = np.array([[1.0 + eta[0], eta[1]], [eta[1], 1.0 - eta[0]]])
        jac = 0.2 * np.einsum("ijn,jkn,kln->iln", rot, par, dist)
        out["dudcol"], out["dudrow"], out["dvdcol"], out["dvdrow"] = (
            jac[0, 0],
            jac[0, 1],
            jac[1, 0],
            jac[1, 1],
        )
        c2, s2 = np.cos(2 * phi), np.sin(2 * phi)
        q = np.array([[c2, np.where(flip, s2, -s2)], [s2, np.where(flip, -c2, c2)]])
        pixel_g = np.einsum("jin,j->in", q, np.asarray(g, dtype=float)) - eta
    shears = {
        "noshear": pixel_g,
        "1p": pixel_g + np.array([[step], [0.0]]),
        "1m": pixel_g - np.array([[step], [0.0]]),
        "2p": pixel_g + np.array([[0.0], [step]]),
        "2m": pixel_g - np.array([[0.0], [step]]),
    }
    if positions:
        out["ra"] = rng.uniform(-1.0, 1.0, n) % 360.0
        out["dec"] = rng.uniform(-1.0, 1.0, n)
    for kind, s in shears.items():
        est = e + np.einsum("ijn,jn->in", r, s)
        for i in (0, 1):
            out[f"pre_g{i + 1}_{kind}"] = est[i]
        out[f"size_{kind}"] = u + est[0] ** 2 + est[1] ** 2
        out[f"flags_{kind}"] = np.zeros(n, dtype=np.int32)
        if weights:
            w = 1.0 / (0.1 + est[0] ** 2 + est[1] ** 2)
            out[f"pre_g1_w_{kind}"] = w
            out[f"pre_g2_w_{kind}"] = w
    for i in (1, 2):
        for j in (1, 2):
            jp, jm = f"{j}p", f"{j}m"
            out[f"mcal_r{i}{j}"] = (out[f"pre_g{i}_{jp}"] - out[f"pre_g{i}_{jm}"]) / (2 * step)
    out["pre_g1"], out["pre_g2"] = out["pre_g1_noshear"], out["pre_g2_noshear"]
    out["flags"] = out["flags_noshear"]
    out["size"] = out["size_noshear"]  # as a metacal catalog's base features
    return out


def with_failures(cat: dict, limit: float = 0.6) -> dict:
    """A metacal catalog ``cat`` where a version fails (flag set, estimates NaN) when its
    ``|estimate| > limit``, as elongated galaxies do: which objects a version keeps depends
    on the shear, and an object's responses (NaN then) need every version."""
    types = ("noshear", "1p", "1m", "2p", "2m")
    out = dict(cat)
    for k in types:
        bad = np.hypot(cat[f"pre_g1_{k}"], cat[f"pre_g2_{k}"]) > limit
        out[f"flags_{k}"] = bad.astype(np.int32)
        for i in "12":
            out[f"pre_g{i}_{k}"] = np.where(bad, np.nan, cat[f"pre_g{i}_{k}"])
    failed = np.any([out[f"flags_{k}"] > 0 for k in types], axis=0)
    for i in "12":
        for j in "12":
            out[f"mcal_r{i}{j}"] = np.where(failed, np.nan, cat[f"mcal_r{i}{j}"])
    out["flags"] = out["flags_noshear"]
    out["pre_g1"], out["pre_g2"] = out["pre_g1_noshear"], out["pre_g2_noshear"]
    return out


def png_size(path) -> tuple[int, int]:
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


#: The biases :func:`crn_synthetic` injects.
CRN_M_TRUE, CRN_C_TRUE = 0.05, 1e-3


def crn_synthetic(
    seed: int,
    crn: bool,
    n_cases: int = 10,
    n_groups: int = 300,
    group_size: int = 2,
    case_response_scatter: float = 0.0,
) -> dict:
    """Estimates ``pre = e + (1 + m + d + mu) g + c + n + eps`` of ``n_groups`` galaxies
    (90-degree pairs: ``e`` opposite within a pair) per case. Per galaxy: intrinsic ``e``,
    response scatter ``d`` and pixel noise ``n``, the same in every case when ``crn`` (else
    new per case); ``eps`` is a small independent per-row noise; ``mu`` a response common to
    the galaxies of a case, N(0, ``case_response_scatter``): what a response that varies with
    the drawn shear does to a set."""
    rng = np.random.default_rng(seed)
    n_rea = n_groups * group_size
    g = rng.uniform(-0.1, 0.1, (2, n_cases))
    mu = rng.normal(0.0, case_response_scatter, (2, n_cases)) if case_response_scatter else None

    def galaxies() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e = rng.normal(0, 0.25, (2, n_groups))
        e = np.repeat(e, group_size, axis=1) * np.tile([1.0, -1.0][:group_size], n_groups)
        d = rng.normal(0, 0.15, (2, n_rea))
        noise = rng.normal(0, 0.1, (2, n_rea))
        return e, d, noise

    shared = galaxies()
    cols: dict[str, list[np.ndarray]] = {
        k: [] for k in ("case", "rea", "tru_g1", "tru_g2", "pre_g1", "pre_g2")
    }
    for k in range(n_cases):
        e, d, noise = shared if crn else galaxies()
        eps = rng.normal(0, 0.01, (2, n_rea))
        cols["case"].append(np.full(n_rea, k))
        cols["rea"].append(np.arange(n_rea))
        for i in (0, 1):
            cols[f"tru_g{i + 1}"].append(np.full(n_rea, g[i, k]))
            cols[f"pre_g{i + 1}"].append(
                e[i]
                + (1 + CRN_M_TRUE + d[i] + (mu[i, k] if mu is not None else 0.0)) * g[i, k]
                + CRN_C_TRUE
                + noise[i]
                + eps[i]
            )
    return {k: np.concatenate(v) for k, v in cols.items()}


GREAT3_BRANCH = """
[structure]
n_cases = 2
n_realizations = 16
per_realization = ["galaxy"]
snc = "pairs"
stamp_size = 32

[shear]
g1 = {type = "uniform", min = -0.05, max = 0.05}
g2 = {type = "uniform", min = -0.05, max = 0.05}

[galaxy]
sersicn = {type = "grid", min = 0.5, max = 2.5, step = 0.5}
rad = {type = "uniform", min = 1.0, max = 2.5}
flux = {type = "uniform", min = 100.0, max = 200.0}
ellipticity = {type = "rayleigh", mode = 0.2, min = 0.0, max = 0.6}

[psf]
type = "moffat"
beta = 3.0
fwhm = {type = "uniform", min = 2.5, max = 3.5}
g1 = {type = "uniform", min = -0.05, max = 0.05}
g2 = {type = "uniform", min = -0.05, max = 0.05}

[noise]
type = "gaussian"
sigma = 0.5
"""


def toy_unit(job: dict, work) -> dict:
    """A :class:`megalut_cli.pipeline.steps.Unit` function (top level, for worker processes): writes
    ``u<i>.txt`` = the content of its source times ``factor``; fails when the source says "bad"."""
    from pathlib import Path

    from megalut_cli.errors import InputError

    text = Path(job["source"]).read_text()
    if text == "bad":
        raise InputError(f"{job['source']}: bad content")
    value = int(text) * job["factor"]
    with open(job["log"], "a") as calls:
        calls.write(f"{job['i']}\n")
    (work.workdir / f"u{job['i']}.txt").write_text(str(value))
    return {"i": job["i"], "value": value, "key": work.key}


def toy_task(data: CaseData, valid: CaseData, **kw) -> MemberTask:
    """A small training task of one member on the Appendix A toy cases."""
    net = Network(
        data.x.shape[1], (5,), "identity", float(data.targets.mean()), float(data.targets.std())
    )
    settings = TrainSettings(
        **{"iterations": 90, "batch_fraction": 0.5, "batch_iterations": 30, **kw}
    )
    return MemberTask(
        "m",
        net,
        settings,
        data,
        valid,
        0,
        np.full(1, 1.4),
        np.full(1, 0.9),
        seed=5,
        keys=(2, 1, 0),
        cost_scale=float(data.targets.std()),
    )


def toy_cases(seed: int, nc: int = 60, nr: int = 100) -> CaseData:
    """``nc`` Appendix A toy cases of ``nr`` realizations."""
    rng = np.random.default_rng(seed)
    cols = appendix_columns(rng.uniform(0.25, 2.0, nc), nr, rng)
    return CaseData.from_padded(
        cols["d"].reshape(nc, nr, 1), np.ones((nc, nr), bool), cols["tru_theta"][::nr]
    )


# Checks of a click ``CliRunner`` result (the ``runner`` fixture keeps stderr apart).


def error_text(result) -> str:
    """What the command wrote to stderr (its whole output where the runner mixes them)."""
    return result.stderr if result.stderr is not None else result.output


def one_line(result) -> str:
    """The command's stderr, stripped, asserted to be one line and no traceback."""
    text = error_text(result).strip()
    assert "Traceback" not in text and len(text.splitlines()) == 1, text
    return text


def assert_ok(result) -> None:
    """Exit status 0 (else both streams in the failure message)."""
    assert result.exit_code == 0, (result.output, getattr(result, "stderr", ""))


def error_line(result, code: int, *words: str) -> str:
    """Exit status ``code`` and exactly one line starting with "Error" (log and usage lines
    aside) that holds each of ``words``; no traceback. Returns that line."""
    text = (result.stderr or result.output).strip()
    assert result.exit_code == code, text
    errors = [ln for ln in text.splitlines() if ln.startswith("Error")]
    assert "Traceback" not in text and len(errors) == 1, text
    for w in words:
        assert w in errors[0], (w, errors[0])
    return errors[0]


def invoke_fails(runner, cli, args, code: int, *words: str) -> str:
    """``megalut ARGS`` exits with ``code``, without a traceback, and its output and stderr
    hold each of ``words``. Returns them."""
    result = runner.invoke(cli, args)
    assert result.exit_code == code, result.output
    text = result.output + (result.stderr if hasattr(result, "stderr") else "")
    assert "Traceback" not in text
    for w in words:
        assert w in text, text
    return text


def metadetect_predictions(
    n: int = 40_000,
    g: tuple[float, float] = (0.02, -0.01),
    seed: int = 1,
    step: float = 0.01,
    n_fields: int = 100,
) -> dict[str, np.ndarray]:
    """A synthetic predicted metadetection catalog (``measure --metadetect`` then
    ``predict``): objects in ``n_fields`` fields (in 90-degree pairs), each with a response
    ``R`` and an estimate ``e + R s`` under the shear ``s`` of each version (``g``, and
    ``g +- step`` along each axis); a version keeps the objects it detects,
    ``u + |estimate|^2 > 0.5`` (``u`` uniform), so that detection responds to the shear."""
    rng = np.random.default_rng(seed)
    m = n // 2
    e0 = rng.normal(0.0, 0.25, (2, m))
    e = np.concatenate([e0, np.array([-e0[0], -e0[1]])], axis=1)
    r = np.tile(rng.uniform(0.6, 1.0, m), 2)
    u = np.tile(rng.uniform(0.0, 1.0, m), 2)
    field = np.tile(rng.integers(0, n_fields, m), 2)
    shears = {
        "noshear": (0.0, 0.0),
        "1p": (step, 0.0),
        "1m": (-step, 0.0),
        "2p": (0.0, step),
        "2m": (0.0, -step),
    }
    parts: dict[str, list[np.ndarray]] = {
        c: [] for c in ("mdet_step", "field", "pre_g1", "pre_g2", "flags")
    }
    for kind, s in shears.items():
        est = e + r * (np.asarray(g)[:, None] + np.asarray(s)[:, None])
        det = u + est[0] ** 2 + est[1] ** 2 > 0.5
        parts["mdet_step"].append(np.full(int(det.sum()), kind))
        parts["field"].append(field[det])
        parts["pre_g1"].append(est[0][det])
        parts["pre_g2"].append(est[1][det])
        parts["flags"].append(np.zeros(int(det.sum()), dtype=np.int32))
    return {c: np.concatenate(v) for c, v in parts.items()}


#: Tolerances of columns that two routes compute with float32 sums of different shapes (the
#: metacal operation's matrix products): bit for bit on an AVX-512 Xeon, on an AMD EPYC up to
#: 1e-7 relative on fluxes and sizes, 1e-8 absolute on shapes near zero, 3e-5 relative on
#: skymad and snr (a median that can pick a neighbouring sample).
FLOAT32_SUMS = {"rtol": 1e-4, "atol": 1e-7}
#: Tolerances of float64 columns summed in another order (a SIMD width, a stride): a few ulp.
FLOAT64_SUMS = {"rtol": 1e-12, "atol": 0.0}


def assert_same_column(actual, desired, name: str, tolerance: dict | None = None) -> None:
    """Integer and boolean columns (flags, indices) equal; float columns equal or, with
    ``tolerance`` (:data:`FLOAT32_SUMS`, :data:`FLOAT64_SUMS`), within it: what differs
    between CPUs is the order of sums, not what is computed."""
    actual, desired = np.asarray(actual), np.asarray(desired)
    if tolerance is None or actual.dtype.kind not in "fc":
        np.testing.assert_array_equal(actual, desired, err_msg=name)
    else:
        np.testing.assert_allclose(actual, desired, err_msg=name, **tolerance)
