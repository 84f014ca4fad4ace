"""Reading the optional report inputs: model-selection and robustness JSON files.

Selection file (``oapcal select --json``)::

    {"n_points": 238, "models": [{"free": ["k1", ...], "k": 8, "aicc": ..., "delta_aicc": ...,
      "weight": ..., "rss": ..., "valid": true, "reason": ""}, ...]}

Robustness file: per model ``free``, ``trials``, ``not_converged``, ``by_reason`` (reason ->
count), ``param_std`` (name -> standard deviation over trials) and
``heldout_mean_error_px``; the models are a list, either the whole file or under
``"models"``, or an object keyed by model name.

Only ``free`` (and ``aicc`` for selection, ``trials`` and ``not_converged`` for robustness)
are required; other keys may be absent.  Problems raise
:class:`~oapcal.errors.InputFileError` naming the file and the field.
"""

from __future__ import annotations

from oapcal.errors import InputFileError
from oapcal.model import PARAM_NAMES


def _load_json(path) -> object:
    from oapcal.io.textfile import read_json

    return read_json(path, "JSON file")


def _free(value, where: str) -> tuple[str, ...]:
    names = [n.strip() for n in value.split(",")] if isinstance(value, str) else value
    if not isinstance(names, list | tuple) or not all(isinstance(n, str) for n in names):
        raise InputFileError(f"{where}: 'free' must be a list of parameter names")
    bad = [n for n in names if n and n not in PARAM_NAMES]
    if bad:
        raise InputFileError(
            f"{where}: 'free' names unknown parameter {bad[0]!r}; use {' '.join(PARAM_NAMES)}"
        )
    return tuple(n for n in PARAM_NAMES if n in names)


def _number(entry: dict, key: str, where: str, required: bool = False):
    if key not in entry or entry[key] is None:
        if required:
            raise InputFileError(f"{where}: missing field '{key}'")
        return None
    value = entry[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputFileError(f"{where}: field '{key}' must be a number, got {value!r}")
    return value


def read_selection(path) -> dict:
    """A validated selection dict: ``n_points`` and ``models`` (each with a tuple ``free``)."""
    name = str(path)
    data = _load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("models"), list):
        raise InputFileError(f"{name}: expected an object with a list 'models' (oapcal select --json output)")
    models = []
    for i, entry in enumerate(data["models"]):
        where = f"{name}: models[{i}]"
        if not isinstance(entry, dict):
            raise InputFileError(f"{where}: must be an object")
        if "free" not in entry:
            raise InputFileError(f"{where}: missing field 'free'")
        model = dict(entry)
        model["free"] = _free(entry["free"], where)
        model["valid"] = bool(entry.get("valid", True))
        # models that could not be scored carry aicc = null (oapcal select --json)
        model["aicc"] = _number(entry, "aicc", where, required=model["valid"])
        for key in ("k", "delta_aicc", "weight", "rss"):
            model[key] = _number(entry, key, where)
        model["reason"] = str(entry.get("reason") or "")
        models.append(model)
    n_points = data.get("n_points")
    return {"n_points": n_points, "models": models, "source": name}


def read_robustness(path) -> dict:
    """A validated robustness dict: ``models``, each with a tuple ``free``."""
    name = str(path)
    data = _load_json(path)
    if isinstance(data, dict) and isinstance(data.get("models"), list | dict):
        entries = data["models"]
    else:
        entries = data
    if isinstance(entries, dict):
        items = [(str(k), v) for k, v in entries.items()]
    elif isinstance(entries, list):
        items = [(None, v) for v in entries]
    else:
        raise InputFileError(f"{name}: expected a list of models (or an object with 'models')")
    models = []
    for i, (key, entry) in enumerate(items):
        where = f"{name}: models[{key if key is not None else i}]"
        if not isinstance(entry, dict):
            raise InputFileError(f"{where}: must be an object")
        if "free" not in entry:
            raise InputFileError(f"{where}: missing field 'free'")
        model = dict(entry)
        model["name"] = key or entry.get("name") or ""
        model["free"] = _free(entry["free"], where)
        model["trials"] = _number(entry, "trials", where, required=True)
        model["not_converged"] = _number(entry, "not_converged", where, required=True)
        model["heldout_mean_error_px"] = _number(entry, "heldout_mean_error_px", where)
        for key2 in ("by_reason", "param_std"):
            value = entry.get(key2) or {}
            if not isinstance(value, dict):
                raise InputFileError(f"{where}: field '{key2}' must be an object (name -> number)")
            model[key2] = value
        models.append(model)
    return {"models": models, "source": name}
