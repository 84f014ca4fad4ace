"""Distortion fields: where an object point lands in the camera image.

A *distortion field* is any object with

* ``forward(xy_u_px)``: paraxial (undistorted) camera px -> distorted camera px, ``(..., 2)``;
* ``inverse(xy_d_px)``: distorted camera px -> paraxial camera px (NaN where it fails);
* ``paraxial_from_object_um(xy_um)``: object-plane um (origin on the optical axis) ->
  paraxial camera px;
* attributes ``pixel_size_um`` and ``image_size`` ``(w, h)``.

(the protocol :class:`PixelField`).  The ray-traced relay of :mod:`oapcal.optics` follows
it; :class:`ModelDistortionField` implements it with any :class:`~oapcal.model.Model`
(``forward`` = the model, ``inverse`` = :meth:`~oapcal.model.Model.inverse`), so a
calibration of any family drives a simulation.

>>> f = setup1_like_field()
>>> f.paraxial_from_object_um(np.array([[0.0, 0.0]])).tolist()
[[319.5, 239.5]]
>>> d = f.forward(f.paraxial_from_object_um(np.array([[500.0, 500.0]])))
>>> bool(np.allclose(f.inverse(d), f.paraxial_from_object_um(np.array([[500.0, 500.0]]))))
True
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from oapcal.errors import DataError, ModelSpecError
from oapcal.model import PRESETS, Model, as_model, params_from_dict


@runtime_checkable
class PixelField(Protocol):
    """The protocol of a distortion field in camera pixels (module docstring): what
    :func:`oapcal.imaging.simulate.simulate_image` draws through.  (Not to be confused
    with :class:`oapcal.optics.field.DistortionField`, the traced relay's field, which
    follows it.)"""

    pixel_size_um: float
    image_size: tuple[int, int]

    def forward(self, xy_u_px: np.ndarray) -> np.ndarray: ...

    def inverse(self, xy_d_px: np.ndarray) -> np.ndarray: ...

    def paraxial_from_object_um(self, xy_um: np.ndarray) -> np.ndarray: ...


#: The protocol's former name (``docs/usaf.md`` named it): :class:`PixelField`.
DistortionField = PixelField


@dataclass(frozen=True)
class ModelDistortionField:
    """A distortion model (a :class:`~oapcal.model.Model` of any family, px units: Eq. (1),
    Eq. (1) with the target's rotation, the relay, the relay with a microscope, or a
    registered family; or a bare parameter vector of a built-in family) as a distortion field.

    The paraxial image of the object point ``xy_um`` is
    ``centre + magnification * xy_um / pixel_size_um`` with ``centre`` the image centre
    ``((w - 1) / 2, (h - 1) / 2)``.  ``params`` is the model's vector, ``model`` the model.
    """

    params: Model | np.ndarray
    pixel_size_um: float = 4.8
    image_size: tuple[int, int] = (640, 480)
    magnification: float = 1.0
    model: Model = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        try:
            model = as_model(self.params)
        except ModelSpecError:
            raise DataError(
                f"a model distortion field needs a Model or one model's parameter vector (13, 14, 36 "
                f"or 39 values), got shape {np.shape(self.params)}"
            ) from None
        if not np.isfinite(model.params).all():
            raise DataError("a model distortion field needs finite parameters")
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "params", model.params)
        if not (self.pixel_size_um > 0 and self.magnification != 0):
            raise DataError("pixel_size_um must be positive and magnification non-zero")

    @classmethod
    def from_calibration(cls, calibration, image_size: tuple[int, int] | None = None):
        """The field of a fitted :class:`~oapcal.calibration.Calibration` (its model, of any
        family): its reference points are taken as the paraxial image, ``calibration.um_per_px``
        um per px."""
        size = image_size or calibration.image_size
        if calibration.um_per_px is None or size is None:
            raise DataError(
                "the calibration has no um_per_px or image_size; refit it with both given "
                "(calibrate(..., um_per_px=..., image_size=...))",
                param="calibration",
            )
        return cls(as_model(calibration), float(calibration.um_per_px), tuple(size), 1.0)

    @property
    def centre_px(self) -> np.ndarray:
        return (np.asarray(self.image_size, float) - 1.0) / 2.0

    def forward(self, xy_u_px):
        return self.model(np.asarray(xy_u_px, float))

    def inverse(self, xy_d_px):
        xy = np.asarray(xy_d_px, float)
        return self.model.inverse(xy.reshape(-1, 2)).xy.reshape(xy.shape)

    def paraxial_from_object_um(self, xy_um):
        scale = self.magnification / self.pixel_size_um
        return self.centre_px + np.asarray(xy_um, float) * scale


def identity_field(pixel_size_um: float = 4.8, image_size=(640, 480)) -> ModelDistortionField:
    """No distortion: ``forward`` and ``inverse`` are the identity."""
    return ModelDistortionField(Model.identity(), pixel_size_um, tuple(image_size))


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
    return ModelDistortionField(Model("brown-conrady", p, PRESETS["paper"]), pixel_size_um, size)


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
