"""Optional dependencies: what each extra brings and the message when it is missing.

The ``dask`` extra adds Dask, distributed and zarr (out-of-core stacks, ``oapcal correct
--dask``).  The core never imports them at module level.  oapcal is not on PyPI, so the
message of a missing extra gives commands that work without it: the packages themselves
(``pip install 'dask[array,distributed]>=2024.1' 'zarr>=3.0'``) or, in a clone of oapcal,
``pip install -e '.[dask]'``.

>>> require("math").sqrt(4.0)
2.0
>>> try:
...     require("surely_not_installed_module", "dask")
... except MissingExtraError as exc:
...     print(str(exc).split("install it with: ")[-1])
pip install 'dask[array,distributed]>=2024.1' 'zarr>=3.0' (or, in a clone of oapcal: pip install -e '.[dask]')
"""

from __future__ import annotations

import importlib
from types import ModuleType

from oapcal.errors import OapcalError

#: The extras of pyproject.toml and the top-level modules each provides.
EXTRAS: dict[str, tuple[str, ...]] = {
    "dask": ("dask", "distributed", "zarr"),
    "tables": ("pandas", "pyarrow"),  # parquet tables and DataFrames of points (io.tables)
}


#: The requirements of each extra, as in pyproject.toml (tests/test_extras.py checks that
#: they are the same): what the message of a missing extra tells pip to install.
REQUIREMENTS: dict[str, tuple[str, ...]] = {
    "dask": ("dask[array,distributed]>=2024.1", "zarr>=3.0"),
    "tables": ("pandas>=2.0", "pyarrow>=14"),
}


class MissingExtraError(OapcalError, ImportError):
    """An optional dependency is not installed; the message says which extra brings it."""


def require(module: str, extra: str = "dask") -> ModuleType:
    """Import ``module`` (e.g. ``"dask.array"``), or raise :class:`MissingExtraError`
    naming the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(
            f"{module} is not installed: it comes with the {extra!r} extra; "
            f"install it with: {install_command(extra)}"
        ) from None


def install_command(extra: str) -> str:
    """The commands that install ``extra``'s packages: by name, or from a clone of oapcal."""
    packages = " ".join(f"'{r}'" for r in REQUIREMENTS.get(extra, ()))
    clone = f"pip install -e '.[{extra}]'"
    return f"pip install {packages} (or, in a clone of oapcal: {clone})" if packages else clone
