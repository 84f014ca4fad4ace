"""The OpenCV conversion lives in ``imaging.opencv``; ``io.opencv_export`` writes the files and
still offers every moved name (the same objects, so old imports behave exactly as before)."""

import ast
from pathlib import Path

import numpy as np
import pytest

import oapcal.imaging.opencv as conversion
import oapcal.io.opencv_export as export_file
from oapcal.model import params_from_dict

MOVED = (
    "opencv_parameters", "opencv_export", "opencv_maps", "brown_conrady_approximation", "Approximation",
    "APPROX_GRID", "APPROX_MIN_SAMPLES", "EXPORT_BYTES_PER_PX", "MAX_EXPORT_BYTES",
)  # fmt: skip


@pytest.mark.parametrize("name", MOVED)
def test_io_module_reexports_the_moved_names(name):
    assert getattr(export_file, name) is getattr(conversion, name)


def test_conversion_imports_no_file_module():
    tree = ast.parse(Path(conversion.__file__).read_text(encoding="utf-8"))
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert "oapcal.imaging.remap" in imported  # the check sees the imports
    assert not {m for m in imported if m.startswith("oapcal.io")}, imported


def test_eq1_parameters_by_hand():
    # k1 F^2 with F = max(640, 480): 1e-7 * 640**2 = 0.04096; c_x and the offset give the matrices.
    d = conversion.opencv_parameters(params_from_dict({"k1": 1e-7, "c_x": 320, "x_off": -320}), (640, 480))
    assert d["dist_coeffs"][0] == pytest.approx(0.04096, rel=1e-12)
    assert d["camera_matrix"][0] == [640.0, 0.0, 320.0] and d["new_camera_matrix"][0] == [640.0, 0.0, 320.0]
    assert d["image_size"] == [640, 480] and d["new_image_size"] == [640, 480]
    assert all(type(v) is int for v in d["image_size"] + d["new_image_size"])  # JSON ints, not a tuple type


def test_rotation_is_turned_back_into_the_offsets():
    p = np.append(params_from_dict({"x_off": 10.0, "y_off": 0.0}), 90.0)
    d = conversion.opencv_parameters(p, (640, 480))
    # offsets (10, 0) turned by -90 deg: (0, -10); R = Rot(-90 deg)
    assert d["new_camera_matrix"][0][2] == pytest.approx(0.0, abs=1e-12)
    assert d["new_camera_matrix"][1][2] == pytest.approx(10.0)
    np.testing.assert_allclose(d["R"], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
