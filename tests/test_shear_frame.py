"""World-frame shears (megalut_cli.shear.frame): the Jacobian's decomposition against
GalSim's drawing through a JacobianWCS, and ``calibrate`` recovering a world-frame shear
through random rotations, flips and residual shears of the pixel grid."""

from __future__ import annotations

import galsim
import numpy as np
import pytest
from helpers import metacal_predictions

from megalut_cli.errors import InputError
from megalut_cli.shear.calibrate import calibrate_columns, calibrated_catalog
from megalut_cli.shear.frame import (
    jacobian_frames,
    response_to_world,
    spin2_to_world,
    versions_to_world,
)


def jacobian(phi: float, flip: bool, eta: tuple[float, float], scale: float = 0.2) -> np.ndarray:
    """``scale R(phi) F (I + eta)``: a rotation, an optional flip of y, a residual shear."""
    rot = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    par = np.diag([1.0, -1.0]) if flip else np.eye(2)
    dist = np.array([[1 + eta[0], eta[1]], [eta[1], 1 - eta[0]]])
    return scale * rot @ par @ dist


def frames_of(jacs: list[np.ndarray]):
    j = np.array(jacs)
    return jacobian_frames(j[:, 0, 0], j[:, 0, 1], j[:, 1, 0], j[:, 1, 1])


def test_decomposition_recovers_angle_parity_and_distortion():
    rng = np.random.default_rng(5)
    phi = rng.uniform(-np.pi, np.pi, 50)
    flip = rng.random(50) < 0.5
    eta = rng.normal(0, 0.03, (50, 2))
    fr = frames_of([jacobian(p, f, e, 0.263) for p, f, e in zip(phi, flip, eta)])
    np.testing.assert_array_equal(fr.parity, np.where(flip, -1, 1))
    np.testing.assert_allclose(fr.distortion, eta, atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (fr.angle - phi))), 0.0, atol=1e-12)
    np.testing.assert_allclose(fr.scale, 0.263, rtol=1e-12)
    # Q is orthogonal: responses keep their trace, and a world shear maps back
    r = {
        (1, 1): np.full(50, 0.8),
        (1, 2): np.full(50, 0.03),
        (2, 1): np.zeros(50),
        (2, 2): np.full(50, 0.7),
    }
    w = response_to_world(fr, r)
    np.testing.assert_allclose(w[(1, 1)] + w[(2, 2)], 1.5, atol=1e-12)


def test_degenerate_jacobian_is_refused():
    with pytest.raises(InputError, match="degenerate Jacobian"):
        jacobian_frames(
            np.array([1.0, 0.2]), np.array([1.0, 0.0]), np.array([1.0, 0.0]), np.array([1.0, 0.2])
        )


@pytest.mark.parametrize("flip", [False, True])
def test_galsim_world_shear_through_any_jacobian(flip):
    """A round Gaussian of world shear g drawn by GalSim through a Jacobian (any angle, a
    flip, a residual shear |eta| <= 0.03): its pixel-frame adaptive-moment shape turned to
    the world frame is g to second order (|g| |eta| (|g| + |eta|) < 2e-4 here), and to 1e-6
    without residual shear; ignoring the frame is off by ~|g|."""
    rng = np.random.default_rng(11 + flip)
    for _ in range(8):
        phi = rng.uniform(0, 2 * np.pi)
        eta = rng.uniform(-0.02, 0.02, 2)
        g = rng.uniform(-0.04, 0.04, 2)
        for e, tol in ((eta, 2e-4), ((0.0, 0.0), 1e-6)):
            j = jacobian(phi, flip, e)
            gal = galsim.Gaussian(sigma=0.8).shear(g1=g[0], g2=g[1])
            wcs = galsim.JacobianWCS(j[0, 0], j[0, 1], j[1, 0], j[1, 1])
            shape = gal.drawImage(nx=64, ny=64, wcs=wcs, method="no_pixel").FindAdaptiveMom()
            fr = frames_of([j])
            obs = np.array([shape.observed_shape.g1]), np.array([shape.observed_shape.g2])
            world = np.array(spin2_to_world(fr, *obs)).ravel()
            assert np.all(np.abs(world - g) < tol), (world, g, e)


def test_world_versions_are_pixel_versions_under_quarter_turns_and_flips():
    """Rotations by 45-degree multiples and flips turn world shears into pixel ones: the
    world versions are then the pixel versions, exactly."""
    rng = np.random.default_rng(2)
    vals = {k: rng.random(4) for k in ("1p", "1m", "2p", "2m")}
    # 90 degrees: Q = -I (1p <-> 1m, 2p <-> 2m); 45 degrees: world 1p is pixel 2m and
    # world 2p pixel 1p; a flip of y: 2p <-> 2m
    fr = frames_of(
        [
            jacobian(np.pi / 2, False, (0, 0)),
            jacobian(np.pi / 4, False, (0, 0)),
            jacobian(0.0, True, (0, 0)),
            jacobian(0.0, False, (0, 0)),
        ]
    )
    out = versions_to_world(fr, vals)
    expect = {
        "1p": [vals["1m"][0], vals["2m"][1], vals["1p"][2], vals["1p"][3]],
        "2p": [vals["2m"][0], vals["1p"][1], vals["2m"][2], vals["2p"][3]],
        "2m": [vals["2p"][0], vals["1m"][1], vals["2p"][2], vals["2m"][3]],
    }
    for kind, e in expect.items():
        np.testing.assert_allclose(out[kind], e, atol=1e-12)


def test_calibrate_recovers_the_world_shear():
    """Metacal predictions of (0.02, -0.01) in the world frame, seen through random
    Jacobians: calibrate gives it back exactly without selection (rings, linear estimates),
    to 1e-3 with a size cut and weights (the world selection response), and the pixel
    frame (Jacobian columns dropped) does not."""
    cat = metacal_predictions(n=4000, seed=7, jacobians=True)
    a = calibrate_columns(cat, unweighted=True).result
    assert a["frame"] == "world"
    np.testing.assert_allclose([a["all"]["g1"], a["all"]["g2"]], (0.02, -0.01), atol=1e-12)
    pixel = {k: v for k, v in cat.items() if k not in ("dudcol", "dudrow", "dvdcol", "dvdrow")}
    p = calibrate_columns(pixel, unweighted=True).result
    assert p["frame"] == "pixel" and abs(p["all"]["g1"] - 0.02) > 5e-3

    big = metacal_predictions(n=100_000, seed=1, weights=True, positions=False, jacobians=True)
    kw = {"select": "size > 0.5", "errors": "bootstrap", "n_bootstrap": 10}
    b = calibrate_columns(big, failures="exclude", **kw).result["all"]
    assert b["selection_response"] is not None
    assert np.all(np.abs(np.array([b["g1"], b["g2"]]) - (0.02, -0.01)) < 1e-3), b
    cal = calibrate_columns(big, **kw)  # the versions' means, in the world frame
    b = cal.result["all"]
    assert b["selection_response"] is None
    assert np.all(np.abs(np.array([b["g1"], b["g2"]]) - (0.02, -0.01)) < 1e-3), b
    out, cards = calibrated_catalog(big, cal)
    assert cards["SHFRAME"][0] == "world"
    w = out["weight"]
    mean = [np.sum(w * out[c]) / np.sum(w) for c in ("g1", "g2")]
    assert np.all(np.abs(np.array(mean) - (0.02, -0.01)) < 2e-3), mean


def dihedral() -> list[np.ndarray]:
    """The 8 symmetries of the pixel grid, as integer matrices on (x, y)."""
    r90 = np.array([[0, -1], [1, 0]])
    flip = np.diag([1, -1])
    return [
        np.linalg.matrix_power(r90, k) @ f for k in range(4) for f in (np.eye(2, dtype=int), flip)
    ]


def transformed(stamps: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``stamps`` ``(n, S, S)`` (``[y, x]``) with their pixels moved by ``t`` about the centre:
    new pixel ``t (x, y)`` holds old pixel ``(x, y)``."""
    size = stamps.shape[-1]
    c = (size - 1) / 2.0
    y, x = np.mgrid[0:size, 0:size]
    inv = np.rint(np.linalg.inv(t)).astype(int)
    ox = inv[0, 0] * (x - c) + inv[0, 1] * (y - c) + c
    oy = inv[1, 0] * (x - c) + inv[1, 1] * (y - c) + c
    return stamps[:, np.rint(oy).astype(int), np.rint(ox).astype(int)]


def test_turned_and_flipped_cutouts_give_the_same_world_shears(tmp_path):
    """The same galaxies and PSFs written as MEDS cutouts turned by quarter turns and flipped,
    each with the Jacobian that keeps the sky where it was: measure, predict (networks
    averaged over the grid's symmetries, d4) and calibrate give the same world-frame
    shears, responses and PSF ellipticities to rounding, on both routes."""
    from megalut_cli.measure.meds import MedsOptions, measure_meds, read_meds, write_meds
    from megalut_cli.nn.model import ShearModel
    from megalut_cli.nn.shipped import shipped_model
    from megalut_cli.shear.predict import predict_columns

    rng = np.random.default_rng(3)
    n, size = 12, 32
    psf = galsim.Gaussian(sigma=1.5).shear(g1=0.05, g2=-0.03)
    stamps = np.empty((n, size, size))
    for i in range(n):
        gal = galsim.Exponential(half_light_radius=1.5 + rng.uniform(), flux=2000.0).shear(
            g1=rng.uniform(-0.3, 0.3), g2=rng.uniform(-0.3, 0.3)
        )
        stamps[i] = galsim.Convolve(gal, psf).drawImage(nx=size, ny=size, scale=1.0).array
    psf_stamp = psf.drawImage(nx=size, ny=size, scale=1.0).array[None]
    j0 = 0.2 * np.eye(2)
    # noisy stamps for the plain route; for metacal noiseless ones with a tiny weight-map
    # noise, as fixnoise's noise field is drawn in each cutout's own pixel frame
    sets = {"noisy": (stamps + rng.normal(0.0, 1.0, stamps.shape), 1.0), "clean": (stamps, 1e10)}
    measured: dict[str, list[dict[str, np.ndarray]]] = {}
    for label, (images, weight) in sets.items():
        measured[label] = []
        for k, t in enumerate(dihedral()):
            path = tmp_path / f"{label}{k}.meds.fits"
            write_meds(
                path,
                transformed(images, t).astype(np.float32),
                weights=np.full((n, size, size), weight),
                psfs=[[p] for p in transformed(np.repeat(psf_stamp, n, axis=0), t)],
                jacobians=np.broadcast_to(j0 @ np.linalg.inv(t), (n, 2, 2)),
            )
            opts = MedsOptions(metacal=label == "clean", seed=5)
            measured[label].append(measure_meds(read_meds(path), opts))
    results = measured["noisy"]
    # features: adaptive moments turn as spin-2 quantities
    ref = results[0]
    for k, cols in enumerate(results):
        assert {c: cols[c].shape for c in ("dudcol", "dvdrow")} == {"dudcol": (n,), "dvdrow": (n,)}
        fr = jacobian_frames(*(cols[c] for c in ("dudcol", "dudrow", "dvdcol", "dvdrow")))
        world = spin2_to_world(fr, cols["adamom_g1"], cols["adamom_g2"])
        np.testing.assert_allclose(
            world, (ref["adamom_g1"], ref["adamom_g2"]), atol=1e-6, err_msg=k
        )
        np.testing.assert_allclose(cols["adamom_sigma"], ref["adamom_sigma"], rtol=1e-6)
    # both routes through the networks averaged over the grid's symmetries (d4)
    for name, step in (("fiducial-d4", None), ("fiducial-metacal-d4", 0.01)):
        model = ShearModel.load(shipped_model(name))
        per_object, pixel = [], []
        for cols in measured["noisy" if step is None else "clean"]:
            pred = {**cols, **predict_columns(model, cols, metacal_step=step)}
            cal = calibrate_columns(
                pred, header={"MCALSTEP": step} if step else {}, errors="bootstrap", n_bootstrap=4
            )
            out, cards = calibrated_catalog(pred, cal)
            assert cards["SHFRAME"][0] == "world" and len(out["g1"]) > n - 2
            per_object.append(out)
            pixel.append(pred["pre_g1"])
        for k, out in enumerate(per_object):
            for c in ("g1", "g2", "R11", "R12", "R22", "psf_g1", "psf_g2", "weight"):
                np.testing.assert_allclose(
                    out[c], per_object[0][c], rtol=1e-5, atol=1e-5, err_msg=f"{name} {k} {c}"
                )
        # in the pixel frame the turned cutouts' estimates differ (a quarter turn: -g1)
        np.testing.assert_allclose(pixel[2], -pixel[0], rtol=1e-5, atol=1e-5)
        assert np.abs(pixel[2] - pixel[0]).max() > 0.05


def test_grid_image_with_a_celestial_wcs(runner, cli, tmp_path):
    """A grid image whose WCS turns the sky by 30 degrees and flips it: measure adds each
    stamp's Jacobian and sky position, and the stamps' shapes turned to the world frame are
    the world shear they were drawn with."""
    import fitsio

    from megalut_cli.catalog import read_catalog_columns

    th, s = np.deg2rad(30.0), 0.2
    cd = s * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([1, -1])
    size, g = 48, (0.03, -0.02)
    wcs = galsim.JacobianWCS(cd[0, 0], cd[0, 1], cd[1, 0], cd[1, 1])
    stamp = (
        galsim.Gaussian(sigma=0.8)
        .shear(g1=g[0], g2=g[1])
        .drawImage(nx=size, ny=size, wcs=wcs, method="no_pixel")
    )
    image = np.tile(stamp.array, (2, 3)).astype(np.float32)
    header = {
        "CTYPE1": "RA---TAN",
        "CTYPE2": "DEC--TAN",
        "CRPIX1": 72.5,
        "CRPIX2": 48.5,
        "CRVAL1": 150.0,
        "CRVAL2": 2.0,
        # u = -RA cos(dec): the CD matrix's first row is -du/dx, -du/dy in degrees
        "CD1_1": -cd[0, 0] / 3600,
        "CD1_2": -cd[0, 1] / 3600,
        "CD2_1": cd[1, 0] / 3600,
        "CD2_2": cd[1, 1] / 3600,
    }
    path = tmp_path / "sky.fits"
    fitsio.write(str(path), image, header=[{"name": k, "value": v} for k, v in header.items()])
    out = tmp_path / "f.fits"
    result = runner.invoke(cli, ["measure", str(path), "--stamp-size", str(size), "-o", str(out)])
    assert result.exit_code == 0, result.output
    cols, _ = read_catalog_columns(out)
    np.testing.assert_allclose(cols["dudcol"], cd[0, 0], rtol=1e-5)  # TAN: 1e-6 over the image
    np.testing.assert_allclose(cols["dvdrow"], cd[1, 1], rtol=1e-5)
    assert np.all(np.abs(cols["dec"] - 2.0) < 0.01)
    fr = jacobian_frames(*(cols[c] for c in ("dudcol", "dudrow", "dvdcol", "dvdrow")))
    world = np.array(spin2_to_world(fr, cols["adamom_g1"], cols["adamom_g2"]))
    np.testing.assert_allclose(world, np.repeat(np.array(g)[:, None], 6, axis=1), atol=1e-5)
    assert np.abs(cols["adamom_g1"] - g[0]).max() > 0.01  # the pixel frame is not the world's


def test_epochs_are_measured_and_combined(runner, cli, tmp_path):
    """``measure --epochs`` on a MEDS file of a coadd and two epochs (the same galaxies,
    the second epoch turned by a quarter turn and flipped, with its Jacobian): one row per
    object and epoch with its own Jacobian; ``calibrate -o`` combines them into one row per
    object, whose world-frame shear is the weighted mean of the epochs' (the two epochs agree
    to rounding, d4 networks); the refusals of misused options."""
    from helpers import invoke_fails

    from megalut_cli.catalog import read_catalog_columns
    from megalut_cli.measure.meds import write_meds

    rng = np.random.default_rng(4)
    n, size = 10, 32
    psf = galsim.Gaussian(sigma=1.5)
    stamps = np.empty((n, size, size))
    for i in range(n):
        gal = galsim.Exponential(half_light_radius=2.0, flux=3000.0).shear(
            g1=rng.uniform(-0.3, 0.3), g2=rng.uniform(-0.3, 0.3)
        )
        stamps[i] = galsim.Convolve(gal, psf).drawImage(nx=size, ny=size, scale=1.0).array
    stamps += rng.normal(0.0, 1.0, stamps.shape)
    psf_stamp = psf.drawImage(nx=size, ny=size, scale=1.0).array
    t = dihedral()[3]  # a quarter turn and a flip
    turned = transformed(stamps, t)
    turned_psf = transformed(psf_stamp[None], t)[0]
    j0 = 0.2 * np.eye(2)
    jac = np.array([[j0, j0, j0 @ np.linalg.inv(t)]] * n)
    path = tmp_path / "ep.meds.fits"
    write_meds(
        path,
        [[s, s, u] for s, u in zip(stamps, turned)],
        weights=[[np.ones((size, size))] * 3] * n,
        psfs=[[psf_stamp, psf_stamp, turned_psf]] * n,
        jacobians=jac,
        ra=rng.uniform(10, 11, n),
        dec=rng.uniform(0, 1, n),
    )
    feats = tmp_path / "f.fits"
    result = runner.invoke(cli, ["measure", str(path), "--epochs", "-o", str(feats)])
    assert result.exit_code == 0, result.output
    cols, header = read_catalog_columns(feats)
    assert header["MEDSCUT"] == -1 and not header["MEDSCOAD"]
    np.testing.assert_array_equal(cols["cutout"], np.tile([1, 2], n))
    np.testing.assert_array_equal(cols["id"], np.repeat(np.arange(1, n + 1), 2))
    np.testing.assert_allclose(cols["dudrow"][1::2], jac[:, 2, 0, 1])
    pred = tmp_path / "p.fits"
    result = runner.invoke(cli, ["predict", str(feats), "--model", "fiducial-d4", "-o", str(pred)])
    assert result.exit_code == 0, result.output
    cal = tmp_path / "c.fits"
    result = runner.invoke(cli, ["calibrate", str(pred), "--errors", "bootstrap", "-o", str(cal)])
    assert result.exit_code == 0, result.output
    assert "epochs of" in result.output
    out, _ = read_catalog_columns(cal)
    usable = np.isin(np.arange(1, n + 1), out["id"])
    assert usable.sum() >= n - 1 and np.all(out["n_epochs"] == 2)
    rows, _ = read_catalog_columns(pred)
    fr = jacobian_frames(*(rows[c] for c in ("dudcol", "dudrow", "dvdcol", "dvdrow")))
    world = np.array(spin2_to_world(fr, rows["pre_g1"], rows["pre_g2"]))
    np.testing.assert_allclose(world[:, 0::2], world[:, 1::2], atol=1e-5)  # the two epochs
    keep = np.isin(rows["id"][0::2], out["id"])
    np.testing.assert_allclose(out["g1"], world[0, 0::2][keep], atol=1e-5)

    invoke_fails(
        runner,
        cli,
        ["measure", str(path), "--epochs", "--cutout", "1", "-o", str(tmp_path / "x.fits")],
        2,
        "--cutout",
        "--epochs",
    )
    grid = tmp_path / "grid.fits"
    import fitsio

    fitsio.write(str(grid), stamps[0].astype(np.float32))
    invoke_fails(
        runner,
        cli,
        ["measure", str(grid), "--stamp-size", "32", "--epochs", "-o", str(tmp_path / "y.fits")],
        2,
        "--epochs",
        "MEDS",
    )
    coadd_only = tmp_path / "coadd.meds.fits"
    write_meds(coadd_only, stamps.astype(np.float32))
    invoke_fails(
        runner,
        cli,
        ["measure", str(coadd_only), "--epochs", "-o", str(tmp_path / "z.fits")],
        1,
        "no single-epoch cutout",
    )
    for p in ("x.fits", "y.fits", "z.fits"):
        assert not (tmp_path / p).exists()
