"""benchmarks/real_usaf.py's id check of a transformed image (``check_turned``): a wrong id is
3 px off in the image's own px, or 3 source px when the transform enlarges it."""

import importlib.util
import sys
from types import SimpleNamespace

import numpy as np

from paths import REPO


def _benchmark():
    spec = importlib.util.spec_from_file_location("real_usaf", REPO / "benchmarks" / "real_usaf.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["real_usaf"] = module
    spec.loader.exec_module(module)
    return module


bench = _benchmark()


def _base_and_moved(factor, k, shift_px):
    """Group 4's corners at 3 um/px as an image's own detection, the same enlarged ``factor``
    times (pixel centres kept, as cv2.resize does) with corner ``k`` moved by ``shift_px``."""
    from oapcal.imaging.usaf import usaf_target

    t = usaf_target((4,))
    xy = 20.0 + (t.corners_um - t.corners_um.min(axis=0)) / 3.0
    base = SimpleNamespace(ids=list(t.corner_ids), xy_d=xy, pose={"layout": t.layout})
    affine = np.array([[factor, 0, 0.5 * factor - 0.5], [0, factor, 0.5 * factor - 0.5]])
    moved = xy @ affine[:, :2].T + affine[:, 2]
    moved[k, 0] += shift_px
    shape = tuple(int(v) for v in np.ceil(xy.max(axis=0)[::-1] + 20))
    return base, SimpleNamespace(ids=list(t.corner_ids), xy_d=moved), affine, shape


def test_an_enlarged_image_is_judged_in_source_px():
    # 4 px at 6.4 times is 0.6 source px: not a wrong id (3 image px would have called it one)
    base, det, affine, shape = _base_and_moved(6.4, 5, 4.0)
    r = bench.check_turned(base, det, (4,), affine, shape)
    assert r["wrong"] == 0 and r["strict"] == 0 and r["found"] == len(det.ids)
    # 25 px at 6.4 times is 3.9 source px: wrong
    base, det, affine, shape = _base_and_moved(6.4, 5, 25.0)
    assert bench.check_turned(base, det, (4,), affine, shape)["wrong"] == 1


def test_at_the_source_scale_or_smaller_3_px_is_the_limit():
    base, det, affine, shape = _base_and_moved(1.0, 5, 3.5)
    assert bench.check_turned(base, det, (4,), affine, shape)["wrong"] == 1
    base, det, affine, shape = _base_and_moved(0.5, 5, 2.5)
    assert bench.check_turned(base, det, (4,), affine, shape)["wrong"] == 0
