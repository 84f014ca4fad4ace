"""A model that folds where a correction map samples it: a calibration (read from a file)
is refused with InputFileError, a vector or Model given in memory with DataError, with the
same message."""

import pytest

from imaging_helpers import known_calibration
from oapcal.errors import DataError, InputFileError
from oapcal.imaging.remap import correction_map
from oapcal.model import Model, params_from_dict

FOLDING = params_from_dict({"k1": -1e-5})


@pytest.mark.parametrize(
    "value", [FOLDING, Model("brown-conrady", FOLDING, ("k1", "m"))], ids=["vector", "Model"]
)
def test_a_value_that_folds_is_a_data_error(value):
    with pytest.raises(DataError, match=r"the calibration: the model folds over at") as err:
        correction_map(value, (480, 640))
    assert not isinstance(err.value, InputFileError)


def test_a_calibration_that_folds_stays_an_input_file_error():
    cal = known_calibration(params=FOLDING, image_size=None, bounds=None)
    with pytest.raises(InputFileError, match=r"the calibration: the model folds over at"):
        correction_map(cal, (480, 640))
