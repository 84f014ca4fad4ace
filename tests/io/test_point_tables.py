"""``correct-points`` on tables of tracks: trackpy and TrackMate files as those tools write
them, any CSV/TSV/parquet with named x/y columns, every column kept, NaN rows kept, px or um;
and the same on a pandas DataFrame.

Each corrected point is checked against the forward model: ``distort(x_c) = x_d`` (in px),
which the inverse under test does not compute."""

import csv
import io

import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.io.calibration import load_calibration, save_calibration
from oapcal.model import distort
from oapcal.synthetic import synthetic_pairs

pd = pytest.importorskip("pandas", reason="pandas comes with the 'tables' extra")

UM_PER_PX = 2.0


@pytest.fixture(scope="module")
def calib(tmp_path_factory):
    data = synthetic_pairs(n_x=8, n_y=6, seed=1)
    cal = calibrate(data.xy_u, data.xy_d, "paper", um_per_px=UM_PER_PX, image_size=(640, 480))
    path = tmp_path_factory.mktemp("cal") / "cal.json"
    save_calibration(cal, path)
    return path


def _forward_error(cal, xy_c_px, xy_d_px) -> float:
    return float(np.abs(distort(np.asarray(xy_c_px, float), cal.params) - xy_d_px).max())


def _trackpy_frame():
    """A table shaped like trackpy's ``link`` output (its column order), with a lost
    particle (NaN position) and trackpy's usual NaN in ``ep``."""
    rng = np.random.default_rng(4)
    n = 12
    frame = pd.DataFrame(
        {
            "y": rng.uniform(60, 420, n),
            "x": rng.uniform(60, 580, n),
            "mass": rng.uniform(800, 2000, n),
            "size": rng.uniform(1.5, 2.5, n),
            "ecc": rng.uniform(0, 0.2, n),
            "signal": rng.uniform(20, 40, n),
            "raw_mass": rng.uniform(7000, 9000, n),
            "ep": rng.uniform(0, 0.05, n),
            "frame": np.repeat(np.arange(6), 2),
            "particle": np.tile([0, 1], 6),
        }
    )
    frame.loc[5, ["x", "y"]] = np.nan
    frame.loc[3, "ep"] = np.nan
    return frame


def test_trackpy_csv_keeps_every_column_and_row(run_cli, calib, tmp_path):
    tracks = _trackpy_frame()
    tracks.to_csv(tmp_path / "tracks.csv")  # as trackpy users save: pandas, with the index column
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "tracks.csv",
        "--preset",
        "trackpy",
        "--out",
        tmp_path / "out.csv",
    )
    assert code == 0, err
    assert "1 of 12 rows have no point" in err
    src = (tmp_path / "tracks.csv").read_text().splitlines()
    out = (tmp_path / "out.csv").read_text().splitlines()
    assert out[0] == src[0] + ",x_c,y_c,converged"
    assert len(out) == len(src)
    for a, b in zip(src[1:], out[1:]):
        assert b.startswith(a + ","), (a, b)  # every cell copied through as it was
    back = pd.read_csv(tmp_path / "out.csv", index_col=0)
    assert list(back.columns) == list(tracks.columns) + ["x_c", "y_c", "converged"]
    assert np.isnan(back.loc[5, ["x_c", "y_c", "converged"]].to_numpy(float)).all()
    good = back.drop(index=5)
    assert (good["converged"] == 1).all()
    cal = load_calibration(calib)
    err_px = _forward_error(cal, good[["x_c", "y_c"]], good[["x", "y"]].to_numpy())
    assert err_px < 1e-8
    # the correction is not the identity: this calibration moves these points by pixels
    assert np.hypot(good.x_c - good.x, good.y_c - good.y).max() > 1.0


TRACKMATE_HEADER = (
    "LABEL,ID,TRACK_ID,QUALITY,POSITION_X,POSITION_Y,POSITION_Z,POSITION_T,FRAME,RADIUS,VISIBILITY,"
    "MANUAL_SPOT_COLOR,MEAN_INTENSITY_CH1\n"
    "Label,Spot ID,Track ID,Quality,X,Y,Z,T,Frame,Radius,Visibility,Manual spot color,Mean intensity ch1\n"
    "Label,Spot ID,Track ID,Quality,X,Y,Z,T,Frame,R,Visibility,Spot color,Mean ch1\n"
    ",,,(quality),({unit}),({unit}),({unit}),(sec),,({unit}),,,(counts)\n"
)


def _trackmate_csv(path, unit="micron", scale=UM_PER_PX):
    """A TrackMate 7 'Spots' CSV export: the feature keys, then the feature names, short
    names and units rows, then one spot per row (in calibrated units)."""
    rng = np.random.default_rng(7)
    lines = [TRACKMATE_HEADER.format(unit=unit)]
    xy_px = rng.uniform([50, 50], [590, 430], (8, 2))
    for i, (x, y) in enumerate(xy_px.tolist()):
        lines.append(
            f"ID{i},{i},{i % 2},{10 + i}.5,{x * scale!r},{y * scale!r},0.0,{i * 0.1:.1f},{i // 2},"
            f"{2.5 * scale},1,,{100 + i}.25\n"
        )
    path.write_text("".join(lines))
    return xy_px


def test_trackmate_export_in_um(run_cli, calib, tmp_path):
    xy_px = _trackmate_csv(tmp_path / "spots.csv")
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "spots.csv",
        "--preset",
        "trackmate",
        "--out",
        tmp_path / "out.csv",
    )
    assert code == 0, err
    rows = list(csv.reader(io.StringIO((tmp_path / "out.csv").read_text())))
    src = list(csv.reader(io.StringIO((tmp_path / "spots.csv").read_text())))
    assert rows[0] == src[0] + ["x_c", "y_c", "converged"]
    assert rows[1] == src[1] + ["X corrected", "Y corrected", "Converged"]
    assert rows[3] == src[3] + ["(micron)", "(micron)", ""]  # the units row, extended
    assert [r[:-3] for r in rows[4:]] == src[4:]
    xy_c_um = np.array([[float(r[-3]), float(r[-2])] for r in rows[4:]])
    cal = load_calibration(calib)
    # um in, camera px = um / 2; out in the calibration's object-space um (its um_per_px = 2)
    assert _forward_error(cal, xy_c_um / UM_PER_PX, xy_px) < 1e-8
    # the units row says micron: --units px contradicts it
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "spots.csv",
        "--preset",
        "trackmate",
        "--units",
        "px",
        "--out",
        tmp_path / "o2.csv",
    )
    assert code == 2 and "units row gives the positions in um" in err and err.count("\n") == 1, err


def test_trackmate_pixel_units_and_tracker_pixel_size(run_cli, calib, tmp_path):
    xy_px = _trackmate_csv(tmp_path / "px.csv", unit="pixel", scale=1.0)
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "px.csv",
        "--preset",
        "trackmate",
        "--out",
        tmp_path / "px_out.csv",
    )
    assert code == 0, err
    out = pd.read_csv(tmp_path / "px_out.csv", skiprows=[1, 2, 3])
    cal = load_calibration(calib)
    assert _forward_error(cal, out[["x_c", "y_c"]].to_numpy(), xy_px) < 1e-8
    # a tracker that was given 2.5 um/px: positions / 2.5 are camera px; x_c in the calibration's um
    xy = _trackmate_csv(tmp_path / "um.csv", unit="micron", scale=2.5)
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "um.csv",
        "--preset",
        "trackmate",
        "--units",
        "um",
        "--table-um-per-px",
        "2.5",
        "--out",
        tmp_path / "um_out.tsv",
    )
    assert code == 0, err
    out = pd.read_csv(tmp_path / "um_out.tsv", sep="\t", skiprows=[1, 2, 3])
    assert _forward_error(cal, out[["x_c", "y_c"]].to_numpy() / UM_PER_PX, xy) < 1e-8


def test_any_tsv_with_named_columns_and_corner_origin(run_cli, calib, tmp_path):
    text = "Track\tX (px)\tY (px)\tnote\na\t120.5\t80.5\tfirst\na\tNaN\tNaN\tlost\nb\t400.5\t300.5\t\n"
    (tmp_path / "t.tsv").write_text(text)
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "t.tsv",
        "--x-column",
        "X (px)",
        "--y-column",
        "Y (px)",
        "--pixel-origin",
        "corner",
        "--out",
        tmp_path / "o.tsv",
    )
    assert code == 0, err
    rows = [line.split("\t") for line in (tmp_path / "o.tsv").read_text().splitlines()]
    assert rows[0] == ["Track", "X (px)", "Y (px)", "note", "x_c", "y_c", "converged"]
    assert rows[2] == ["a", "NaN", "NaN", "lost", "", "", ""]
    cal = load_calibration(calib)
    xy_c = np.array([[float(rows[i][4]), float(rows[i][5])] for i in (1, 3)])
    # corner origin: oapcal's px are the file's minus 0.5, and x_c comes back in the file's convention
    assert _forward_error(cal, xy_c - 0.5, np.array([[120.0, 80.0], [400.0, 300.0]])) < 1e-8


def test_parquet_in_and_out(run_cli, calib, tmp_path):
    pytest.importorskip("pyarrow", reason="pyarrow comes with the 'tables' extra")
    tracks = _trackpy_frame()
    tracks.to_parquet(tmp_path / "t.parquet")
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "t.parquet",
        "--preset",
        "trackpy",
        "--out",
        tmp_path / "o.parquet",
    )
    assert code == 0, err
    back = pd.read_parquet(tmp_path / "o.parquet")
    pd.testing.assert_frame_equal(back[tracks.columns], tracks)
    assert back["converged"].dtype == "boolean" and back["converged"].isna().tolist() == [
        i == 5 for i in range(12)
    ]
    cal = load_calibration(calib)
    good = back.drop(index=5)
    assert _forward_error(cal, good[["x_c", "y_c"]], good[["x", "y"]].to_numpy()) < 1e-8
    # a CSV input cannot become parquet (its cells are text): one line, nothing written
    tracks.to_csv(tmp_path / "t.csv")
    code, _, err = run_cli(
        "correct-points",
        calib,
        "--distorted",
        tmp_path / "t.csv",
        "--preset",
        "trackpy",
        "--out",
        tmp_path / "o2.parquet",
    )
    assert code == 2 and "give a .csv or .tsv output" in err and not (tmp_path / "o2.parquet").exists()


def test_dataframe_function_matches_the_command(run_cli, calib, tmp_path):
    from oapcal.io.tables import correct_points_frame

    cal = load_calibration(calib)
    tracks = _trackpy_frame()
    out = correct_points_frame(tracks, cal, preset="trackpy")
    pd.testing.assert_frame_equal(out[tracks.columns], tracks)
    tracks.to_csv(tmp_path / "t.csv")
    assert (
        run_cli(
            "correct-points",
            calib,
            "--distorted",
            tmp_path / "t.csv",
            "--preset",
            "trackpy",
            "--out",
            tmp_path / "o.csv",
        )[0]
        == 0
    )
    cli = pd.read_csv(tmp_path / "o.csv", index_col=0)
    np.testing.assert_array_equal(out[["x_c", "y_c"]].to_numpy(), cli[["x_c", "y_c"]].to_numpy())
    # um: x, y in um at the calibration's pixel size; x_c in um
    um = tracks.assign(x=tracks.x * UM_PER_PX, y=tracks.y * UM_PER_PX)
    out_um = correct_points_frame(um, cal, preset="trackpy", units="um")
    np.testing.assert_allclose(
        out_um[["x_c", "y_c"]].to_numpy(), out[["x_c", "y_c"]].to_numpy() * UM_PER_PX, rtol=1e-12
    )


@pytest.mark.parametrize(
    "text,args,message",
    [
        ("x,y,f\n1,2,0\nabc,3,1\n", [], "line 3, column 'x': 'abc' is not a number"),
        ("x,y,f\n1,2,0\ninf,3,1\n", [], "line 3, column 'x': inf is not a finite number"),
        ("xx,y\n1,2\n", [], "no column 'x' (did you mean 'xx'?)"),
        ("x,y\n1,2\n", ["--pair-by", "corner"], "--pair-by corner: no such column"),
        ("x,y\n1,2\n", ["--units", "um", "--table-um-per-px", "0"], "--table-um-per-px"),
    ],
)
def test_table_mistakes_are_one_line(run_cli, calib, tmp_path, text, args, message):
    (tmp_path / "t.csv").write_text(text)
    code, _, err = run_cli(
        "correct-points", calib, "--distorted", tmp_path / "t.csv", *args, "--out", tmp_path / "o.csv"
    )
    assert code == 2 and err.startswith("oapcal: error: ") and err.count("\n") == 1, err
    assert message in err, err
    assert not (tmp_path / "o.csv").exists()


def test_um_needs_a_calibration_with_a_pixel_size(run_cli, tmp_path):
    data = synthetic_pairs(n_x=6, n_y=5, seed=2)
    save_calibration(calibrate(data.xy_u, data.xy_d, "paper"), tmp_path / "c.json")
    (tmp_path / "t.csv").write_text("x,y\n100,200\n")
    code, _, err = run_cli(
        "correct-points",
        tmp_path / "c.json",
        "--distorted",
        tmp_path / "t.csv",
        "--units",
        "um",
        "--out",
        tmp_path / "o.csv",
    )
    assert code == 2 and "has no um_per_px" in err and "(set by --units)" in err, err
