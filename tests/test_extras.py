"""Optional extras: a missing one is named with the command that installs it."""

import sys

import numpy as np
import pytest
import tifffile

from imaging_helpers import write_calibration
from oapcal.extras import EXTRAS, MissingExtraError, require


@pytest.fixture
def without_dask(monkeypatch):
    """Make ``import dask`` (and distributed, zarr) fail as on a machine without the extra."""
    for name in list(sys.modules):
        if name.split(".")[0] in EXTRAS["dask"]:
            monkeypatch.delitem(sys.modules, name)
    for name in EXTRAS["dask"]:
        monkeypatch.setitem(sys.modules, name, None)  # None in sys.modules -> ImportError


def test_require_names_the_extra(without_dask):
    expected = r"pip install 'dask\[array,distributed\]>=2024.1' 'zarr>=3.0' \(or, in a clone of oapcal: "
    with pytest.raises(MissingExtraError, match=expected + r"pip install -e '\.\[dask\]'\)"):
        require("dask.array")
    assert issubclass(MissingExtraError, ImportError)


def test_correct_dask_without_the_extra_says_how_to_install_it(tmp_path, without_dask, run_cli):
    cal_path = write_calibration(tmp_path / "calib.json")
    tifffile.imwrite(tmp_path / "s.tif", np.zeros((2, 480, 640), np.uint8))
    code, out, err = run_cli("correct", cal_path, tmp_path / "s.tif", "--dask", "--out-dir", tmp_path / "out")
    assert code == 2, err
    assert "pip install 'dask[array,distributed]>=2024.1' 'zarr>=3.0' (or, in a clone of oapcal: " in err
    assert "oapcal[dask]'" not in err.replace("-e '.[dask]'", "")  # oapcal is not on PyPI
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out" / "s.zarr").exists()


@pytest.mark.parametrize("extra", sorted(EXTRAS))
def test_the_install_command_installs_the_extras_packages(extra):
    """The packages in the message are exactly the extra's requirements in pyproject.toml,
    so that ``pip install`` of them gives what the extra gives, and pip reads them."""
    import shlex
    import tomllib
    from pathlib import Path

    from oapcal.extras import install_command

    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    wanted = pyproject["project"]["optional-dependencies"][extra]
    command = install_command(extra)
    packages = shlex.split(command.split(" (or")[0].removeprefix("pip install "))
    assert packages == wanted
    from packaging.requirements import Requirement  # what pip parses a requirement with

    assert [str(Requirement(p)) for p in packages] == wanted
    assert command.endswith(f"pip install -e '.[{extra}]')")
