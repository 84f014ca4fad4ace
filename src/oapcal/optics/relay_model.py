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

from oapcal.errors import ModelSpecError
from oapcal.model import RELAY, RELAY_MISALIGNMENT_NAMES, RELAY_POSE_NAMES
from oapcal.optics.misalign import PARAMETERS, Misalignment
from oapcal.optics.relay import DEFAULT_FOCAL_LENGTH_MM, oap_relay, paraxial_matrix

#: The parameters fitted by default (``--model relay``): the target's whole pose and the
#: misalignments that the traced field of a relay with the stop at its first mirror can
#: tell apart (``docs/models.md``, Identifiability).
DEFAULT_FREE = ("scale", "rotation", "shift_x", "shift_y", "m2_tilt_x", "m2_tilt_y", "d1", "camera_tilt_x",
                "camera_tilt_y")  # fmt: skip

#: Short names accepted in subsets (``relay:d1,tilt2x,camera``): each stands for these
#: parameters.
ALIASES: dict[str, tuple[str, ...]] = {
    "pose": RELAY_POSE_NAMES,
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
}


@dataclass(frozen=True)
class RelayDesign:
    """The nominal relay a fit starts from (as ``oapcal simulate relay`` takes it).

    ``setup`` 1 or 2 (the paper's d1 = 860 / 660 mm) unless ``d1_mm`` is given;
    ``focal_length_mm`` both mirrors' (``focal_length_2_mm`` the second's if different);
    ``orientation`` ``"U"`` or ``"Z"``; ``stop_distance_mm`` (0: at the first mirror);
    ``pixel_size_um`` the camera's pixel pitch; ``centre`` (px) the point of the
    reference frame on the relay's axis (None: the middle of the reference points).
    """

    setup: int | None = 1
    d1_mm: float | None = None
    focal_length_mm: float = DEFAULT_FOCAL_LENGTH_MM
    focal_length_2_mm: float | None = None
    orientation: str = "U"
    stop_distance_mm: float = 0.0
    pixel_size_um: float = 4.8
    centre: tuple[float, float] | None = None

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
        return RelayDesign(**{**self.to_dict(), "centre": (float(mid[0]), float(mid[1]))})

    def to_dict(self) -> dict:
        return {
            "setup": self.setup, "d1_mm": self.d1_mm, "focal_length_mm": self.focal_length_mm,
            "focal_length_2_mm": self.focal_length_2_mm, "orientation": self.orientation,
            "stop_distance_mm": self.stop_distance_mm, "pixel_size_um": self.pixel_size_um,
            "centre": None if self.centre is None else [float(c) for c in self.centre],
        }  # fmt: skip

    @classmethod
    def from_dict(cls, data: Mapping) -> RelayDesign:
        data = dict(data)
        if data.get("centre") is not None:
            data["centre"] = tuple(float(c) for c in data["centre"])
        return cls(**data)


def relay_params(design: RelayDesign, misalignment=None, pose: Mapping | None = None) -> np.ndarray:
    """The relay family's parameter vector ``(36,)``: ``pose`` (``scale``, ``rotation``
    deg, ``shift_x``, ``shift_y`` px; identity by default), the ``misalignment`` (a
    :class:`~oapcal.optics.misalign.Misalignment` or dict; none by default) and the
    ``design``'s constants.  ``design.centre`` must be set (:meth:`RelayDesign.with_centre`)."""
    if design.centre is None:
        raise ModelSpecError("the relay design needs its centre (px): give it or use with_centre(points)")
    if misalignment is None:
        mis = Misalignment()
    elif isinstance(misalignment, Misalignment):
        mis = misalignment
    else:
        mis = Misalignment.from_dict(misalignment)
    pose = {"scale": 1.0, "rotation": 0.0, "shift_x": 0.0, "shift_y": 0.0, **dict(pose or {})}
    unknown = sorted(set(pose) - set(RELAY_POSE_NAMES))
    if unknown:
        raise ModelSpecError(f"unknown pose value {unknown[0]!r}: use {', '.join(RELAY_POSE_NAMES)}")
    relay = design.relay()
    inv = np.linalg.inv(paraxial_matrix(relay))
    f1, f2 = relay.focal_lengths_mm
    design_values = {
        "d1_mm": relay.d1_mm, "f1_mm": f1, "f2_mm": f2,
        "orientation": 1.0 if relay.orientation == "U" else -1.0,
        "stop_mm": relay.stop_distance_mm, "pixel_mm": float(design.pixel_size_um) * 1e-3,
        "cx": float(design.centre[0]), "cy": float(design.centre[1]),
        "a11": inv[0, 0], "a12": inv[0, 1], "a21": inv[1, 0], "a22": inv[1, 1],
    }  # fmt: skip
    values = {**pose, **mis.to_dict(), **design_values}
    return np.array([float(values[n]) for n in RELAY.param_names])


def relay_mask(spec="default") -> np.ndarray:
    """The free-parameter mask ``(36,)`` of a relay subset: ``"default"``
    (:data:`DEFAULT_FREE`), ``"all"`` (every pose and misalignment value), or names and
    :data:`ALIASES` separated by commas (``"pose,d1,tilt2x,tilt2y,camera"``); a subset
    always fits the pose (an unknown target has one)."""
    if isinstance(spec, str):
        text = spec.strip()
        if text.startswith("relay:"):
            text = text[len("relay:") :]
        if text in ("", "default", "relay"):
            names = set(DEFAULT_FREE)
        elif text == "all":
            names = set(RELAY_POSE_NAMES) | set(RELAY_MISALIGNMENT_NAMES)
        else:
            names = set(RELAY_POSE_NAMES)
            for item in (t.strip() for t in text.split(",")):
                if item in ALIASES:
                    names.update(ALIASES[item])
                elif item in PARAMETERS or item in RELAY_POSE_NAMES:
                    names.add(item)
                else:
                    raise ModelSpecError(
                        f"unknown relay parameter {item!r}: use names of oapcal.optics.misalign.PARAMETERS, "
                        f"the pose ({', '.join(RELAY_POSE_NAMES)}) or {', '.join(ALIASES)}"
                    )
    else:
        names = set(spec)
    return np.array([n in names for n in RELAY.param_names])


__all__ = ["RELAY", "RelayDesign", "relay_params", "relay_mask", "DEFAULT_FREE", "ALIASES"]
