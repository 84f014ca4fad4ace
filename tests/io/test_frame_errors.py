"""A pandas DataFrame given in memory is not a file: its mistakes raise DataError (the same
message as before), while the same mistake in a parquet file stays an InputFileError."""

import numpy as np
import pytest

from oapcal.errors import DataError, InputFileError
from oapcal.io.tables import correct_points_frame
from oapcal.model import params_from_dict

pd = pytest.importorskip("pandas", reason="the tables extra (pandas) is not installed")
PARAMS = params_from_dict({"x_off": 1.0})


@pytest.mark.parametrize(
    "frame,message",
    [
        ({"x": [1.0, np.inf], "y": [1.0, 2.0]}, "row 1, column 'x': inf is not a finite number; give"),
        ({"x": [1.0, 2e7], "y": [1.0, 2.0]}, r"row 1, column 'x': 2e\+07 is far outside any image \(limit"),
        ({"xx": [1.0], "y": [1.0]}, r"line 1: no column 'x' \(did you mean 'xx'\?\)"),
        ({"x": ["a"], "y": [1.0]}, "column 'x' holds .* values, not numbers"),
    ],
)
def test_a_dataframe_mistake_is_a_data_error(frame, message):
    with pytest.raises(DataError, match="^the DataFrame: " + message) as err:
        correct_points_frame(pd.DataFrame(frame), PARAMS)
    assert not isinstance(err.value, InputFileError)


def test_a_parquet_file_keeps_input_file_error(tmp_path):
    pytest.importorskip("pyarrow", reason="the tables extra (pyarrow) is not installed")
    from oapcal.io.tables import read_point_table

    pd.DataFrame({"x": [1.0, np.inf], "y": [1.0, 2.0]}).to_parquet(tmp_path / "t.parquet")
    with pytest.raises(InputFileError, match=r"t\.parquet: row 1, column 'x': inf is not a finite number"):
        read_point_table(tmp_path / "t.parquet")
