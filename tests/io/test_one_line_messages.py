"""Errors are one line even when the user's file puts line breaks into what they quote (a
CSV that starts with a quote holds the whole file in one header cell)."""

import pytest

from oapcal.errors import InputFileError, OapcalError
from oapcal.io.landmarks.tables import read_table


def test_a_quoted_header_holding_the_whole_file_gives_one_line(tmp_path):
    path = tmp_path / "fuzzed.csv"
    path.write_text('"id,x_u,y_u,x_d,y_d\nc0,1,2,3,4\r\nc1,5,6,7,8\n')
    with pytest.raises(InputFileError) as err:
        read_table(path, x_column="x_d", y_column="y_d")
    msg = str(err.value)
    assert "\n" not in msg and "\r" not in msg and "fuzzed.csv" in msg
    assert "\\n" in msg  # the break is shown, escaped


def test_every_error_escapes_control_characters():
    msg = str(OapcalError("a\tb\x1b[2Jc\u202ed"))
    assert msg == "a\\tb\\x1b[2Jc\\u202ed"
    assert str(OapcalError("plain message, é and µm kept")) == "plain message, é and µm kept"
