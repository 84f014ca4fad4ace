"""Hardening, round three (issue 24): group texts, tolerance and ESF limits checked before
any work, and messages that say what is wrong.  Every failure is one line on stderr, exit 2,
nothing written."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from oapcal.errors import DataError
from oapcal.imaging.usaf import HIGHEST_GROUP, LOWEST_GROUP, parse_groups


def one_error(code, err, expect_code=2):
    assert code == expect_code, err
    assert err.startswith("oapcal: error: ") and err.count("\n") == 1, repr(err)
    assert "internal error" not in err


# -- item 14 and 24: group texts --------------------------------------------------------------------

GROUP = st.integers(LOWEST_GROUP, HIGHEST_GROUP)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(GROUP, GROUP), min_size=1, max_size=4))
def test_group_ranges_written_low_to_high_give_their_groups(ranges):
    ranges = [(min(a, b), max(a, b)) for a, b in ranges]
    expected = [g for lo, hi in ranges for g in range(lo, hi + 1)]
    text = ",".join(f"{lo}-{hi}" if lo != hi else f"{lo}" for lo, hi in ranges)
    if len(set(expected)) != len(expected):
        with pytest.raises(DataError, match="listed twice"):
            parse_groups(text)
    else:
        assert parse_groups(text) == tuple(sorted(expected))


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=st.sampled_from("0123456789-, _\u0664\uff14e+.x"), max_size=30) | st.text(max_size=9))
def test_any_group_text_is_groups_or_one_line_naming_groups(text):
    try:
        groups = parse_groups(text)
    except DataError as exc:
        assert exc.param == "groups" and "\n" not in str(exc)
        return
    assert groups == tuple(sorted(set(groups))) and all(LOWEST_GROUP <= g <= HIGHEST_GROUP for g in groups)
    assert all(c in "0123456789-, " or c.isspace() for c in text)  # ASCII digits only


@pytest.mark.parametrize(
    "text,words",
    [
        ("4-99999999999999999999", ["-2 to 9", "not 99999999999999999999"]),
        ("4-" + "9" * 5000, ["-2 to 9"]),
        ("9-3", ["reversed", "3-9"]),
        ("4_5", ["not a group range"]),
        ("\u0664-\u0665", ["not a group range"]),  # Arabic-Indic 4-5
        ("", ["no group given"]),
    ],
)
def test_group_texts_that_are_refused(text, words):
    with pytest.raises(DataError) as info:
        parse_groups(text)
    for w in words:
        assert w in str(info.value)


@pytest.mark.parametrize("groups", ["4-99999999999999999999", "9-3"])
def test_detect_refuses_such_groups_in_one_line_before_reading_the_image(run_cli, tmp_path, groups):
    out = tmp_path / "p.csv"
    args = ("--groups", groups, "--um-per-px", "4.8", "--out", out)
    code, _, err = run_cli("detect", tmp_path / "missing.png", *args)
    one_error(code, err)
    assert "--groups" in err and not out.exists()
