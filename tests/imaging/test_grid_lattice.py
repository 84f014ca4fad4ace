"""The lattice indexing of dot grids and chessboards (``oapcal.imaging.detect.lattice``) on
point sets with a known index: warped, turned, with holes, extra points and wrong ones."""

import numpy as np
import pytest

from oapcal.imaging.detect.lattice import index_lattice, lattice_period


def warped_lattice(rows, cols, pitch=12.0, turn_deg=0.0, seed=0, noise=0.05, bend=0.0):
    """Points of a rows x cols lattice, turned, bent by a smooth non-radial field of ``bend``
    px at the corners, with noise; and their true (row, col)."""
    rng = np.random.default_rng(seed)
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    rc = np.stack([r.ravel(), c.ravel()], axis=1)
    g = (rc[:, ::-1] - (np.array([cols, rows]) - 1) / 2) * pitch
    t = np.radians(turn_deg)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    xy = g @ rot.T
    half = np.abs(xy).max(axis=0)
    u = xy / half
    # quadratic + cubic, different in x and y: not radial
    xy = xy + bend * np.stack(
        [0.6 * u[:, 1] ** 2 + 0.4 * u[:, 0] ** 3, 0.8 * u[:, 0] ** 2 - 0.2 * u[:, 0] * u[:, 1]], 1
    )
    xy = xy + 400 + rng.normal(0, noise, xy.shape)
    return xy, rc


def assert_right(lat, xy_true_rc):
    """Every indexed node has the truth's index under one lattice symmetry and shift."""
    assert lat.ok, lat.message
    truth = xy_true_rc[lat.point]
    best = 0
    for m in (np.eye(2), np.array([[0, 1], [-1, 0]]), -np.eye(2), np.array([[0, -1], [1, 0]])):
        for f in (np.eye(2), np.diag([1, -1])):
            mapped = lat.rc @ (m @ f).astype(int).T
            off = truth - mapped
            _, cnt = np.unique(off, axis=0, return_counts=True)
            best = max(best, int(cnt.max()))
    assert best == len(lat.rc), f"{len(lat.rc) - best} of {len(lat.rc)} nodes have a wrong index"


@pytest.mark.parametrize("turn", [0.0, 17.0, 45.0, 90.0, 133.0, -62.0])
def test_turned_and_bent_lattices_are_indexed_rightly(turn):
    xy, rc = warped_lattice(21, 25, turn_deg=turn, bend=45.0, seed=int(turn) % 7)
    lat = index_lattice(xy)
    assert_right(lat, rc)
    assert len(lat.rc) == len(xy)
    assert lat.counts["shared_with_second_seed"] > 0.5 * len(xy)


def test_holes_and_extra_points_are_left_out():
    xy, rc = warped_lattice(21, 21, bend=40.0, seed=3)
    rng = np.random.default_rng(5)
    drop = rng.choice(len(xy), 40, replace=False)
    keep = np.setdiff1d(np.arange(len(xy)), drop)
    # dust: extra points near some dots (ambiguous) and between them (not on the lattice)
    near = xy[rng.choice(keep, 10)] + rng.normal(0, 3.0, (10, 2))
    between = xy[rng.choice(keep, 10)] + 6.0
    pts = np.vstack([xy[keep], near, between])
    truth = np.vstack([rc[keep], np.full((20, 2), -999)])
    lat = index_lattice(pts)
    assert lat.ok, lat.message
    assert (lat.point < len(keep)).all(), "a dust point was indexed"
    assert_right(lat, truth)
    assert len(lat.rc) >= len(keep) - 3 * 10  # only nodes with dust close by may be left out


def test_a_missing_row_is_bridged_without_a_slip():
    xy, rc = warped_lattice(15, 15, bend=20.0, seed=2)
    keep = rc[:, 0] != 7
    lat = index_lattice(xy[keep])
    assert_right(lat, rc[keep])
    assert len(lat.rc) == keep.sum()
    # the rows on both sides of the gap are 2 apart in the index
    rows = np.unique(lat.rc[:, 0])
    assert len(rows) == 14 and np.ptp(rows) == 14


def test_random_points_are_refused():
    rng = np.random.default_rng(1)
    lat = index_lattice(rng.uniform(0, 500, (400, 2)))
    assert not lat.ok
    assert lat.reason in ("no_seed", "too_few", "inconsistent", "seeds_disagree")


def test_too_few_points_are_refused():
    xy, _ = warped_lattice(2, 3)
    lat = index_lattice(xy)
    assert not lat.ok and lat.reason == "too_few"


def test_parity_refuses_a_neighbour_of_the_wrong_kind():
    xy, rc = warped_lattice(11, 11, seed=4)
    parity = np.where((rc.sum(axis=1) % 2) == 0, 1, -1)
    wrong = parity.copy()
    flip = (rc[:, 0] == 5) & (rc[:, 1] == 3)
    wrong[flip] *= -1
    lat = index_lattice(xy, parity=wrong)
    assert lat.ok
    assert np.flatnonzero(flip)[0] not in set(lat.point.tolist())
    assert_right(lat, rc)


def test_lattice_period_of_a_dot_image():
    from oapcal.imaging.grid_targets import GridTarget

    img, _ = GridTarget("dots", 30, 30, pitch_um=10.0, dot_um=5.0).source(1.0)  # 10 px pitch
    assert lattice_period(img) == pytest.approx(10.0, rel=0.02)
    board, _ = GridTarget("chessboard", 20, 20, pitch_um=12.0).source(1.0)
    assert lattice_period(board) == pytest.approx(12.0, rel=0.03)
    assert np.isnan(lattice_period(np.zeros((64, 64))))
