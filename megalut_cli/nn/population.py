"""What a model was trained on, and the biases recorded for it (told by ``megalut predict``
and ``megalut info``).

The training population comes from the training catalog's ``CONFIG`` HDU (written by
``simulate``): the ``[galaxy]``, ``[psf]`` and ``[noise]`` tables of the effective
configuration, stored in the model's ``/provenance`` ``population`` attribute; its domain
(the measured distributions of its training rows) in ``domain``
(:mod:`megalut_cli.nn.domain`). A model bias measured on real galaxies (``megalut evaluate
--twin``) is stored with :func:`record_real_bias` in the ``/validation``
``real_galaxy_bias`` attribute (``docs/model-format.md``).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from megalut_cli.configfile import read_toml
from megalut_cli.errors import InputError
from megalut_cli.nn.domain import DOMAIN_KEY, MEDIAN_RANGE, domain_summary, model_domain
from megalut_cli.sim.distributions import short_text
from megalut_cli.sim.profiles import GALAXY_PROFILES

#: Attribute of ``/validation`` holding the recorded model bias on real galaxies (JSON).
REAL_BIAS_ATTR = "real_galaxy_bias"
#: Keys a real-galaxy bias record must hold.
REAL_BIAS_KEYS = ("dm_g1", "dm_g1_err", "dm_g2", "dm_g2_err", "scheme", "setup", "command")
#: Attribute of ``/validation`` holding the model's own bias on a simulated validation set
#: (JSON, :func:`record_simulated_bias`): ``m_g1, m_g1_err, m_g2, m_g2_err, c_g1, c_g2``...
SIMULATED_BIAS_ATTR = "simulated_bias"
#: What ``dm_g1, dm_g2`` of a record are unless it says (optional key ``quantity``): the paired
#: real-vs-twin difference (docs/realgal.md); a metacal model records ``m_real`` itself.
REAL_BIAS_QUANTITY = "m_real - m_twin"


def training_population(catalog: str | os.PathLike) -> dict[str, Any] | None:
    """The population of a simulated training catalog (its config's galaxy, PSF and noise
    tables, and the config file name), or None when the catalog has no ``CONFIG`` HDU."""
    import fitsio

    try:
        with fitsio.FITS(str(catalog)) as f:
            if "CONFIG" not in f:
                return None
            row = f["CONFIG"].read()[0]
    except (OSError, ValueError):
        return None
    try:
        text = row["config_json"]
        raw = json.loads(text.decode("ascii") if isinstance(text, bytes) else str(text))
    except (ValueError, UnicodeDecodeError):
        return None
    pop = {k: raw.get(k, {}) for k in ("galaxy", "psf", "noise")}
    pop["config"] = Path(str(catalog)).name
    pop["description"] = raw.get("description", "")
    pop["summary"] = population_summary(pop)
    return pop


def population_summary(pop: Mapping[str, Any]) -> str:
    """One line: the galaxies as their profile says them (e.g. the real catalog and twin
    mode), PSF type and size, noise."""
    gal, psf, noise = pop.get("galaxy", {}), pop.get("psf", {}), pop.get("noise", {})
    name = gal.get("profile", "sersic")
    profile = GALAXY_PROFILES.get(name) if isinstance(name, str) else None
    g = profile.describe(gal) if profile is not None else f"{name} galaxies"
    p = f"{psf.get('type', '?')} PSF" + "".join(
        f" {k} {short_text(psf[k])}" for k in ("sigma", "fwhm", "beta") if k in psf
    )
    sigma = f" sigma {short_text(noise['sigma'])}" if "sigma" in noise else ""
    n = f"{noise.get('type', '?')} noise{sigma}"
    return f"{g}; {p}; {n}"


#: Units of the population's keys in plain words, by table.
_UNITS = {
    "galaxy": {"rad": "px", "angle": "deg", "flux": "adu", "sb": "adu/px2"},
    "psf": {"sigma": "px", "fwhm": "px", "rad": "px"},
    "noise": {"sigma": "adu"},
}
#: Keys told first (size and brightness before shape), the others as recorded.
_FIRST = ("sersicn", "rad", "sb", "flux", "mag", "sigma", "fwhm", "beta", "ellipticity", "angle")
#: How plain words name the population's tables.
_TABLE_NAMES = {"galaxy": "galaxies", "psf": "PSF", "noise": "noise"}


def _num(v: Any) -> str:
    return f"{v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def describe_value(v: Any, unit: str = "") -> str:
    """A config value (a number, a string, a distribution table) in plain words, e.g.
    ``uniform 2 to 8 px``, ``Rayleigh of mode 0.2 in 0 to 0.6``, ``grid 1 to 4 step 0.1``."""
    u = f" {unit}" if unit else ""
    if not isinstance(v, Mapping):
        if isinstance(v, (list, tuple)):
            return ", ".join(_num(x) for x in v) + u
        return _num(v) + (u if isinstance(v, (int, float)) and not isinstance(v, bool) else "")
    t = v.get("type", "")
    lo, hi = v.get("min"), v.get("max")
    span = f" in {_num(lo)} to {_num(hi)}{u}" if lo is not None and hi is not None else ""
    if t == "constant":
        return f"{_num(v.get('value'))}{u}"
    if t == "uniform":
        return f"uniform {_num(lo)} to {_num(hi)}{u}"
    if t == "normal":
        return f"normal {_num(v.get('mean'))} ± {_num(v.get('sigma'))}{u}{span}"
    if t == "rayleigh":
        return f"Rayleigh of mode {_num(v.get('mode'))}{span}"
    if t == "grid":
        if "values" in v:
            return f"one of {describe_value(list(v['values']), unit)}"
        step = (
            f" step {_num(v['step'])}"
            if "step" in v
            else f" ({_num(v['n'])} values)"
            if "n" in v
            else ""
        )
        return f"grid {_num(lo)} to {_num(hi)}{u}{step}"
    if t == "sequence" and "values" in v:
        return f"in turn {describe_value(list(v['values']), unit)}"
    if t == "catalog":
        return f"column {v.get('column')} of the catalog"
    return ", ".join(f"{k} {describe_value(x)}" for k, x in v.items())


def population_lines(pop: Mapping[str, Any], setup: Mapping[str, Any] | None = None) -> list[str]:
    """The population (and the setup's stamp size) in plain words, one line per table:
    ``galaxies: sersic; rad uniform 2 to 8 px; ...``, ``PSF: gaussian; sigma 2 px``,
    ``noise: gaussian; sigma 1 adu``, ``stamp size: 64 px``."""
    lines = []
    for table in ("galaxy", "psf", "noise"):
        t = pop.get(table)
        if not isinstance(t, Mapping) or not t:
            continue
        head = t.get("profile", t.get("type"))
        first = [k for k in _FIRST if k in t]
        items = [
            f"{k} {describe_value(t[k], _UNITS[table].get(k, ''))}"
            for k in [*first, *(k for k in t if k not in first)]
            if k not in ("profile", "type")
        ]
        lines.append(
            f"{_TABLE_NAMES[table]}: " + "; ".join([str(head)] * (head is not None) + items)
        )
    size = (setup or {}).get("stamp_size")
    if size:
        lines.append(f"stamp size: {size} px")
    return lines


def domain_line(domain: Mapping[str, Any]) -> str:
    """One line: the domain's ranges, and the rows they come from."""
    lo, hi = (f"{100 * p:g}" for p in MEDIAN_RANGE)
    rows = f"{domain.get('n_rows')} usable rows" if domain.get("n_rows") else "the usable rows"
    of = f" of {domain['source']}" if domain.get("source") else ""
    if isinstance(domain.get("derived"), Mapping):
        d = domain["derived"]
        of += f", derived by {d.get('script')} (seed {d.get('seed')}, {d.get('n_stamps')} stamps)"
    version = f", {domain['version']} columns" if domain.get("version") else ""
    return f"{lo}–{hi} % of {rows}{of}{version}: {domain_summary(domain)}"


def model_report(model: Any) -> list[str]:
    """Lines telling what ``model`` (a ShearModel) was trained on (population and domain)
    and its recorded biases."""
    lines = []
    prov = model.provenance
    chain = [prov] + ([prov["parent"]] if isinstance(prov.get("parent"), Mapping) else [])
    for p in chain:
        pop = p.get("population")
        what = "point estimates" if p.get("command") == "train-point" else "weights"
        if isinstance(pop, Mapping):
            lines.append(
                f"model {what} trained on: {pop.get('summary') or population_summary(pop)} "
                f"({pop.get('config')})"
            )
        elif p.get("command"):
            lines.append(f"model {what}: training population not recorded in the model file")
    domain = model_domain(prov)
    if domain is not None:
        lines.append(f"model domain ({domain_line(domain)})")
    else:
        lines.append(
            f"model domain: not recorded in the model file ({DOMAIN_KEY}; docs/model-format.md)"
        )
    rec = model.validation.get(REAL_BIAS_ATTR)
    if isinstance(rec, Mapping):
        lines.append(
            f"recorded model bias on real galaxies ({rec.get('setup')}, {rec.get('scheme')}): "
            f"{rec.get('quantity', REAL_BIAS_QUANTITY)} = "
            f"{rec.get('dm_g1'):+.2e} ± {rec.get('dm_g1_err'):.1e} (g1), "
            f"{rec.get('dm_g2'):+.2e} ± {rec.get('dm_g2_err'):.1e} (g2)"
        )
    else:
        lines.append("no model bias on real galaxies recorded for this model (docs/realgal.md)")
    return lines


def population_from_config(config_path: str | os.PathLike) -> dict[str, Any]:
    """The population of a simulation config file, or of the ``[simulation]`` table of a
    pipeline file (for models whose training catalog is gone)."""
    raw, _ = read_toml(config_path)
    if "galaxy" not in raw and isinstance(raw.get("simulation"), Mapping):
        raw = {**raw["simulation"], "description": raw.get("description", "")}
    pop = {k: raw.get(k, {}) for k in ("galaxy", "psf", "noise")}
    pop["config"] = Path(str(config_path)).name
    pop["description"] = raw.get("description", "")
    pop["summary"] = population_summary(pop)
    return pop


def record_real_bias(model_path: str | os.PathLike, record: Mapping[str, Any]) -> None:
    """Store ``record`` (keys :data:`REAL_BIAS_KEYS`) as the model's real-galaxy bias,
    in place but atomically (a modified copy replaces the file)."""
    missing = [k for k in REAL_BIAS_KEYS if k not in record]
    if missing:
        raise InputError(f"real-galaxy bias record: missing {', '.join(missing)}")
    _set_json_attr(model_path, "validation", REAL_BIAS_ATTR, dict(record))


def simulated_bias_record(
    evaluation: Mapping[str, Any], scheme: str = "weighted"
) -> dict[str, Any]:
    """The :data:`SIMULATED_BIAS_ATTR` record of an evaluation (the JSON of ``megalut evaluate
    --json``, a run's ``evaluation.json``): m and c of each component with ``scheme``
    (``weighted``, else ``unweighted``), its input's file name and rows."""
    fits = evaluation.get(scheme) or evaluation.get("unweighted")
    if not isinstance(fits, Mapping) or not all(
        isinstance(fits.get(g), Mapping) for g in ("g1", "g2")
    ):
        raise InputError(f"evaluation: no m, c of g1 and g2 ({scheme} or unweighted)")
    used = scheme if evaluation.get(scheme) else "unweighted"
    record: dict[str, Any] = {"scheme": used}
    for g in ("g1", "g2"):
        for key in ("m", "c"):
            record[f"{key}_{g}"] = float(fits[g][key])
            record[f"{key}_{g}_err"] = float(fits[g][f"{key}_err"])
    record["input"] = Path(str(evaluation.get("input", ""))).name
    record["n_rows"] = evaluation.get("n_valid", evaluation.get("n_rows"))
    return record


def record_simulated_bias(model_path: str | os.PathLike, evaluation: Mapping[str, Any]) -> None:
    """Store the model's bias on a simulated validation set (:func:`simulated_bias_record` of
    ``evaluation``), in place but atomically; ``megalut predict`` reports a model whose
    recorded |m| exceeds the Stage IV requirement."""
    _set_json_attr(model_path, "validation", SIMULATED_BIAS_ATTR, simulated_bias_record(evaluation))


def record_validated_model(
    trained: str | os.PathLike,
    evaluation: Mapping[str, Any],
    output: str | os.PathLike,
    overwrite: bool = False,
) -> None:
    """Write ``output``: the model ``trained`` with its simulated validation ``evaluation``
    recorded (:func:`record_simulated_bias`), whole or not at all."""
    from megalut_cli.atomic import atomic_output

    with atomic_output(output, overwrite) as tmp:
        shutil.copyfile(trained, tmp)
        record_simulated_bias(tmp, evaluation)


def record_population(model_path: str | os.PathLike, population: Mapping[str, Any]) -> None:
    """Store ``population`` as the training population of a model that lacks one, for its
    weights and its point estimates alike (``/provenance`` ``population`` and the
    ``parent`` provenance's), in place but atomically: for models whose sets all come
    from one simulation, such as those of ``megalut run``."""

    def update(prov: dict[str, Any]) -> None:
        prov["population"] = dict(population)
        parent = prov.get("parent")
        if isinstance(parent, str):
            parent = json.loads(parent)
        if isinstance(parent, dict):
            update(parent)
            prov["parent"] = json.dumps(parent, sort_keys=True)

    def edit(f: Any) -> None:
        prov = {
            k: (v.decode() if isinstance(v, bytes) else v)
            for k, v in f.require_group("provenance").attrs.items()
        }
        update(prov)
        f["provenance"].attrs["population"] = json.dumps(dict(population), sort_keys=True)
        if "parent" in prov:
            f["provenance"].attrs["parent"] = prov["parent"]

    _edit_model(model_path, edit)


def update_provenance(
    model_path: str | os.PathLike, change: Callable[[dict[str, Any]], dict[str, Any]]
) -> None:
    """Replace a model's ``/provenance`` by ``change(provenance)`` (decoded as
    :meth:`ShearModel.load` decodes it, ``parent`` included), in place but atomically; the
    networks are not touched (only the attributes of ``/provenance`` are rewritten)."""

    def edit(f: Any) -> None:
        group = f.require_group("provenance")
        prov = {}
        for key, val in group.attrs.items():
            val = val.decode() if isinstance(val, bytes) else str(val)
            try:
                prov[key] = json.loads(val)
            except json.JSONDecodeError:
                prov[key] = val
        new = change(prov)
        for key in list(group.attrs):
            if key not in new:
                del group.attrs[key]
        for key, val in new.items():
            group.attrs[key] = val if isinstance(val, str) else json.dumps(val, sort_keys=True)

    _edit_model(model_path, edit)


def _set_json_attr(model_path: str | os.PathLike, group: str, key: str, value: Any) -> None:
    """Set the JSON attribute ``key`` of ``group`` in a copy of the model file, then rename it."""

    def edit(f: Any) -> None:
        f.require_group(group).attrs[key] = json.dumps(value, sort_keys=True)

    _edit_model(model_path, edit)


def _edit_model(model_path: str | os.PathLike, edit: Any) -> None:
    """Apply ``edit(h5py.File)`` to a copy of the model file, then rename the copy over it."""
    import h5py

    src = Path(model_path)
    fd, tmp = tempfile.mkstemp(prefix=f".{src.name}.", suffix=".tmp", dir=src.parent)
    os.close(fd)
    try:
        shutil.copyfile(src, tmp)
        shutil.copymode(src, tmp)  # mkstemp's 0600 would replace the file's mode
        with h5py.File(tmp, "a") as f:
            edit(f)
        os.replace(tmp, src)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
