"""The printed numbers decide a mirror that the bars leave open (imaging/detect/digits.py)."""

import numpy as np
import pytest

from oapcal.imaging.detect.digits import _render, mirror_from_digits, reflected_matrix
from oapcal.imaging.usaf import usaf_target

#: Group 7 element 1's two triplets' centres (um) in the target's own coordinates.
TARGET = usaf_target((7,))


def _element_centres():
    from oapcal.imaging.detect.pose import RefTriplets

    ref = RefTriplets.from_target(TARGET)
    sel = (ref.group == 7) & (ref.element == 1)
    return ref.centre[sel]


def test_the_reflection_keeps_collinear_centres_and_refuses_others():
    centres = _element_centres()
    f, c = reflected_matrix(np.eye(2), centres)
    assert np.linalg.det(f) == pytest.approx(-1.0)
    np.testing.assert_allclose(c + (centres - c) @ f.T, centres, atol=1e-9)
    # a point off the line goes to the other side of it, at the same distance
    p = centres.mean(axis=0) + [0.0, 10.0] if abs(np.ptp(centres[:, 1])) < 1e-9 else centres[0] + [10.0, 0]
    q = c + f @ (p - c)
    assert not np.allclose(p, q) and np.hypot(*(p - c)) == pytest.approx(np.hypot(*(q - c)))
    assert reflected_matrix(np.eye(2), np.array([[0.0, 0], [1, 0], [0, 1]])) is None


def _pose(angle_deg=84.0, mirrored=False, s=8.5):
    a = np.radians(angle_deg)
    lin = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    if mirrored:
        lin = lin @ np.diag([1.0, -1.0])
    centre_px = np.array([300.0, 500.0])
    t = centre_px - s * lin @ _element_centres().mean(axis=0)
    return s, lin, t


@pytest.mark.parametrize("angle", [0.0, 84.0, 200.0])
@pytest.mark.parametrize("truth_mirrored", [False, True])
def test_the_numbers_pick_the_hypothesis_that_drew_them(angle, truth_mirrored):
    s, lin, t = _pose(angle)
    f, c = reflected_matrix(lin, _element_centres())
    hyps = {False: (s * lin, t), True: (s * lin @ f, s * lin @ (c - f @ c) + t)}
    ink, _ = _render(TARGET, range(len(TARGET.labels)), *hyps[truth_mirrored], (1000, 800))
    rng = np.random.default_rng(0)
    image = 0.1 + 0.8 * ink + rng.normal(0, 0.05, ink.shape)
    ev = mirror_from_digits(image, TARGET, s, lin, t, _element_centres(), +1.0)
    assert ev.mirrored is truth_mirrored and ev.n_numbers > 0
    # dark print on a bright field, given as such: the same answer
    ev = mirror_from_digits(1.0 - image, TARGET, s, lin, t, _element_centres(), -1.0)
    assert ev.mirrored is truth_mirrored


def test_a_pose_that_is_itself_mirrored_names_its_own_hypothesis():
    s, lin, t = _pose(84.0, mirrored=True)
    ink, _ = _render(TARGET, range(len(TARGET.labels)), s * lin, t, (1000, 800))
    ev = mirror_from_digits(0.1 + 0.8 * ink, TARGET, s, lin, t, _element_centres(), +1.0)
    assert ev.mirrored is True


def test_no_numbers_in_view_or_none_printed_decide_nothing():
    s, lin, t = _pose(84.0)
    blank = np.full((1000, 800), 0.1) + np.random.default_rng(1).normal(0, 0.05, (1000, 800))
    assert mirror_from_digits(blank, TARGET, s, lin, t, _element_centres(), +1.0).mirrored is None
    far = t + 1e5  # every number far outside the image
    ev = mirror_from_digits(blank, TARGET, s, lin, far, _element_centres(), +1.0)
    assert ev.mirrored is None and ev.n_numbers == 0
