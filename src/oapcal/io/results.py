"""Selection and robustness files: versioned JSON that loads back into the typed results.

``oapcal select --json`` writes a :class:`~oapcal.select.Selection`, ``oapcal robustness
--json`` a :class:`~oapcal.select.Robustness`, each as a JSON object with a ``format``
(``oapcal-selection`` or ``oapcal-robustness``) and a ``version`` (1), checked against
``results.schema.json`` on load.  Non-finite numbers are ``null`` in the file and NaN
back in Python; a robustness file does not store the per-trial codes, so
``trial_codes`` comes back empty.  Files written before the format had a name (no
``format`` field) still load when they hold the same fields.

>>> from oapcal.synthetic import synthetic_pairs
>>> from oapcal.select import select_models
>>> data = synthetic_pairs(seed=0)
>>> sel = select_models(data.xy_u, data.xy_d, masks=[[True] * 13], init="pixel")
>>> selection_from_dict(selection_to_dict(sel)) == sel
True
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError
from oapcal.records import nan_if_none
from oapcal.select import ModelRobustness, ModelScore, Robustness, Selection

SELECTION_FORMAT = "oapcal-selection"
ROBUSTNESS_FORMAT = "oapcal-robustness"
FAMILY_SELECTION_FORMAT = "oapcal-family-selection"
VERSION = 1
#: The schema branch (``results.schema.json``) of each format.
_BRANCH = {SELECTION_FORMAT: "selection_file", ROBUSTNESS_FORMAT: "robustness_file",
           FAMILY_SELECTION_FORMAT: "family_selection_file"}  # fmt: skip


@cache
def _schema() -> dict:
    return json.loads(resources.files("oapcal.io").joinpath("results.schema.json").read_text())


# ------------------------------------------------------------------------ to files


def selection_to_dict(selection: Selection) -> dict:
    """The JSON object of a selection: ``format``, ``version`` and :meth:`Selection.to_dict`."""
    return {"format": SELECTION_FORMAT, "version": VERSION, **selection.to_dict()}


def robustness_to_dict(result: Robustness) -> dict:
    """The JSON object of a robustness test: ``format``, ``version`` and its ``to_dict``."""
    return {"format": ROBUSTNESS_FORMAT, "version": VERSION, **result.to_dict()}


def save_selection(selection: Selection, path: str | Path) -> None:
    """Write a selection file atomically (``-``: stdout)."""
    from oapcal.io.jsonfile import write_json

    write_json(path, selection_to_dict(selection))


def save_robustness(result: Robustness, path: str | Path) -> None:
    """Write a robustness file atomically (``-``: stdout)."""
    from oapcal.io.jsonfile import write_json

    write_json(path, robustness_to_dict(result))


# ---------------------------------------------------------------------- from files


def _validate(data, expected: str, source: str) -> None:
    import jsonschema

    if not isinstance(data, dict):
        raise InputFileError(f"{source}: expected a JSON object ({expected} file)")
    fmt = data.get("format")
    if fmt != expected:
        raise InputFileError(
            f"{source}: field 'format' is {fmt!r}, expected {expected!r}; "
            f"is this a file written by save_{expected.removeprefix('oapcal-')} "
            f"(the JSON of 'oapcal {expected.removeprefix('oapcal-')}')?"
        )
    if data.get("version") != VERSION:
        raise InputFileError(
            f"{source}: field 'version' is {data.get('version')!r}; this oapcal reads version {VERSION}"
        )
    branch = _BRANCH[expected]
    schema = {"$defs": _schema()["$defs"], "$ref": f"#/$defs/{branch}"}
    error = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema).iter_errors(data))
    if error is not None:
        where = ".".join(str(p) for p in error.absolute_path) or "(top level)"
        raise InputFileError(f"{source}: field '{where}': {error.message}")


def _upgrade(data, expected: str):
    """Files of version 0 (no ``format``) get the fields the versioned format requires."""
    if isinstance(data, dict) and "format" not in data:
        data = {"format": expected, "version": VERSION, **data}
        if expected == SELECTION_FORMAT and isinstance(data.get("models"), list):
            data["models"] = [
                {"reason_code": _guess_code(m), **m} if isinstance(m, dict) else m for m in data["models"]
            ]
    return data


def _guess_code(model: dict) -> str:
    """The reason code of a version-0 model entry, from its message (only for old files)."""
    reason = str(model.get("reason") or "")
    for prefix, code in (
        ("fit did not converge", "not_converged"),
        ("too few residuals", "too_few_residuals"),
        ("inverse failed", "inverse_failed"),
        ("AICc is not finite", "aicc_not_finite"),
    ):
        if reason.startswith(prefix):
            return code
    return ""


def selection_from_dict(data: dict, source: str = "selection") -> Selection:
    """A :class:`Selection` from its JSON object (validated; ``source`` names it in errors)."""
    data = _upgrade(data, SELECTION_FORMAT)
    _validate(data, SELECTION_FORMAT, source)
    models = tuple(ModelScore.from_dict(m) for m in data["models"])
    return Selection(int(data["n_points"]), data["normalize"], data["init"], models, data["cv_folds"])


def robustness_from_dict(data: dict, source: str = "robustness") -> Robustness:
    """A :class:`Robustness` from its JSON object (validated); ``trial_codes`` are empty."""
    data = _upgrade(data, ROBUSTNESS_FORMAT)
    _validate(data, ROBUSTNESS_FORMAT, source)
    models = tuple(
        ModelRobustness(
            name=name,
            free=tuple(m["free"]),
            trials=int(m["trials"]),
            not_converged=int(m["not_converged"]),
            by_reason={k: int(v) for k, v in m["by_reason"].items()},
            param_std={k: None if v is None else float(v) for k, v in m["param_std"].items()},
            heldout_mean_error=nan_if_none(m["heldout_mean_error_px"]),
            heldout_failed=int(m["heldout_failed_points"]),
            reference_rms=nan_if_none(m["reference_rms"]),
            trial_codes=np.zeros(0, dtype=np.int64),
        )
        for name, m in data["models"].items()
    )
    return Robustness(
        n_points=int(data["n_points"]),
        n_keep=int(data["n_keep"]),
        fraction=float(data["fraction"]),
        seed=int(data["seed"]),
        init=data["init"],
        normalization=data["normalize"],
        wrong_minimum_ratio=float(data["wrong_minimum_ratio"]),
        models=models,
    )


def family_selection_to_dict(selection) -> dict:
    """The JSON object of a :class:`~oapcal.families.FamilySelection` (``select --families``)."""
    return {"format": FAMILY_SELECTION_FORMAT, "version": VERSION, **selection.to_dict()}


def save_family_selection(selection, path: str | Path) -> None:
    """Write a family-selection file atomically (``-``: stdout)."""
    from oapcal.io.jsonfile import write_json

    write_json(path, family_selection_to_dict(selection))


def family_selection_from_dict(data: dict, source: str = "family selection"):
    """A :class:`~oapcal.families.FamilySelection` from its JSON object (validated)."""
    from oapcal.families import Candidate, FamilySelection

    _validate(data, FAMILY_SELECTION_FORMAT, source)
    candidates = tuple(
        Candidate(
            family=c["family"],
            spec=c["spec"],
            free=tuple(c["free"]),
            k=int(c["k"]),
            aicc=nan_if_none(c["aicc"]),
            delta_aicc=nan_if_none(c["delta_aicc"]),
            mean_error=nan_if_none(c["mean_error"]),
            valid=bool(c["valid"]),
            reason=c["reason"],
            cv_mean_error=None if c["cv_mean_error"] is None else float(c["cv_mean_error"]),
            cv_failed=int(c["cv_failed"]),
        )  # fmt: skip
        for c in data["candidates"]
    )
    recommended = next((c for c in candidates if c.spec == data["recommended"]), None)
    if data["recommended"] is not None and recommended is None:
        raise InputFileError(
            f"{source}: field 'recommended' is {data['recommended']!r}, which is none of the candidates"
        )
    return FamilySelection(int(data["n_points"]), int(data["cv_folds"]), candidates, recommended)


def load_any_selection(path: str | Path):
    """A selection file of either kind: ``oapcal select --json`` (a :class:`Selection`) or
    ``oapcal select --families ... --json`` (a :class:`~oapcal.families.FamilySelection`)."""
    from oapcal.io.userfile import read_json

    data = read_json(path, "selection file")
    if isinstance(data, dict) and data.get("format") == FAMILY_SELECTION_FORMAT:
        return family_selection_from_dict(data, str(path))
    return selection_from_dict(data, str(path))


def load_selection(path: str | Path) -> Selection:
    """Read a selection file (``oapcal select --json``) back into a :class:`Selection`."""
    from oapcal.io.userfile import read_json

    return selection_from_dict(read_json(path, "selection file"), str(path))


def load_robustness(path: str | Path) -> Robustness:
    """Read a robustness file (``oapcal robustness --json``) back into a :class:`Robustness`."""
    from oapcal.io.userfile import read_json

    return robustness_from_dict(read_json(path, "robustness file"), str(path))
