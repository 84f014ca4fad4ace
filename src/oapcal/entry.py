"""The one entry point of calibration: :func:`calibrate` (``oapcal.calibrate``) fits an
Eq. (1) model spec or the physical relay from a :class:`~oapcal.optics.relay_model.RelayDesign`
with one signature, and applies every rule a front-end used to apply itself: the point
checks, the rotation policy, the refusal of a fit that gives no usable model
(:func:`oapcal.calibration.check_fit_usable`) and of an implausible relay fit.  It sits
above :mod:`oapcal.optics` (which holds the relay), so that the core
(:mod:`oapcal.calibration`, below the optics) needs no upward import.

>>> from oapcal.synthetic import synthetic_pairs
>>> data = synthetic_pairs(seed=0)
>>> cal = calibrate(data.xy_u, data.xy_d, "paper", error_model=False)
>>> cal.model_family, cal.fit.converged
('brown-conrady', True)
"""

from __future__ import annotations

from oapcal import calibration as _calibration
from oapcal.calibration import Calibration, UnusableFitError
from oapcal.errors import ModelSpecError
from oapcal.optics.relay_model import RelayDesign

__all__ = ["Calibration", "calibrate", "is_relay_spec"]


def is_relay_spec(model) -> bool:
    """Whether ``model`` names the relay family: ``"relay"`` or ``"relay:NAMES"``."""
    return isinstance(model, str) and (model.strip() == "relay" or model.strip().startswith("relay:"))


def calibrate(
    xy_u,
    xy_d,
    model="paper",
    *,
    design: RelayDesign | None = None,
    priors=None,
    check: bool = True,
    **options,
) -> Calibration:
    """Fit ``model`` to reference points ``xy_u`` and distorted points ``xy_d`` ``(N, 2)``.

    ``model`` is an Eq. (1) spec (:func:`oapcal.calibration.calibrate`, whose keywords
    ``init``, ``normalization``, ``um_per_px``, ``image_size``, ``name``, ``source``,
    ``rotation``, ``error_model`` and the solver's options go in ``options``); or a
    :class:`~oapcal.optics.relay_model.RelayDesign` (the relay model with its default free
    subset); or a relay spec ``"relay"`` / ``"relay:NAMES"`` with the nominal relay in
    ``design`` (:func:`oapcal.optics.relay_model.calibrate_relay`, which takes
    ``priors``, ``um_per_px``, ``image_size``, ``name``, ``source`` and the solver's options).

    With ``check`` (default True) a fit that gives no usable model raises
    :class:`~oapcal.calibration.UnusableFitError` (:func:`~oapcal.calibration.check_fit_usable`),
    as does a converged relay fit that is not a plausible misalignment
    (:func:`oapcal.optics.relay_model.implausible`); bad input raises the library's named
    errors as before.
    """
    if isinstance(model, RelayDesign):
        design, model = model, "default"
    elif is_relay_spec(model) and design is None:
        raise ModelSpecError(
            f"model {model!r} is the physical relay: give its nominal design (design=RelayDesign(...))",
            param="design",
        )
    if design is None:
        if priors is not None:
            raise ModelSpecError(
                "priors apply to a relay model: give model a RelayDesign (or a relay spec and design)",
                param="priors",
            )
        return _calibration.calibrate(xy_u, xy_d, model, check=check, **options)
    from oapcal.optics.relay_model import calibrate_relay

    cal = calibrate_relay(xy_u, xy_d, design, model, priors=priors, check=check, **options)
    if check:
        check_relay_plausible(cal, options.get("source"))
    return cal


def check_relay_plausible(cal: Calibration, source: str | None = None) -> None:
    """Refuse a converged relay fit that is not a plausible misalignment of its design
    (:func:`oapcal.optics.relay_model.implausible`): :class:`~oapcal.calibration.UnusableFitError`
    with code ``"implausible"``."""
    from oapcal.optics.relay_model import implausible

    if cal.relay_design is None or not cal.fit.converged:
        return
    problem = implausible(cal)
    if problem:
        raise UnusableFitError(
            f"{source or cal.source or 'the point data'}: {problem}", code="implausible", param="model"
        )
