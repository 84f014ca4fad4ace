"""The relay model family against the NumPy ray tracer, and its fit on traced fields."""

import numpy as np
import pytest

from oapcal.errors import ModelSpecError
from oapcal.fitting import fit_batch
from oapcal.model import RELAY, distort, jacobian_params, jacobian_point, undistort
from oapcal.optics.misalign import PARAMETERS
from oapcal.optics.relay import chief_rays, paraxial_matrix
from oapcal.optics.relay_model import RelayDesign, relay_mask, relay_params

PIX = 4.8e-3  # mm


def _random_misalignment(rng, scale=1.0):
    out = {}
    for name, (unit, _) in PARAMETERS.items():
        size = 0.05 if unit == "deg" else 0.2
        if name.startswith("camera_tilt") or name.startswith("object_tilt"):
            size = 1.0
        out[name] = float(rng.uniform(-1, 1) * size * scale)
    return out


def _traced(design, mis, ref, pose=None):
    """Distorted px of reference points ``ref`` by the NumPy tracer: the independent
    reference for the compiled model."""
    c = np.asarray(design.centre)
    pose = {"scale": 1.0, "rotation": 0.0, "shift_x": 0.0, "shift_y": 0.0, **(pose or {})}
    th = np.radians(pose["rotation"])
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    posed = pose["scale"] * (ref - c) @ rot.T + [pose["shift_x"], pose["shift_y"]]
    jac = paraxial_matrix(design.relay())
    obj = (posed * design.pixel_size_um * 1e-3) @ np.linalg.inv(jac).T
    return chief_rays(design.relay(mis), obj, full=False).xy_mm / (design.pixel_size_um * 1e-3) + c


@pytest.mark.parametrize(
    "design",
    [
        RelayDesign(setup=1, centre=(320.0, 240.0)),
        RelayDesign(setup=2, orientation="Z", centre=(10.0, -5.0)),
        RelayDesign(
            d1_mm=500.0,
            focal_length_mm=40.0,
            focal_length_2_mm=60.0,
            stop_distance_mm=100.0,
            pixel_size_um=3.45,
            centre=(0.0, 0.0),
        ),
    ],
    ids=["setup1-U", "setup2-Z", "unequal-f-stop-away"],
)
def test_the_compiled_model_is_the_ray_tracer(design):
    rng = np.random.default_rng(3)
    ref = np.asarray(design.centre) + rng.uniform(-100, 100, (40, 2))
    for k in range(3):
        mis = _random_misalignment(rng) if k else {}
        pose = {"scale": 1.01, "rotation": 0.7, "shift_x": 4.0, "shift_y": -3.0} if k == 2 else None
        p = relay_params(design, mis, pose)
        got = distort(ref, p, family=RELAY)
        want = _traced(design, mis, ref, pose)
        assert np.abs(got - want).max() < 1e-8  # px; both trace to ~1e-12 mm
        assert np.abs(got - ref).max() > 1.0  # and the field is distorted


def test_point_jacobian_and_inverse():
    design = RelayDesign(setup=1, centre=(0.0, 0.0))
    p = relay_params(design, {"m2_tilt_x": 0.04, "camera_tilt_y": 0.5})
    ref = np.random.default_rng(0).uniform(-90, 90, (20, 2))
    jac = jacobian_point(ref, p, family=RELAY)
    h = 1e-2
    for k in range(2):
        step = np.zeros(2)
        step[k] = h
        fd = (distort(ref + step, p, family=RELAY) - distort(ref - step, p, family=RELAY)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, k], fd, atol=1e-6)
    back = undistort(distort(ref, p, family=RELAY), p, family=RELAY)
    assert back.converged.all()
    np.testing.assert_allclose(back.xy, ref, atol=1e-8)


def test_parameter_columns_match_larger_steps():
    design = RelayDesign(setup=1, centre=(0.0, 0.0))
    p = relay_params(design, {"m2_tilt_x": 0.02})
    ref = np.random.default_rng(1).uniform(-90, 90, (10, 2))
    cols = jacobian_params(ref, p, family=RELAY)
    for name, h in (("m2_tilt_y", 1e-4), ("d1", 0.05), ("rotation", 1e-3), ("camera_defocus", 1e-3)):
        i = RELAY.param_names.index(name)
        q1, q2 = p.copy(), p.copy()
        q1[i] += h
        q2[i] -= h
        fd = (distort(ref, q1, family=RELAY) - distort(ref, q2, family=RELAY)) / (2 * h)
        np.testing.assert_allclose(cols[..., i], fd, rtol=1e-4, atol=1e-6, err_msg=name)


def test_fit_recovers_misalignment_and_pose_within_three_standard_errors():
    rng = np.random.default_rng(7)
    design = RelayDesign(setup=1, centre=(0.0, 0.0))
    truth = {"m2_tilt_x": 0.03, "m2_tilt_y": -0.04, "d1": 20.0, "camera_tilt_x": 0.6, "camera_tilt_y": -0.3}
    pose = {"scale": 1.002, "rotation": 0.5, "shift_x": 3.0, "shift_y": -2.0}
    ref = rng.uniform(-100, 100, (300, 2))
    xd = _traced(design, truth, ref, pose) + rng.normal(0, 0.03, (300, 2))
    mask = relay_mask("relay:tilt2,d1,camera")
    fit = fit_batch(ref, xd, mask[None], relay_params(design)[None], family=RELAY).item(0)
    assert fit.converged, fit.message
    values = {**truth, **pose}
    for name, want in values.items():
        i = RELAY.param_names.index(name)
        assert abs(fit.params[i] - want) <= 3 * fit.stderr[i], (name, fit.params[i], fit.stderr[i])
    # the design constants are carried unchanged
    np.testing.assert_array_equal(fit.params[24:], relay_params(design)[24:])
    # and the residual is the noise: no model floor
    resid = distort(ref, fit.params, family=RELAY) - xd
    assert np.sqrt((resid**2).sum(-1).mean()) < 0.03 * np.sqrt(2) * 1.1


def test_design_constants_cannot_be_fitted_and_names_are_checked():
    mask = relay_mask("default")
    mask[RELAY.param_names.index("pixel_mm")] = True
    p0 = relay_params(RelayDesign(centre=(0.0, 0.0)))
    with pytest.raises(ModelSpecError, match="constant"):
        fit_batch(np.zeros((10, 2)), np.zeros((10, 2)), mask[None], p0[None], family=RELAY)
    with pytest.raises(ModelSpecError, match="unknown relay parameter 'tilt3x'"):
        relay_mask("relay:d1,tilt3x")
    names = {n for n, m in zip(RELAY.param_names, relay_mask("relay:d1,tilt2x,tilt2y,camera")) if m}
    assert names == {"scale", "rotation", "shift_x", "shift_y", "d1", "m2_tilt_x", "m2_tilt_y",
                     "camera_tilt_x", "camera_tilt_y"}  # fmt: skip


def test_misalignment_names_are_the_tracers():
    assert RELAY.param_names[4:24] == tuple(PARAMETERS)


@pytest.mark.parametrize(
    "options,pattern",
    [
        (["--d1", "0.001"], "derivatives are not finite"),
        (["--focal-length", "1e-10"], "has no paraxial image"),
        (["--relay-centre", "1e308,1e308"], "does not image 81 of 81 reference points"),
    ],
)
def test_relay_designs_inside_the_option_ranges_that_trace_nothing_are_one_line(
    run_cli, tmp_path, options, pattern
):
    # values the options accept but no relay has: a named error (exit 2), not LinAlgError
    grid = tmp_path / "grid.csv"
    code, _, err = run_cli("simulate", "relay", "--units", "px", "--image-size", "640x480", "--grid", "9",
                           "--reference", "design", "--out", grid)  # fmt: skip
    assert code == 0, err
    code, _, err = run_cli("fit", grid, "--model", "relay", *options, "--out", tmp_path / "c.json")
    assert code == 2 and pattern in err and "internal error" not in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "c.json").exists()
