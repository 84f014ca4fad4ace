"""A small version of ``benchmarks/models.py``: on a misaligned relay's traced field, the
relay family has no model floor where Brown-Conrady (Eq. 1, even with the target's
rotation) has one of tenths of a px (``docs/models.md``)."""

import numpy as np
import pytest

from oapcal.fitting import fit, fit_batch, initial_params
from oapcal.model import BROWN_CONRADY_POSE, RELAY, parse_model, undistort
from oapcal.optics.relay import chief_rays, object_grid, paraxial_matrix
from oapcal.optics.relay_model import RelayDesign, relay_mask, relay_params

DESIGN = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
PIX = 4.8e-3  # mm
#: Every misalignment the benchmark's truth perturbs, at about its range.
ALL_DOF = dict(
    m1_tilt_x=0.04, m1_tilt_y=-0.03, m1_decentre_x=0.15, m1_decentre_y=-0.1, m1_clock=0.03,
    m1_focal_length=0.1, m2_tilt_x=-0.02, m2_tilt_y=0.05, m2_decentre_x=-0.18, m2_decentre_y=0.12,
    m2_clock=-0.04, m2_focal_length=-0.15, d1=30.0, stop_decentre_x=0.1, stop_decentre_y=-0.2,
    camera_tilt_x=0.7, camera_tilt_y=-0.5, camera_defocus=0.15, object_tilt_x=-0.6, object_tilt_y=0.8,
)  # fmt: skip


def _field(mis, turn_deg, n=15):
    """Reference px (the ideal image of an n x n target over 1 mm) and their distorted px
    traced by the NumPy tracer with the target turned by ``turn_deg``."""
    jac = paraxial_matrix(DESIGN.relay())
    c = np.asarray(DESIGN.centre)
    ref = object_grid(n, 1.0) @ jac.T / PIX + c
    th = np.radians(turn_deg)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    obj = ((ref - c) @ rot.T * PIX) @ np.linalg.inv(jac).T
    return ref, chief_rays(DESIGN.relay(mis), obj, full=False).xy_mm / PIX + c


def _relay_error(ref, dist, spec):
    res = fit_batch(ref, dist, relay_mask(spec)[None], relay_params(DESIGN)[None], family=RELAY).item(0)
    assert res.converged, res.message
    return np.hypot(*(undistort(dist, res.params, family=RELAY).xy - ref).T)


def _bc_errors(ref, dist):
    """Eq. (1) with all 13 terms, and with the rotation, on the paper's grid normalization."""

    def frame(xy):
        return 0.5 * (xy.min(0) + xy.max(0)), 1.0 / np.ptp(xy[:, 1])

    (cu, su), (cd, sd) = frame(ref), frame(dist)
    u, d = (ref - cu) * su, (dist - cd) * sd
    plain = fit(u, d, "full")
    p0 = np.append(initial_params("zero", u, d, parse_model("full")), 0.0)
    turned = fit_batch(u, d, np.ones((1, 14), bool), p0[None], family=BROWN_CONRADY_POSE).item(0)
    assert plain.converged and turned.converged
    out = []
    for params, family in ((plain.params, None), (turned.params, BROWN_CONRADY_POSE)):
        back = undistort(d, params, family=family).xy / su + cu
        out.append(np.hypot(*(back - ref).T))
    return out


def test_relay_fit_has_no_floor_where_brown_conrady_has_one():
    # A relay misaligned only in the degrees of freedom the subset fits: the model is exact.
    mis = {"m2_decentre_x": 0.15, "m2_decentre_y": -0.1, "d1": -25.0, "camera_defocus": 0.12,
           "camera_tilt_x": 0.6, "camera_tilt_y": -0.8}  # fmt: skip
    ref, dist = _field(mis, 0.6)
    relay = _relay_error(ref, dist, "relay:decentre2,d1,defocus,camera")
    bc, bc_rot = _bc_errors(ref, dist)
    assert relay.max() < 1e-6  # px: the fit reproduces the traced field
    # Eq. (1) has a floor of tenths of a px mean (issue 13: 0.27-0.56 px on misaligned
    # relays, 0.23-0.68 px from a 0.13-0.71 deg turn alone); the rotation lowers it.
    assert bc.mean() > 0.2
    assert bc_rot.mean() < bc.mean()
    assert bc_rot.mean() > 0.1


@pytest.mark.parametrize(
    ("spec", "mean_px", "max_px"),
    [("relay:decentre2,d1,defocus,camera", 0.01, 0.03), ("relay:d1,tilt2x,tilt2y,camera", 0.1, 0.6)],
    ids=["ten-parameter", "nine-without-defocus"],
)
def test_relay_subsets_absorb_the_unfitted_misalignments(spec, mean_px, max_px):
    # Every one of the 20 degrees of freedom perturbed: what a subset does not fit is
    # absorbed by what it fits (docs/models.md, Identifiability), leaving a small floor;
    # without the defocus (the first default subset) it is larger.
    ref, dist = _field(ALL_DOF, -0.4)
    relay = _relay_error(ref, dist, spec)
    bc, _ = _bc_errors(ref, dist)
    assert relay.mean() < mean_px and relay.max() < max_px
    assert relay.mean() < bc.mean() / 4
