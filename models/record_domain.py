"""Record the domain of the shipped models (megalut_cli/data/*.h5), whose training catalogs are
gone.

A model trained today records the quantiles of skymad, snr, adamom_sigma, adamom_flux (and
psf_adamom_sigma when present) over its training rows, and its stamp size (``/provenance``
``domain``, docs/model-format.md), which ``megalut predict`` compares catalogs with. The
shipped models were trained before that. This script draws a fresh sample of each model's
weight-training set (TW) from the pipeline file that made it (20 000 stamps, seed 61, the
fast engine; no set or training of these models used seed 61), checks that its galaxy, PSF
and noise tables are the population the model records, measures it as training did (for
fiducial-metacal: the metacal versions, whose noshear features are its domain), and stores
the quantiles of its usable rows (flags == 0, finite features) with how they were derived.

It also replaces the absolute paths of the machine the models were made on (recorded
inputs and command lines) by file names, and records both edits in the provenance
(``edits``). Only attributes of ``/provenance`` change: the networks stay bit for bit
(tests/test_domain.py). Rerun after models/make_fiducial_metacal.py. From the repository
root (about 1 min, plus 4 min for the metacal sample, on 2 cores):

    python models/record_domain.py [NAME ...]
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from megalut_cli.catalog import VersionColumns
from megalut_cli.nn.data import valid_rows
from megalut_cli.nn.domain import DOMAIN_KEY, domain_record, domain_summary
from megalut_cli.nn.fit import config_psf_domain
from megalut_cli.nn.model import ShearModel
from megalut_cli.nn.population import update_provenance
from megalut_cli.nn.shipped import SHIPPED_MODELS, shipped_model
from megalut_cli.pipeline.file import load_pipeline
from megalut_cli.provenance import sha256_file, shown_command, shown_path
from megalut_cli.sim.options import SIMULATE
from megalut_cli.sim.simulate import simulate_table

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = "models/record_domain.py"
#: Model -> (the pipeline file that trained it, whether its domain is the metacal noshear features).
SOURCES = {
    "fiducial": ("fiducial-pipeline.toml", False),
    "fiducial-1e6": ("fiducial-1e6-pipeline.toml", False),
    "fiducial-metacal": ("fiducial-pipeline.toml", True),
}
SEED = 61
N_CASES, N_REALIZATIONS = 200, 100  # 20 000 stamps (even realizations: TW draws pairs)
SET = "tw"
NPROC = 2


def sample_domain(name: str, model: ShearModel) -> dict[str, Any]:
    """The domain of a fresh sample of the model's TW set (see the module doc)."""
    pipeline, metacal = SOURCES[name]
    pipe = load_pipeline(ROOT / "models" / pipeline)
    config = pipe.sets[SET].config
    recorded = model.provenance.get("population") or {}
    for table in ("galaxy", "psf", "noise"):
        if config.raw.get(table) != recorded.get(table):
            raise SystemExit(
                f"{name}: [{table}] of {pipeline} differs from the population the model records"
            )
    config = config.with_structure(n_cases=N_CASES, n_realizations=N_REALIZATIONS)
    columns, _ = simulate_table(
        config,
        SEED,
        measure=True,
        nproc=NPROC,
        engine="fast",
        metacal_step=SIMULATE["metacal_step"].default if metacal else None,
    )
    table: Any = VersionColumns(columns, "noshear") if metacal else columns
    usable = valid_rows(table, model.features, len(columns["case"]))
    derived = {
        "script": SCRIPT,
        "seed": SEED,
        "n_stamps": N_CASES * N_REALIZATIONS,
        "engine": "fast",
        "pipeline": f"models/{pipeline}",
        "set": SET,
        "metacal": metacal,
    }
    about: dict[str, Any] = {
        "source": f"a fresh sample of [sets.{SET}] of {pipeline}",
        "selection": None,
        "derived": derived,
    }
    if metacal:
        about["version"] = "noshear"
    domain = domain_record(table, usable, config.structure.stamp_size, **about)
    return config_psf_domain(
        domain, config.raw["psf"], config.structure.stamp_size
    )  # as train-point records it


def _named_inputs(prov: dict[str, Any]) -> dict[str, Any]:
    """``prov`` (and its parents) with inputs named by file name and no absolute path in argv."""
    out = dict(prov)
    inputs = out.get("inputs")
    if isinstance(inputs, dict):
        out["inputs"] = {
            role: {
                "name": Path(str(v.get("path", ""))).name,
                **v,
                "path": shown_path(str(v.get("path"))),
            }
            if isinstance(v, dict) and "path" in v
            else v
            for role, v in inputs.items()
        }
    if isinstance(out.get("argv"), str):
        out["argv"] = shown_command(out["argv"])
    if isinstance(out.get("parent"), dict):
        out["parent"] = _named_inputs(out["parent"])
    return out


def record(name: str) -> None:
    path = shipped_model(name)
    model = ShearModel.load(path)
    domain = sample_domain(name, model)
    edit = {
        "by": SCRIPT,
        "what": "domain added (a fresh sample of the training set, see domain.derived); "
        "absolute paths of the machine the model was made on replaced by file names",
    }

    def change(prov: dict[str, Any]) -> dict[str, Any]:
        new = _named_inputs(prov)
        new[DOMAIN_KEY] = domain
        new["edits"] = [e for e in new.get("edits", []) if e.get("by") != SCRIPT] + [edit]
        return new

    update_provenance(path, change)
    print(
        f"{name}: {domain_summary(domain)} ({domain['n_rows']} usable rows); "
        f"sha256 {sha256_file(path)}"
    )


if __name__ == "__main__":
    names = sys.argv[1:] or list(SHIPPED_MODELS)
    unknown = [n for n in names if n not in SOURCES]
    if unknown:
        raise SystemExit(f"unknown model(s) {', '.join(unknown)} (known: {', '.join(SOURCES)})")
    for n in names:
        record(n)
