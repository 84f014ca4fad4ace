"""Optional dependencies: what each extra brings and the message when it is missing.

``pip install 'oapcal[dask]'`` adds Dask, distributed and zarr (out-of-core stacks,
``oapcal correct --dask``).  The core never imports them at module level.

>>> require("math").sqrt(4.0)
2.0
>>> try:
...     require("surely_not_installed_module", "dask")
... except MissingExtraError as exc:
...     print(str(exc).split(": ")[-1])
pip install 'oapcal[dask]'
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
            f"install it with: pip install 'oapcal[{extra}]'"
        ) from None
