import csv
import json

import numpy as np
import pytest

from landmark_writers import bigwarp_csv, labelled, napari_csv, plain_csv, via2_csv, via2_json, via3_json
from oapcal.errors import DataError, InputFileError
from oapcal.io.landmarks import detect_format, read_landmark_pairs, read_landmarks
from oapcal.io.points import write_point_pairs

# -- each format, with values worked out by hand -------------------------------------------------

VIA2_CSV = (
    "filename,file_size,file_attributes,region_count,region_id,region_shape_attributes,region_attributes\n"
    'cam.png,100,"{}",3,0,"{""name"":""point"",""cx"":11,""cy"":21}","{""corner"":""A""}"\n'
    'cam.png,100,"{}",3,1,"{""name"":""point"",""cx"":31,""cy"":5}","{""corner"":""B""}"\n'
    'cam.png,100,"{}",3,2,"{""name"":""rect"",""x"":1,""y"":2,""width"":3,""height"":4}","{}"\n'
)


def test_via2_csv_corner_origin_to_pixel_centres(tmp_path):
    (tmp_path / "v.csv").write_text(VIA2_CSV)
    ls = read_landmarks(tmp_path / "v.csv")
    # VIA's (11, 21) is measured from the image corner: the pixel centre (10.5, 20.5).
    assert [(lm.x, lm.y, lm.attrs["corner"]) for lm in ls.landmarks] == [(10.5, 20.5, "A"), (30.5, 4.5, "B")]
    assert len(ls.ignored) == 1 and "'rect'" in ls.ignored[0]


def test_via2_json_picks_the_named_image_and_reads_via1_region_dicts(tmp_path):
    data = {
        "a.png1": {"filename": "a.png",
                   "regions": {"0": {"shape_attributes": {"name": "point", "cx": 1, "cy": 2},
                                     "region_attributes": {"id": 7}}}},
        "b.png1": {"filename": "dir/b.png",
                   "regions": [{"shape_attributes": {"name": "point", "cx": 5, "cy": 6},
                                "region_attributes": {"id": "x"}}]},
    }  # fmt: skip
    path = tmp_path / "v.json"
    path.write_text(json.dumps(data))
    a = read_landmarks(path, image="a.png")
    assert (a.landmarks[0].x, a.landmarks[0].y, a.landmarks[0].attrs) == (0.5, 1.5, {"id": "7"})
    b = read_landmarks(path, image="b.png")  # the base name is enough
    assert (b.landmarks[0].x, b.landmarks[0].y) == (4.5, 5.5)
    with pytest.raises(InputFileError, match=r"point regions on 2 images \('a.png', 'dir/b.png'\)"):
        read_landmarks(path)
    with pytest.raises(InputFileError, match="has no image 'c.png'"):
        read_landmarks(path, image="c.png")


def test_via3_project_maps_attribute_ids_and_option_labels(tmp_path):
    project = {
        "project": {}, "config": {},
        "attribute": {"1": {"aname": "corner", "type": 3, "options": {"0": "top-left", "1": "top-right"}}},
        "file": {"1": {"fid": "1", "fname": "cam.png"}},
        "view": {"1": {"fid_list": ["1"]}},
        "metadata": {
            "1_a": {"vid": "1", "z": [], "xy": [1, 10.25, 20.75], "av": {"1": "0"}},
            "1_b": {"vid": "1", "z": [], "xy": [1, 40, 2], "av": {"1": "1"}},
            "1_c": {"vid": "1", "z": [], "xy": [2, 1, 1, 5, 5], "av": {}},
            "1_d": {"vid": "1", "z": [], "xy": [], "av": {}},
        },
    }  # fmt: skip
    (tmp_path / "p.json").write_text(json.dumps(project))
    ls = read_landmarks(tmp_path / "p.json")
    assert [(lm.x, lm.y, lm.attrs) for lm in ls.landmarks] == [
        (9.75, 20.25, {"corner": "top-left"}),
        (39.5, 1.5, {"corner": "top-right"}),
    ]
    assert len(ls.ignored) == 1 and "rectangle" in ls.ignored[0]


def test_napari_axis0_is_the_row(tmp_path):
    (tmp_path / "n.csv").write_text("index,axis-0,axis-1,label\n0,12.5,3.0,a\n1,7,40,b\n")
    ls = read_landmarks(tmp_path / "n.csv")
    # napari: pixel centres at integers already; axis-0 = row = y, axis-1 = column = x.
    assert [(lm.x, lm.y) for lm in ls.landmarks] == [(3.0, 12.5), (40.0, 7.0)]
    assert ls.landmarks[1].attrs == {"index": "1", "label": "b"}


def test_napari_stack_must_be_one_plane(tmp_path):
    (tmp_path / "ok.csv").write_text("index,axis-0,axis-1,axis-2\n0,4,1,2\n1,4,5,6\n")
    assert [(lm.x, lm.y) for lm in read_landmarks(tmp_path / "ok.csv").landmarks] == [(2, 1), (6, 5)]
    (tmp_path / "bad.csv").write_text("index,axis-0,axis-1,axis-2\n0,4,1,2\n1,5,5,6\n")
    with pytest.raises(InputFileError, match=r"line 3: the point is in plane \(5.0,\) but earlier"):
        read_landmarks(tmp_path / "bad.csv")


def test_bigwarp_moving_is_distorted_and_unused_rows_are_reported(tmp_path):
    text = (
        '"Pt-0","true","10.0","20.0","11.0","19.0"\n'
        '"Pt-1","false","30.0","20.0","31.0","19.5"\n'
        '"Pt-2","true","Infinity","Infinity","50.0","60.0"\n'
        '"Pt-3","true","40.0","50.0","41.5","52.0"\n'
        '"Pt-4","true","5.0","70.0","4.0","71.0"\n'
    )
    (tmp_path / "bw.csv").write_text(text)
    pairs = read_landmark_pairs(tmp_path / "bw.csv")
    assert pairs.ids == ("Pt-0", "Pt-3", "Pt-4")
    np.testing.assert_array_equal(pairs.xy_d, [[10, 20], [40, 50], [5, 70]])
    np.testing.assert_array_equal(pairs.xy_u, [[11, 19], [41.5, 52], [4, 71]])
    (note,) = pairs.warnings
    assert "2 entries not used" in note and "'Pt-1' is disabled" in note
    assert "'Pt-2' is placed in only one" in note


def test_plain_tsv_with_mapped_columns_and_corner_origin(tmp_path):
    (tmp_path / "m.tsv").write_text(" \tX\tY\n1\t10.5\t20.5\n2\t3.5\t4.5\n")
    ls = read_landmarks(tmp_path / "m.tsv", x_column="X", y_column="Y", origin="corner")
    # ImageJ-style: the top-left pixel's centre is (0.5, 0.5), so subtract half a pixel.
    assert [(lm.x, lm.y) for lm in ls.landmarks] == [(10.0, 20.0), (3.0, 4.0)]
    with pytest.raises(InputFileError, match=r"line 1: no column 'col'.*with x_column"):
        read_landmarks(tmp_path / "m.tsv", x_column="col", y_column="Y")


@pytest.mark.parametrize(
    "text,fmt",
    [
        (VIA2_CSV, "via"),
        ('{"a.png1": {"filename": "a.png", "regions": []}}', "via"),
        ('{"project": {}, "file": {}, "view": {}, "metadata": {}}', "via"),
        ("index,axis-0,axis-1\n0,1,2\n", "napari"),
        ('"Pt-0","true","1","2","3","4"\n', "bigwarp"),
        ("corner,x,y\nA,1,2\n", "csv"),
    ],
)
def test_detect_format(tmp_path, text, fmt):
    (tmp_path / "f").write_text(text)
    assert detect_format(tmp_path / "f") == fmt


# -- pairing -------------------------------------------------------------------------------------


def _two_csvs(tmp_path, dist_rows, ref_rows):
    (tmp_path / "d.csv").write_text("corner,x,y\n" + "".join(f"{r}\n" for r in dist_rows))
    (tmp_path / "r.csv").write_text("corner,x,y\n" + "".join(f"{r}\n" for r in ref_rows))
    return tmp_path / "d.csv", tmp_path / "r.csv"


def test_pairing_errors_name_the_file_and_landmark(tmp_path):
    d, r = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "A,3,9"], ["A,1,1", "B,5,5"])
    with pytest.raises(InputFileError, match=r"d.csv: line 4: corner 'A' is already used at line 2"):
        read_landmark_pairs(d, r, pair_by="corner")
    d, r = _two_csvs(tmp_path, ["A,1,2", ",5,1"], ["A,1,1"])
    with pytest.raises(InputFileError, match=r"d.csv: line 3: attribute 'corner' is empty"):
        read_landmark_pairs(d, r, pair_by="corner")
    d, r = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "C,3,9"], ["D,1,1", "E,5,5", "F,2,7"])
    with pytest.raises(DataError, match="no corner value is on both sides"):
        read_landmark_pairs(d, r, pair_by="corner")
    with pytest.raises(InputFileError, match="no attribute 'label' to pair by"):
        read_landmark_pairs(d, r, pair_by="label")
    with pytest.raises(InputFileError, match=r"pair up: by an attribute, pair_by \(attributes on every"):
        read_landmark_pairs(d, r)
    d, r = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "C,3,9"], ["A,1,1", "B,5,5"])
    with pytest.raises(DataError, match="has 3 landmarks but .*r.csv has 2; pairing by order"):
        read_landmark_pairs(d, r, pair_by_order=True)


def test_pair_by_order_and_duplicate_points(tmp_path):
    d, r = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "C,3,9"], ["x,0,0", "y,6,1", "z,2,8"])
    pairs = read_landmark_pairs(d, r, pair_by_order=True)
    assert pairs.ids == ("0", "1", "2")
    assert pairs.xy_u[2].tolist() == [2, 8] and pairs.xy_d[2].tolist() == [3, 9]
    d, r = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "C,1,2"], ["A,0,0", "B,6,1", "C,2,8"])
    with pytest.raises(DataError, match=r"d.csv: line 2 and line 4: two distorted landmarks at the same"):
        read_landmark_pairs(d, r, pair_by="corner")


def test_distorted_only_for_correcting_points(tmp_path):
    d, _ = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "C,3,9"], [])
    pairs = read_landmark_pairs(d, pair_by="corner", require=("x_d", "y_d"))
    assert pairs.ids == ("A", "B", "C") and np.isnan(pairs.xy_u).all()
    with pytest.raises(InputFileError, match="holds the distorted landmarks only"):
        read_landmark_pairs(d, pair_by="corner")


def test_via_file_holding_both_images(tmp_path, pairs):
    ids = [f"c{i}" for i in range(len(pairs.xy_u))]
    path = via2_json(tmp_path / "both.json", {"cam.png": labelled(pairs.xy_d, ids),
                                               "ref.png": labelled(pairs.xy_u, ids)})  # fmt: skip
    got = read_landmark_pairs(path, pair_by="corner", distorted_image="cam.png", reference_image="ref.png")
    np.testing.assert_allclose(got.xy_u, pairs.xy_u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.xy_d, pairs.xy_d, rtol=0, atol=1e-12)
    assert got.source == str(path)


# -- every format gives the same pairs; the acceptance test --------------------------------------


def _format_files(tmp_path, pairs, fmt):
    """Distorted and reference files of ``fmt`` with the reference landmarks shuffled."""
    n = len(pairs.xy_u)
    ids = [f"c{i}" for i in range(n)]
    order = np.random.default_rng(5).permutation(n)
    d = labelled(pairs.xy_d, ids)
    r = [labelled(pairs.xy_u, ids)[i] for i in order]
    if fmt == "via2-json":
        return via2_json(tmp_path / "d.json", {"cam.png": d}), via2_json(tmp_path / "r.json", {"ref.png": r})
    if fmt == "via2-csv":
        return via2_csv(tmp_path / "d.csv", {"cam.png": d}), via2_csv(tmp_path / "r.csv", {"ref.png": r})
    if fmt == "via3":
        return via3_json(tmp_path / "d.json", {"cam.png": d}), via3_json(tmp_path / "r.json", {"ref.png": r})
    if fmt == "napari":
        return napari_csv(tmp_path / "d.csv", d), napari_csv(tmp_path / "r.csv", r)
    if fmt == "csv":
        return plain_csv(tmp_path / "d.csv", d), plain_csv(tmp_path / "r.tsv", r, delimiter="\t")
    raise AssertionError(fmt)


@pytest.mark.parametrize("fmt", ["via2-json", "via2-csv", "via3", "napari", "csv"])
def test_every_format_recovers_the_pairs(tmp_path, pairs, fmt):
    d, r = _format_files(tmp_path, pairs, fmt)
    got = read_landmark_pairs(d, r, pair_by="corner")
    assert got.ids == tuple(f"c{i}" for i in range(len(pairs.xy_u)))
    np.testing.assert_allclose(got.xy_u, pairs.xy_u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.xy_d, pairs.xy_d, rtol=0, atol=1e-12)


def test_bigwarp_recovers_the_pairs(tmp_path, pairs):
    path = bigwarp_csv(tmp_path / "bw.csv", pairs.xy_d, pairs.xy_u)
    got = read_landmark_pairs(path)
    np.testing.assert_array_equal(got.xy_u, pairs.xy_u)
    np.testing.assert_array_equal(got.xy_d, pairs.xy_d)


def test_fit_from_via_export_equals_fit_from_plain_csv(run_cli, tmp_path, pairs):
    d, r = _format_files(tmp_path, pairs, "via2-json")
    plain = tmp_path / "points.csv"
    write_point_pairs(plain, pairs.xy_u, pairs.xy_d)
    code, out_via, err = run_cli("fit", "--distorted", d, "--reference", r, "--pair-by", "corner",
                                 "--out", tmp_path / "via.json", "--json")  # fmt: skip
    assert code == 0, err
    code, out_csv, err = run_cli("fit", plain, "--out", tmp_path / "csv.json", "--json")
    assert code == 0, err
    via, ref = json.loads(out_via), json.loads(out_csv)
    assert via["free"] == ref["free"]
    for name, value in ref["params"].items():
        assert via["params"][name] == pytest.approx(value, rel=1e-9, abs=1e-12), name
    # The residuals go through the iterative inverse, which stops within its tolerance
    # (1e-10 px, or the model's rounding level): the two files list the points in another
    # order, so sums round differently and the max residual moved by 1.7e-9 relative
    # (1.8e-9 px) between runs with freshly compiled and cached kernels.
    for key, value in ref["residuals"].items():
        assert via["residuals"][key] == pytest.approx(value, rel=1e-8, abs=1e-12), key


# -- command line --------------------------------------------------------------------------------


def test_landmarks_convert_writes_ids_and_reports_unpaired(run_cli, tmp_path):
    d, r = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "C,3,9", "Q,7,7"], ["C,2,8", "A,0,0", "B,6,1"])
    out = tmp_path / "points.csv"
    code, stdout, err = run_cli("landmarks", "convert", "--distorted", d, "--reference", r,
                                "--pair-by", "corner", "--out", out)  # fmt: skip
    assert code == 0, err
    assert "wrote 3 point pairs" in stdout
    assert err == "oapcal: warning: 1 distorted landmark has no reference partner and is not used: Q\n"
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["id"], r["x_u"], r["y_u"], r["x_d"], r["y_d"]) for r in rows] == [
        ("A", "0.0", "0.0", "1.0", "2.0"),
        ("B", "6.0", "1.0", "5.0", "1.0"),
        ("C", "2.0", "8.0", "3.0", "9.0"),
    ]


def test_correct_points_from_distorted_landmarks(run_cli, tmp_path, pairs):
    plain = tmp_path / "points.csv"
    write_point_pairs(plain, pairs.xy_u, pairs.xy_d)
    assert run_cli("fit", plain, "--out", tmp_path / "cal.json")[0] == 0
    d, _ = _format_files(tmp_path, pairs, "napari")
    out = tmp_path / "corrected.csv"
    code, _, err = run_cli("correct-points", tmp_path / "cal.json", "--distorted", d, "--pair-by", "corner",
                           "--out", out)  # fmt: skip
    assert code == 0, err
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["id", "x_d", "y_d", "x_c", "y_c", "converged"] and rows[3]["id"] == "c3"
    xy_c = np.array([[float(r["x_c"]), float(r["y_c"])] for r in rows])
    assert np.hypot(*(xy_c - pairs.xy_u).T).mean() < 0.6  # corrected onto the references


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["fit", "{points}", "--distorted", "{d}"], "either POINTS or --distorted/--reference"),
        (["fit"], "give a point-pair file POINTS, or landmark files"),
        (["fit", "--reference", "{r}"], "--reference needs --distorted FILE too"),
        (["fit", "{points}", "--pair-by", "corner"], "--pair-by applies to --distorted/--reference"),
        (["fit", "--distorted", "{d}", "--reference", "{r}", "--pair-by", "c", "--pair-by-order"],
         "not both"),
        (["fit", "--distorted", "{d}", "--reference", "{r}"], "say how landmarks pair up"),
        (["fit", "--distorted", "{d}", "--reference", "{r}", "--pair-by", "corner", "--out", "{d}"],
         "would overwrite the input"),
        (["landmarks", "convert", "--out", "{tmp}/o.csv"], "give the landmark files"),
        (["landmarks", "convert", "--distorted", "{d}", "--reference", "{r}", "--pair-by", "corner",
          "--out", "{r}"], "would overwrite the input"),
        (["landmarks", "convert", "--distorted", "{d}", "--reference", "{r}", "--format", "via",
          "--pair-by", "corner", "--out", "{tmp}/o.csv"], "line 1: not a VIA file"),
    ],
)  # fmt: skip
def test_usage_errors_are_one_line_exit_2_and_write_nothing(run_cli, tmp_path, args, pattern):
    d, r = _two_csvs(tmp_path, ["A,1,2", "B,5,1", "C,3,9"], ["C,2,8", "A,0,0", "B,6,1"])
    points = tmp_path / "points.csv"
    points.write_text("x_u,y_u,x_d,y_d\n0,0,0,0\n1,0,1,0\n0,1,0,1\n")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    code, _, err = run_cli(*(a.format(points=points, d=d, r=r, tmp=tmp_path) for a in args))
    assert code == 2
    assert err.count("\n") == 1 and pattern in err and "Traceback" not in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
