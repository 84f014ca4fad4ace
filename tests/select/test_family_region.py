"""select --families by the predicted error over the region to be corrected."""

import json

import numpy as np
from tests_priors_case import few_central_case

from oapcal.families import region_points, select_families


def test_recommends_by_the_predicted_error_over_the_region_and_says_what_it_saw():
    design, xy_u, xy_d, field = few_central_case()
    sel = select_families(xy_u, xy_d, design, ("bc", "relay"), cv=3, cv_top=2, region=field, priors="default")
    r = sel.recommended
    assert r.family == "relay" and r.predicted_error is not None
    scored = [c for c in sel.candidates if c.predicted_error is not None]
    assert {c.family for c in scored} == {"brown-conrady", "relay"}
    for c in scored:  # predicted = held-out error and the propagated sigma together
        assert np.isclose(c.predicted_error, np.hypot(c.cv_mean_error, c.region_sigma))
    # Eq. (1) extrapolates from the centre with a larger propagated uncertainty
    best_bc = min(c.predicted_error for c in scored if c.family == "brown-conrady")
    assert best_bc > r.predicted_error
    assert any("relay:all" == c.spec for c in scored)  # with priors the full relay is always scored
    data = sel.to_dict()
    assert data["region"] == list(field) and data["priors"]["spec"] == "default"
    assert {"recommended", "candidates", "heldout_best", "notes"} <= set(data)
    assert {"cv_mean_error", "region_sigma_px", "predicted_error_px"} <= set(data["candidates"][0])
    json.dumps(data)


def test_region_points_cover_the_box_or_the_hull():
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    box = region_points(xy, (0, 0, 20, 10))
    assert box[:, 0].max() == 20 and len(box) == 21 * 21
    hull = region_points(xy)
    assert (hull.sum(axis=1) <= 10 + 1e-9).all()  # inside the triangle
