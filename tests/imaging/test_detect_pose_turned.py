"""The pose search's second pass with turned seeds (issue 20, item 1): under a strongly
distorted field a triplet's bars are turned against the target's pose by several degrees,
so a seed's own angle predicts the other triplets too poorly to find the pose."""

import numpy as np
import pytest

from oapcal.imaging.detect import pose as P
from oapcal.imaging.detect.bars import Triplets
from oapcal.imaging.detect.core import _reference_triplets

SHAPE = (480, 640)


def _image_triplets(turn_deg, bar_error_deg, um_per_px=4.8):
    """Groups 4-5's triplets seen through an exact similarity (scale, turn about the image
    centre) with every triplet's bar angle off the pose by +-``bar_error_deg`` (alternating
    with the triplet's element, as a shear turns H and V bars opposite ways).  Returns the
    triplets, the reference index of each and the pose."""
    ref = _reference_triplets(None)
    j = np.flatnonzero(np.isin(ref.group, [4, 5]))
    phi = np.deg2rad(turn_deg)
    lin = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    s = 1.0 / um_per_px
    centre_um = 0.5 * (ref.centre[j].min(axis=0) + ref.centre[j].max(axis=0))
    t = (np.array(SHAPE[::-1], float) - 1) / 2 - s * lin @ centre_um
    xy = s * ref.centre[j] @ lin.T + t
    inside = ((xy > 20) & (xy < np.array(SHAPE[::-1]) - 20)).all(axis=1) & (ref.width[j] * s >= 3.0)
    j, xy = j[inside], xy[inside]
    sign = np.where(ref.orient[j] == "H", 1.0, -1.0)
    angle = (ref.angle[j] + phi + sign * np.deg2rad(bar_error_deg)) % np.pi
    width = ref.width[j] * s
    trips = Triplets(xy, angle, width, 5 * width, np.ones(len(j)), np.zeros((len(j), 3, 2)))
    return trips, ref, j, (s, phi)


def _search(trips, ref):
    return P.search_pose(trips, ref, SHAPE, listed=np.isin(ref.group, [4, 5]))


@pytest.mark.slow  # 5-13 s: three times the seeds of one search
@pytest.mark.parametrize("turn_deg", [45.0, 135.0])
def test_turned_seeds_find_a_pose_whose_bars_are_turned_against_it(turn_deg):
    trips, ref, j, (s, phi) = _image_triplets(turn_deg, bar_error_deg=9.0)
    res = _search(trips, ref)
    assert res.status == 0, res.message
    best = res.pose
    assert best.s == pytest.approx(s, rel=0.02)
    assert abs((np.rad2deg(np.arctan2(best.lin[1, 0], best.lin[0, 0])) - turn_deg + 180) % 360 - 180) < 1.0
    assert not best.mirrored
    # every match is the image triplet's own reference triplet (no wrong id)
    assert len(best.matches) >= 0.8 * len(j)
    assert all(j[i] == jr for i, jr in best.matches)


def test_turned_seeds_keep_their_triplet_in_place(monkeypatch):
    """The second pass scores every seed turned by each of SEED_TURNS_DEG about its own
    image triplet: the seed's reference triplet still lands on that triplet."""
    trips, ref, j, _ = _image_triplets(45.0, bar_error_deg=9.0)
    hyps = P._hypotheses(trips, ref, None, None, None, 120)
    seen = {}

    def spy(h, scene, chunk=2000):
        seen["hyps"] = h
        return np.full(len(h.s), -1.0)

    monkeypatch.setattr(P, "_score_hypotheses", spy)
    monkeypatch.setattr(P, "_refined_poses", lambda *a: [P.Pose(1.0, np.eye(2), np.zeros(2))])
    monkeypatch.setattr(P, "_slip_scores", lambda *a: {})
    monkeypatch.setattr(P, "_judge", lambda *a: P.PoseResult(None, None, 1, "no", {}, 0, kind="not_found"))
    first = P.PoseResult(None, None, 1, "first", {}, 0, kind="not_found")
    assert P._search_turned_seeds(hyps, None, 40, None, first) is first
    h, n = seen["hyps"], len(hyps.s)
    assert len(h.s) == n * (1 + len(P.SEED_TURNS_DEG))
    for k, deg in enumerate((0.0, *P.SEED_TURNS_DEG)):
        part = slice(k * n, (k + 1) * n)
        turn = np.rad2deg(np.arctan2(h.lin[part, 1, 0], h.lin[part, 0, 0]))
        base = np.rad2deg(np.arctan2(hyps.lin[:, 1, 0], hyps.lin[:, 0, 0]))
        np.testing.assert_allclose((turn - base - deg + 180) % 360 - 180, 0.0, atol=1e-9)
        # the seed's own reference triplet stays on its image triplet: a point p maps to
        # anchor + R (old(p) - anchor), so old(p) = anchor stays at anchor
        old = np.einsum("hij,hj->hi", hyps.lin, np.ones((n, 2))) * hyps.s[:, None] + hyps.t
        new = np.einsum("hij,hj->hi", h.lin[part], np.ones((n, 2))) * h.s[part, None] + h.t[part]
        r = np.deg2rad(deg)
        rot = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]])
        np.testing.assert_allclose(new, hyps.anchor + (old - hyps.anchor) @ rot.T, atol=1e-9)


@pytest.mark.slow  # 5-8 s: one whole search
def test_without_turned_seeds_the_same_triplets_are_refused(monkeypatch):
    """The case above needs the second pass: with no turns added it is refused."""
    monkeypatch.setattr(P, "SEED_TURNS_DEG", ())
    trips, ref, _, _ = _image_triplets(45.0, bar_error_deg=9.0)
    res = _search(trips, ref)
    assert res.status != 0


@pytest.mark.slow  # 5-6 s: one whole search
def test_turned_seeds_leave_a_found_pose_alone(monkeypatch):
    """Bars along the pose: the first pass finds it and the second never runs."""
    calls = []
    monkeypatch.setattr(P, "_search_turned_seeds", lambda *a: calls.append(a) or a[-1])
    trips, ref, j, _ = _image_triplets(45.0, bar_error_deg=0.0)
    res = _search(trips, ref)
    assert res.status == 0 and not calls
