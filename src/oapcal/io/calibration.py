"""The calibration file: versioned JSON, validated on load, never a pickle.

Layout (``docs/file-formats.md`` has an annotated example)::

    {"format": "oapcal-calibration", "version": 1, "oapcal_version": ..., "created_utc": ...,
     "free": ["k1", ...], "params": {all 13 by name}, "stderr": {free ones by name},
     "covariance": [[...]]  (free parameters, in "free" order),
     "fit": {"n_points", "n_residuals", "k", "rss", "aic", "aicc", "bic", "converged",
             "status", "message", "n_iter", "init", "normalize"},
     "residuals": {"max_px", "mean_px", "rms_px", "total_px", "n_points", "n_failed",
                   and "*_um" with a scale},
     "um_per_px": S or null, "image_size": [width, height] or null,
     "bounds": [x_min, y_min, x_max, y_max] of the reference points, or null,
     "hull": convex hull of the reference points [[x, y], ...], or null}

Non-finite numbers are written as null.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from oapcal import __version__
from oapcal.errors import InputFileError
from oapcal.io.atomic import atomic_write
from oapcal.io.jsonfile import json_safe
from oapcal.io.textfile import read_json
from oapcal.model import INDEX, N_PARAMS, PARAM_NAMES, parse_model

FORMAT = "oapcal-calibration"
VERSION = 1


def _schema() -> dict:
    return json.loads(resources.files("oapcal.io").joinpath("calibration.schema.json").read_text())


@dataclass(frozen=True)
class Calibration:
    """A fitted distortion model and what is known about it.

    ``params`` is the ``(13,)`` vector; ``stderr`` the ``(13,)`` standard errors (NaN for
    fixed parameters); ``covariance`` the ``k x k`` covariance over ``free``.
    ``fit`` and ``residuals`` are plain dicts (see the module docstring).
    """

    free: tuple[str, ...]
    params: np.ndarray
    stderr: np.ndarray
    covariance: np.ndarray
    fit: dict
    residuals: dict
    um_per_px: float | None = None
    image_size: tuple[int, int] | None = None
    bounds: tuple[float, float, float, float] | None = None
    hull: np.ndarray | None = None
    name: str | None = None
    source: str | None = None
    oapcal_version: str = __version__
    created_utc: str = field(default_factory=lambda: _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"))

    @property
    def mask(self) -> np.ndarray:
        return parse_model(self.free)

    @property
    def params_dict(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(PARAM_NAMES, self.params)}

    def to_dict(self) -> dict:
        return json_safe(
            {
                "format": FORMAT,
                "version": VERSION,
                "oapcal_version": self.oapcal_version,
                "created_utc": self.created_utc,
                "name": self.name,
                "source": self.source,
                "free": list(self.free),
                "params": self.params_dict,
                "stderr": {n: float(self.stderr[INDEX[n]]) for n in self.free},
                "covariance": np.asarray(self.covariance, float).tolist(),
                "fit": self.fit,
                "residuals": self.residuals,
                "um_per_px": self.um_per_px,
                "image_size": list(self.image_size) if self.image_size else None,
                "bounds": list(self.bounds) if self.bounds is not None else None,
                "hull": np.asarray(self.hull).tolist() if self.hull is not None else None,
            }
        )

    @classmethod
    def from_dict(cls, data: dict, source: str = "calibration") -> Calibration:
        validate(data, source)
        free = tuple(n for n in PARAM_NAMES if n in data["free"])
        params = np.array([float(data["params"][n]) for n in PARAM_NAMES])
        for name in PARAM_NAMES:
            if name not in free and params[INDEX[name]] != 0.0:
                raise InputFileError(
                    f"{source}: field 'params.{name}' is {params[INDEX[name]]:g} but {name} is not "
                    "in 'free'; fixed parameters must be 0"
                )
        stderr = np.full(N_PARAMS, np.nan)
        for name, value in data["stderr"].items():
            if name not in free:
                raise InputFileError(f"{source}: field 'stderr.{name}': {name} is not a free parameter")
            stderr[INDEX[name]] = np.nan if value is None else float(value)
        rows = data["covariance"]
        k = len(free)
        if len(rows) != k or any(len(row) != k for row in rows):
            raise InputFileError(
                f"{source}: field 'covariance' must be {k} x {k} (one row and column per free "
                "parameter, in 'free' order)"
            )
        cov = np.array([[np.nan if v is None else float(v) for v in row] for row in rows], float)
        cov = cov.reshape(k, k)
        size = data.get("image_size")
        hull = data.get("hull")
        return cls(
            free=free,
            params=params,
            stderr=stderr,
            covariance=cov,
            fit=dict(data["fit"]),
            residuals=dict(data["residuals"]),
            um_per_px=data.get("um_per_px"),
            image_size=tuple(size) if size else None,
            bounds=tuple(data["bounds"]) if data.get("bounds") else None,
            hull=np.array(hull, float) if hull else None,
            name=data.get("name"),
            source=data.get("source"),
            oapcal_version=data.get("oapcal_version", "unknown"),
            created_utc=data.get("created_utc", "unknown"),
        )


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
    if data.get("version") != VERSION:
        raise InputFileError(
            f"{source}: field 'version' is {data.get('version')!r}; this oapcal reads version "
            f"{VERSION} calibration files"
        )
    validator = jsonschema.Draft202012Validator(_schema())
    error = jsonschema.exceptions.best_match(validator.iter_errors(data))
    if error is not None:
        where = ".".join(str(p) for p in error.absolute_path) or "(top level)"
        raise InputFileError(f"{source}: field '{where}': {error.message}")


def save_calibration(calibration: Calibration, path: str | Path) -> None:
    """Write a calibration file atomically (``-`` writes to stdout)."""
    text = json.dumps(calibration.to_dict(), indent=2) + "\n"
    if str(path) == "-":
        import sys

        sys.stdout.write(text)
        return
    with atomic_write(path) as fh:
        fh.write(text)


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate a calibration file; errors name the file and the bad field."""
    name = str(path)
    data = read_json(
        path, "calibration file", missing="no such calibration file; run 'oapcal fit' to make one"
    )
    return Calibration.from_dict(data, source=name)
