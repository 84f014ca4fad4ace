"""The inverse converges wherever the model is defined, to the model's own precision.

A point's inverse is accepted when its residual is below the absolute ``tol`` or, where
the model's evaluation cannot be that exact, when the residual is at the evaluation's
rounding level and a full Newton step no longer reduces it (``docs/models.md``, "Point
correction").  These tests take the relay at 4.8, 0.96 and 0.1 um pixels, where its
rounding is ~4e-11, ~2e-10 and ~2e-9 px (an absolute 1e-10 px test left 3.7 % and 3.8 % of
the 1 mm field uncorrected at the two small pitches), and Eq. (1) in coordinates large
enough that its rounding exceeds 1e-10, and check every valid point against the truth and
against SciPy's solver; points without a preimage, or where the map folds, or cut off by
the iteration cap, still fail.
"""

import numpy as np
import pytest
from scipy.optimize import least_squares

import reference_model as ref
from oapcal.model import (
    RELAY,
    correction_errors,
    distort,
    jacobian_point,
    params_from_dict,
    scale_params,
    undistort,
)
from oapcal.optics.relay_model import RelayDesign, relay_params
from oapcal.synthetic import EXAMPLE_TRUTH

EPS = np.finfo(float).eps
TOL = 1e-10  # undistort's default absolute tolerance
MISALIGNMENT = {"m2_tilt_x": 0.03, "m2_decentre_y": -0.08, "d1": 20.0, "camera_tilt_y": 0.5,
                "camera_defocus": 0.1}  # fmt: skip
POSE = {"rotation": 0.3, "scale": 1.002}


def relay_case(pixel_um: float, n: int = 101):
    """The relay (setup 1, misaligned, the target turned) at this pixel pitch, and an
    ``n x n`` grid of reference points over the whole 1 mm field (unit magnification:
    1 mm is 1 / pixel px)."""
    size = 1.0 / (pixel_um * 1e-3)
    design = RelayDesign(setup=1, pixel_size_um=pixel_um, centre=(size / 2, size / 2))
    p = relay_params(design, MISALIGNMENT, POSE)
    g = np.linspace(0.0, size, n)
    return p, np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def relay_rounding(p, xy_u, xy_d, jac):
    """The documented rounding allowance of the relay: 16 eps times the lengths the trace
    goes through in px, ``(|d1| + |f1| + |f2| + |stop|) / pixel``, plus the points' own
    magnitudes (``docs/models.md``)."""
    names = RELAY.param_names
    v = dict(zip(names, p))
    length = abs(v["d1_mm"] + v["d1"]) + abs(v["f1_mm"]) + abs(v["f2_mm"]) + abs(v["stop_mm"])
    jmax = np.abs(jac).max(axis=(-1, -2))
    scale = length / v["pixel_mm"] + np.abs(xy_d).sum(-1) + jmax * np.abs(xy_u).sum(-1)
    return 16 * EPS * scale


def smallest_singular_value(jac):
    return np.linalg.svd(jac, compute_uv=False)[..., -1]


def error_bound(allowed, jac):
    """How far from the truth a point may be whose computed residual is within ``allowed``:
    the computed values of the point and of the truth (which is ``xy_d`` itself) are each
    within rounding (<= ``allowed``) of the exact ones, so the exact values differ by at
    most ``3 allowed``; divided by the map's smallest stretch."""
    return 3 * allowed / smallest_singular_value(jac)


@pytest.mark.parametrize("pixel_um", [4.8, 0.96, 0.1])
def test_relay_round_trip_converges_over_the_whole_field(pixel_um):
    p, xy_u = relay_case(pixel_um)
    xy_d = distort(xy_u, p, family=RELAY)
    inv = undistort(xy_d, p, family=RELAY)
    assert inv.converged.all(), f"{(~inv.converged).sum()} of {len(xy_u)} points not corrected"
    assert not inv.folded.any()
    jac = jacobian_point(xy_u, p, family=RELAY)
    allowed = np.maximum(TOL, relay_rounding(p, xy_u, xy_d, jac))
    residual = np.hypot(*(distort(inv.xy, p, family=RELAY) - xy_d).T)
    assert (residual <= allowed).all()
    err = np.hypot(*(inv.xy - xy_u).T)
    assert (err <= error_bound(allowed, jac)).all()
    if pixel_um < 1:
        # the model's own precision is coarser than the absolute tolerance here: these
        # points converge only because the test respects it
        assert (residual > TOL).mean() > 0.1
    # the allowance stays far below anything that matters (at 0.1 um px 3e-8 px)
    assert allowed.max() < 5e-8


@pytest.mark.parametrize("pixel_um", [0.96, 0.1])
def test_relay_inverse_agrees_with_scipy(pixel_um):
    """The independent reference: SciPy's least squares on the forward map, to the tightest
    tolerances, started from the truth moved by 0.3 px."""
    p, xy_u = relay_case(pixel_um, n=9)
    xy_d = distort(xy_u, p, family=RELAY)
    inv = undistort(xy_d, p, family=RELAY)
    assert inv.converged.all()
    jac = jacobian_point(xy_u, p, family=RELAY)
    allowed = np.maximum(TOL, relay_rounding(p, xy_u, xy_d, jac))
    for i in range(len(xy_u)):
        sol = least_squares(lambda x, i=i: distort(x[None], p, family=RELAY)[0] - xy_d[i], xy_u[i] + 0.3,
                            method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)  # fmt: skip
        assert np.hypot(*(inv.xy[i] - sol.x)) <= error_bound(allowed[i], jac[i])


def test_eq1_round_trip_over_the_whole_field_is_unchanged_and_exact():
    """In px coordinates Eq. (1) rounds ~1e-13 px: the absolute tolerance decides, as
    before, and every point of the field comes back."""
    g = np.stack(np.meshgrid(np.linspace(-50, 690, 149), np.linspace(-50, 530, 117)), -1).reshape(-1, 2)
    xy_d = distort(g, EXAMPLE_TRUTH)
    inv = undistort(xy_d, EXAMPLE_TRUTH)
    assert inv.converged.all()
    assert np.abs(distort(inv.xy, EXAMPLE_TRUTH) - xy_d).max() <= TOL
    jac = jacobian_point(g, EXAMPLE_TRUTH)
    assert (np.hypot(*(inv.xy - g).T) <= error_bound(TOL, jac)).all()
    # the rounding allowance is below the tolerance everywhere here
    assert (ref.rounding_level(g, xy_d, EXAMPLE_TRUTH, jac) < TOL).all()


def test_eq1_in_large_coordinates_converges_at_its_rounding_level():
    """The example distortion in units 1e5 times finer (coordinates up to 6.4e7): Eq. (1)'s
    rounding there is ~1e-8, far above 1e-10; every point converges, to within that of the
    truth, the same as the NumPy reference, and each fails with an absolute test alone."""
    f = 1e-5
    p = scale_params(EXAMPLE_TRUTH, f)
    g = np.stack(np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25)), -1).reshape(-1, 2) / f
    xy_d = distort(g, p)
    inv = undistort(xy_d, p)
    assert inv.converged.all()
    jac = jacobian_point(g, p)
    allowed = np.maximum(TOL, ref.rounding_level(g, xy_d, p, jac))
    assert allowed.min() > 100 * TOL
    assert (np.hypot(*(inv.xy - g).T) <= error_bound(allowed, jac)).all()
    want = ref.undistort(xy_d, p)
    np.testing.assert_array_equal(want.converged, inv.converged)
    np.testing.assert_allclose(inv.xy, want.xy, rtol=0, atol=error_bound(allowed, jac).max())


def test_unreachable_folded_and_capped_points_still_fail():
    # Eq. (1) with strong barrel: x (1 - 0.3 x^2) never exceeds ~0.70, so 0.9 has no
    # preimage; started at 1.5 Newton sits where the map folds
    p = params_from_dict({"k1": -0.3})
    inv = undistort(np.array([[0.9, 0.0], [0.5, 0.0]]), p)
    assert not inv.converged[0] and inv.converged[1]
    folded = undistort(distort(np.array([[1.5, 0.0]]), p), p, xy_start=np.array([[1.5, 0.0]]))
    assert folded.folded[0] and not folded.converged[0]
    # the relay: its traced values stay within ~1.1e6 px however far out the reference
    # point, so a distorted point at 1e8 px has no preimage
    p, xy_u = relay_case(0.96, n=5)
    rays = np.array([[1e8, 520.0], [520.0, 1e8], [-1e8, 520.0], [520.0, -1e8], [1e8, 1e8], [-1e8, -1e8]])
    assert np.nanmax(np.abs(distort(rays, p, family=RELAY))) < 2e6
    out = undistort(np.array([[1e8, 1e8], [1e8, 520.0]]), p, family=RELAY)
    assert not out.converged.any() and np.isnan(out.xy).all()
    # the iteration cap: one Newton step from 40 px away does not reach rounding level
    xy_d = distort(xy_u, p, family=RELAY)
    capped = undistort(xy_d, p, family=RELAY, max_iter=1, xy_start=xy_u + 40.0)
    assert not capped.converged.any()
    assert undistort(xy_d, p, family=RELAY, xy_start=xy_u + 40.0).converged.all()


def test_selection_scores_keep_every_relay_point_at_small_pixels():
    """``correction_errors`` (what select scores) on the relay at 0.96 um: no point of any
    model dropped for rounding, and the errors those of the truth."""
    p, xy_u = relay_case(0.96, n=31)
    xy_d = distort(xy_u, p, family=RELAY)
    models = np.repeat(p[None], 3, 0)
    models[1, RELAY.param_names.index("m2_tilt_x")] += 1e-3
    models[2, RELAY.param_names.index("d1")] -= 1.0
    rss, mean_dist, n_bad, n_folded = correction_errors(models, xy_d, xy_u)
    assert (n_bad == 0).all() and (n_folded == 0).all()
    assert mean_dist[0] < 1e-8
    for i in (1, 2):
        inv = undistort(xy_d, models[i], family=RELAY)
        assert inv.converged.all()
        assert mean_dist[i] == pytest.approx(np.hypot(*(inv.xy - xy_u).T).mean(), rel=1e-9)
        assert mean_dist[i] > 1e-3


def test_select_families_at_small_pixels_disqualifies_no_relay_subset_for_rounding():
    """``select --families`` on a relay at 0.96 um px (behind a 5x microscope): with an
    absolute 1e-10 px test 59 of the 64 relay subsets were disqualified ("inverse failed")
    on 200 points and a worse subset recommended; now no subset fails its inverse and the
    recommended one holds the truth's terms, at the noise level held out."""
    from oapcal.families import select_families

    pixel_um = 0.96
    size = 1.0 / (pixel_um * 1e-3)
    design = RelayDesign(setup=1, pixel_size_um=pixel_um, centre=(size / 2, size / 2))
    misalignment = {"m2_decentre_x": 0.12, "m2_decentre_y": -0.08, "d1": 20.0, "camera_defocus": 0.1,
                    "camera_tilt_y": 0.5}  # fmt: skip
    truth = relay_params(design, misalignment, {"rotation": 0.3})
    rng = np.random.default_rng(3)
    xy_u = rng.uniform(0.05 * size, 0.95 * size, (80, 2))
    xy_d = distort(xy_u, truth, family=RELAY) + rng.normal(0, 0.02, xy_u.shape)
    sel = select_families(xy_u, xy_d, design, ("relay",), cv=2, cv_top=2)
    failed = [c.spec for c in sel.candidates if "inverse failed" in c.reason]
    assert failed == []
    assert sum(c.valid for c in sel.candidates) >= 32
    assert {"m2_decentre_x", "m2_decentre_y", "d1", "camera_defocus"} <= set(sel.recommended.free)
    assert sel.recommended.cv_mean_error < 0.04


def test_correct_points_and_full_extent_at_small_pixels(run_cli, tmp_path):
    """``correct-points`` with a relay calibration at 0.96 um px leaves no point of the
    field empty and warns of none; the ``full`` output region (the frame's border inverted)
    is found."""
    import csv

    from oapcal.imaging.remap import correction_map
    from oapcal.io.calibration import save_calibration
    from oapcal.io.points import write_point_pairs
    from oapcal.optics.relay_model import calibrate_relay

    p, grid = relay_case(0.96, n=41)
    size = int(round(grid.max()))
    design = RelayDesign(setup=1, pixel_size_um=0.96, centre=(size / 2, size / 2))
    rng = np.random.default_rng(5)
    xy_u = rng.uniform(0, size, (150, 2))
    xy_d = distort(xy_u, p, family=RELAY) + rng.normal(0, 0.02, xy_u.shape)
    cal = calibrate_relay(xy_u, xy_d, design, "tilt2,d1,camera,defocus", image_size=(size, size))
    save_calibration(cal, tmp_path / "relay.json")
    write_point_pairs(tmp_path / "pts.csv", grid, distort(grid, cal.params, family=RELAY))
    calib, points, out = tmp_path / "relay.json", tmp_path / "pts.csv", tmp_path / "c.csv"
    code, _, err = run_cli("correct-points", calib, points, "--out", out)
    assert code == 0, err
    assert "could not be corrected" not in err
    with open(tmp_path / "c.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["converged"] for r in rows] == ["1"] * len(grid)
    got = np.array([[float(r["x_c"]), float(r["y_c"])] for r in rows])
    np.testing.assert_allclose(got, grid, rtol=0, atol=1e-6)
    cmap = correction_map(cal, (size, size), extent="full", out_size=(200, 200))
    assert cmap.shape == (200, 200)
