"""How detection combines its registrations (``core._combine``): corners a quarter to half a
bar width apart are dropped, farther apart the image is refused unless one registration put
them on another element's bars (it is outvoted), corners only one registration kept are
added; the bar grouping of a thin middle bar; the dense registration on small images
without a scale."""

import numpy as np
import pytest

from oapcal.imaging.detect import checks, core
from oapcal.imaging.detect.bars import group_triplets
from oapcal.imaging.usaf import usaf_target

UM_PER_PX = 4.8


def _registration(elements, shift=None):
    """A successful detection of the corners of ``elements`` (e.g. ``["G4E1", "G4E2"]``) under
    a smooth radial field, ``shift`` ``{id: (dx, dy)}`` px added to some corners."""
    t = usaf_target((4, 5))
    ref = t.reference_px(UM_PER_PX, (640, 480))
    keep = [
        k
        for k, c in enumerate(t.corner_ids)
        if any(c.startswith(e + "H") or c.startswith(e + "V") for e in elements)
    ]
    ids = tuple(t.corner_ids[k] for k in keep)
    xy_u = ref[keep]
    r = xy_u - [319.5, 239.5]
    xy_d = xy_u + r * 1e-6 * (r**2).sum(axis=1, keepdims=True)
    for cid, d in (shift or {}).items():
        xy_d[ids.index(cid)] += d
    return core.Detection(ids, xy_u, xy_d, np.full(len(ids), 0.02), len(ids), um_per_px=UM_PER_PX,
                          consistency={"rms_px": 0.05}, pose={"method": "dense"})  # fmt: skip


def _width_px(cid):
    t = usaf_target((4, 5))
    return dict(zip(t.corner_ids, t.corner_width_um))[cid] / UM_PER_PX


def test_a_corner_under_half_a_bar_width_apart_is_dropped_not_the_image():
    cid = "G4E2V1C2"
    a = _registration(["G4E1", "G4E2"])
    b = _registration(["G4E1", "G4E2"], {cid: (0.35 * _width_px(cid), 0.0)})
    det = core._combine([a, b])
    assert det.ok and cid not in det.ids and len(det.ids) == len(a.ids) - 1


def test_a_corner_over_half_a_bar_width_apart_refuses_the_image():
    cid = "G4E2V1C2"
    a = _registration(["G4E1", "G4E2"])
    b = _registration(["G4E1", "G4E2"], {cid: (0.6 * _width_px(cid), 0.0)})
    det = core._combine([a, b])
    assert not det.ok and det.reason == "registrations_disagree" and len(det.ids) == 0


def test_many_corners_a_little_apart_refuse_the_image():
    a = _registration(["G4E1", "G4E2"])
    n = int(np.ceil(core.MAX_DISPUTED_FRACTION * len(a.ids))) + 1
    shift = {cid: (0.35 * _width_px(cid), 0.0) for cid in a.ids[:n]}
    det = core._combine([a, _registration(["G4E1", "G4E2"], shift)])
    assert not det.ok and det.reason == "registrations_disagree"


def test_corners_only_one_registration_kept_are_added():
    a = _registration(["G4E1", "G4E2", "G4E3"])
    b = _registration(["G4E2", "G4E3", "G4E4"])
    det = core._combine([a, b])
    assert det.ok
    assert set(det.ids) == set(a.ids) | set(b.ids)
    k = [det.ids.index(c) for c in b.ids]
    np.testing.assert_array_equal(det.xy_d[k], b.xy_d)
    assert det.pose["method"] == "triplets"  # the first (the triplet path's) had as many


def test_a_registration_with_other_reference_points_adds_nothing():
    a = _registration(["G4E1", "G4E2", "G4E3"])
    b = _registration(["G4E2", "G4E3", "G4E4"])
    b = core._replace(b, xy_u=b.xy_u * 1.01)  # another scale of the reference points
    det = core._combine([a, b])
    assert det.ok and set(det.ids) == set(a.ids)


def test_a_thin_middle_bar_still_makes_a_triplet():
    """A blurred middle bar thresholds narrower than its neighbours (measured through the
    relay, target turned by 90 degrees: 4.8 px between two of 6.0 px, 12.9 px apart);
    the spacing's upper limit comes from the wider bar."""
    bars = np.array(
        [
            [369.0, 187.5, 6.0, 27.0, np.pi / 2],
            [381.9, 189.9, 4.8, 27.2, np.pi / 2],
            [395.0, 192.5, 6.0, 27.0, np.pi / 2],
        ]
    )
    t = group_triplets(bars, np.full(3, -1.0))
    assert len(t) == 1
    np.testing.assert_allclose(t.centre[0], [381.9, 189.9])
    assert t.width[0] == pytest.approx(6.5, abs=0.1)


def test_a_small_image_without_a_scale_is_registered_densely_too():
    """The triplet path alone left group 4's corners up to 0.54 px off on this simulation
    and was returned whenever it kept 90 %; the dense registration leaves 0.1 px."""
    from oapcal.imaging.detect import detect_usaf
    from oapcal.imaging.field import setup1_like_field
    from oapcal.imaging.simulate import simulate_image

    sim = simulate_image((4, 5), setup1_like_field(), sigma_px=0.8, snr=50, seed=7)
    det = detect_usaf(sim.image, (4, 5))
    assert det.ok and det.pose["method"] != "triplets"
    k = [sim.ids.index(i) for i in det.ids]
    assert np.hypot(*(det.xy_d - sim.xy_d[k]).T).max() < 0.2


def _slipped(det, element, onto, reference):
    """``det`` with the corners of ``element`` (e.g. ``"G4E3V"``) put where ``reference`` has
    the same corners of ``onto`` (``"G4E4V"``): a triplet matched one element off."""
    xy = det.xy_d.copy()
    for n, cid in enumerate(det.ids):
        if cid.startswith(element):
            xy[n] = reference.xy_d[reference.ids.index(onto + cid[len(element) :])]
    return core._replace(det, xy_d=xy)


def test_a_registration_that_put_a_triplet_on_another_elements_bars_is_outvoted():
    dense = _registration(["G4E1", "G4E2", "G4E3", "G4E4"])
    triplets = _slipped(_registration(["G4E1", "G4E2", "G4E3"]), "G4E3V", "G4E4V", dense)
    det = core._combine([triplets, dense])
    assert det.ok
    assert det.ids == dense.ids
    np.testing.assert_array_equal(det.xy_d, dense.xy_d)
    assert len(det.pose["outvoted"]) == 1 and det.pose["outvoted"][0].startswith("triplets: ")
    # the other way round (the registration that looks slipped is a dense one, the first
    # the triplet path): a dense registration names its corners through one smooth warp and
    # is never outvoted; the image is refused
    right = _registration(["G4E1", "G4E2", "G4E3", "G4E4"])
    wrong = _slipped(_registration(["G4E1", "G4E2", "G4E3"]), "G4E3V", "G4E4V", right)
    det = core._combine([right, wrong])
    assert not det.ok and det.reason == "registrations_disagree"


def test_two_registrations_that_each_look_slipped_are_refused():
    """Each put G4E3V where the other has G4E4V (and the reverse): the corners cannot tell."""
    a = _registration(["G4E1", "G4E2", "G4E3", "G4E4"])
    b = _slipped(_slipped(a, "G4E3V", "G4E4V", a), "G4E4V", "G4E3V", a)
    det = core._combine([a, b])
    assert not det.ok and det.reason == "registrations_disagree"
    disputed = [c for c in a.ids if c.startswith(("G4E3V", "G4E4V"))]
    assert checks.outvoted(disputed, a.ids, a.xy_d, b.ids, b.xy_d) == 0


def test_disputed_corners_on_two_other_elements_or_nowhere_decide_nothing():
    a = _registration(["G4E1", "G4E2", "G4E3", "G4E4", "G4E5"])
    part = _registration(["G4E1", "G4E2", "G4E3", "G4E4"])
    # G4E3V's first bar put on G4E4V's, the other two on G4E5V's: not one slip
    two = core._replace(part, xy_d=part.xy_d.copy())
    for n, cid in enumerate(two.ids):
        if cid.startswith("G4E3V"):
            onto = "G4E4V" if cid.startswith("G4E3V0") else "G4E5V"
            two.xy_d[n] = a.xy_d[a.ids.index(onto + cid[5:])]
    disputed = [c for c in part.ids if c.startswith("G4E3V")]
    assert checks.outvoted(disputed, two.ids, two.xy_d, a.ids, a.xy_d) == 0
    # moved by a bar width and a half, onto no corner of the other registration
    shift = {c: (1.5 * _width_px(c), 1.5 * _width_px(c)) for c in disputed}
    moved = _registration(["G4E1", "G4E2", "G4E3", "G4E4"], shift)
    assert checks.outvoted(disputed, moved.ids, moved.xy_d, a.ids, a.xy_d) == 0
    assert not core._combine([moved, a]).ok


def test_a_triplet_of_unevenly_thresholded_bars_is_grouped():
    """G4E1's vertical triplet of the LAB-UMK micrograph through the misaligned relay (seed
    2), as the bar finder measured it: outer bars 9.0 and 7.7 px, the middle one 5.1 px
    (found on different pyramid levels), at a period of 13.6 px; the period gives the
    triplet's width."""
    bars = np.array(
        [
            [302.5, 126.5, 9.00, 23.0, np.pi / 2],
            [315.7, 124.9, 5.12, 23.0, np.pi / 2],
            [329.7, 124.9, 7.68, 23.0, np.pi / 2],
        ]
    )
    t = group_triplets(bars, np.ones(3))
    assert len(t) == 1
    np.testing.assert_allclose(t.centre[0], [315.7, 124.9])
    assert t.width[0] == pytest.approx(13.6 / 2, abs=0.1)


def test_a_triplet_squeezed_along_its_bars_is_grouped():
    """G4E2's vertical triplet through the same relay: bars 18-19 px long at a period of
    12.1 px, 3.0 bar widths (the target's 5, squeezed to 0.75 by the relay, the ends rounded
    off by blur); two bars as long as they are wide apart are still no triplet."""
    bars = np.array(
        [
            [370.5, 262.0, 7.00, 18.0, np.pi / 2],
            [382.6, 263.5, 6.32, 19.2, np.pi / 2],
            [395.0, 266.0, 6.00, 18.0, np.pi / 2],
        ]
    )
    t = group_triplets(bars, np.ones(3))
    assert len(t) == 1 and t.width[0] == pytest.approx(12.1 / 2, abs=0.1)
    stubby = bars.copy()
    stubby[:, 3] = 15.0  # 2.5 bar widths
    assert len(group_triplets(stubby, np.ones(3))) == 0
