"""The one progress interface: long library operations open it with the totals they know."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from helpers import make_model
from sim_configs import write

from megalut_cli.catalog import catalog_info
from megalut_cli.progress import Update, no_progress, relabelled
from megalut_cli.shear.predict import predict_catalog
from megalut_cli.sim.config import load_config
from megalut_cli.sim.simulate import n_work_units, simulate


class Recorder:
    """A :data:`megalut_cli.progress.Progress` that records (label, total, units reported)."""

    def __init__(self) -> None:
        self.bars: list[tuple[str, int, int]] = []

    @contextlib.contextmanager
    def __call__(self, label: str, total: int, parallel: int = 1) -> Iterator[Update]:
        done: list[int] = []
        yield done.append
        self.bars.append((label, total, sum(done)))


def test_simulate_and_predict_report_their_whole_totals(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path))
    rec = Recorder()
    simulate(cfg, tmp_path / "c.fits", measure=True, seed=1, progress=rec)
    units = n_work_units(cfg)
    assert rec.bars == [("simulate", units, units)]
    model = tmp_path / "m.h5"
    make_model(model)
    rec.bars.clear()
    predict_catalog(
        tmp_path / "c.fits",
        model,
        tmp_path / "p.fits",
        chunk_rows=5,
        progress=relabelled(rec, "vo"),
    )
    rows = catalog_info(tmp_path / "c.fits")[0]
    assert rec.bars == [("vo", rows, rows)] and rows == cfg.structure.n_stamps


def test_no_progress_is_silent() -> None:
    with no_progress("anything", 10) as update:
        assert update(3) is None
