"""Misalignment of an OAP relay: small rigid motions of its parts away from the design.

A :class:`Misalignment` holds one number per degree of freedom (angles in degrees,
lengths in mm; all 0 is the aligned relay).  :func:`oapcal.optics.relay.oap_relay`
applies it; ``docs/optics.md`` (Misalignment) has the figure and the sign conventions:

* each mirror ``m1`` (the first, the paper's OAP 2) and ``m2``: a right-handed frame
  ``(a, b, n)`` at its centre, ``n`` the surface normal there (pointing to the reflecting,
  concave side), ``a = +x`` (perpendicular to the fold plane), ``b = n x a`` (in the fold
  plane, in the tangent plane).  ``tilt_x`` / ``tilt_y`` rotate the mirror about ``a`` /
  ``b`` through its centre (as a kinematic mount's two adjusters do), ``clock`` about
  ``n``; ``decentre_x`` / ``decentre_y`` move it along ``a`` / ``b``; ``focal_length``
  changes its reflected focal length with its centre and the normal there fixed (the
  focus moves along the central ray; the object and the camera stay).  The rotation is
  ``R = R_b(tilt_y) R_a(tilt_x) R_n(clock)`` (clock first, then the mount's tip and tilt
  about the fixed axes), all right-handed, then the decentre.
* ``d1``: the collimated path grows by this many mm (the second mirror and the camera
  move together along it, as on a common breadboard).
* ``stop_decentre_x`` / ``_y``: the aperture stop moves within its plane along its own
  ``x`` / ``y`` axes.  A stop at the first mirror (``stop_distance_mm`` 0) is that mirror's
  aperture and moves with it; a stop elsewhere on the collimated path stays put.
* ``camera_tilt_x`` / ``_y``: the image plane (sensor) rotates about its own ``x`` /
  ``y`` axis through its centre (``R = R_y R_x``); ``camera_defocus``: it moves along its
  normal, positive along the light (away from the second mirror).  Image coordinates are
  always measured in the sensor's own axes.
* ``object_tilt_x`` / ``_y``: the target plane rotates about its ``x_obj`` / ``y_obj``
  axis through the field centre (``R = R_y R_x``); object coordinates are measured in the
  tilted plane.

>>> m = Misalignment(m2_tilt_x=0.05, camera_defocus=0.1)
>>> m.is_zero, Misalignment().is_zero
(False, True)
>>> {k: v for k, v in m.to_dict().items() if v}
{'m2_tilt_x': 0.05, 'camera_defocus': 0.1}
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from oapcal.errors import GeometrySpecError

_MIRROR = (
    ("tilt_x", "deg", "tip: rotation about the tangent-plane axis a = +x (perpendicular to the fold plane)"),
    ("tilt_y", "deg", "tilt: rotation about the tangent-plane axis b = n x a (in the fold plane)"),
    ("decentre_x", "mm", "decentre along a"),
    ("decentre_y", "mm", "decentre along b"),
    ("clock", "deg", "clocking: rotation about the normal n at the centre"),
    ("focal_length", "mm", "change of the reflected focal length (centre and normal there fixed)"),
)

#: Every degree of freedom: name -> (unit, description).
PARAMETERS: dict[str, tuple[str, str]] = {
    **{
        f"m{i}_{key}": (unit, f"{('first', 'second')[i - 1]} mirror: {text}")
        for i in (1, 2)
        for key, unit, text in _MIRROR
    },  # fmt: skip
    "d1": ("mm", "collimated path length change (the second mirror and the camera move together)"),
    "stop_decentre_x": ("mm", "aperture stop moved along its x axis"),
    "stop_decentre_y": ("mm", "aperture stop moved along its y axis"),
    "camera_tilt_x": ("deg", "image plane rotated about its x axis (columns)"),
    "camera_tilt_y": ("deg", "image plane rotated about its y axis (rows)"),
    "camera_defocus": ("mm", "image plane moved along its normal, + along the light"),
    "object_tilt_x": ("deg", "object (target) plane rotated about its x axis"),
    "object_tilt_y": ("deg", "object (target) plane rotated about its y axis"),
}

#: The degrees of freedom that keep the relay's mirror symmetry about its fold plane
#: ``x = 0`` (rotations about x, moves within the fold plane); with only these the
#: distortion keeps ``dx`` odd and ``dy`` even in ``x``.
SYMMETRIC = (
    "m1_tilt_x", "m1_decentre_y", "m1_focal_length", "m2_tilt_x", "m2_decentre_y", "m2_focal_length",
    "d1", "stop_decentre_y", "camera_tilt_x", "camera_defocus", "object_tilt_x",
)  # fmt: skip


@dataclass(frozen=True)
class Misalignment:
    """Deviations of a relay from its design (see the module docstring; deg and mm)."""

    m1_tilt_x: float = 0.0
    m1_tilt_y: float = 0.0
    m1_decentre_x: float = 0.0
    m1_decentre_y: float = 0.0
    m1_clock: float = 0.0
    m1_focal_length: float = 0.0
    m2_tilt_x: float = 0.0
    m2_tilt_y: float = 0.0
    m2_decentre_x: float = 0.0
    m2_decentre_y: float = 0.0
    m2_clock: float = 0.0
    m2_focal_length: float = 0.0
    d1: float = 0.0
    stop_decentre_x: float = 0.0
    stop_decentre_y: float = 0.0
    camera_tilt_x: float = 0.0
    camera_tilt_y: float = 0.0
    camera_defocus: float = 0.0
    object_tilt_x: float = 0.0
    object_tilt_y: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise GeometrySpecError(f"misalignment {f.name} must be a number, got {value!r}") from None
            if not np.isfinite(value):
                raise GeometrySpecError(f"misalignment {f.name} must be a finite number, got {value}")
            object.__setattr__(self, f.name, value)

    @classmethod
    def from_dict(cls, values) -> Misalignment:
        """From ``{name: value}`` (names of :data:`PARAMETERS`; others raise)."""
        values = dict(values or {})
        unknown = sorted(set(values) - set(PARAMETERS))
        if unknown:
            raise GeometrySpecError(
                f"unknown misalignment {unknown[0]!r}: use one of {', '.join(PARAMETERS)}"
            )
        return cls(**values)

    @classmethod
    def of(cls, value) -> Misalignment:
        """``value`` as a :class:`Misalignment`: None (aligned), one already, or a dict."""
        if value is None:
            return cls()
        return value if isinstance(value, Misalignment) else cls.from_dict(value)

    def to_dict(self) -> dict[str, float]:
        """``{name: value}`` of every degree of freedom, in :data:`PARAMETERS` order."""
        return {name: getattr(self, name) for name in PARAMETERS}

    def replace(self, **values) -> Misalignment:
        """A copy with some values changed (names checked)."""
        return Misalignment.from_dict({**self.to_dict(), **values})

    @property
    def is_zero(self) -> bool:
        return not any(self.to_dict().values())

    def mirror(self, i: int) -> dict[str, float]:
        """The six values of mirror ``i`` (1 or 2), keyed without the ``m{i}_`` prefix."""
        return {key: getattr(self, f"m{i}_{key}") for key, _, _ in _MIRROR}


def rotation(axis, angle_deg: float) -> np.ndarray:
    """The right-handed rotation matrix by ``angle_deg`` about the unit vector ``axis``
    (:class:`scipy.spatial.transform.Rotation`)."""
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * float(angle_deg), degrees=True).as_matrix()


def rotations(*steps) -> np.ndarray:
    """The product of rotations ``(axis, angle_deg)`` applied in the order given (the
    first is applied first); zero angles are skipped, none gives the identity."""
    out = np.eye(3)
    for axis, angle in steps:
        if angle:
            out = rotation(axis, angle) @ out
    return out
