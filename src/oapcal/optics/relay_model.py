"""The physical relay as a distortion model: fit the relay's misalignment and the target's
pose to point pairs (``docs/models.md``).

The model family :data:`oapcal.model.RELAY` maps a reference point (px, the ideal image
of the target) to the distorted point (px) by tracing its chief ray through a relay built
from a nominal design (:class:`RelayDesign`) plus the misalignment being fitted; the
compiled point function is :func:`oapcal._relay_kernel.relay_point_value`.  Everything of
the one solver (:func:`oapcal.fitting.fit_batch`) works for it; this module adds the
design, the parameter vector and its subsets, and the fit with physical standard errors
and an identifiability check.

>>> design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(320.0, 240.0))
>>> p = relay_params(design, {"m2_tilt_x": 0.02})
>>> names = [n for n, v in zip(RELAY.param_names, p) if v and n in RELAY_MISALIGNMENT_NAMES]
>>> names
['m2_tilt_x']
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError, InputFileError, ModelSpecError
from oapcal.model import (
    MICROSCOPE_NAMES,
    RELAY,
    RELAY_MICROSCOPE,
    RELAY_MISALIGNMENT_NAMES,
    RELAY_POSE_NAMES,
    distort,
)
from oapcal.optics.design import DESIGN_FIELDS, FIELDS, MICROSCOPE_MAGNIFICATION_RANGE
from oapcal.optics.misalign import PARAMETERS, Misalignment
from oapcal.optics.relay import oap_relay, paraxial_matrix

#: The parameters fitted by default (``--model relay``): the target's whole pose and the
#: six misalignment directions that reproduced fields of relays with all 20 values
#: perturbed best in ``benchmarks/models.py`` (``docs/models.md``): the second mirror's
#: decentre (its tilt acts almost the same way), d1, the camera's defocus and tilts.
DEFAULT_FREE = ("scale", "rotation", "shift_x", "shift_y", "m2_decentre_x", "m2_decentre_y", "d1",
                "camera_defocus", "camera_tilt_x", "camera_tilt_y")  # fmt: skip

#: With a microscope behind the relay (``relay+microscope``) the default is the same:
#: the microscope's magnification stays the design's (the target's scale absorbs an error
#: of it: the two differ only through the relay's own distortion, and fitted together the
#: fit does not converge in 5 of 6 cases) and its radial term is left out (fitted from
#: landmarks over the middle third of the frame it extrapolates worse than it helps: frame
#: max 3.5 against 2.3 px, ``benchmarks/microscope.py``); add ``microscope`` for it.
DEFAULT_FREE_MICROSCOPE = DEFAULT_FREE

#: Short names accepted in subsets (``relay:d1,tilt2x,camera``): each stands for these
#: parameters (``microscope`` and ``magnification`` only with a microscope).
ALIASES: dict[str, tuple[str, ...]] = {
    "pose": RELAY_POSE_NAMES,
    "tilt1": ("m1_tilt_x", "m1_tilt_y"),
    "tilt2": ("m2_tilt_x", "m2_tilt_y"),
    "tilt1x": ("m1_tilt_x",),
    "tilt1y": ("m1_tilt_y",),
    "tilt2x": ("m2_tilt_x",),
    "tilt2y": ("m2_tilt_y",),
    "decentre1": ("m1_decentre_x", "m1_decentre_y"),
    "decentre2": ("m2_decentre_x", "m2_decentre_y"),
    "clock1": ("m1_clock",),
    "clock2": ("m2_clock",),
    "focal1": ("m1_focal_length",),
    "focal2": ("m2_focal_length",),
    "camera": ("camera_tilt_x", "camera_tilt_y"),
    "defocus": ("camera_defocus",),
    "object": ("object_tilt_x", "object_tilt_y"),
    "stop": ("stop_decentre_x", "stop_decentre_y"),
    "microscope": ("microscope_k1",),
    "magnification": ("microscope_magnification",),
}


def _two_finite(xy) -> bool:
    try:
        return len(xy) == 2 and all(
            not isinstance(c, bool | str | bytes) and np.isfinite(float(c)) for c in xy
        )
    except (TypeError, ValueError):
        return False


@dataclass(frozen=True)
class RelayDesign:
    """The nominal relay a fit starts from (as ``oapcal simulate relay`` takes it).

    ``setup`` 1 or 2 (the paper's d1 = 860 / 660 mm) unless ``d1_mm`` is given;
    ``focal_length_mm`` both mirrors' (``focal_length_2_mm`` the second's if different);
    ``orientation`` ``"U"`` or ``"Z"``; ``stop_distance_mm`` (0: at the first mirror);
    ``pixel_size_um`` the camera's pixel pitch; ``centre`` (px) the point of the
    reference frame on the relay's axis (None: the middle of the reference points);
    ``microscope_magnification`` a finite-conjugate microscope between the relay's image
    and the camera, its lateral magnification, negative when it inverts the image (-5: a
    5x objective forming a real, inverted image); None (default): the camera is at the
    relay's image plane.  With a microscope the model family is ``relay+microscope``.

    Units, defaults and ranges: :data:`oapcal.optics.design.DESIGN_FIELDS` (one table, which
    the commands' design options are built from too).
    """

    setup: int | None = FIELDS["setup"].default
    d1_mm: float | None = FIELDS["d1_mm"].default
    focal_length_mm: float = FIELDS["focal_length_mm"].default
    focal_length_2_mm: float | None = FIELDS["focal_length_2_mm"].default
    orientation: str = FIELDS["orientation"].default
    stop_distance_mm: float = FIELDS["stop_distance_mm"].default
    pixel_size_um: float = FIELDS["pixel_size_um"].default
    centre: tuple[float, float] | None = FIELDS["centre"].default
    microscope_magnification: float | None = FIELDS["microscope_magnification"].default

    def __post_init__(self):
        """Refuse, naming the field, a design value that is not a number in its range
        (:data:`~oapcal.optics.design.DESIGN_FIELDS`): a NaN or negative pixel size would
        otherwise show only as a relay that images nothing."""
        for f in _RANGED:
            value = getattr(self, f.name)
            ok = isinstance(value, int | float | np.integer | np.floating) or value is None
            if not (ok and f.accepts(value)):
                raise DataError(f"relay design {f.name} is {value!r}; it must be a number in "
                                f"{f.describe_range()}", param="design")  # fmt: skip
        if self.centre is not None and not _two_finite(self.centre):
            raise DataError(f"relay design centre is {self.centre!r}; it must be two finite numbers (px)",
                            param="design")  # fmt: skip

    @property
    def family(self):
        """The model family of this design: :data:`~oapcal.model.RELAY`, or
        :data:`~oapcal.model.RELAY_MICROSCOPE` with a microscope."""
        return RELAY if self.microscope_magnification is None else RELAY_MICROSCOPE

    @property
    def object_um_per_px(self) -> float:
        """Object um per reference px: the pixel size over the relay's and the microscope's
        magnification (their absolute values)."""
        f1, f2 = self.relay().focal_lengths_mm
        mag = 1.0 if self.microscope_magnification is None else abs(float(self.microscope_magnification))
        return float(self.pixel_size_um) * f1 / f2 / mag

    def relay(self, misalignment=None):
        """The relay (:func:`oapcal.optics.relay.oap_relay`) of this design."""
        return oap_relay(self.setup, d1_mm=self.d1_mm, orientation=self.orientation,
                         stop_distance_mm=self.stop_distance_mm, focal_length_mm=self.focal_length_mm,
                         focal_length_2_mm=self.focal_length_2_mm, misalignment=misalignment)  # fmt: skip

    def with_centre(self, xy_u) -> RelayDesign:
        """This design with ``centre`` set to the middle of the points' range if unset."""
        if self.centre is not None:
            return self
        xy_u = np.asarray(xy_u, float)
        mid = 0.5 * (xy_u.min(axis=0) + xy_u.max(axis=0))
        return RelayDesign.from_dict({**self.to_dict(), "centre": (float(mid[0]), float(mid[1]))})

    def to_dict(self) -> dict:
        out = {
            "setup": self.setup, "d1_mm": self.d1_mm, "focal_length_mm": self.focal_length_mm,
            "focal_length_2_mm": self.focal_length_2_mm, "orientation": self.orientation,
            "stop_distance_mm": self.stop_distance_mm, "pixel_size_um": self.pixel_size_um,
            "centre": None if self.centre is None else [float(c) for c in self.centre],
        }  # fmt: skip
        # written only with a microscope: a relay design's record is what it was before
        if self.microscope_magnification is not None:
            out["microscope_magnification"] = float(self.microscope_magnification)
        return out

    @classmethod
    def from_dict(cls, data: Mapping) -> RelayDesign:
        data = dict(data)
        if data.get("centre") is not None:
            data["centre"] = tuple(float(c) for c in data["centre"])
        return cls(**data)


def relay_params(
    design: RelayDesign, misalignment=None, pose: Mapping | None = None, microscope: Mapping | None = None
) -> np.ndarray:
    """The relay family's parameter vector ``(36,)``: ``pose`` (``scale``, ``rotation``
    deg, ``shift_x``, ``shift_y`` px; identity by default), the ``misalignment`` (a
    :class:`~oapcal.optics.misalign.Misalignment` or dict; none by default) and the
    ``design``'s constants.  ``design.centre`` must be set (:meth:`RelayDesign.with_centre`).

    With a microscope in the design, the ``relay+microscope`` vector ``(39,)``: the same,
    then ``microscope`` (``microscope_magnification``, default the design's, and
    ``microscope_k1``, default 0) and the design's magnification."""
    if design.centre is None:
        raise ModelSpecError("the relay design needs its centre (px): give it or use with_centre(points)")
    mis = Misalignment.of(misalignment)
    pose = {"scale": 1.0, "rotation": 0.0, "shift_x": 0.0, "shift_y": 0.0, **dict(pose or {})}
    unknown = sorted(set(pose) - set(RELAY_POSE_NAMES))
    if unknown:
        raise ModelSpecError(f"unknown pose value {unknown[0]!r}: use {', '.join(RELAY_POSE_NAMES)}")
    relay = design.relay()
    with np.errstate(all="ignore"):
        paraxial = paraxial_matrix(relay)
    if not np.isfinite(paraxial).all() or abs(np.linalg.det(paraxial)) < 1e-300:
        raise DataError(
            f"the relay design {_design_words(design)} has no paraxial image (its paraxial matrix "
            "is singular or not finite): check the design values",
            param="design",
        )
    inv = np.linalg.inv(paraxial)
    f1, f2 = relay.focal_lengths_mm
    design_values = {
        "d1_mm": relay.d1_mm, "f1_mm": f1, "f2_mm": f2,
        "orientation": 1.0 if relay.orientation == "U" else -1.0,
        "stop_mm": relay.stop_distance_mm, "pixel_mm": float(design.pixel_size_um) * 1e-3,
        "cx": float(design.centre[0]), "cy": float(design.centre[1]),
        "a11": inv[0, 0], "a12": inv[0, 1], "a21": inv[1, 0], "a22": inv[1, 1],
    }  # fmt: skip
    values = {**pose, **mis.to_dict(), **design_values}
    family = design.family
    if family is RELAY_MICROSCOPE:
        mag = float(design.microscope_magnification)
        scope = {"microscope_magnification": mag, "microscope_k1": 0.0, **dict(microscope or {})}
        unknown = sorted(set(scope) - set(MICROSCOPE_NAMES))
        if unknown:
            raise ModelSpecError(
                f"unknown microscope value {unknown[0]!r}: use {', '.join(MICROSCOPE_NAMES)}"
            )
        values.update(scope, microscope_design_magnification=mag)
    elif microscope:
        raise ModelSpecError("microscope values need a design with a microscope (microscope_magnification)")
    return np.array([float(values[n]) for n in family.param_names])


#: The design's number fields (:data:`~oapcal.optics.design.DESIGN_FIELDS`), and their
#: ranges as ``field -> (lowest, highest, lowest excluded, may be null)``.
_RANGED = tuple(f for f in DESIGN_FIELDS if f.numeric)
DESIGN_RANGES = {f.name: (f.low, f.high, f.low_open, f.nullable) for f in _RANGED}


def _design_words(design: RelayDesign) -> str:
    """The design's values in a message: ``(d1 0.001 mm, focal length 50.8 mm, ...)``."""
    relay_d1 = design.relay().d1_mm  # the setup's d1 unless d1_mm is given
    centre = None if design.centre is None else f"centre ({design.centre[0]:.4g}, {design.centre[1]:.4g}) px"
    parts = [
        f"d1 {relay_d1:g} mm",
        f"focal length {design.focal_length_mm:g} mm",
        f"pixel {design.pixel_size_um:g} um",
        centre,
    ]
    return "(" + ", ".join(p for p in parts if p) + ")"


def design_from_record(record, params, source: str = "calibration") -> RelayDesign:
    """The :class:`RelayDesign` a relay calibration stores (``record``: its
    ``relay_design``), checked: every field known and in range (:data:`DESIGN_RANGES`,
    ``setup`` 1, 2 or null, ``orientation`` U or Z, ``centre`` two finite numbers), and the
    design constants in ``params`` (never fitted) those the design gives.  Raises
    :class:`~oapcal.errors.InputFileError` naming the field; a hand-edited constant would
    otherwise show only as a model that folds or is not finite.
    """

    def bad(field, what):
        return InputFileError(f"{source}: field '{field}' {what}")

    _check_record(record, bad)
    design = RelayDesign.from_dict(record)
    family = design.family
    if len(params) != family.n_params:
        raise bad(
            "relay_design.microscope_magnification",
            f"says the model is {family.name!r} ({family.n_params} parameters) but the file holds "
            f"{len(params)}; restore the design or refit",
        )
    try:
        expected = relay_params(design)
    except DataError as exc:  # e.g. no paraxial image: name the file's field
        raise bad("relay_design", f"describes no working relay: {exc}") from None
    for name in family.never_free:
        i = family.param_names.index(name)
        if not abs(params[i] - expected[i]) <= 1e-9 * max(1.0, abs(expected[i])):
            raise bad(
                f"params.{name}",
                f"is {params[i]:.12g} but the relay_design gives {expected[i]:.12g}; design constants "
                "are never fitted: restore the value or refit",
            )
    return design


def _check_record(record, bad) -> None:
    """The checks of :func:`design_from_record` on the record's fields, each raising
    ``bad(field, what)``."""
    if not isinstance(record, Mapping):
        raise bad("relay_design", "must be an object (the design a relay model was fitted from)")
    unknown = sorted(set(record) - set(RelayDesign.__dataclass_fields__))
    if unknown:
        raise bad(
            f"relay_design.{unknown[0]}",
            f"is not a design field (fields: {', '.join(RelayDesign.__dataclass_fields__)})",
        )
    for f in _RANGED:
        value = record.get(f.name, f.default)
        if not ((value is None or isinstance(value, int | float)) and f.accepts(value)):
            raise bad(f"relay_design.{f.name}", f"is {value!r}; it must be a number in {f.describe_range()}")
    if record.get("setup", 1) not in (1, 2, None) or isinstance(record.get("setup"), bool):
        raise bad("relay_design.setup", f"is {record.get('setup')!r}; it must be 1, 2 or null")
    if record.get("setup", 1) is None and record.get("d1_mm") is None:
        raise bad("relay_design.d1_mm", "is null and so is 'setup'; give one of them")
    if record.get("orientation", "U") not in ("U", "Z"):
        raise bad("relay_design.orientation", f'is {record.get("orientation")!r}; it must be "U" or "Z"')
    centre = record.get("centre")
    if not (
        isinstance(centre, list | tuple) and len(centre) == 2
        and all(isinstance(c, int | float) and not isinstance(c, bool) and np.isfinite(c) for c in centre)
    ):  # fmt: skip
        raise bad("relay_design.centre", f"is {centre!r}; it must be two numbers [x, y] in px")
    mag = record.get("microscope_magnification")
    lo, hi = MICROSCOPE_MAGNIFICATION_RANGE
    if mag is not None and (
        isinstance(mag, bool) or not isinstance(mag, int | float) or not lo <= abs(mag) <= hi
    ):
        raise bad(
            "relay_design.microscope_magnification",
            f"is {mag!r}; it must be null (no microscope) or a number with {lo:g} <= |M| <= {hi:g} "
            "(negative: the microscope inverts the image)",
        )


def relay_mask(spec="default", family=RELAY) -> np.ndarray:
    """The free-parameter mask ``(36,)`` of a relay subset: ``"default"``
    (:data:`DEFAULT_FREE`), ``"all"`` (every pose and misalignment value), or names and
    :data:`ALIASES` separated by commas (``"pose,d1,tilt2x,tilt2y,camera"``); a subset
    always fits the pose (an unknown target has one).

    ``family`` :data:`~oapcal.model.RELAY_MICROSCOPE` (``design.family`` of a design with a
    microscope): the mask ``(39,)``; ``"default"`` is then :data:`DEFAULT_FREE_MICROSCOPE`,
    ``"all"`` adds the microscope's magnification and radial term, and the names may
    include them (``microscope``, ``magnification``)."""
    scope = family is RELAY_MICROSCOPE
    if isinstance(spec, str):
        text = spec.strip()
        if text.startswith("relay:"):
            text = text[len("relay:") :]
        if text in ("", "default", "relay"):
            names = set(DEFAULT_FREE_MICROSCOPE if scope else DEFAULT_FREE)
        elif text == "all":
            names = set(RELAY_POSE_NAMES) | set(RELAY_MISALIGNMENT_NAMES)
            names |= set(MICROSCOPE_NAMES) if scope else set()
        else:
            names = set(RELAY_POSE_NAMES)
            for item in (t.strip() for t in text.split(",")):
                if item in ALIASES:
                    names.update(ALIASES[item])
                elif item in PARAMETERS or item in RELAY_POSE_NAMES or item in MICROSCOPE_NAMES:
                    names.add(item)
                else:
                    raise ModelSpecError(
                        f"unknown relay parameter {item!r}: use names of oapcal.optics.misalign.PARAMETERS, "
                        f"the pose ({', '.join(RELAY_POSE_NAMES)}) or {', '.join(ALIASES)}"
                    )
    else:
        names = set(spec)
    if not scope and names & set(MICROSCOPE_NAMES):
        name = sorted(names & set(MICROSCOPE_NAMES))[0]
        raise ModelSpecError(
            f"the relay parameter {name!r} is the microscope's: give the design a microscope "
            "(its microscope_magnification, e.g. -5 for a 5x objective that inverts the image)",
            param="microscope_magnification",
        )
    return np.array([n in names for n in family.param_names])


#: A subset whose normalized parameter Jacobian has a singular value below this fraction of
#: the largest is not identifiable from the points (the chief-ray trace is exact to
#: ~1e-13 mm, so central differences resolve ~1e-8; the exact degeneracies of the relay,
#: e.g. a mirror's tilt against its decentre, sit at 1e-9 .. 1e-11).
RANK_TOL = 1e-6


@dataclass(frozen=True)
class Identifiability:
    """How well points determine a relay subset: ``singular`` the singular values of the
    parameter Jacobian with unit-norm columns (largest first, relative to the largest);
    ``degenerate`` for each one below :data:`RANK_TOL` the parameters that move together
    in its null direction (component above 0.3), strongest first."""

    names: tuple[str, ...]
    singular: np.ndarray
    degenerate: tuple[tuple[str, ...], ...]

    @property
    def ok(self) -> bool:
        return not self.degenerate

    def message(self) -> str:
        groups = "; ".join(" ~ ".join(g) for g in self.degenerate)
        return (
            f"the points cannot tell these relay parameters apart (rank-deficient Jacobian): {groups}; "
            "fit a subset without one of each group"
        )


def identifiability(xy_u, params, mask, jac: np.ndarray | None = None, *, family=None) -> Identifiability:
    """The identifiability of the free parameters ``mask`` of the relay model ``params`` at
    the reference points ``xy_u (N, 2)`` (:class:`Identifiability`).  ``jac`` is the
    parameter Jacobian ``(N, 2, P)`` there if already known (many subsets of one model).
    ``family``: the model's family (a design's ``family``); None: the relay family of the
    mask's length."""
    from oapcal.model import family_of, jacobian_params

    mask = np.asarray(mask, bool)
    family = family_of(mask, family)
    names = tuple(n for n, m in zip(family.param_names, mask) if m)
    if jac is None:
        jac = jacobian_params(np.asarray(xy_u, float), np.asarray(params, float), family=family)
    jac = jac[..., mask]
    a = jac.reshape(-1, int(mask.sum()))
    if not np.isfinite(a).all():
        bad = tuple(n for n, ok in zip(names, np.isfinite(a).all(axis=0)) if not ok)
        raise DataError(
            f"the relay model's derivatives are not finite at the reference points for {', '.join(bad)}: "
            "the design (d1, focal lengths, pixel size, centre) does not describe a working relay "
            "for these points; check the design values and the points' units",
            param="design",
        )
    norms = np.linalg.norm(a, axis=0)
    dead = tuple((n,) for n, v in zip(names, norms) if not v > 0)
    a = a / np.where(norms > 0, norms, 1.0)
    _, s, vt = np.linalg.svd(a, full_matrices=False)
    rel = s / s[0] if s[0] > 0 else np.zeros_like(s)
    groups = list(dead)
    for value, v in zip(rel[::-1], vt[::-1]):
        if value >= RANK_TOL:
            break
        order = np.argsort(-np.abs(v))
        group = tuple(names[i] for i in order if abs(v[i]) > 0.3)
        if group and group not in groups:
            groups.append(group)
    return Identifiability(names, rel, tuple(groups))


def default_centre(design: RelayDesign, xy_u, image_size=None) -> RelayDesign:
    """``design`` with its centre set if unset: the image centre ``((w - 1) / 2, (h - 1) /
    2)`` with ``image_size``, else the middle of the reference points ``xy_u``."""
    if design.centre is not None:
        return design
    if image_size is not None:
        w, h = image_size
        return RelayDesign.from_dict({**design.to_dict(), "centre": ((float(w) - 1) / 2, (float(h) - 1) / 2)})
    return design.with_centre(xy_u)


#: The iteration cap of a relay fit (:func:`calibrate_relay`; the solver's default is 200).
RELAY_MAX_ITER = 1000

# ------------------------------------------------------------------------------ priors

#: The default priors (``--priors default``): one Gaussian per misalignment value, centred
#: on the design, its width (1 sigma) the tolerance of its group in the words of
#: ``oapcal tolerance`` (:data:`oapcal.optics.tolerance.GROUPS`): mirror tip/tilt and
#: clocking 0.05 deg (kinematic mounts after alignment), mirror and stop decentres 0.2 mm,
#: focal lengths 0.2 mm (0.4 % of a 50.8 mm OAP), d1 5 % of the design's (a rail set by a
#: ruler), camera and object-plane tilt 1 deg (a C-mount and a stage), camera defocus
#: 0.2 mm; and the target's scale 1 % (the reference points of a relay fit are the target's
#: ideal image in px at the design's magnification: a target printed or measured to 1 %).
#: The target's placement (rotation, shift) and the microscope's values take no prior.
DEFAULT_PRIORS: dict[str, float] = {
    "scale": 1.0,
    "tilt": 0.05, "decentre": 0.2, "clock": 0.05, "focal_length": 0.2, "d1": 5.0, "stop_decentre": 0.2,
    "camera_tilt": 1.0, "defocus": 0.2, "object_tilt": 1.0,
}  # fmt: skip
#: The words of :data:`DEFAULT_PRIORS` with their units (``d1`` in % of the design's d1).
PRIOR_UNITS = {"scale": "%", "tilt": "deg", "decentre": "mm", "clock": "deg", "focal_length": "mm", "d1": "%",
               "stop_decentre": "mm", "camera_tilt": "deg", "defocus": "mm",
               "object_tilt": "deg"}  # fmt: skip
#: The noise-scale iterations of a MAP fit without a given noise (:func:`map_fit`).
NOISE_ITERATIONS = 4
#: The least landmark noise (px per coordinate) that weighs the priors when the noise is
#: estimated from the fit (:func:`map_fit`; ``--priors noise_floor_px=...`` sets it).  A
#: prior row is ``s (p - p0) / width``: as the estimate ``s`` goes to 0 (landmarks traced
#: without noise) the priors become rigid constraints that fight the data, and ``relay:all``
#: hit the iteration cap (1,000 Jacobians, 47 s) on a noise-free 11 x 11 grid.  No landmark
#: is located better than about 0.05 px (rendered dot grids and chessboards: 0.017-0.050 px,
#: docs/detection.md) and a relay fit's residual carries a 0.03-0.1 px model floor (mirror
#: figure, sensor), so a noise below 0.05 px is not evidence the priors should tighten.
NOISE_FLOOR_PX = 0.05


@dataclass(frozen=True)
class RelayPriors:
    """Gaussian priors on a relay's misalignment (:func:`parse_priors`).

    ``widths``: the 1-sigma width of each group of :data:`DEFAULT_PRIORS` (``d1`` in % of
    the design's d1, ``scale`` in % of the target's scale) or of one misalignment value by
    its name (deg or mm; ``d1_mm`` for d1 in mm); ``inf``: no prior (that value as free as
    without priors); ``0``: fixed at the design.  Every prior is centred on the design (no
    misalignment, scale 1).  ``noise_px``: the landmarks' noise (px per coordinate) that
    weighs the priors against the residuals; None (default): estimated from the fit's own
    residuals, ``sqrt(RSS / (n - k_eff))``, and never below ``noise_floor_px``
    (:data:`NOISE_FLOOR_PX`; a given ``noise_px`` is used as given).
    """

    widths: Mapping[str, float]
    noise_px: float | None = None
    spec: str = "default"
    noise_floor_px: float = NOISE_FLOOR_PX

    def sigma(self, design: RelayDesign) -> dict[str, float]:
        """The width (deg or mm) of every misalignment value of :data:`PARAMETERS`, and of the
        target's ``scale`` (a fraction) when it has one."""
        from oapcal.optics.tolerance import GROUPS

        d1_mm = design.relay().d1_mm
        out = {name: np.inf for name in PARAMETERS}
        for key, value in self.widths.items():
            if key in GROUPS:
                for name in GROUPS[key]:
                    out[name] = value * d1_mm / 100.0 if key == "d1" else value
        for key, value in self.widths.items():
            if key == "scale":  # in %: the target's scale is 1 when the reference is its ideal image
                out["scale"] = value / 100.0
            elif key == "d1_mm":
                out["d1"] = value
            elif key in PARAMETERS and key not in GROUPS:
                out[key] = value
        return out

    def arrays(self, design: RelayDesign, noise_px: float) -> tuple[np.ndarray, np.ndarray]:
        """``(mean, sigma)`` over the family's parameters for :func:`oapcal.fitting.fit_batch`
        (its ``prior``): the design's vector, and each width over ``noise_px`` (a prior row
        ``(p - p0) / width`` weighs like a residual of ``noise_px``); inf where none."""
        family = design.family
        sig = self.sigma(design)
        sigma = np.array([sig.get(n, np.inf) / float(noise_px) for n in family.param_names])
        return relay_params(design), sigma

    def to_dict(self, design: RelayDesign | None = None) -> dict:
        """The record a calibration keeps: ``spec``, ``widths`` (the user's words), the
        ``noise_px`` given, and with ``design`` the ``sigma`` of every value with a finite
        prior (deg or mm)."""
        out = {"spec": self.spec, "widths": {k: float(v) for k, v in self.widths.items() if np.isfinite(v)},
               "free_of_prior": sorted(k for k, v in self.widths.items() if not np.isfinite(v)),
               "noise_px": None if self.noise_px is None else float(self.noise_px),
               "noise_floor_px": float(self.noise_floor_px)}  # fmt: skip
        if design is not None:
            out["sigma"] = {k: float(v) for k, v in self.sigma(design).items() if np.isfinite(v)}
        return out


def _prior_value(key, value) -> float:
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("inf", "none", "off", "free"):
            return np.inf
        try:
            value = float(text)
        except ValueError:
            raise ModelSpecError(
                f"prior {key!r}: {value!r} is not a number; give a width (>= 0) or inf", param="priors"
            ) from None
    if isinstance(value, bool) or not isinstance(value, int | float) or np.isnan(value) or value < 0:
        raise ModelSpecError(f"prior {key!r}: {value!r} must be a width >= 0 (inf: no prior)", param="priors")
    return float(value)


def priors_from_dict(data: Mapping, spec: str = "file") -> RelayPriors:
    """:class:`RelayPriors` from ``{"tilt": 0.05, ..., "noise_px": 0.3}`` (the defaults for
    the words not given; ``{"default": false}`` or ``"base": "none"`` starts from no priors
    instead), or ``{"widths": {...}, "noise_px": ...}``; unknown words raise
    :class:`~oapcal.errors.ModelSpecError` naming them."""
    if not isinstance(data, Mapping):
        raise ModelSpecError('priors must be an object of widths such as {"tilt": 0.05}', param="priors")
    data = dict(data)
    if isinstance(data.get("widths"), Mapping):
        data = {**data.pop("widths"), **data}
    noise = data.pop("noise_px", data.pop("noise", None))
    floor = data.pop("noise_floor_px", NOISE_FLOOR_PX)
    base = data.pop("base", "default")
    if base not in ("default", "none"):
        raise ModelSpecError(f"prior 'base' must be 'default' or 'none', got {base!r}", param="priors")
    widths = dict(DEFAULT_PRIORS) if base == "default" else {}
    known = set(DEFAULT_PRIORS) | (set(PARAMETERS) - {"d1"}) | {"d1_mm", "scale"}
    for key, value in data.items():
        if key not in known:
            raise ModelSpecError(
                f"unknown prior {key!r}: use {', '.join(DEFAULT_PRIORS)} (d1 and scale in %), a "
                "misalignment name of oapcal.optics.misalign.PARAMETERS, d1_mm, noise_px or noise_floor_px",
                param="priors",
            )
        widths[key] = _prior_value(key, value)
    if noise is not None:
        noise = _prior_value("noise_px", noise)
        if not 0 < noise < np.inf:
            raise ModelSpecError(f"prior 'noise_px' must be a positive number of px, got {noise!r}",
                                 param="priors")  # fmt: skip
    floor = _prior_value("noise_floor_px", floor)
    if not floor < np.inf:
        raise ModelSpecError(f"prior 'noise_floor_px' must be a number of px >= 0, got {floor!r}",
                             param="priors")  # fmt: skip
    return RelayPriors(widths, noise, spec, floor)


def parse_priors(text) -> RelayPriors | None:
    """``"off"`` (None: no priors, the fit as without them), ``"default"``
    (:data:`DEFAULT_PRIORS`), or ``"key=value,..."`` over the defaults
    (``"tilt=0.1,d1=2,noise_px=0.3"``; ``base=none`` starts from no priors); a mapping as
    :func:`priors_from_dict`.  (A JSON file is read by the command line into a mapping.)"""
    if text is None or isinstance(text, RelayPriors):
        return text
    if isinstance(text, Mapping):
        return priors_from_dict(text)
    text = str(text).strip()
    if text in ("off", "none", ""):
        return None
    if text == "default":
        return RelayPriors(dict(DEFAULT_PRIORS))
    values = {}
    for item in (t.strip() for t in text.split(",") if t.strip()):
        key, sep, value = item.partition("=")
        if not sep:
            raise ModelSpecError(
                f"bad prior {item!r}: use 'off', 'default', a JSON file or key=value pairs such as "
                "'tilt=0.1,d1=2'",
                param="priors",
            )
        values[key.strip()] = value.strip()
    return priors_from_dict(values, spec=text)


# Ten parameters: the data, the design and the subsets, then keyword options of fit_batch's.
def map_fit(xy_u, xy_d, design: RelayDesign, masks, priors: RelayPriors, *, p0=None, points=None,
            covariance: bool = True, max_iter: int = RELAY_MAX_ITER, noise_px=None):  # fmt: skip
    """The maximum a posteriori fit of relay subsets ``masks (B, P)`` under ``priors``:
    :func:`oapcal.fitting.fit_batch` with the priors' rows.  Without a noise in the priors
    (or ``noise_px``, one per item or shared) the landmarks' noise that weighs the rows is
    estimated from the fit itself: from 1 px, refitted at ``sqrt(RSS / (n - k_eff))``, but
    at least the priors' ``noise_floor_px`` (:data:`NOISE_FLOOR_PX`), until it changes by
    under 5 % (at most :data:`NOISE_ITERATIONS` fits).  Returns ``(BatchFit, noise_px (B,))``."""
    from oapcal.fitting import fit_batch

    masks = np.atleast_2d(np.asarray(masks, bool))
    start = relay_params(design) if p0 is None else np.asarray(p0, float)
    start = np.broadcast_to(start, masks.shape)
    given = priors.noise_px if noise_px is None else noise_px
    noise = np.broadcast_to(np.asarray(1.0 if given is None else given, float), (len(masks),)).copy()
    mean, unit = priors.arrays(design, 1.0)
    rounds = 1 if given is not None else NOISE_ITERATIONS
    for _ in range(rounds):
        used = noise
        fits = fit_batch(xy_u, xy_d, masks, start, points=points, covariance=covariance, max_iter=max_iter,
                         family=design.family, prior=(mean, unit[None] / used[:, None]))  # fmt: skip
        if given is not None:
            break
        with np.errstate(invalid="ignore", divide="ignore"):
            new = np.sqrt(fits.rss / np.maximum(fits.n - fits.k_eff, 1.0))
        noise = np.where(np.isfinite(new) & (new > 0), np.maximum(new, priors.noise_floor_px), used)
        if np.all(np.abs(noise / used - 1.0) < 0.05):
            break
    return fits, used


# Ten parameters: the points, the design and the subset, then the keyword options of
# calibrate() (a public signature, kept as it is).
def calibrate_relay(
    xy_u,
    xy_d,
    design: RelayDesign,
    free="default",
    *,
    um_per_px: float | None = None,
    image_size: tuple[int, int] | None = None,
    name: str | None = None,
    source: str | None = None,
    priors: RelayPriors | str | Mapping | None = None,
    **fit_options,
):
    """Fit the relay model (``free``: a subset for :func:`relay_mask`) to reference points
    ``xy_u`` (px, the ideal image of the target) and distorted points ``xy_d`` (camera px),
    starting from ``design``; returns a :class:`~oapcal.calibration.Calibration`.

    The design's ``centre`` defaults to the image centre ``((w - 1) / 2, (h - 1) / 2)``
    with ``image_size``, else the middle of the reference points.  ``um_per_px`` (object
    um per reference px) defaults to the pixel size over the design's magnification.
    Raises :class:`~oapcal.errors.DataError` when the points do not determine the subset
    (:func:`identifiability`), naming the parameters that cannot be told apart.

    ``priors`` (:func:`parse_priors`: ``"default"``, key=value pairs, a mapping or a
    :class:`RelayPriors`; None or ``"off"``: none) makes it the maximum a posteriori fit
    (:func:`map_fit`): the values with a prior need not be identifiable from the points
    (their prior determines them), the covariance is the posterior one, AICc counts the
    effective number of parameters, and the calibration records the priors (``priors``).
    """
    from oapcal.calibration import calibrate
    from oapcal.fitting import check_enough_points

    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    mask = relay_mask(free, design.family)
    check_enough_points(len(xy_u), int(mask.sum()), source=source or "the point data")
    design = default_centre(design, xy_u, image_size)
    p0 = _imaging_start(design, xy_u, source)
    priors = parse_priors(priors)
    _check_identifiable(xy_u, p0, mask, design, priors, source)
    if um_per_px is None:
        um_per_px = design.object_um_per_px
    # Behind a microscope the misalignment moves the image by hundreds of px and the fit
    # creeps along the scale-defocus-d1 valley: 228 iterations in one of six cases of
    # benchmarks/microscope.py.  The cap only ends fits that would not stop by themselves.
    fit_options.setdefault("max_iter", RELAY_MAX_ITER)
    record = None
    if priors is not None:
        _, noise = map_fit(xy_u, xy_d, design, mask[None], priors, covariance=False,
                           max_iter=fit_options["max_iter"])  # fmt: skip
        fit_options["prior"] = priors.arrays(design, float(noise[0]))
        record = {**priors.to_dict(design), "noise_used_px": float(noise[0])}
    return calibrate(xy_u, xy_d, mask, init=p0, um_per_px=um_per_px, image_size=image_size, name=name,
                     source=source, relay_design=design.to_dict(), priors=record, **fit_options)  # fmt: skip


def _imaging_start(design: RelayDesign, xy_u: np.ndarray, source: str | None) -> np.ndarray:
    """The design's parameter vector, refused (:class:`~oapcal.errors.DataError`) when its
    relay does not image every reference point (a trace that is not finite)."""
    p0 = relay_params(design)
    with np.errstate(all="ignore"):
        start = distort(xy_u, p0, family=design.family)
    bad = ~np.isfinite(start).all(axis=1)
    if not np.isfinite(p0).all() or bad.any():
        raise DataError(
            f"{source or 'the point data'}: the relay design {_design_words(design)} does not image "
            f"{int(bad.sum()) or len(xy_u)} of {len(xy_u)} reference points (the trace is not finite "
            "there): check the design values (d1, focal lengths, pixel size, centre) and the points' units",
            param="design",
        )
    return p0


def _check_identifiable(xy_u, p0, mask, design: RelayDesign, priors, source: str | None) -> None:
    """Refuse a subset the points do not determine (:func:`identifiability`); the values
    with a finite prior count as determined, but their derivatives must be finite too (a
    design that images nothing is refused by name, with priors or without)."""
    from oapcal.model import jacobian_params

    unconstrained = mask.copy()
    jac = None
    if priors is not None:
        sig = priors.sigma(design)
        unconstrained &= np.array([not np.isfinite(sig.get(n, np.inf)) for n in design.family.param_names])
        jac = jacobian_params(np.asarray(xy_u, float), np.asarray(p0, float), family=design.family)
        identifiability(xy_u, p0, mask, jac, family=design.family)  # raises where not finite
    ident = identifiability(xy_u, p0, unconstrained, jac, family=design.family)
    if not ident.ok:
        raise DataError(f"{source or 'the point data'}: {ident.message()}", param="free")


#: Largest misalignment angle (deg) of a plausible fit: what ``oapcal simulate relay``
#: accepts (beyond it the value describes another relay, not a misaligned one).
PLAUSIBLE_ANGLE_DEG = 45.0


def implausible(calibration) -> str:
    """Why a relay calibration is not a plausible fit, or ``""``: a fitted angle beyond
    +/- :data:`PLAUSIBLE_ANGLE_DEG` deg, a decentre, defocus or focal-length change beyond the
    mirrors' focal length, a d1 change beyond the design's d1 (or leaving none), or the
    inverse failing at more than half of the calibration points.  Points in the wrong unit
    (mm given as px) fit that way: the misalignment runs off to absorb a scale the design
    cannot have."""
    design = RelayDesign.from_dict(calibration.relay_design)
    f1, f2 = design.relay().focal_lengths_mm
    d1 = design.relay().d1_mm
    values = calibration.params_dict
    problems = []
    for name in calibration.free:
        if name not in PARAMETERS:
            continue
        unit = PARAMETERS[name][0]
        v = values[name]
        if unit == "deg":
            limit, words = PLAUSIBLE_ANGLE_DEG, f"+/- {PLAUSIBLE_ANGLE_DEG:g} deg"
        elif name == "d1":
            limit, words = 0.999 * d1, f"the design's d1 of {d1:g} mm"
        else:
            limit, words = min(f1, f2), f"the focal length of {min(f1, f2):g} mm"
        if not abs(v) <= limit:
            problems.append(f"{name} = {v:.4g} {unit} is beyond {words}")
    failed = int(getattr(calibration.residuals, "n_failed", 0) or 0)
    n = int(calibration.fit.n_points)
    if failed * 2 > n:
        problems.append(f"{failed} of {n} calibration points cannot be corrected through it")
    if not problems:
        return ""
    return (
        "the relay fit is not a plausible misalignment (" + "; ".join(problems[:3]) + "): check the points' "
        "units (reference and distorted points in px) and the design, or fit with the priors (priors "
        "'default')"
    )


def describe(calibration) -> list[str]:
    """One line per fitted parameter in physical words, with its standard error:
    ``"OAP 2: tip: rotation about ... : 0.0301 +/- 0.0001 deg"``."""
    lines = []
    units = {"scale": "", "rotation": "deg", "shift_x": "px", "shift_y": "px"}
    words = {"scale": "target scale", "rotation": "target turned (counter-clockwise)",
             "shift_x": "target shifted in x", "shift_y": "target shifted in y",
             "microscope_magnification": "microscope: magnification (negative: inverting)",
             "microscope_k1": "microscope: radial term at the sensor"}  # fmt: skip
    units["microscope_k1"] = "1/mm^2"
    names = calibration.family.param_names
    for i, n in enumerate(names):
        if n not in calibration.free:
            continue
        unit, text = PARAMETERS.get(n, (units.get(n, ""), words.get(n, n)))
        value, err = float(calibration.params[i]), float(calibration.stderr[i])
        lines.append(f"{n}: {text}: {value:.4g} +/- {err:.2g} {unit}".rstrip())
    if calibration.family is RELAY_MICROSCOPE:
        p = dict(zip(names, np.asarray(calibration.params, float)))
        m = p["microscope_magnification"]
        lines.append(
            f"microscope: magnification {m:.6g} ({'inverting' if m < 0 else 'upright'}; design "
            f"{p['microscope_design_magnification']:.6g})"
        )
    return lines


__all__ = ["RELAY", "RELAY_MICROSCOPE", "RelayDesign", "relay_params", "relay_mask", "DEFAULT_FREE",
           "DEFAULT_FREE_MICROSCOPE", "ALIASES", "identifiability", "Identifiability", "calibrate_relay",
           "describe", "DEFAULT_PRIORS", "RelayPriors", "parse_priors", "priors_from_dict",
           "map_fit", "NOISE_FLOOR_PX", "implausible", "PLAUSIBLE_ANGLE_DEG"]  # fmt: skip
