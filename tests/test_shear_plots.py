"""`evaluate --plot`: units on axes, requirement band, m/c clear of the data, |m| > 0.1 warning."""

from __future__ import annotations

import re

import numpy as np
import pytest
from helpers import synthetic

from megalut_cli.catalog import write_catalog
from megalut_cli.shear.bias import STAGE_IV_C, STAGE_IV_M
from megalut_cli.shear.evaluate import evaluate_columns
from megalut_cli.shear.plots import axis_label, evaluation_figure

WARN_RED = (0.75, 0.0, 0.0)


def _panels(fig):
    return [ax for ax in fig.axes if ax.get_visible()]


def _is_red(color) -> bool:
    from matplotlib.colors import to_rgb

    return np.allclose(to_rgb(color), WARN_RED, atol=0.01)


def test_axis_labels_carry_units():
    assert axis_label("tru_rad") == "tru_rad [pixel]"
    assert axis_label("adamom_flux") == "adamom_flux [adu]"
    assert axis_label("snr") == "snr (dimensionless)"
    assert axis_label("mean(adamom_sigma)") == "mean(adamom_sigma) [pixel]"
    assert (
        axis_label("sqrt(tru_e1**2+tru_e2**2)") == "sqrt(tru_e1**2+tru_e2**2)"
    )  # unknown: no unit
    assert axis_label("mycol") == "mycol"


def test_warning_needs_m_beyond_its_error():
    from megalut_cli.shear.evaluate import m_too_large

    assert m_too_large(-0.5, 0.01) and m_too_large(0.15, None) and m_too_large(0.12, 0.01)
    assert not m_too_large(-0.108, 0.044)  # noise: 2.5 sigma from 0, not beyond 0.1
    assert (
        not m_too_large(0.05, None)
        and not m_too_large(None, None)
        and not m_too_large(float("nan"), 0.1)
    )


def test_good_model_figure():
    r = evaluate_columns(
        synthetic(seed=3, n_cases=40, weights=True, m=(2e-3, 0), sigma=0.05),
        by=["tru_rad", "mean(snr)"],
        bins=3,
    )
    fig = evaluation_figure(r)
    assert "WARNING" not in fig._suptitle.get_text()
    panels = _panels(fig)
    residual = [ax for ax in panels if "true shear" in ax.get_xlabel()]
    assert len(residual) == 4  # (unweighted, weighted) x (g1, g2)
    for ax in residual:
        assert len(ax.texts) == 0  # m and c in the title, never drawn over the data
        title = ax.get_title()
        assert "m = " in title and "c = " in title and "|m| >" not in title
        assert not _is_red(ax.spines["left"].get_edgecolor())
        # the shaded requirement band: |m g + c| < 2e-3 |g| + 2e-4
        (band,) = [c for c in ax.collections if c.get_label() == "Stage IV requirement"]
        y = band.get_paths()[0].vertices[:, 1]
        g_max = ax.get_xlim()[1]
        assert y.max() == pytest.approx(STAGE_IV_M * g_max + STAGE_IV_C, rel=1e-6)
    labels = {ax.get_xlabel() for ax in panels}
    assert {"tru_rad [pixel]", "mean(snr) (dimensionless)"} <= labels
    assert {"m (multiplicative bias)", "c (additive bias)"} <= {ax.get_ylabel() for ax in panels}
    assert "Stage IV requirement" in [t.get_text() for leg in fig.legends for t in leg.get_texts()]


def test_large_m_is_flagged_in_red():
    r = evaluate_columns(
        synthetic(seed=3, n_cases=40, m=(-0.5, 0.0), sigma=0.05), by=["tru_rad"], bins=3
    )
    fig = evaluation_figure(r)
    sup = fig._suptitle
    assert "WARNING: |m| > 0.1 in 1 fit(s)" in sup.get_text()
    assert float(re.search(r"unweighted g1: m = ([-+.\d]+)", sup.get_text())[1]) == pytest.approx(
        -0.5, abs=0.03
    )
    assert _is_red(sup.get_color())
    by_title = {ax.get_title().split("\n")[0]: ax for ax in _panels(fig)}
    g1 = by_title["unweighted $g_1$ (40 cases)"]
    g2 = by_title["unweighted $g_2$ (40 cases)"]
    assert "|m| > 0.1" in g1.get_title() and _is_red(g1.spines["left"].get_edgecolor())
    assert "|m| > 0.1" not in g2.get_title() and not _is_red(g2.spines["left"].get_edgecolor())
    assert not _is_red(by_title["unweighted m by tru_rad"].spines["left"].get_edgecolor())
    assert not _is_red(by_title["unweighted c by tru_rad"].spines["left"].get_edgecolor())


def test_cli_warns_on_large_m(runner, cli, tmp_path):
    src = tmp_path / "shears.fits"
    write_catalog(
        src,
        synthetic(seed=4, n_cases=30, n_rea=20, m=(0.3, 0.0), sigma=0.05),
        fmt="megalut.predictions",
    )
    png = tmp_path / "ev.png"
    result = runner.invoke(cli, ["evaluate", str(src), "--plot", str(png)])
    assert result.exit_code == 0, result.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    err = result.stderr
    found = re.search(r"warning: \|m\| > 0.1 \(unweighted g1: m = ([-+.\d]+) ± [.\d]+\)", err)
    assert found and float(found[1]) == pytest.approx(0.3, abs=0.03), err
    good = tmp_path / "good.fits"
    write_catalog(
        good, synthetic(seed=4, n_cases=30, n_rea=20, sigma=0.05), fmt="megalut.predictions"
    )
    result = runner.invoke(cli, ["evaluate", str(good)])
    assert result.exit_code == 0 and "|m| >" not in result.stderr
