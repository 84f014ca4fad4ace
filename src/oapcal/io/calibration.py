"""The calibration file: versioned JSON, validated on load, never a pickle.

The record itself is :class:`oapcal.calibration.Calibration` (re-exported here).

Layout (``docs/file-formats.md`` has an annotated example)::

    {"format": "oapcal-calibration", "version": 2, "oapcal_version": ..., "created_utc": ...,
     "model_family": "brown-conrady" | "brown-conrady+rotation" | "relay" | "relay+microscope",
     "relay_design": {the nominal relay of a relay model} or null,
     "free": ["k1", ...], "params": {all of the family's by name}, "stderr": {free ones by name},
     "covariance": [[...]]  (free parameters, in "free" order),
     "fit": {"n_points", "n_residuals", "k", "rss", "aic", "aicc", "aicc_forward" (= "aicc"),
             "aicc_corrected", "bic", "converged", "status", "message", "n_iter", "init",
             "normalize"},
     "residuals": {"max_px", "mean_px", "rms_px", "total_px", "n_points", "n_failed",
                   and "*_um" with a scale},
     "um_per_px": S or null, "image_size": [width, height] or null,
     "bounds": [x_min, y_min, x_max, y_max] of the reference points, or null,
     "hull": convex hull of the reference points [[x, y], ...], or null,
     "priors": the priors of a maximum a posteriori relay fit (only then),
     "error_model": {"floor_px", "noise_px", "extrapolation", "ramp_px", ...} (optional:
                    oapcal.uncertainty.ErrorModel; files without it load, with None),
     "checked": {"sha256": ...} (relay families only, optional: the content passed every
                check below under this oapcal's code; see _checks_passed),
     "selfcal": {"frames", "pairs", "matches", "inliers", "gauge", "pair_table", ...} (only
                from ``oapcal selfcal``: oapcal.selfcal.solve.selfcal_record)}

Version 1 (no ``model_family``: Eq. 1) is still read.  Non-finite numbers are written as
null.  On reading, every number must be finite (NaN, Infinity and numbers too large for
a double are refused, naming the field), the parameters must lie in :data:`PARAM_LIMIT`
with ``m`` in :data:`M_RANGE`, ``um_per_px`` in
:data:`UM_PER_PX_RANGE`, each side of ``image_size`` at most :data:`MAX_IMAGE_SIDE`,
``bounds`` must be ordered and ``hull`` a polygon; and the model must be usable where it
is applied: finite and not folding over (Jacobian determinant > 0) on the reference points'
bounds and on the ``image_size`` frame (:func:`check_model_region`).

Loading a relay calibration is light when its ``checked`` record matches: the design's
constants and the region are checked by tracing rays through the relay (Numba's kernels,
~0.5 s in a fresh process), and a file that passed them, written by this same code and
unchanged since, passes them again.  The record is a digest, not a signature: it tells an
edited or foreign file from the one written, nothing more; such a file is checked in full
and refused with the same message as before.
"""

from __future__ import annotations

import functools
import hashlib
import json
from importlib import resources
from pathlib import Path

import numpy as np

from oapcal.calibration import CHECK_GRID, Calibration, FitSummary, ModelRegion, check_model_region
from oapcal.errors import InputFileError
from oapcal.io.atomic import atomic_write
from oapcal.io.jsonfile import json_safe
from oapcal.io.userfile import read_json
from oapcal.model import BROWN_CONRADY, FAMILIES, RELAY_FAMILIES
from oapcal.records import nan_if_none
from oapcal.uncertainty import ErrorModel

__all__ = [
    "CHECK_GRID",
    "Calibration",
    "calibration_from_dict",
    "calibration_to_dict",
    "check_model_region",
    "load_calibration",
    "save_calibration",
    "validate",
]

FORMAT = "oapcal-calibration"
#: Version written: 2 adds ``model_family`` and ``relay_design``; version 1 files (always
#: Eq. 1) still load.
VERSION = 2
VERSIONS = (1, 2)

#: Largest absolute value of any parameter (far beyond any real fit in px, um or mm).
PARAM_LIMIT = 1e30
#: Allowed range of the magnification ``m``.
M_RANGE = (1e-12, 1e12)
#: Allowed range of ``um_per_px`` (1 pm to 1 m per px).
UM_PER_PX_RANGE = (1e-6, 1e6)
#: Largest side of ``image_size`` (px).
MAX_IMAGE_SIDE = 1_000_000


def _schema() -> dict:
    return json.loads(resources.files("oapcal.io").joinpath("calibration.schema.json").read_text())


def calibration_to_dict(calibration: Calibration) -> dict:
    """The JSON object of a calibration file.

    A relay calibration's object carries ``checked``, the record that this very content
    passed every check of :func:`calibration_from_dict` (:func:`_checks_passed`), when it
    does; loading it then skips the checks that trace rays."""
    data = json_safe(
        {
            "format": FORMAT,
            "version": VERSION,
            "model_family": calibration.family.name,
            "relay_design": calibration.relay_design,
            "oapcal_version": calibration.oapcal_version,
            "created_utc": calibration.created_utc,
            "name": calibration.name,
            "source": calibration.source,
            "free": list(calibration.free),
            "params": calibration.params_dict,
            "stderr": {
                n: float(calibration.stderr[calibration.family.param_names.index(n)])
                for n in calibration.free
            },  # fmt: skip
            "covariance": np.asarray(calibration.covariance, float).tolist(),
            "fit": calibration.fit.to_dict(),
            "residuals": calibration.residuals.to_dict(),
            "um_per_px": calibration.um_per_px,
            "image_size": list(calibration.image_size) if calibration.image_size else None,
            "bounds": list(calibration.bounds) if calibration.bounds is not None else None,
            "hull": np.asarray(calibration.hull).tolist() if calibration.hull is not None else None,
            # written only for a fit with priors: other files are as before
            **({"priors": calibration.priors} if calibration.priors is not None else {}),
            **({"error_model": calibration.error_model.to_dict()} if calibration.error_model else {}),
            **({"selfcal": calibration.selfcal} if calibration.selfcal is not None else {}),
        }
    )
    if calibration.family in RELAY_FAMILIES:
        try:
            calibration_from_dict(data)
        except Exception:  # noqa: BLE001 - whatever fails, the file is written without the record
            pass  # (as before: loading it then reports the problem)
        else:
            data[CHECKED_KEY] = {"sha256": _content_digest(data)}
    return data


#: The key of a relay calibration file's record of its checks: ``{"sha256": digest}``, the
#: digest (:func:`_content_digest`) of the file's other content and of this oapcal's code.
CHECKED_KEY = "checked"


@functools.cache
def _code_digest() -> bytes:
    """SHA-256 of every source file of this oapcal (and the file schema), read as package
    data: a record of checks made by other code is not trusted."""
    package = resources.files("oapcal")
    names, folders = [], [()]
    while folders:  # the package's own files, not a user's
        parts = folders.pop()
        for item in package.joinpath(*parts).iterdir():
            if item.is_dir() and item.name != "__pycache__":
                folders.append((*parts, item.name))
            elif item.name.endswith(".py") or item.name == "calibration.schema.json":
                names.append((*parts, item.name))
    digest = hashlib.sha256()
    for parts in sorted(names):
        digest.update("/".join(parts).encode())
        digest.update(resources.files("oapcal").joinpath(*parts).read_bytes())
    return digest.digest()


def _content_digest(data: dict) -> str:
    """The digest of a calibration object's content (all but :data:`CHECKED_KEY`, as
    canonical JSON) under this oapcal's code."""
    content = {k: v for k, v in data.items() if k != CHECKED_KEY}
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(_code_digest() + text.encode()).hexdigest()


def _checks_passed(data: dict) -> bool:
    """Whether ``data`` (a relay calibration) records that its content, exactly as it is,
    passed every check of :func:`calibration_from_dict` under this oapcal's code: then the
    design's constants (:func:`~oapcal.optics.relay_model.design_from_record`) and the
    region (:func:`check_model_region`) need not be traced again, as their outcome is
    decided by that content.  A file edited anywhere, or written by other code, is checked
    in full."""
    record = data.get(CHECKED_KEY)
    if not isinstance(record, dict) or not isinstance(record.get("sha256"), str):
        return False
    return record["sha256"] == _content_digest(data)


def _fit_summary(fit: dict) -> FitSummary:
    """The ``fit`` object of a file as a :class:`FitSummary` (:meth:`FitSummary.from_dict`)."""
    return FitSummary.from_dict(fit)


def _residual_stats(residuals: dict):
    """The ``residuals`` object of a file as a :class:`~oapcal.stats.ResidualStats` (the
    ``*_um`` entries follow from ``um_per_px``; absent distances are NaN)."""
    from oapcal.stats import ResidualStats

    return ResidualStats(
        max_px=nan_if_none(residuals.get("max_px")),
        mean_px=nan_if_none(residuals.get("mean_px")),
        rms_px=nan_if_none(residuals.get("rms_px")),
        total_px=nan_if_none(residuals.get("total_px")),
        n_points=int(residuals.get("n_points") or 0),
        n_failed=int(residuals.get("n_failed") or 0),
        um_per_px=residuals.get("um_per_px"),
    )


def calibration_from_dict(data: dict, source: str = "calibration") -> Calibration:
    """A validated :class:`Calibration` from the JSON object of a calibration file."""
    validate(data, source)
    _check_numbers(data, source)
    family = _family(data)
    names = family.param_names
    free = tuple(n for n in names if n in data["free"])
    params = np.array([float(data["params"][n]) for n in names])
    if family.zero_when_fixed:
        for i, name in enumerate(names):
            if name not in free and params[i] != 0.0:
                raise InputFileError(
                    f"{source}: field 'params.{name}' is {params[i]:g} but {name} is not "
                    "in 'free'; fixed parameters must be 0"
                )
    stderr = np.full(len(names), np.nan)
    for name, value in data["stderr"].items():
        if name not in free:
            raise InputFileError(f"{source}: field 'stderr.{name}': {name} is not a free parameter")
        stderr[names.index(name)] = nan_if_none(value)
    rows = data["covariance"]
    k = len(free)
    if len(rows) != k or any(len(row) != k for row in rows):
        raise InputFileError(
            f"{source}: field 'covariance' must be {k} x {k} (one row and column per free "
            "parameter, in 'free' order)"
        )
    cov = np.array([[nan_if_none(v) for v in row] for row in rows], float)
    cov = cov.reshape(k, k)
    traced = family in RELAY_FAMILIES and not _checks_passed(data)
    if traced:
        from oapcal.optics.relay_model import design_from_record

        design_from_record(data.get("relay_design"), params, source)
    size = data.get("image_size")
    hull = data.get("hull")
    cal = Calibration(
        free=free,
        params=params,
        stderr=stderr,
        covariance=cov,
        fit=_fit_summary(data["fit"]),
        residuals=_residual_stats(data["residuals"]),
        um_per_px=data.get("um_per_px"),
        image_size=tuple(size) if size else None,
        bounds=tuple(data["bounds"]) if data.get("bounds") else None,
        hull=np.array(hull, float) if hull else None,
        name=data.get("name"),
        source=data.get("source"),
        oapcal_version=data.get("oapcal_version", "unknown"),
        created_utc=data.get("created_utc", "unknown"),
        relay_design=data.get("relay_design"),
        priors=data.get("priors"),
        error_model=ErrorModel.from_dict(data.get("error_model")),
        family=family,
        selfcal=data.get("selfcal"),
    )
    if traced or family not in RELAY_FAMILIES:
        check_model_region(cal, source=source)
    return cal


def _family(data: dict):
    """The model family a (validated) file names; version 1 files are Eq. (1)."""
    return FAMILIES[data.get("model_family") or BROWN_CONRADY.name]


def validate(data, source: str = "calibration") -> None:
    """Raise :class:`InputFileError` naming the first bad field of a calibration dict."""
    import jsonschema

    if not isinstance(data, dict):
        raise InputFileError(f"{source}: is not an oapcal calibration (expected a JSON object)")
    if data.get("format") != FORMAT:
        raise InputFileError(
            f"{source}: field 'format' is {data.get('format')!r}, expected {FORMAT!r}; "
            "is this an oapcal calibration file?"
        )
    version = data.get("version")
    if isinstance(version, bool) or version not in VERSIONS:
        raise InputFileError(
            f"{source}: field 'version' is {version!r}; this oapcal reads versions "
            f"{' and '.join(str(v) for v in VERSIONS)} of calibration files"
        )
    if version == 1 and data.get("model_family", BROWN_CONRADY.name) != BROWN_CONRADY.name:
        raise InputFileError(
            f"{source}: field 'model_family' is {data.get('model_family')!r}, but version 1 files hold "
            "Eq. (1) only; write it as version 2"
        )
    validator = jsonschema.Draft202012Validator(_schema())
    error = jsonschema.exceptions.best_match(validator.iter_errors(data))
    if error is not None:
        where = ".".join(str(p) for p in error.absolute_path) or "(top level)"
        raise InputFileError(f"{source}: field '{where}': {error.message}")


def _where(path) -> str:
    return ".".join(str(p) for p in path)


def _walk_numbers(value, path=()):
    """(path, number) for every number (not bool) in a JSON value."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _walk_numbers(item, (*path, key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _walk_numbers(item, (*path, i))
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield path, value


def _check_numbers(data: dict, source: str) -> None:
    """Every number finite and every field in its range (after the schema)."""
    import math

    for path, value in _walk_numbers(data):
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an integer too large for a double
            finite = False
        if not finite:
            raise InputFileError(
                f"{source}: field '{_where(path)}' is {value if isinstance(value, float) else 'too large'}; "
                "calibration numbers must be finite (write null where a statistic is unknown)"
            )
    family = _family(data)
    for name in family.param_names:
        value = float(data["params"][name])
        if abs(value) > PARAM_LIMIT:
            raise InputFileError(
                f"{source}: field 'params.{name}' is {value:g}, beyond +-{PARAM_LIMIT:g}; "
                "this is not a fitted model (refit with 'oapcal fit')"
            )
    m = float(data["params"].get("m", 1.0))
    if not M_RANGE[0] <= m <= M_RANGE[1]:
        raise InputFileError(
            f"{source}: field 'params.m' is {m:g}; the magnification m must be between "
            f"{M_RANGE[0]:g} and {M_RANGE[1]:g} (positive)"
        )
    um = data.get("um_per_px")
    if um is not None and not UM_PER_PX_RANGE[0] <= um <= UM_PER_PX_RANGE[1]:
        raise InputFileError(
            f"{source}: field 'um_per_px' is {um:g}; it must be between {UM_PER_PX_RANGE[0]:g} and "
            f"{UM_PER_PX_RANGE[1]:g} um per px (or null)"
        )
    size = data.get("image_size")
    if size is not None and max(size) > MAX_IMAGE_SIDE:
        raise InputFileError(
            f"{source}: field 'image_size' is {size[0]}x{size[1]}; a side over {MAX_IMAGE_SIDE} px is "
            "not a camera image"
        )
    bounds = data.get("bounds")
    if bounds is not None and not (bounds[0] < bounds[2] and bounds[1] < bounds[3]):
        raise InputFileError(
            f"{source}: field 'bounds' is {bounds}; it must be [x_min, y_min, x_max, y_max] with "
            "x_min < x_max and y_min < y_max"
        )
    hull = data.get("hull")
    if hull is not None and len(hull) < 3:
        raise InputFileError(
            f"{source}: field 'hull' has {len(hull)} vertices; a convex hull needs at least 3 (or null)"
        )


def save_calibration(calibration: Calibration, path: str | Path) -> None:
    """Write a calibration file atomically (``-`` writes to stdout)."""
    text = json.dumps(calibration_to_dict(calibration), indent=2) + "\n"
    if str(path) == "-":
        import sys

        sys.stdout.write(text)
        return
    with atomic_write(path) as fh:
        fh.write(text)


def load_calibration(path: str | Path, image_size: tuple[int, int] | None = None) -> Calibration:
    """Read and validate a calibration file; errors name the file and the bad field.

    With ``image_size = (width, height)`` the model must also be finite and not fold over
    anywhere on that image (:func:`check_model_region`), as when it is applied to all of it;
    a calibration's own ``image_size`` frame may hold a fold beyond its reference points'
    bounds (where its trust region has ended)."""
    name = str(path)
    data = read_json(
        path, "calibration file", missing="no such calibration file; run 'oapcal fit' to make one"
    )
    cal = calibration_from_dict(data, source=name)
    if image_size is not None:  # the bounds and own frame were checked: that image alone, strictly
        region = ModelRegion(cal.params, cal.family)
        check_model_region(region, image_size, source=name, folds_beyond_bounds=False)
    return cal
