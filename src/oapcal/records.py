"""Plain values from results: the one place where non-finite numbers become ``None`` and
NumPy scalars and arrays become Python numbers and lists (oapcal's JSON never holds NaN or
infinity, which are not valid JSON).

>>> import numpy as np
>>> json_safe({"a": np.float64(1.5), "b": [np.nan, np.int64(2)], "c": np.array([True])})
{'a': 1.5, 'b': [None, 2], 'c': [True]}
>>> finite_or_none(float("inf")) is None
True
"""

from __future__ import annotations

import math

import numpy as np


def finite_or_none(value) -> float | None:
    """``float(value)``, or None when it is None, NaN or infinite."""
    return float(value) if value is not None and math.isfinite(value) else None


def json_safe(value):
    """A JSON-ready copy: NumPy scalars and arrays to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [json_safe(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return finite_or_none(value)
    return value
