from pathlib import Path

import numpy as np
import pytest

from oapcal.errors import DataError, InputFileError
from oapcal.io.points import read_points, write_point_pairs

GOOD = "id,x_u,y_u,x_d,y_d,extra\na,0,0,1,1,x\nb,10,0,11,1,y\nc,0,10,1,12,z\n"


def write(tmp_path, text, name="p.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_reads_pairs_ids_and_keeps_other_columns(tmp_path):
    pts = read_points(write(tmp_path, GOOD))
    np.testing.assert_array_equal(pts.xy_u, [[0, 0], [10, 0], [0, 10]])
    np.testing.assert_array_equal(pts.xy_d, [[1, 1], [11, 1], [1, 12]])
    assert pts.ids == ("a", "b", "c") and pts.rows[2]["extra"] == "z" and pts.lines == (2, 3, 4)


def test_tab_separated(tmp_path):
    pts = read_points(write(tmp_path, GOOD.replace(",", "\t")))
    assert len(pts) == 3


def test_round_trip(tmp_path, pairs):
    p = tmp_path / "out.csv"
    write_point_pairs(p, pairs.xy_u, pairs.xy_d, ids=range(len(pairs.xy_u)))
    back = read_points(p)
    np.testing.assert_array_equal(back.xy_u, pairs.xy_u)
    np.testing.assert_array_equal(back.xy_d, pairs.xy_d)


@pytest.mark.parametrize(
    "text,pattern",
    [
        ("x_u,y_u,x_dd,y_d\n0,0,1,1\n", r"line 1: missing column 'x_d' \(found 'x_dd': rename it\)"),
        ("x_u,y_u,x_d,y_d\n0,0,abc,1\n", r"line 2, column 'x_d': 'abc' is not a number"),
        ("x_u,y_u,x_d,y_d\n0,0,,1\n", r"line 2, column 'x_d': an empty cell is not a number"),
        ("x_u,y_u,x_d,y_d\n0,0,1,1\n0,nan,1,1\n", r"line 3, column 'y_u': nan is not a finite"),
        ("x_u,y_u,x_d,y_d\n0,0,1,inf\n", r"line 2, column 'y_d': inf is not a finite"),
        ("", r"is empty"),
        ("x_u,y_u,x_d,y_d\n", r"no data rows"),
        ("x_u,y_u,x_d,y_d\n1,2,3\n", r"line 2: 3 cells but the header has 4"),
        ("id,x_u,y_u,x_d,y_d\na,0,0,1,1\na,1,1,2,2\n", r"line 3: id 'a' already used on line 2"),
    ],
)
def test_bad_files_name_the_line_and_column(tmp_path, text, pattern):
    path = write(tmp_path, text)
    with pytest.raises(InputFileError, match=pattern) as err:
        read_points(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_duplicated_and_collinear_points(tmp_path):
    dup = "x_u,y_u,x_d,y_d\n0,0,1,1\n5,5,6,7\n0,0,2,2\n"
    with pytest.raises(DataError, match="lines 2 and 4 have the same reference point"):
        read_points(write(tmp_path, dup))
    line = "x_u,y_u,x_d,y_d\n0,0,0,0\n1,1,1,1.5\n2,2,2,2.5\n3,3,3,3.1\n"
    with pytest.raises(DataError, match="all reference points lie on one line"):
        read_points(write(tmp_path, line))


def test_missing_binary_and_non_utf8_files(tmp_path):
    with pytest.raises(InputFileError, match="no such file"):
        read_points(tmp_path / "nope.csv")
    (tmp_path / "b.csv").write_bytes(b"x_u,y_u\x00\x01")
    with pytest.raises(InputFileError, match="binary"):
        read_points(tmp_path / "b.csv")
    (tmp_path / "l.csv").write_bytes("x_u,y_u,x_d,y_d\n\xe9".encode("latin-1"))
    with pytest.raises(InputFileError, match="not UTF-8"):
        read_points(tmp_path / "l.csv")


def test_only_required_columns(tmp_path):
    pts = read_points(write(tmp_path, "x_d,y_d\n1,2\n3,5\n4,1\n"), require=("x_d", "y_d"))
    assert np.isnan(pts.xy_u).all() and pts.xy_d.shape == (3, 2)


def test_points_spread_below_float_resolution_are_refused(tmp_path):
    """Issue 14 item 6: coordinates near 1e-300 once fitted to k1 = inf with exit 0."""

    path = tmp_path / "tiny.csv"
    path.write_text(
        "x_u,y_u,x_d,y_d\n0,0,0,0\n1e-300,0,1e-300,0\n0,1e-300,0,1e-300\n1e-300,1e-300,1e-300,1e-300\n"
    )
    with pytest.raises(DataError, match=r"tiny\.csv: the reference points spread over only 1e-300 x 1e-300"):
        read_points(path)


def test_landmarks_spread_below_float_resolution_are_refused(tmp_path):
    from oapcal.io.landmarks import read_landmark_pairs

    (tmp_path / "d.csv").write_text("id,x,y\na,0,0\nb,1e-300,0\nc,0,1e-300\nd,1e-300,1e-300\n")
    (tmp_path / "r.csv").write_text("id,x,y\na,0,0\nb,10,0\nc,0,10\nd,10,10\n")
    with pytest.raises(DataError, match=r"d\.csv: the paired distorted landmark points spread over only"):
        read_landmark_pairs(tmp_path / "d.csv", tmp_path / "r.csv", pair_by="id")


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom"])
def test_devices_are_refused_without_reading_them_whole(device):
    """Issue 14 item 20: the 64 MiB limit was checked with stat, which says 0 for a device."""
    if not Path(device).exists():
        pytest.skip(f"{device} is absent on this system")
    with pytest.raises(InputFileError, match=f"{device}: contains binary data"):
        read_points(device)


def test_an_endless_text_stream_is_cut_at_the_limit(monkeypatch):
    import io

    import oapcal.io.userfile as userfile

    class Endless(io.RawIOBase):
        def readable(self):
            return True

        def readinto(self, buf):
            buf[:] = b"a" * len(buf)
            return len(buf)

    monkeypatch.setattr(userfile, "MAX_FILE_BYTES", 3 * 2**20)
    stdin = io.TextIOWrapper(io.BufferedReader(Endless()))
    monkeypatch.setattr("sys.stdin", stdin)
    with pytest.raises(InputFileError, match="-: is over 3 MiB"):
        read_points("-")


def test_write_truth_keeps_every_corner_to_full_precision(tmp_path):
    from types import SimpleNamespace

    from oapcal.io.points import write_truth

    sim = SimpleNamespace(
        ids=["4.1.h.0", "4.1.h.1"],
        xy_u=np.array([[0.1, 1 / 3], [2.0, 3.0]]),
        xy_d=np.array([[0.2, 2 / 3], [-1.5, 1e-17]]),
        visible=np.array([True, False]),
    )
    write_truth(tmp_path / "t.csv", sim)
    assert (tmp_path / "t.csv").read_text().splitlines() == [
        "id,x_u,y_u,x_d,y_d,visible",
        "4.1.h.0,0.1,0.3333333333333333,0.2,0.6666666666666666,1",
        "4.1.h.1,2.0,3.0,-1.5,1e-17,0",
    ]
    back = read_points(tmp_path / "t.csv")
    np.testing.assert_array_equal(back.xy_d, sim.xy_d)
