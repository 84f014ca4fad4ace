"""Which layout the detected corners follow (:mod:`oapcal.imaging.detect.layouts`): the
cubic map's residuals decide between layouts, and a detection in a wrong layout, or one that
kept too few resolved corners, is run again (the real micrographs rendered through the
relay are in tests/imaging/test_e2e_real.py)."""

from types import SimpleNamespace

import numpy as np
import pytest

from oapcal.imaging.detect.layouts import (
    BETTER_RATIO,
    MIN_CORNERS,
    RETRY_RATIO,
    SUSPECT_RMS_PX,
    WIDE_BAR_PX,
    better_layout,
    layout_residuals,
    layouts_to_retry,
    prefer,
    resolved_coverage,
)
from oapcal.imaging.usaf import LAYOUTS, usaf_target

GROUPS = (4, 5)


def _corners(layout, noise_px=0.03, seed=0, turn_deg=135.0, mirror=True):
    """The corners of groups 4-5 in ``layout`` at 4.8 um/px, turned, mirrored and bent by a
    smooth radial field of ~25 px at the edge of the target, with noise."""
    t = usaf_target(GROUPS, layout_name=layout)
    um = t.corners_um - t.corners_um.mean(axis=0)
    th = np.radians(turn_deg)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    flip = np.diag([-1.0, 1.0]) if mirror else np.eye(2)
    px = um @ (rot @ flip).T / 4.8
    r2 = (px**2).sum(axis=1, keepdims=True) / 150.0**2
    px = px * (1 + 0.15 * r2) + [320.0, 240.0]
    rng = np.random.default_rng(seed)
    return list(t.corner_ids), px + rng.normal(0, noise_px, px.shape)


def test_the_right_layout_fits_its_corners_to_their_noise_and_the_others_do_not():
    ids, xy = _corners("compact")
    rms = layout_residuals(ids, xy, GROUPS, list(LAYOUTS))
    assert set(rms) == set(LAYOUTS)
    assert rms["compact"] < 0.06  # the noise (0.03 px per axis) and the field's non-cubic rest
    assert all(rms[k] > 5 * rms["compact"] for k in LAYOUTS if k != "compact")


@pytest.mark.parametrize("truth", list(LAYOUTS))
def test_a_detection_in_another_layout_names_the_right_one(truth):
    ids, xy = _corners(truth, seed=1)
    for current in LAYOUTS:
        choice, rms = better_layout(ids, xy, GROUPS, current, list(LAYOUTS))
        if current == truth:
            assert choice is None
        else:
            assert rms[current] > SUSPECT_RMS_PX and choice == truth


def test_few_corners_or_one_element_cannot_tell_layouts_apart():
    ids, xy = _corners("compact")
    assert layout_residuals(ids[: MIN_CORNERS - 1], xy[: MIN_CORNERS - 1], GROUPS, list(LAYOUTS)) == {}
    one = [k for k, c in enumerate(ids) if c.startswith("G4E2")]
    assert len(one) == 24
    assert layout_residuals([ids[k] for k in one], xy[one], GROUPS, list(LAYOUTS)) == {}
    assert better_layout([ids[k] for k in one], xy[one], GROUPS, "spaced", list(LAYOUTS)) == (None, {})


def _det(ids, xy, ok=True, pose_status=0, expected=None):
    """A detection's fields that the layout decisions read: ``expected`` the ids predicted in
    view (default: ``ids``), at 4.8 um/px."""
    expected = ids if expected is None else expected
    predicted = dict.fromkeys(expected, (0.0, 0.0))
    return SimpleNamespace(ok=ok, ids=tuple(ids), xy_d=np.asarray(xy), um_per_px=4.8,
                           predicted=predicted, pose={"status": pose_status})  # fmt: skip


def test_resolved_coverage_counts_only_corners_of_bars_wide_enough():
    t = usaf_target(GROUPS)
    ids = list(t.corner_ids)
    width_px = dict(zip(ids, t.corner_width_um / 4.8))
    wide = [c for c in ids if width_px[c] >= WIDE_BAR_PX]
    narrow = [c for c in ids if width_px[c] < WIDE_BAR_PX]
    assert wide and narrow  # groups 4-5 at 4.8 um/px: G5E4-E6 are narrower than 2.5 px
    xy = np.zeros((len(ids), 2))
    # every wide corner kept, no narrow one: fully covered
    assert resolved_coverage(_det(wide, xy[: len(wide)], expected=ids), GROUPS) == 1.0
    # half the wide ones kept
    half = wide[::2]
    got = resolved_coverage(_det(half + narrow, xy[: len(half) + len(narrow)], expected=ids), GROUPS)
    assert got == pytest.approx(len(half) / len(wide))


def test_what_is_run_again():
    ids, xy = _corners("compact", seed=2)
    lays = list(LAYOUTS)
    # right layout, every corner kept: nothing
    assert layouts_to_retry(_det(ids, xy), GROUPS, "compact", lays)[0] == []
    # right layout by its corners but few kept: every other layout
    few = _det(ids[:100], xy[:100], expected=ids)
    assert layouts_to_retry(few, GROUPS, "compact", lays)[0] == ["spaced", "whole-target"]
    # a wrong layout that the corners show: that one
    assert layouts_to_retry(_det(ids, xy), GROUPS, "whole-target", lays)[0] == ["compact"]
    # a refusal is not run again, whether a pose was found or not
    failed = _det((), np.zeros((0, 2)), ok=False)
    assert layouts_to_retry(failed, GROUPS, "spaced", lays)[0] == []
    failed.pose = {"status": 1}
    assert layouts_to_retry(failed, GROUPS, "spaced", lays)[0] == []


def test_a_wrong_layout_that_the_corners_show_only_dimly_is_run_again_and_judged_by_the_new_run():
    """Corners detected in a wrong layout carry its error, so the right layout fits them
    better but not by the factor that keeps a detection (:data:`BETTER_RATIO`): the detection
    runs again in it (:data:`RETRY_RATIO`), and :func:`prefer` keeps the new run only when its
    own corners fit its layout clearly better."""
    ids, xy = _corners("compact", noise_px=0.45, seed=5)
    rms = layout_residuals(ids, xy, GROUPS, list(LAYOUTS))
    ratio = rms["compact"] / rms["whole-target"]
    assert BETTER_RATIO < ratio <= RETRY_RATIO  # the case this rule is for (0.6 here)
    assert better_layout(ids, xy, GROUPS, "whole-target", list(LAYOUTS))[0] is None
    assert layouts_to_retry(_det(ids, xy), GROUPS, "whole-target", list(LAYOUTS))[0] == ["compact"]
    # the new run's corners, refined in the right layout, fit it to their noise: kept
    _, clean = _corners("compact", seed=5)
    assert prefer(_det(ids, clean), "compact", _det(ids, xy), "whole-target", GROUPS)
    # a new run no better than the corners it was asked from: the first detection stays
    assert not prefer(_det(ids, xy), "compact", _det(ids, xy), "whole-target", GROUPS)
    # the right layout's own corners, however noisy, never ask for another layout
    assert layouts_to_retry(_det(ids, xy), GROUPS, "compact", list(LAYOUTS))[0] == []


def test_which_detection_is_kept():
    ids, xy = _corners("compact", seed=3)
    right = _det(ids, xy)
    fewer = _det(ids[:150], xy[:150])
    failed = _det((), np.zeros((0, 2)), ok=False)
    assert prefer(right, "compact", failed, "spaced", GROUPS)
    assert not prefer(failed, "spaced", right, "compact", GROUPS)
    # the same corners read in a wrong layout fit it worse: never kept over the right one
    assert not prefer(right, "whole-target", right, "compact", GROUPS)
    assert prefer(right, "compact", right, "whole-target", GROUPS)
    # more corners in the same (right) layout: kept; about as many: not
    assert prefer(right, "compact", fewer, "compact", GROUPS)
    assert not prefer(fewer, "compact", right, "compact", GROUPS)


@pytest.mark.parametrize(("pose_layout", "runs"), [("whole-target", [None, "compact"]), ("compact", [None])])
def test_detection_runs_again_in_the_layout_its_corners_follow(monkeypatch, pose_layout, runs):
    """``core._detect``: when the pose search's layout is ``whole-target`` and the corners
    follow ``compact``, the detection in ``compact`` is kept, with ``pose.layout_from_corners``;
    when the corners follow the pose's layout, nothing runs again."""
    from oapcal.imaging.detect import core

    ids, xy = _corners("compact", seed=4)
    calls = []

    def detect_in(img, groups, opts, progress):
        calls.append(opts.layout)
        layout = opts.layout or pose_layout
        return core.Detection(tuple(ids), xy, xy.copy(), np.zeros(len(ids)), len(ids), um_per_px=4.8,
                              pose={"status": 0, "layout": layout}, predicted=dict.fromkeys(ids))  # fmt: skip

    monkeypatch.setattr(core, "_detect_in_layouts", detect_in)
    monkeypatch.setattr(core, "_layouts", lambda: list(LAYOUTS))
    opts = core._Options(None, "auto", "auto", 1.0, 0.3, 1.5, core.ORIENTATION_RATIO, "auto", ())
    det = core._detect(np.zeros((480, 640)), GROUPS, opts, None)
    assert calls == runs
    assert det.pose["layout"] == "compact"
    if len(runs) > 1:
        note = det.pose["layout_from_corners"]
        assert note["pose_layout"] == "whole-target"
        assert note["rms_px"]["whole-target"] > 5 * note["rms_px"]["compact"]
    else:
        assert "layout_from_corners" not in det.pose
