"""Camera images of a real picture of a target through a distortion model, with the exact
truth of every pixel (``docs/detection.md``, "End to end on real content").

Where :mod:`oapcal.imaging.simulate` draws the USAF target from its geometry, this module
takes a real image of a target (a 2-D array and its own um per pixel, the *source*) and
renders what a camera sees of it through a distortion given as a model parameter vector of
any family (Eq. 1, Eq. 1 + rotation, or the relay of
:func:`oapcal.optics.relay_model.relay_params`).  A :class:`Scene` holds the geometry; for
each camera pixel centre ``p``:

1. behind a microscope (optional, :class:`Microscope`): the camera sees the relay's image
   magnified ``M`` times (``M < 0`` when it inverts it), so the relay's image point is
   ``q = c + (p - c) / M`` (``c`` the image centre, in the relay camera's pixels);
2. the model's reference point ``r = undistort(q, params)`` (px: the ideal image);
3. the object point ``X = A (r - c_r)`` (um): for the relay family ``A`` and ``c_r`` come
   from the design constants in ``params`` (the aligned relay's paraxial inverse, which
   turns the image by 180 degrees, times the pixel pitch, about the design's centre); for
   the other families ``A = object_um_per_px * I`` about the image centre;
4. the source pixel ``s = s0 + F R(-rotation) X / um_per_px`` (:class:`Placement`: the
   source point ``s0`` on the optical axis, the target turned by ``rotation`` degrees in the
   object plane's axes from x towards y, ``F`` a mirror ``x -> -x`` of the target).

Steps 1-4 are evaluated exactly at every pixel centre (and one pixel beyond the border);
the ``oversample x oversample`` sub-pixels between them are interpolated bilinearly
(:func:`oapcal.imaging.simulate.bilinear_upsample`: exact for affine maps, ~1e-4 px for
the relay's smooth field).  The source is sampled at the sub-pixels with ``cv2.remap``
(bilinear; outside the source: the ``background`` level), blurred by the camera's Gaussian
PSF, averaged over each camera pixel and exposed (shot and read noise at ``snr``,
quantized) by the helpers of :mod:`oapcal.imaging.simulate`.  ``oversample`` defaults to
the number of sub-pixels that makes a sub-pixel no larger than a source pixel (at least 2,
at most 8): anti-aliasing by area sampling.

The truth (:class:`Rendering`) is, for every camera pixel centre, its reference point,
object point (um) and source pixel, and whether the model's inverse converged there.
:meth:`Scene.camera_from_source` maps the other way (source px -> camera px, through
:func:`oapcal.model.distort`), for points such as a target's corners found in the source.

>>> import numpy as np
>>> from oapcal.model import identity_params
>>> src = np.tile(np.linspace(0.0, 1.0, 64), (48, 1))
>>> cam = Camera(size=(64, 48), snr=None, sigma_px=0)
>>> scene = Scene(identity_params(), Placement(4.8, (31.5, 23.5)), cam)
>>> r = render_scene(src, scene)
>>> r.image.shape, r.image.dtype.name, bool(r.valid.all())
((48, 64), 'uint8', True)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError, ModelSpecError
from oapcal.model import RELAY, Model, as_model

#: Absolute tolerance (px) of the model's inverse when rendering: far below anything an
#: image shows, and above the relay model's own floating-point precision (~1e-9 px).
RENDER_INVERSE_TOL = 1e-7
#: The automatic oversampling: at least this many sub-pixels per pixel side (pixel
#: integration) ...
MIN_OVERSAMPLE = 2
#: ... and at most this many.
MAX_OVERSAMPLE = 8


@dataclass(frozen=True)
class Camera:
    """The camera: ``size`` ``(w, h)`` px, ``pixel_size_um`` its pitch, ``sigma_px`` the
    Gaussian blur (camera px; 0: none), ``snr`` at the brightest level (None: no noise),
    ``read_noise_e`` electrons, ``bits`` 8 or 16, ``oversample`` sub-pixels per side (None:
    automatic, module docstring)."""

    size: tuple[int, int] = (640, 480)
    pixel_size_um: float = 4.8
    sigma_px: float = 0.8
    snr: float | None = 50.0
    read_noise_e: float = 5.0
    bits: int = 8
    oversample: int | None = None

    def __post_init__(self):
        w, h = (int(v) for v in self.size)
        if w < 2 or h < 2:
            raise DataError(f"camera size {self.size}: needs at least 2 x 2 px", param="size")
        object.__setattr__(self, "size", (w, h))
        if not self.pixel_size_um > 0:
            raise DataError(f"pixel_size_um {self.pixel_size_um}: must be positive", param="pixel_size_um")
        if self.oversample is not None and int(self.oversample) < 1:
            raise DataError(f"oversample {self.oversample}: must be at least 1", param="oversample")
        self.settings(1)  # the exposure's own checks (bits, snr, sigma)

    def settings(self, oversample: int):
        """The :class:`~oapcal.imaging.simulate.ImageSettings` of the exposure helpers."""
        from oapcal.imaging.simulate import ImageSettings

        return ImageSettings(sigma_px=self.sigma_px, snr=self.snr, read_noise_e=self.read_noise_e,
                             bits=self.bits, oversample=oversample)  # fmt: skip


@dataclass(frozen=True)
class Placement:
    """How the source image lies in the object plane: ``um_per_px`` object um per source
    pixel, ``centre_px`` the source point ``(x, y)`` on the optical axis, ``rotation_deg``
    the target's turn (object-plane axes, from x towards y), ``mirror`` a mirror ``x -> -x``
    of the target before the turn, ``background`` the relative level outside the source
    (None: the source's median)."""

    um_per_px: float
    centre_px: tuple[float, float]
    rotation_deg: float = 0.0
    mirror: bool = False
    background: float | None = None

    def __post_init__(self):
        if not (np.isfinite(self.um_per_px) and self.um_per_px > 0):
            raise DataError(f"um_per_px {self.um_per_px}: must be a positive number", param="um_per_px")
        c = tuple(float(v) for v in self.centre_px)
        if len(c) != 2 or not np.isfinite(c).all():
            raise DataError(
                f"centre_px {self.centre_px}: must be two finite numbers (x, y)", param="centre_px"
            )
        object.__setattr__(self, "centre_px", c)

    def matrix(self) -> np.ndarray:
        """``F R(-rotation) / um_per_px``: object um -> source px (about the centre)."""
        t = np.radians(self.rotation_deg)
        rot = np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])  # R(-rotation)
        flip = np.diag([-1.0 if self.mirror else 1.0, 1.0])
        return flip @ rot / float(self.um_per_px)


@dataclass(frozen=True)
class Microscope:
    """A finite-conjugate microscope behind the relay: the camera sees the relay's image
    ``magnification`` times larger, turned by 180 degrees when ``inverted`` (the paper's
    third setup: 5x, inverted, 0.96 um per 4.8 um camera pixel)."""

    magnification: float = 5.0
    inverted: bool = True

    def __post_init__(self):
        if not (np.isfinite(self.magnification) and self.magnification > 0):
            raise DataError(f"magnification {self.magnification}: must be positive", param="magnification")

    @property
    def signed(self) -> float:
        return -float(self.magnification) if self.inverted else float(self.magnification)


@dataclass(frozen=True)
class Scene:
    """The geometry of a rendering (module docstring, steps 1-4): the model ``params`` (a
    :class:`~oapcal.model.Model` of any family, or a bare parameter vector of a built-in
    family; ``model`` is the model), the source's ``placement``, the ``camera``, an
    optional ``microscope`` behind the model, and for families other than the relay
    ``object_um_per_px`` (object um per reference px; None: the camera's pixel pitch)."""

    params: Model | np.ndarray
    placement: Placement
    camera: Camera = field(default_factory=Camera)
    microscope: Microscope | None = None
    object_um_per_px: float | None = None
    model: Model = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        try:
            model = as_model(self.params)
        except ModelSpecError as exc:
            if np.ndim(self.params) == 1:
                raise  # a vector of no family: the model's own message
            raise DataError("the scene's params must be one finite parameter vector", param="params") from exc
        if not np.isfinite(model.params).all():
            raise DataError("the scene's params must be one finite parameter vector", param="params")
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "params", model.params)

    # ------------------------------------------------------------------ the geometry
    @property
    def centre(self) -> np.ndarray:
        """The camera image's centre ``((w - 1) / 2, (h - 1) / 2)`` (px)."""
        return (np.asarray(self.camera.size, float) - 1.0) / 2.0

    def paraxial(self) -> tuple[np.ndarray, np.ndarray]:
        """``A (2, 2)`` um per reference px and the reference centre ``c_r``: ``X = A (r - c_r)``."""
        if self.model.family is RELAY:
            names = RELAY.param_names
            v = {n: self.params[names.index(n)] for n in ("a11", "a12", "a21", "a22", "pixel_mm", "cx", "cy")}
            mat = np.array([[v["a11"], v["a12"]], [v["a21"], v["a22"]]]) * (v["pixel_mm"] * 1e3)
            return mat, np.array([v["cx"], v["cy"]])
        scale = self.camera.pixel_size_um if self.object_um_per_px is None else float(self.object_um_per_px)
        return np.eye(2) * scale, self.centre

    @property
    def camera_um_per_px(self) -> float:
        """Object um per camera px of the paraxial image (behind the microscope, if any)."""
        mat, _ = self.paraxial()
        m = abs(self.microscope.signed) if self.microscope is not None else 1.0
        return float(np.sqrt(abs(np.linalg.det(mat)))) / m

    def model_from_camera(self, xy):
        """Step 1: camera px -> the model's distorted px (the relay's image)."""
        xy = np.asarray(xy, float)
        if self.microscope is None:
            return xy
        return self.centre + (xy - self.centre) / self.microscope.signed

    def camera_from_model(self, xy):
        xy = np.asarray(xy, float)
        if self.microscope is None:
            return xy
        return self.centre + (xy - self.centre) * self.microscope.signed

    def reference_from_camera(self, xy) -> tuple[np.ndarray, np.ndarray]:
        """Steps 1-2: camera px ``(N, 2)`` -> reference px and whether the inverse converged
        (NaN where not)."""
        inv = self.model.inverse(self.model_from_camera(xy), tol=RENDER_INVERSE_TOL)
        return inv.xy, np.asarray(inv.converged, bool)

    def camera_from_reference(self, xy):
        return self.camera_from_model(self.model(np.asarray(xy, float)))

    def object_from_reference(self, xy):
        mat, c = self.paraxial()
        return (np.asarray(xy, float) - c) @ mat.T

    def reference_from_object(self, xy):
        mat, c = self.paraxial()
        return c + np.asarray(xy, float) @ np.linalg.inv(mat).T

    def source_from_object(self, xy):
        return np.asarray(self.placement.centre_px) + np.asarray(xy, float) @ self.placement.matrix().T

    def object_from_source(self, xy):
        mat = np.linalg.inv(self.placement.matrix())
        return (np.asarray(xy, float) - np.asarray(self.placement.centre_px)) @ mat.T

    def camera_from_source(self, xy):
        """Source px ``(N, 2)`` -> camera px (the forward model, exact)."""
        return self.camera_from_reference(self.reference_from_object(self.object_from_source(xy)))


@dataclass(frozen=True)
class Rendering:
    """A rendered camera image and its truth.

    ``image`` ``(h, w)`` uint8 or uint16; ``clean`` the noise-free relative intensity
    (the source's 99.5th percentile is 1); per camera pixel centre ``(h, w, 2)``:
    ``reference_px`` (the model's inverse), ``object_um``, ``source_px`` (NaN where the
    inverse did not converge); ``valid`` ``(h, w)`` where it converged and the source point
    lies inside the source; ``oversample`` used; ``peak_electrons`` (None without noise).
    """

    image: np.ndarray
    clean: np.ndarray
    reference_px: np.ndarray
    object_um: np.ndarray
    source_px: np.ndarray
    valid: np.ndarray
    oversample: int
    peak_electrons: float | None


def relative_intensity(source) -> tuple[np.ndarray, float]:
    """The source as float32 relative intensity (its 99.5th percentile at 1) and its median."""
    src = np.asarray(source)
    if src.ndim == 3:
        src = src[..., :3].mean(axis=-1)
    if src.ndim != 2 or min(src.shape) < 2:
        raise DataError(f"source has shape {src.shape}: expected a 2-D grey or colour image", param="source")
    src = src.astype(np.float64)
    if not np.isfinite(src).all():
        raise DataError("the source has non-finite values", param="source")
    top = float(np.percentile(src, 99.5))
    if not top > 0:
        raise DataError("the source is dark (its 99.5th percentile is not positive)", param="source")
    rel = (src / top).astype(np.float32)
    return rel, float(np.median(rel))


def auto_oversample(camera_um_per_px: float, source_um_per_px: float) -> int:
    """Sub-pixels per side so that a sub-pixel is no larger than a source pixel (module docstring)."""
    q = int(np.ceil(camera_um_per_px / source_um_per_px - 1e-9))
    return int(min(MAX_OVERSAMPLE, max(MIN_OVERSAMPLE, q)))


def render(
    source,
    to_source,
    camera: Camera,
    *,
    oversample: int,
    background: float | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, float | None, np.ndarray]:
    """The camera image of ``source`` for the map ``to_source`` (camera px ``(N, 2)`` ->
    source px, NaN where undefined): ``(image, clean, peak_electrons, source_px)`` with
    ``source_px`` ``(h + 2, w + 2, 2)`` the map at the pixel centres ``-1 .. w`` x ``-1 .. h``.
    Steps 5 of the module docstring; :func:`render_scene` is the whole chain."""
    import cv2

    from oapcal.imaging.simulate import bilinear_upsample, blur, expose

    w, h = camera.size
    q = int(oversample)
    if q < 1:
        raise DataError(f"oversample {oversample}: must be at least 1", param="oversample")
    rel, median = relative_intensity(source)
    level = median if background is None else float(background)
    gx, gy = np.meshgrid(np.arange(-1.0, w + 1.0), np.arange(-1.0, h + 1.0))
    coarse = np.asarray(to_source(np.stack([gx, gy], -1).reshape(-1, 2)), float).reshape(h + 2, w + 2, 2)
    fine = bilinear_upsample(coarse, q, (h, w)).astype(np.float32)  # (q h, q w, 2) source px
    # NaN (no inverse) -> far outside, so the border value is used
    fine[~np.isfinite(fine)] = -1e6
    sub = cv2.remap(rel, fine[..., 0], fine[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=level)  # fmt: skip
    settings = camera.settings(q)
    sub = blur(sub, q, settings.sigma_px, None, None, camera.pixel_size_um)
    clean = sub.reshape(h, q, w, q).mean(axis=(1, 3), dtype=np.float64)
    image, peak = expose(clean, settings, seed)
    return image, clean, peak, coarse


def render_scene(source, scene: Scene, *, seed: int = 0) -> Rendering:
    """Render ``source`` (a 2-D array, grey or colour) through ``scene`` with the noise seeded
    by ``seed``; the image and the exact truth of every pixel (:class:`Rendering`)."""
    cam = scene.camera
    q = cam.oversample or auto_oversample(scene.camera_um_per_px, scene.placement.um_per_px)
    store = {}

    def to_source(xy):
        ref, ok = scene.reference_from_camera(xy)
        ref = np.where(ok[:, None], ref, np.nan)
        store["ref"], store["ok"] = ref, ok
        return scene.source_from_object(scene.object_from_reference(ref))

    image, clean, peak, coarse = render(source, to_source, cam, oversample=q,
                                        background=scene.placement.background, seed=seed)  # fmt: skip
    w, h = cam.size
    inner = (slice(1, h + 1), slice(1, w + 1))
    ref = store["ref"].reshape(h + 2, w + 2, 2)[inner]
    ok = store["ok"].reshape(h + 2, w + 2)[inner]
    src = coarse[inner]
    rows, cols = np.asarray(source).shape[:2]
    with np.errstate(invalid="ignore"):
        inside = (src[..., 0] >= -0.5) & (src[..., 0] <= cols - 0.5) & (src[..., 1] >= -0.5)
        inside &= src[..., 1] <= rows - 0.5
    return Rendering(
        image=image,
        clean=clean,
        reference_px=ref,
        object_um=scene.object_from_reference(ref),
        source_px=src,
        valid=ok & inside,
        oversample=q,
        peak_electrons=peak,
    )


__all__ = ["Camera", "Microscope", "Placement", "Rendering", "Scene", "auto_oversample", "render",
           "render_scene", "relative_intensity"]  # fmt: skip
