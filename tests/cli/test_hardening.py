"""Malformed input never crashes oapcal: every loader and every command either works or
fails with one line naming the problem, exit code 2, and nothing written.

The harness is two tables: ``LOADERS`` (library readers) and ``COMMANDS`` (command lines
with one fuzzed file).  Adding a command is one line in ``COMMANDS``: its argv with
``{bad}`` where the fuzzed file goes, ``{out}`` for the output directory, and the other
files by seed name.  ``tests/data/bad/`` is a corpus of bad files with the message each
must give (``expected.json``).
"""

import json
import re
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from landmark_writers import bigwarp_csv, labelled, napari_csv, via2_csv, via2_json, via3_json
from oapcal.calibration import calibrate
from oapcal.errors import OapcalError
from oapcal.io.calibration import load_calibration, save_calibration
from oapcal.io.landmarks import read_landmark_pairs, read_landmarks
from oapcal.io.points import read_points, write_point_pairs
from oapcal.synthetic import synthetic_pairs
from paths import DATA

BAD = DATA / "bad"

# -- good seed files, which the strategies break -------------------------------------------------


def _make_seeds(directory: Path) -> dict[str, Path]:
    data = synthetic_pairs(n_x=5, n_y=4, seed=3)
    ids = [f"c{i}" for i in range(len(data.xy_u))]
    d, r = labelled(data.xy_d, ids), labelled(data.xy_u, ids)
    seeds = {
        "points": directory / "points.csv",
        "calib": directory / "calib.json",
        "via2": via2_json(directory / "dist.json", {"cam.png": d}),
        "via2_ref": via2_json(directory / "ref.json", {"ref.png": r}),
        "via2csv": via2_csv(directory / "dist_via.csv", {"cam.png": d}),
        "via3": via3_json(directory / "dist_via3.json", {"cam.png": d}),
        "napari": napari_csv(directory / "dist_napari.csv", d),
        "bigwarp": bigwarp_csv(directory / "bigwarp.csv", data.xy_d, data.xy_u),
    }
    write_point_pairs(seeds["points"], data.xy_u, data.xy_d, ids=ids)
    save_calibration(calibrate(data.xy_u, data.xy_d, um_per_px=4.8, image_size=(640, 480)), seeds["calib"])
    # a camera image of the USAF target (for correct, esf, detect)
    import cv2

    from oapcal.imaging.simulate import simulate_image

    seeds["png"] = directory / "usaf.png"
    cv2.imwrite(str(seeds["png"]), simulate_image((4, 5), sigma_px=0.8, snr=50, seed=1).image)
    return seeds


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return _make_seeds(tmp_path_factory.mktemp("seeds"))


# -- the tables ----------------------------------------------------------------------------------

#: name -> (seed kind the fuzzed file starts from, reader of a path)
LOADERS = {
    "read_points": ("points", read_points),
    "read_points distorted only": ("points", lambda p: read_points(p, require=("x_d", "y_d"))),
    "load_calibration": ("calib", load_calibration),
    "VIA 2 JSON": ("via2", lambda p: read_landmarks(p, "via")),
    "VIA 2 CSV": ("via2csv", lambda p: read_landmarks(p, "via")),
    "VIA 3 JSON": ("via3", lambda p: read_landmarks(p, "via")),
    "napari": ("napari", lambda p: read_landmarks(p, "napari")),
    "bigwarp": ("bigwarp", lambda p: read_landmark_pairs(p, fmt="bigwarp")),
    "auto-detected landmarks": ("napari", read_landmarks),
    "plain CSV landmarks": ("points", lambda p: read_landmarks(p, "csv", x_column="x_d", y_column="y_d")),
}

#: name -> (seed kind of the fuzzed file, argv).  One line per command and fuzzed input.
COMMANDS = {
    "fit POINTS": ("points", "fit {bad} --out {out}/c.json"),
    "fit --distorted": ("via2", "fit --distorted {bad} --reference {via2_ref} --pair-by corner "
                        "--out {out}/c.json"),
    "fit --reference": ("via2_ref", "fit --distorted {via2} --reference {bad} --pair-by corner "
                        "--out {out}/c.json"),
    "fit bigwarp": ("bigwarp", "fit --distorted {bad} --out {out}/c.json"),
    "correct-points CALIB": ("calib", "correct-points {bad} {points} --out {out}/p.csv"),
    "correct-points POINTS": ("points", "correct-points {calib} {bad} --out {out}/p.csv"),
    "correct-points --distorted": ("napari", "correct-points {calib} --distorted {bad} --out {out}/p.csv"),
    "landmarks convert VIA 3": ("via3", "landmarks convert --distorted {bad} --reference {via2_ref} "
                                "--pair-by corner --out {out}/p.csv"),
    "landmarks convert VIA CSV": ("via2csv", "landmarks convert --distorted {bad} --reference {via2_ref} "
                                  "--pair-by corner --out {out}/p.csv"),
    "select POINTS": ("points", "select {bad} --json {out}/s.json"),
    "robustness POINTS": ("points", "robustness {bad} --models paper --trials 20 --json {out}/r.json"),
    "correct CALIB": ("calib", "correct {bad} {png} --out-dir {out}/c"),
    "correct IMAGE": ("png", "correct {calib} {bad} --out-dir {out}/c"),
    "export-opencv CALIB": ("calib", "export-opencv {bad} --image-size 640x480 --out {out}/cv.json"),
    "esf IMAGE": ("png", "esf {bad} --auto --plot {out}/e.png"),
    "report CALIB": ("calib", "report {bad} --out {out}/r.html"),
    "report POINTS": ("points", "report {calib} --points {bad} --out {out}/r.html"),
    "simulate image CALIB": ("calib", "simulate image --calibration {bad} --image-size 160x120 --groups 4 "
                             "--out {out}/x.png"),
    "detect IMAGE": ("png", "detect {bad} --target usaf --groups 4-5 --um-per-px 4.8 --out {out}/p.csv"),
}  # fmt: skip

#: Rows whose intact-file run takes seconds (plots, detection, many fits): fuzzed only in the
#: slow job, where a fuzzed file that stays valid costs a full run.
HEAVY = {"robustness POINTS", "esf IMAGE", "report CALIB", "report POINTS", "detect IMAGE", "select POINTS"}
LIGHT = [n for n in COMMANDS if n not in HEAVY]

# -- strategies ----------------------------------------------------------------------------------

BAD_TOKENS = [
    "", "nan", "NaN", "inf", "-Infinity", "1e999", "-1e308", "1e300", "9" * 5000, "0x1F", "abc", '"', "'",
    "{", "}", "[", "]", ",", ":", "\n", "\t", "null", "true", "[]", "{}", '{"a": [1]}', "é", "\u2028",
    "\x00", '"point"', '"rect"', "-", "1,2",
]  # fmt: skip
_TOKEN = re.compile(rb'-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?|"[^"\n]*"|[{}\[\],:\n]|true|false|null')


@st.composite
def malformed(draw, seed: bytes) -> bytes:
    """A broken version of ``seed``: truncated, junk, a token replaced or inserted,
    re-encoded, emptied, or lines dropped / repeated."""
    how = draw(st.sampled_from(["truncate", "junk", "replace", "replace", "insert", "encoding", "lines"]))
    if how == "truncate":
        return seed[: draw(st.integers(0, max(len(seed) - 1, 0)))]
    if how == "junk":
        return draw(st.binary(max_size=300))
    if how in ("replace", "insert"):
        tokens = list(_TOKEN.finditer(seed))
        new = draw(st.one_of(st.sampled_from(BAD_TOKENS), st.text(max_size=12))).encode(
            "utf-8", "surrogatepass"
        )
        if tokens and how == "replace":
            for _ in range(draw(st.integers(1, 3))):
                m = draw(st.sampled_from(tokens))
                seed = seed[: m.start()] + new + seed[m.end() :]
                tokens = list(_TOKEN.finditer(seed)) or tokens
                if not tokens:
                    break
            return seed
        at = draw(st.integers(0, len(seed)))
        return seed[:at] + new + seed[at:]
    if how == "encoding":
        try:
            text = seed.decode("utf-8")
        except UnicodeDecodeError:  # a binary seed (an image): flip a few bytes instead
            data = bytearray(seed)
            for _ in range(draw(st.integers(1, 8))):
                at = draw(st.integers(0, max(len(data) - 1, 0)))
                data[at] ^= draw(st.integers(1, 255))
            return bytes(data)
        codec = draw(st.sampled_from(["utf-16", "utf-32", "latin-1", "cp1252"]))
        return (text.replace("c1", "é1") if codec in ("latin-1", "cp1252") else text).encode(codec)
    lines = seed.split(b"\n")
    keep = draw(st.lists(st.integers(0, len(lines) - 1), max_size=len(lines) + 3))
    return b"\n".join(lines[i] for i in keep)


def _check_loader(loader, path: Path) -> None:
    try:
        loader(path)
    except OapcalError as exc:
        msg = str(exc)
        assert msg.strip() and "\n" not in msg and "\r" not in msg, repr(msg)
        assert path.name in msg, f"message does not name the file: {msg!r}"


def _run_command(run_cli, argv: str, bad: bytes, kind: str, seeds: dict) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        out = tmp / "out"
        out.mkdir()
        bad_path = tmp / f"bad{seeds[kind].suffix}"
        bad_path.write_bytes(bad)
        names = {k: str(v) for k, v in seeds.items()} | {"bad": str(bad_path), "out": str(out)}
        code, stdout, err = run_cli(*(a.format(**names) for a in argv.split()))
        assert code in (0, 2, 3, 4), f"exit {code}: {err}"
        if code == 2:
            assert err.count("\n") == 1 and err.startswith("oapcal: error: "), repr(err)
            assert list(out.iterdir()) == [], "an output was written although the command failed"
        if code == 4:  # a batch (``correct``) that reported and skipped its bad inputs
            assert "oapcal: error: " in err and bad_path.name in err, repr(err)
            assert [p for p in out.rglob("*") if p.is_file()] == [], "a partial output was left"


_CHECKS = [HealthCheck.function_scoped_fixture, HealthCheck.too_slow]
FAST = settings(max_examples=25, deadline=None, database=None, suppress_health_check=_CHECKS)
SLOW = settings(max_examples=2000, deadline=None, database=None, suppress_health_check=_CHECKS)


# -- property tests ------------------------------------------------------------------------------


def _loader_property(name, seeds, data):
    kind, loader = LOADERS[name]
    bad = data.draw(malformed(seeds[kind].read_bytes()), label="file")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"fuzzed{seeds[kind].suffix}"
        path.write_bytes(bad)
        _check_loader(loader, path)


def _command_property(run_cli, name, seeds, data):
    kind, argv = COMMANDS[name]
    _run_command(run_cli, argv, data.draw(malformed(seeds[kind].read_bytes()), label="file"), kind, seeds)


@pytest.mark.parametrize("name", list(LOADERS))
@FAST
@given(data=st.data())
def test_loaders_fail_cleanly(seeds, name, data):
    _loader_property(name, seeds, data)


@pytest.mark.parametrize("name", LIGHT)
@settings(FAST, max_examples=12)
@given(data=st.data())
def test_commands_fail_cleanly(run_cli, seeds, name, data):
    _command_property(run_cli, name, seeds, data)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(LOADERS))
@SLOW
@given(data=st.data())
def test_loaders_fail_cleanly_long_run(seeds, name, data):
    _loader_property(name, seeds, data)


@pytest.mark.slow
@pytest.mark.parametrize("name", LIGHT)
@settings(SLOW, max_examples=400)
@given(data=st.data())
def test_commands_fail_cleanly_long_run(run_cli, seeds, name, data):
    _command_property(run_cli, name, seeds, data)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(HEAVY))
@settings(SLOW, max_examples=30)
@given(data=st.data())
def test_heavy_commands_fail_cleanly(run_cli, seeds, name, data):
    _command_property(run_cli, name, seeds, data)


def test_the_seeds_themselves_load(seeds):
    """The strategies start from good files (else the properties would test little)."""
    for name, (kind, loader) in LOADERS.items():
        if name != "plain CSV landmarks":
            loader(seeds[kind])


@pytest.mark.parametrize("name", list(COMMANDS))
def test_each_command_works_on_its_seed(run_cli, seeds, name, tmp_path):
    """Each command line of the table succeeds on the unbroken file, so its failures under
    fuzzing come from the breakage, not from a wrong command line."""
    kind, argv = COMMANDS[name]
    names = {k: str(v) for k, v in seeds.items()} | {"bad": str(seeds[kind]), "out": str(tmp_path)}
    code, _, err = run_cli(*(a.format(**names) for a in argv.split()))
    assert code == 0, err
    assert len(list(tmp_path.iterdir())) == 1


# -- the corpus of bad files ---------------------------------------------------------------------

_CORPUS = json.loads((BAD / "expected.json").read_text())
_REFERENCE = "corner,x,y\nA,0,0\nB,4,5\nC,8,0\nD,3,9\n"


def _corpus_loader(entry, tmp_path):
    kind = entry["loader"]
    if kind == "points":
        return read_points
    if kind == "calibration":
        return load_calibration
    if kind == "landmarks":
        return read_landmarks
    reference = tmp_path / "reference.csv"
    reference.write_text(_REFERENCE)
    return lambda p: read_landmark_pairs(p, reference, pair_by="corner")


def test_corpus_manifest_lists_every_file():
    on_disk = {p.name for p in BAD.iterdir()} - {"expected.json"}
    assert on_disk == set(_CORPUS)


@pytest.mark.parametrize("name", sorted(_CORPUS))
def test_corpus_file_gives_its_message(name, tmp_path):
    entry = _CORPUS[name]
    loader = _corpus_loader(entry, tmp_path)
    with pytest.raises(OapcalError) as err:
        loader(BAD / name)
    msg = str(err.value)
    assert entry["expect"] in msg and name in msg and "\n" not in msg


_CORPUS_COMMAND = {
    "points": "fit {bad} --out {out}/c.json",
    "calibration": "correct-points {bad} {points} --out {out}/p.csv",
    "landmarks": "landmarks convert --distorted {bad} --pair-by corner --out {out}/p.csv",
    "landmark_pairs": "fit --distorted {bad} --reference {reference} --pair-by corner --out {out}/c.json",
}


@pytest.mark.parametrize("name", sorted(_CORPUS))
def test_corpus_file_through_the_command_line(name, run_cli, seeds, tmp_path):
    entry = _CORPUS[name]
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "reference.csv").write_text(_REFERENCE)
    names = {k: str(v) for k, v in seeds.items()}
    names |= {"bad": str(BAD / name), "out": str(out), "reference": str(tmp_path / "reference.csv")}
    code, _, err = run_cli(*(a.format(**names) for a in _CORPUS_COMMAND[entry["loader"]].split()))
    assert code == 2 and err.count("\n") == 1 and entry["expect"] in err, err
    assert list(out.iterdir()) == []
