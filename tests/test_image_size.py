"""One image-size type: ``records.ImageSize(width, height)``, a (w, h) tuple with the array
shape (rows, cols) = (height, width)."""

import json

import numpy as np
import pytest

from oapcal import validate
from oapcal.errors import DataError
from oapcal.records import ImageSize


def test_image_size_is_the_width_height_tuple():
    size = ImageSize(640, 480)
    assert size == (640, 480) and tuple(size) == (640, 480)
    assert size.width == 640 and size.height == 480
    w, h = size
    assert (w, h) == (640, 480)
    assert json.dumps(size) == "[640, 480]"


def test_shape_is_rows_cols():
    assert ImageSize(640, 480).shape == (480, 640)
    assert np.zeros(ImageSize(3, 2).shape).shape == (2, 3)


@pytest.mark.parametrize("shape", [(480, 640), (480, 640, 3)])
def test_of_an_array_and_of_a_shape(shape):
    assert ImageSize.of(np.zeros(shape, np.uint8)) == (640, 480)
    assert ImageSize.of(shape) == (640, 480)
    assert all(type(v) is int for v in ImageSize.of(np.zeros(shape)))


def test_validate_returns_one():
    size = validate.image_size([640, 480])
    assert isinstance(size, ImageSize) and size.shape == (480, 640)
    with pytest.raises(DataError, match="image_size height must be a whole number from 1"):
        validate.image_size((640, 0))
