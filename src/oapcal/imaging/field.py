"""Distortion fields: where an object point lands in the camera image.

A *distortion field* is any object with

* ``forward(xy_u_px)``: paraxial (undistorted) camera px -> distorted camera px, ``(..., 2)``;
* ``inverse(xy_d_px)``: distorted camera px -> paraxial camera px (NaN where it fails);
* ``paraxial_from_object_um(xy_um)``: object-plane um (origin on the optical axis) ->
  paraxial camera px;
* attributes ``pixel_size_um`` and ``image_size`` ``(w, h)``.

The ray-traced relay of :mod:`oapcal.optics` follows this protocol;
:class:`ModelDistortionField` implements it with the distortion model of Eq. (1)
(``forward`` = :func:`oapcal.model.distort`, ``inverse`` = :func:`oapcal.model.undistort`).

>>> f = setup1_like_field()
>>> f.paraxial_from_object_um(np.array([[0.0, 0.0]])).tolist()
[[319.5, 239.5]]
>>> d = f.forward(f.paraxial_from_object_um(np.array([[500.0, 500.0]])))
>>> bool(np.allclose(f.inverse(d), f.paraxial_from_object_um(np.array([[500.0, 500.0]]))))
True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from oapcal.errors import DataError
from oapcal.model import distort, family_of, identity_params, params_from_dict, undistort


@runtime_checkable
class DistortionField(Protocol):
    """The protocol of a distortion field (module docstring)."""

    pixel_size_um: float
    image_size: tuple[int, int]

    def forward(self, xy_u_px: np.ndarray) -> np.ndarray: ...

    def inverse(self, xy_d_px: np.ndarray) -> np.ndarray: ...

    def paraxial_from_object_um(self, xy_um: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class ModelDistortionField:
    """A fitted model's parameter vector ``params`` (px units; any family: Eq. (1), Eq. (1)
    with the target's rotation, the relay, the relay with a microscope) as a distortion field.

    The paraxial image of the object point ``xy_um`` is
    ``centre + magnification * xy_um / pixel_size_um`` with ``centre`` the image centre
    ``((w - 1) / 2, (h - 1) / 2)``.
    """

    params: np.ndarray
    pixel_size_um: float = 4.8
    image_size: tuple[int, int] = (640, 480)
    magnification: float = 1.0

    def __post_init__(self):
        p = np.array(self.params, dtype=float)
        if p.ndim != 1 or family_of(p).n_params != p.shape[0]:
            raise DataError(
                f"a model distortion field needs one model's parameter vector (13, 14, 36 or 39 "
                f"values), got shape {p.shape}"
            )
        if not np.isfinite(p).all():
            raise DataError("a model distortion field needs finite parameters")
        p.setflags(write=False)
        object.__setattr__(self, "params", p)
        if not (self.pixel_size_um > 0 and self.magnification != 0):
            raise DataError("pixel_size_um must be positive and magnification non-zero")

    @classmethod
    def from_calibration(cls, calibration, image_size: tuple[int, int] | None = None):
        """The field of a fitted :class:`~oapcal.io.calibration.Calibration`: its reference
        points are taken as the paraxial image, ``calibration.um_per_px`` um per px."""
        size = image_size or calibration.image_size
        if calibration.um_per_px is None or size is None:
            raise DataError(
                "the calibration has no um_per_px or image_size; refit it with both given "
                "(calibrate(..., um_per_px=..., image_size=...))",
                param="calibration",
            )
        return cls(np.asarray(calibration.params), float(calibration.um_per_px), tuple(size), 1.0)

    @property
    def centre_px(self) -> np.ndarray:
        return (np.asarray(self.image_size, float) - 1.0) / 2.0

    def forward(self, xy_u_px):
        return distort(np.asarray(xy_u_px, float), self.params)

    def inverse(self, xy_d_px):
        xy = np.asarray(xy_d_px, float)
        flat = xy.reshape(-1, 2)
        return undistort(flat, self.params).xy.reshape(xy.shape)

    def paraxial_from_object_um(self, xy_um):
        scale = self.magnification / self.pixel_size_um
        return self.centre_px + np.asarray(xy_um, float) * scale


def identity_field(pixel_size_um: float = 4.8, image_size=(640, 480)) -> ModelDistortionField:
    """No distortion: ``forward`` and ``inverse`` are the identity."""
    return ModelDistortionField(identity_params(), pixel_size_um, tuple(image_size))


#: Eq. (1) parameters (px, 640 x 480 camera) of :func:`setup1_like_field`.
SETUP1_LIKE = params_from_dict(
    {"k1": 2.0e-6, "p1": 2.0e-4, "s3": 1.2e-3, "x_off": -319.5, "y_off": -239.5,
     "c_x": 319.5, "c_y": 239.5, "m": 1.0}
)  # fmt: skip


def setup1_like_field(pixel_size_um: float = 4.8, image_size=(640, 480)) -> ModelDistortionField:
    """A model field resembling the paper's setup 1 after the relay: over the central
    1 mm x 1 mm of object space (groups 4-5 of the USAF target) the distorted points are
    up to about 40 px (mean about 12 px) from the paraxial ones, more in y than in x.

    The magnitudes were chosen to match the paper's numbers; the field is a stand-in for
    the ray-traced relay, not a trace.
    """
    size = tuple(int(v) for v in image_size)
    p = SETUP1_LIKE.copy()
    centre = (np.asarray(size, float) - 1.0) / 2.0
    p[8:12] = [-centre[0], -centre[1], centre[0], centre[1]]
    return ModelDistortionField(p, pixel_size_um, size)


def distortion_stats(field, half_width_um: float = 500.0, n: int = 17) -> dict:
    """Max and mean distance (px) between distorted and paraxial points on an ``n x n`` grid
    over ``+-half_width_um`` of object space, and the max of each component."""
    g = np.linspace(-half_width_um, half_width_um, n)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    u = field.paraxial_from_object_um(xy)
    d = field.forward(u) - u
    dist = np.hypot(d[:, 0], d[:, 1])
    return {
        "max_px": float(dist.max()),
        "mean_px": float(dist.mean()),
        "max_x_px": float(np.abs(d[:, 0]).max()),
        "max_y_px": float(np.abs(d[:, 1]).max()),
    }
