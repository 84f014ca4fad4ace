"""Every preset converges from the default start on the landmarks detected in the real
USAF-1951 images of ../shared/real/usaf (slow: detection takes seconds per image)."""

import numpy as np
import pytest

from oapcal.calibration import calibrate
from paths import REAL as SHARED_REAL

REAL = SHARED_REAL / "usaf"
needs_real = pytest.mark.skipif(
    not REAL.is_dir(), reason="../shared/real/usaf (the real images) is not present"
)

#: file, groups in view (as in tests/imaging/test_detect_real.py)
IMAGES = [
    ("fpm_brightfield.png", (4, 5)),
    ("fpm_brightfield.png", (3, 4, 5, 6, 7)),
    ("labumk_negative.tif", (4, 5, 6, 7)),
    ("whole_target.png", (-2, -1, 0, 1)),
]


@pytest.fixture(scope="module")
def detections():
    from oapcal.imaging.detect import detect_usaf
    from oapcal.io.imagefile import read_image_grey

    cache = {}

    def get(name, groups):
        if (name, groups) not in cache:
            det = detect_usaf(read_image_grey(REAL / name), groups)
            assert det.ok, det.message
            cache[name, groups] = det
        return cache[name, groups]

    return get


@pytest.mark.slow
@needs_real
@pytest.mark.parametrize("name,groups", IMAGES, ids=[f"{n}-{len(g)}groups" for n, g in IMAGES])
@pytest.mark.parametrize("preset", ["paper", "full", "radial"])
def test_every_preset_converges_by_default_on_real_landmarks(detections, name, groups, preset):
    det = detections(name, groups)
    cal = calibrate(det.xy_u, det.xy_d, preset)
    assert cal.fit.converged, (cal.fit.message, cal.notes)
    # a converged fit that explains the corners: the detected corners scatter by ~0.2-0.4 px
    assert cal.residuals.mean_px < 0.5, cal.residuals.mean_px
    assert np.isfinite(cal.params).all()
