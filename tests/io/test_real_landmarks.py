"""Real landmark files exported by VIA 1/2/3, napari and BigWarp (``../shared/real/landmarks``,
sources in its ``SOURCES.md``): read correctly where they hold points, and where they hold
none or are not 2-D, one message saying what was found.  Expected values are worked out
from the files with the csv/json modules, not by oapcal."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from oapcal.errors import InputFileError
from oapcal.io.landmarks import read_landmark_pairs, read_landmarks
from paths import REAL as SHARED_REAL

REAL = SHARED_REAL / "landmarks"
pytestmark = pytest.mark.skipif(
    not REAL.is_dir(), reason="the real landmark files (../shared/real/landmarks) are not on this machine"
)


def real(name: str) -> Path:
    return next(REAL.glob(f"*/{name}"))


# -- files with points ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["bigwarp_2d_blobs.csv", "bigwarp_2d_testpoints.csv"])
def test_bigwarp_2d_files(name):
    rows = [r for r in csv.reader(real(name).read_text().splitlines()) if r]
    pairs = read_landmark_pairs(real(name))
    assert pairs.ids == tuple(r[0] for r in rows if r[1] == "true")
    np.testing.assert_array_equal(pairs.xy_d, [[float(r[2]), float(r[3])] for r in rows if r[1] == "true"])
    np.testing.assert_array_equal(pairs.xy_u, [[float(r[4]), float(r[5])] for r in rows if r[1] == "true"])


def test_napari_3d_points_in_one_plane():
    rows = list(csv.DictReader(real("napari_points_3d_cells.csv").read_text().splitlines()))
    ls = read_landmarks(real("napari_points_3d_cells.csv"))
    assert len(ls) == 15 == len(rows)
    np.testing.assert_array_equal([lm.x for lm in ls.landmarks], [float(r["axis-2"]) for r in rows])
    np.testing.assert_array_equal([lm.y for lm in ls.landmarks], [float(r["axis-1"]) for r in rows])


def test_via2_csv_with_state_names_as_region_ids():
    rows = list(csv.DictReader(real("via2_export_points_map.csv").read_text().splitlines()))
    shapes = [json.loads(r["region_shape_attributes"]) for r in rows]
    ls = read_landmarks(real("via2_export_points_map.csv"))
    assert len(ls) == 41 == sum(s["name"] == "point" for s in shapes)
    assert ls.landmarks[0].x == shapes[0]["cx"] - 0.5 and ls.landmarks[0].y == shapes[0]["cy"] - 0.5


@pytest.mark.parametrize("name", ["via1_mixed_points.csv", "via1_mixed_points.json"])
def test_via1_files_pick_an_image(name):
    ls = read_landmarks(real(name), image="test_pattern_qbist.jpg")
    assert len(ls) == 4 and len(ls.ignored) == 4  # ellipse, rect, circle, polygon
    names = {lm.attrs.get("name") for lm in ls.landmarks}
    assert 'red "dot"' in names
    with pytest.raises(
        InputFileError,
        match=r"point regions on 2 images .*; choose one by its name with distorted_image$",
    ):
        read_landmark_pairs(real(name), require=("x_d", "y_d"))


@pytest.mark.parametrize("name", ["via2_export_points_crowd.json", "via2_project_points_crowd.json"])
def test_via2_crowd_files_every_image(name):
    data = json.loads(real(name).read_text())
    meta = data.get("_via_img_metadata", data)
    for entry in list(meta.values())[:10]:
        points = [r["shape_attributes"] for r in entry["regions"] if r["shape_attributes"]["name"] == "point"]
        if not points:
            continue
        ls = read_landmarks(real(name), image=entry["filename"])
        assert len(ls) == len(points)
        np.testing.assert_array_equal([lm.x for lm in ls.landmarks], [p["cx"] - 0.5 for p in points])


# -- issue 14 item 25: BigWarp z (and napari's leading axes) compared with a tolerance -------------


def test_bigwarp_plane_noise_is_one_plane():
    """``bigwarp_3d_settings.csv``: rows 1-3 have fixed z 126.86263579832789 / ...79 (one
    plane up to 1.4e-14), rows 4-5 are at z = 170.56 (another plane): the refusal is at row 4."""
    with pytest.raises(
        InputFileError, match=r"line 4: moving z = 170\.56\d* differs from earlier landmarks \(z = 130\)"
    ):
        read_landmark_pairs(real("bigwarp_3d_settings.csv"))


def test_bigwarp_first_three_rows_of_the_settings_file_pair(tmp_path):
    lines = real("bigwarp_3d_settings.csv").read_text().splitlines()[:3]
    (tmp_path / "three.csv").write_text("\n".join(lines) + "\n")
    pairs = read_landmark_pairs(tmp_path / "three.csv", check_geometry=False)
    assert len(pairs) == 3


@pytest.mark.parametrize(
    "name,line",
    [("bigwarp_3d_mri_translation.csv", 4), ("bigwarp_3d_mr_p2p2p4.csv", 2),
     ("bigwarp_3d_mri_stack_old.csv", 5), ("bigwarp_3d_excel_edited.csv", 2)],
)  # fmt: skip
def test_bigwarp_3d_files_in_several_planes_are_refused(name, line):
    with pytest.raises(
        InputFileError, match=rf"{name}: line {line}: moving z = .* oapcal needs landmarks of one 2-D plane"
    ):
        read_landmark_pairs(real(name))


def test_napari_leading_axis_noise_is_one_plane(tmp_path):
    (tmp_path / "n.csv").write_text(
        "index,axis-0,axis-1,axis-2\n0,31.000000000000004,1,2\n1,31.0,5,6\n2,30.999999999999996,9,3\n"
    )
    assert len(read_landmarks(tmp_path / "n.csv")) == 3
    (tmp_path / "m.csv").write_text("index,axis-0,axis-1,axis-2\n0,31,1,2\n1,32,5,6\n")
    with pytest.raises(
        InputFileError, match=r"line 3: the point is in plane \(32\.0,\) but earlier ones are in \(31\.0,\)"
    ):
        read_landmarks(tmp_path / "m.csv")


# -- items 26, 27, 29: VIA's undefined, Windows paths, messages ---------------------------------


def test_via_undefined_attribute_reads_as_missing():
    """Line 97 of the real export is a rect with ``{"Label":undefined}``: once the whole file failed."""
    with pytest.raises(InputFileError, match=r"has no point regions \(found 121 images, 128 rect regions\)"):
        read_landmarks(real("via2_export_rects_undefined.csv"))


def test_via_undefined_on_a_point(tmp_path):
    header = real("via2_export_rects_undefined.csv").read_text().splitlines()[0]
    (tmp_path / "u.csv").write_text(
        header + "\n"
        'a.png,1,"{}",2,0,"{""name"":""point"",""cx"":3,""cy"":4}","{""Label"":undefined,""id"":""undefined""}"\n'
        'a.png,1,"{}",2,1,"{""name"":""point"",""cx"":7,""cy"":9}","{""Label"":""B""}"\n'
    )
    ls = read_landmarks(tmp_path / "u.csv")
    assert [lm.attrs for lm in ls.landmarks] == [{"id": "undefined"}, {"Label": "B"}]


def test_windows_file_url_matches_the_base_name():
    with pytest.raises(
        InputFileError,
        match=r"image 'file://C:\\\\_Denis\\\\img\\\\IMG-0001-00001.jpg' has no point regions "
        r"\(found 1 circle region\)",
    ):
        read_landmarks(real("via2_export_circle_fileurl.csv"), image="IMG-0001-00001.jpg")


def test_via1_0_semicolon_csv_is_named_unsupported():
    with pytest.raises(
        InputFileError,
        match=r"line 2: column region_shape_attributes is 'name=circle;.*VIA 1\.0's 'name=\.\.\.;' format",
    ):
        read_landmarks(real("via1_0_semicolon_shapes.csv"))


@pytest.mark.parametrize(
    "name,found",
    [
        ("via2_export_rects_receipts.csv", "6 images, 18 rect regions"),
        ("via2_export_rects_receipts.json", "6 images, 18 rect regions"),
        ("via2_project_polygons_barcode.json", "40 images, 40 polygon regions"),
        ("via2_project_no_regions.json", "1 image, no regions"),
        ("via3_video_temporal_only.json", "1 image, 5 temporal segments"),
        ("via3_video_multi_temporal.json", "4 images, 13 temporal segments"),
    ],
)
def test_files_without_points_say_what_they_hold(name, found):
    with pytest.raises(InputFileError, match=rf"has no point regions \(found {found}\)"):
        read_landmarks(real(name))


def test_malformed_via_cell_is_one_message_without_nesting(tmp_path):
    header = real("via2_export_rects_undefined.csv").read_text().splitlines()[0]
    (tmp_path / "m.csv").write_text(header + "\n" + 'a.png,1,"{}",1,0,"{""name"":""point"",""cx"":3,","{}"\n')
    with pytest.raises(InputFileError) as err:
        read_landmarks(tmp_path / "m.csv")
    msg = str(err.value)
    assert "m.csv: line 2: column region_shape_attributes: malformed JSON (" in msg and msg.count("line") == 1


# -- hints name the right tool and option ---------------------------------------------------------


def test_napari_file_alone_gets_no_via_hint(run_cli, tmp_path):
    code, _, err = run_cli(
        "fit", "--distorted", real("napari_points_3d_cells.csv"), "--out", tmp_path / "c.json"
    )
    assert (
        code == 2 and "give the reference landmarks too: their file as reference (set by --reference)" in err
    )
    assert "VIA" not in err and "reference_image" not in err, err


def test_correct_points_hint_names_only_the_distorted_image(run_cli, tmp_path):
    from oapcal.calibration import calibrate
    from oapcal.io.calibration import save_calibration
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(n_x=5, n_y=4, seed=3)
    save_calibration(calibrate(data.xy_u, data.xy_d), tmp_path / "c.json")
    code, _, err = run_cli(
        "correct-points",
        tmp_path / "c.json",
        "--distorted",
        real("via1_mixed_points.json"),
        "--out",
        tmp_path / "p.csv",
    )
    assert code == 2 and "choose one by its name with distorted_image (set by --distorted-image)" in err
    assert "reference_image" not in err and "--reference-image" not in err, err


def test_convert_to_stdout_with_json_is_refused(run_cli, tmp_path):
    code, out, err = run_cli(
        "landmarks", "convert", "--distorted", real("bigwarp_2d_blobs.csv"), "--out", "-", "--json"
    )
    assert code == 2 and "--out - writes the CSV to stdout" in err and out == "", err
    code, out, _ = run_cli("landmarks", "convert", "--distorted", real("bigwarp_2d_blobs.csv"), "--out", "-")
    assert code == 0 and out.startswith("id,x_u,y_u,x_d,y_d\n") and out.count("\n") == 6
