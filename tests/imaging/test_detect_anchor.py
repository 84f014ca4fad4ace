"""Anchors (elements the user names) and the pixel-size answer of detection.

The anchored detections of real images are checked against the detection of the same image
unturned, mapped through the known turn: every corner must be nearer to the mapped corner of
its own id than to any other (docs/detection.md, "Naming an element").
"""

import hashlib
import json

import numpy as np
import pytest

from oapcal.errors import DataError
from oapcal.imaging.detect import detect_usaf
from oapcal.imaging.detect.anchor import Anchor, parse_anchor, parse_anchors
from oapcal.imaging.detect.pixel_size import measure_pixel_size, pixel_size_answer
from paths import REAL as SHARED_REAL

REAL = SHARED_REAL / "usaf"
needs_real = pytest.mark.skipif(
    not REAL.is_dir(), reason="../shared/real/usaf (the real images) is not present"
)


# ---------------------------------------------------------------------------- parsing


@pytest.mark.parametrize(
    "text,expected",
    [
        ("G6E3", Anchor(6, 3)),
        ("G6E3V", Anchor(6, 3, "V")),
        ("G-2E1H@10.5,20", Anchor(-2, 1, "H", (10.5, 20.0))),
        (" G4E2@512,300 ", Anchor(4, 2, None, (512.0, 300.0))),
    ],
)
def test_anchor_texts_are_parsed(text, expected):
    assert parse_anchor(text) == expected
    assert parse_anchor(parse_anchor(text)) == expected


@pytest.mark.parametrize("text", ["G6E7", "6E3", "G6E3@1", "G12E1", "G6E3X", "", "G6E3@a,b"])
def test_bad_anchor_texts_are_refused_naming_the_parameter(text):
    with pytest.raises(DataError) as err:
        parse_anchor(text)
    assert err.value.param == "anchors" and repr(text) in str(err.value)


def test_the_same_element_twice_is_refused():
    with pytest.raises(DataError, match="named twice"):
        parse_anchors(["G6E3", "G6E3@10,10"])
    assert parse_anchors(None) == () and parse_anchors("G6E3") == (Anchor(6, 3),)


def test_cli_words_name_the_flag():
    from oapcal.cli.detect import _cli_words

    msg = "ambiguous; name the element you read there in anchors, e.g. 'G4E2@512,300'"
    assert (
        _cli_words(msg)
        == "ambiguous; name the element you read there with --anchor, e.g. --anchor G4E2@512,300"
    )


# ---------------------------------------------------------------------------- pixel size


def test_pixel_size_of_a_known_similarity_with_noise():
    rng = np.random.default_rng(1)
    um = rng.uniform(-400, 400, (300, 2))
    scale, phi = 1 / 3.7, np.deg2rad(33.0)  # px per um
    rot = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    px = scale * um @ rot.T + (320, 240) + rng.normal(0, 0.05, (300, 2))
    m = measure_pixel_size(um, px, mirrored=False)
    assert abs(m["um_per_px"] - 3.7) < 3 * m["statistical"] and m["statistical"] < 1e-3
    assert m["anisotropy"] < 3e-3 and m["corners"] == 300
    # mirrored: the same scale only when told so
    flipped = px * (-1, 1)
    assert abs(measure_pixel_size(um, flipped, mirrored=True)["um_per_px"] - 3.7) < 1e-3
    assert measure_pixel_size(um[:5], px[:5], mirrored=False) is None


def test_anisotropy_and_field_variation_enter_the_uncertainty():
    um = np.stack(np.meshgrid(np.linspace(-300, 300, 12), np.linspace(-300, 300, 12)), -1).reshape(-1, 2)
    px = um / np.array([3.0, 3.3])  # 3.0 um/px along x, 3.3 along y
    m = measure_pixel_size(um, px, mirrored=False, labels=np.repeat(np.arange(12), 12))
    assert m["anisotropy"] == pytest.approx(0.15, abs=1e-9)
    assert 3.0 < m["um_per_px"] < 3.3
    ans = pixel_size_answer(m, m["um_per_px"], given=False, image_size=(640, 480))
    assert ans["um_per_px_sigma"] >= 0.15
    assert ans["field_of_view_um"] == pytest.approx([640 * m["um_per_px"], 480 * m["um_per_px"]])
    given = pixel_size_answer(m, 3.1, given=True, image_size=(640, 480))
    assert given["um_per_px_sigma"] is None and given["um_per_px"] == 3.1 and given["pixel_size"] is m


# ---------------------------------------------------------------------------- simulated target


@pytest.fixture(scope="module")
def flat():
    """Groups 4-5 without distortion (4.8 um/px): the truth of every corner is exact."""
    from oapcal.imaging.field import ModelDistortionField, setup1_like_field
    from oapcal.imaging.simulate import simulate_image

    p = setup1_like_field().params.copy()
    p[:8] = 0.0
    sim = simulate_image((4, 5), ModelDistortionField(p), sigma_px=0.8, snr=50, seed=2)
    return sim, detect_usaf(sim.image, (4, 5))


def test_pixel_size_found_on_an_undistorted_target(flat):
    sim, det = flat
    assert det.ok, det.message
    s = det.summary()
    assert s["um_per_px_sigma"] is not None and 0 < s["um_per_px_sigma"] < 0.01 * sim.um_per_px
    assert abs(s["um_per_px"] - sim.um_per_px) < 3 * s["um_per_px_sigma"] + 1e-3
    assert abs(s["pixel_size"]["um_per_px"] - sim.um_per_px) < 0.002 * sim.um_per_px
    h, w = sim.image.shape
    assert s["field_of_view_um"] == pytest.approx([w * s["um_per_px"], h * s["um_per_px"]])
    assert s["image_sha256"] == ""  # an array has no file to digest


@pytest.mark.slow  # the default suite keeps the refusal of a wrong anchor and the real turned image
def test_a_right_anchor_gives_the_same_detection(flat):
    sim, det = flat
    k = list(sim.ids).index("G4E2H1C0")
    x, y = sim.xy_d[k]
    anchored = detect_usaf(sim.image, (4, 5), anchors=[f"G4E2@{x:.0f},{y:.0f}"])
    assert anchored.ok, anchored.message
    assert anchored.ids == det.ids
    np.testing.assert_allclose(anchored.xy_d, det.xy_d, atol=1e-9)


def test_a_wrong_anchor_is_refused_not_obeyed(flat):
    # the user names G4E3 where G4E2 is: the bars say otherwise clearly, so no detection
    sim, _ = flat
    k = list(sim.ids).index("G4E2H1C0")
    x, y = sim.xy_d[k]
    det = detect_usaf(sim.image, (4, 5), anchors=[f"G4E3@{x:.0f},{y:.0f}"])
    assert not det.ok and len(det.ids) == 0
    assert "contradict" in det.message and "anchors" in det.param


# ---------------------------------------------------------------------------- real images


def _read(name):
    from oapcal.io.imagefile import read_image_grey

    return read_image_grey(REAL / name)


def _turn(img, angle):
    """``img`` turned by ``angle`` degrees about its centre onto a canvas that holds it all,
    and the 2x3 map from the old pixel coordinates to the new."""
    import cv2

    h, w = img.shape
    c = ((w - 1) / 2, (h - 1) / 2)
    m = cv2.getRotationMatrix2D(c, angle, 1.0)
    nw = int(np.ceil(w * abs(m[0, 0]) + h * abs(m[0, 1])))
    nh = int(np.ceil(h * abs(m[0, 0]) + w * abs(m[0, 1])))
    m[0, 2] += (nw - 1) / 2 - c[0]
    m[1, 2] += (nh - 1) / 2 - c[1]
    out = cv2.warpAffine(
        img.astype(np.float32), m, (nw, nh), flags=cv2.INTER_LINEAR, borderValue=float(np.median(img))
    )
    return out, m


@pytest.mark.slow
@needs_real
def test_a_turned_real_image_is_named_with_and_without_an_anchor():
    """LAB-UMK turned by 30 degrees: found without an anchor (refused before the bar width
    came from the blob's moments: the turned bars' rectangles were too wide to make
    triplets), and ``G4E3`` named gives the same ids; every corner lies on the unturned
    detection's corner of its id (measured: median 0.07 px, 8 of 336 over 0.4 px, at most
    1.1 px at bars cut by the micrograph's edge, whose turned neighbourhood is padding; a
    wrong id would be a bar width, 5 px and more, away)."""
    from scipy.spatial import cKDTree

    img = _read("labumk_negative.tif")
    groups = (4, 5, 6, 7)
    base = detect_usaf(img, groups)
    assert base.ok, base.message
    turned, m = _turn(img, 30.0)
    mapped = base.xy_d @ m[:, :2].T + m[:, 2]
    tree = cKDTree(mapped)
    index = {i: n for n, i in enumerate(base.ids)}
    found = detect_usaf(turned, groups)
    named = detect_usaf(turned, groups, anchors="G4E3")
    for det in (found, named):
        assert det.ok, det.message
        shared = [(i, xy) for i, xy in zip(det.ids, det.xy_d) if i in index]
        assert len(shared) >= 0.85 * len(base.ids)
        err = []
        for cid, xy in shared:
            d, k = tree.query(xy)
            assert base.ids[k] == cid and d < 3.0, (cid, base.ids[k], d)
            err.append(np.hypot(*(xy - mapped[index[cid]])))
        assert np.median(err) < 0.15 and np.percentile(err, 90) < 0.3 and max(err) < 1.2
        assert det.um_per_px == pytest.approx(base.um_per_px, rel=0.01)
        assert det.um_per_px_sigma is not None and abs(det.um_per_px - 3.7) < 3 * det.um_per_px_sigma
    assert named.ids == found.ids


@pytest.mark.slow
@needs_real
def test_cli_reports_the_pixel_size_and_the_image_digest(run_cli, tmp_path):
    path = REAL / "whole_target.png"
    code, out, err = run_cli(
        "detect", str(path), "--groups", "-2-1", "--out", str(tmp_path / "p.csv"), "--json"
    )
    assert code == 0, err
    data = json.loads(out)
    assert data["image_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert abs(data["um_per_px"] - 130.0) < 3 * data["um_per_px_sigma"] + 0.01 * 130.0
    assert data["field_of_view_um"] == pytest.approx([512 * data["um_per_px"], 512 * data["um_per_px"]])
    assert {"um_per_px", "pose", "triplets_found", "work", "pixel_size"} <= set(data)


@pytest.mark.slow
@needs_real
def test_cli_refusal_says_which_anchor_would_decide_it(run_cli, tmp_path):
    code, out, err = run_cli(
        "detect", str(REAL / "highmag_g7e1.jpg"), "--groups", "7", "--out", str(tmp_path / "p.csv")
    )
    assert code == 3 and "ambiguous" in err and "--anchor G7E1@" in err and "Traceback" not in err
    assert not (tmp_path / "p.csv").exists()


def test_cli_a_bad_anchor_is_one_line_naming_the_flag(run_cli, tmp_path):
    import cv2

    img = tmp_path / "img.png"
    cv2.imwrite(str(img), np.zeros((40, 50), np.uint8))
    code, out, err = run_cli("detect", img, "--anchor", "G4E9", "--out", tmp_path / "p.csv")
    assert code == 2 and "'G4E9' is not an element name" in err and "(set by --anchor)" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "p.csv").exists()


#: Points on the middle of each bar of the single element of highmag_g7e1.jpg, read off the
#: image by eye (the element and group numbers printed beside it), as benchmarks/real_usaf.py
#: has them: (triplet bar id, x, y).
HIGHMAG_BARS = (("G7E1H0", 342, 567), ("G7E1H1", 257, 567), ("G7E1H2", 172, 567))


@pytest.mark.slow  # a 1024 x 1280 image (~10 s each)
@needs_real
@pytest.mark.parametrize("flipped", [False, True])
def test_the_single_element_is_named_by_its_anchor_alone(run_cli, tmp_path, flipped):
    """One element in view, named G7E1 by the user: its two triplets are mirror symmetric,
    the printed numbers decide the mirror (also of the image flipped left-right); --groups
    left out searches the anchor's group."""
    import csv

    import cv2

    path = REAL / "highmag_g7e1.jpg"
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if flipped:
        path = tmp_path / "flipped.png"
        cv2.imwrite(str(path), cv2.flip(img, 1))
    out = tmp_path / "p.csv"
    code, stdout, err = run_cli("detect", path, "--anchor", "G7E1", "--out", out, "--json")
    assert code == 0, err
    assert "searching the --anchor's group 7" in err
    evidence = json.loads(stdout)["pose"]["mirror_from_digits"]
    assert evidence["mirrored"] is flipped
    with out.open() as f:
        rows = {r["id"]: (float(r["x_d"]), float(r["y_d"])) for r in csv.DictReader(f)}
    assert len(rows) >= 12 and all(i.startswith("G7E1") for i in rows)
    w = img.shape[1]
    for bar, x, y in HIGHMAG_BARS:  # each bar's four corners surround the point read on it
        x = w - 1 - x if flipped else x
        xy = np.array([rows[f"{bar}C{c}"] for c in range(4)])
        assert xy[:, 0].min() < x < xy[:, 0].max() and xy[:, 1].min() < y < xy[:, 1].max()
    # the corners go round each bar the same way as in the unflipped image: C0 -> C1 turns
    # one way, C1 -> C2 the other way round in the mirror image
    c = np.array([rows[f"G7E1H1C{k}"] for k in range(3)])
    (ax, ay), (bx, by) = c[1] - c[0], c[2] - c[1]
    turn = ax * by - ay * bx
    assert (turn < 0) == flipped  # (in the image as taken: C0 -> C1 -> C2 turns clockwise on screen)


def test_an_anchor_outside_the_groups_searched_is_refused_naming_groups():
    with pytest.raises(
        DataError, match=r"anchor G7E1 names group 7, which is not among the groups searched \(4, 5\)"
    ) as e:
        detect_usaf(np.zeros((40, 50)), (4, 5), anchors="G7E1")
    assert e.value.param == "groups"


def test_cli_anchor_without_groups_searches_the_anchors_group(run_cli, tmp_path):
    import cv2

    img = tmp_path / "img.png"
    cv2.imwrite(str(img), np.zeros((40, 50), np.uint8))
    code, _, err = run_cli("detect", img, "--anchor", "G7E1", "--out", tmp_path / "p.csv")
    assert code == 3 and "searching the --anchor's group 7" in err  # (a uniform image: not found)
    code, _, err = run_cli("detect", img, "--groups", "4-5", "--anchor", "G7E1", "--out", tmp_path / "p.csv")
    assert code == 2 and "(set by --groups)" in err and len(err.strip().splitlines()) == 1


def test_the_dense_warp_is_affine_when_the_pose_matched_one_element():
    from oapcal.imaging.detect.core import LEVELS, dense_degree_limit

    assert dense_degree_limit(1) == 1
    assert dense_degree_limit(2) == dense_degree_limit(9) == LEVELS[-1][1] > 1
