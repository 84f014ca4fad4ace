"""JSON outputs: one way to make values JSON-safe and to write them.

oapcal's JSON never holds NaN or infinity (not valid JSON): non-finite numbers become
``null``.  NumPy scalars and arrays become plain numbers and lists.

>>> import numpy as np
>>> json_safe({"a": np.float64(1.5), "b": [np.nan, np.int64(2)], "c": np.array([True])})
{'a': 1.5, 'b': [None, 2], 'c': [True]}
>>> finite_or_none(float("inf")) is None
True
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from oapcal.records import finite_or_none, json_safe

__all__ = ["dumps", "finite_or_none", "json_safe", "write_json"]


def dumps(obj: dict) -> str:
    """The text of a JSON object, with each entry of a ``models`` list or object on one
    line (readable, and the 4,096 models of a selection stay compact)."""
    obj = json_safe(obj)
    lines = []
    for key, value in obj.items():
        if key == "models" and isinstance(value, list):
            inner = ",\n".join("  " + json.dumps(v, allow_nan=False) for v in value)
            lines.append(f' "models": [\n{inner}\n ]')
        elif key == "models" and isinstance(value, dict):
            entries = (f"  {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in value.items())
            lines.append(' "models": {\n' + ",\n".join(entries) + "\n }")
        else:
            lines.append(f" {json.dumps(key)}: {json.dumps(value, allow_nan=False)}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def write_json(path: str | Path, obj: dict) -> None:
    """Write :func:`dumps` of ``obj`` atomically; ``-`` writes to stdout."""
    text = dumps(obj)
    if str(path) == "-":
        sys.stdout.write(text)
        return
    from oapcal.io.atomic import atomic_write

    with atomic_write(path) as fh:
        fh.write(text)
