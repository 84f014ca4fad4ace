"""Camera images of the USAF-1951 target through a distortion field, with ground truth.

The chain, for every camera pixel (``docs/usaf.md``):

1. the pixel is split into ``oversample x oversample`` sub-pixels; the centre of each is
   mapped back through the field (``inverse``: distorted -> paraxial camera px, evaluated
   on the pixel grid and interpolated bilinearly, which is exact to ~1e-3 px for smooth
   fields) and from paraxial px to object um (the inverse of the affine
   ``paraxial_from_object_um``);
2. the target's transmission there is read from an area-sampled raster of the whole target
   (bars, reference squares, printed numbers, in its true layout) in object space, one
   raster cell per sub-pixel (:func:`oapcal.imaging.usaf.target_coverage`);
3. the sub-pixel image is blurred by the point-spread function in the camera plane: a
   Gaussian of ``sigma_px`` or the Airy pattern ``(2 J1(v) / v)^2``, ``v = 2 pi NA r / lambda``
   of an image-space numerical aperture and wavelength;
4. sub-pixels are averaged over each camera pixel (integration over the pixel area);
5. shot noise (Poisson) and read noise (Gaussian, ``read_noise_e`` electrons) are added,
   with the number of electrons at the brightest level chosen so that its signal-to-noise
   ratio is ``snr``, and the result is quantized to 8 or 16 bits (the brightest level at
   80 % of full scale).

The ground truth lists every bar corner: ``x_u, y_u`` its reference position at
``um_per_px`` (:meth:`oapcal.imaging.usaf.UsafTarget.reference_px`) turned into the
image's orientation (the orientation nearest to the field's paraxial map, e.g. ``rot180``
for the relay, whose paraxial map is ``-I``), ``x_d, y_d`` its true
position in the camera image, and ``visible`` whether it lies at least
:data:`VISIBLE_MARGIN_PX` inside the image.  The target's bounding-box centre is put on the
optical axis.

>>> sim = simulate_image((5,), snr=None, oversample=2, seed=0)
>>> sim.image.dtype.name, sim.image.shape, int(sim.visible.sum())
('uint8', (480, 640), 144)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError
from oapcal.imaging.usaf import intensity, nearest_orientation, target_coverage, usaf_target
from oapcal.progress import Stages
from oapcal.records import ImageSize

#: A corner is *fully visible* when it is at least this far (px) inside the image.
VISIBLE_MARGIN_PX = 3.0
#: The brightest level maps to this fraction of the full scale of the output integers.
WHITE_FRACTION = 0.8


@dataclass(frozen=True)
class SimulatedImage:
    """A simulated camera image and its ground truth.

    ``image`` ``(h, w)`` uint8 or uint16; ``clean`` the noise-free float image in relative
    intensity (brightest level 1); ``ids``, ``xy_u`` (reference px at ``um_per_px``),
    ``xy_d`` (true camera px), ``visible`` (bool) per corner; ``peak_electrons`` the
    electrons at the brightest level (None without noise); ``orientation`` the target's
    orientation in the image (a key of :data:`oapcal.imaging.usaf.ORIENTATIONS`), which
    ``xy_u`` follows.
    """

    image: np.ndarray
    clean: np.ndarray
    ids: tuple[str, ...]
    xy_u: np.ndarray
    xy_d: np.ndarray
    visible: np.ndarray
    um_per_px: float
    groups: tuple[int, ...]
    peak_electrons: float | None
    orientation: str = "none"


def _paraxial_affine(field) -> tuple[np.ndarray, np.ndarray]:
    """``p0, M`` with ``paraxial_from_object_um(X) = p0 + M X`` (X in um)."""
    pts = np.array([[0.0, 0.0], [1000.0, 0.0], [0.0, 1000.0]])
    q = np.asarray(field.paraxial_from_object_um(pts), float)
    p0 = q[0]
    mat = np.stack([(q[1] - p0) / 1000.0, (q[2] - p0) / 1000.0], axis=1)
    if not np.isfinite(mat).all() or abs(np.linalg.det(mat)) < 1e-12:
        raise DataError("the field's paraxial_from_object_um is not an invertible affine map")
    return p0, mat


def bilinear_upsample(coarse: np.ndarray, q: int, shape: tuple[int, int]) -> np.ndarray:
    """Sub-pixel values from a map sampled at pixel centres ``-1 .. w`` x ``-1 .. h``.

    ``coarse`` is ``(h + 2, w + 2, c)``; the result ``(q h, q w, c)`` at sub-pixel centres
    ``(i + 1/2) / q - 1/2``.  Separable linear interpolation (the same numbers as
    ``scipy.ndimage.map_coordinates(order=1)``, tested) written out because the sub-pixel
    grid is a tensor product, which makes it ~10x faster on a 2560 x 1920 grid.
    """
    h, w = shape

    def axis_weights(n):
        pos = (np.arange(n * q) + 0.5) / q - 0.5 + 1.0  # in coarse index units
        j0 = np.clip(np.floor(pos).astype(int), 0, n)
        return j0, (pos - j0)[:, None]

    jx, tx = axis_weights(w)
    jy, ty = axis_weights(h)
    along_x = coarse[:, jx] * (1 - tx) + coarse[:, jx + 1] * tx  # (h + 2, q w, c)
    return along_x[jy] * (1 - ty[..., None]) + along_x[jy + 1] * ty[..., None]


def airy_kernel(na: float, wavelength_um: float, px_um: float, *, radius_zeros: float = 4.0) -> np.ndarray:
    """The Airy PSF ``(2 J1(v) / v)^2``, ``v = 2 pi NA r / lambda``, integrated over square
    cells of ``px_um`` (4 x 4 samples each), out to ``radius_zeros`` first dark rings
    (``0.61 lambda / NA``), normalised to sum 1."""
    from scipy.special import j1

    if not (0 < na < 1 and wavelength_um > 0):
        raise DataError(f"Airy PSF: need 0 < NA < 1 and a positive wavelength (got {na}, {wavelength_um})")
    r_zero = 0.61 * wavelength_um / na
    half = max(2, int(np.ceil(radius_zeros * r_zero / px_um)))
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    c = np.arange(-half, half + 1)
    xs = (c[:, None] + sub[None, :]).ravel() * px_um
    rr = np.hypot(xs[None, :], xs[:, None])
    v = 2 * np.pi * na * rr / wavelength_um
    with np.errstate(invalid="ignore", divide="ignore"):
        psf = np.where(v > 1e-9, (2 * j1(v) / v) ** 2, 1.0)
    n = 2 * half + 1
    kernel = psf.reshape(n, 4, n, 4).sum(axis=(1, 3))
    return kernel / kernel.sum()


def peak_electrons_for_snr(snr: float, read_noise_e: float) -> float:
    """Electrons ``N`` at the brightest level with ``N / sqrt(N + r^2) = snr`` (shot + read)."""
    s2 = float(snr) ** 2
    return 0.5 * (s2 + np.sqrt(s2 * s2 + 4.0 * s2 * float(read_noise_e) ** 2))


@dataclass(frozen=True)
class ImageSettings:
    """The optics, camera and drawing of :func:`simulate_image` (module docstring).

    The PSF is the Airy pattern when ``na`` and ``wavelength_um`` are given, else a Gaussian
    of ``sigma_px`` (0: no blur); ``snr=None`` gives a noise-free (only quantized) image;
    ``read_noise_e`` electrons of read noise; ``bits`` 8 or 16; ``polarity`` ``bright`` or
    ``dark`` bars on a ``background`` of that relative level; ``oversample`` sub-pixels per
    pixel side; the target is drawn in the layout ``layout_name`` (default ``"compact"``,
    :data:`oapcal.imaging.usaf.LAYOUTS`) with its reference squares (``squares``) and
    printed numbers (``digits``).  Invalid values raise :class:`~oapcal.errors.DataError`.

    >>> ImageSettings(snr=None, oversample=2).bits
    8
    """

    sigma_px: float = 0.8
    na: float | None = None
    wavelength_um: float | None = None
    snr: float | None = 50.0
    read_noise_e: float = 5.0
    bits: int = 8
    polarity: str = "bright"
    background: float = 0.05
    oversample: int = 4
    squares: bool = True
    digits: bool = True
    layout_name: str | None = None

    def __post_init__(self):
        if self.bits not in (8, 16):
            raise DataError(f"bits {self.bits}: use 8 or 16", param="bits")
        object.__setattr__(self, "oversample", int(self.oversample))
        if self.oversample < 1:
            raise DataError(f"oversample {self.oversample}: must be at least 1", param="oversample")
        if self.sigma_px < 0:
            raise DataError(f"sigma_px {self.sigma_px}: must be >= 0", param="sigma_px")
        if self.snr is not None and not self.snr > 0:
            raise DataError(f"snr {self.snr}: must be positive (or None for no noise)", param="snr")
        if (self.na is None) != (self.wavelength_um is None):
            raise DataError("an Airy PSF needs both na and wavelength_um", param=("na", "wavelength_um"))


def simulate_image(
    groups=(4, 5),
    field=None,
    *,
    settings: ImageSettings | None = None,
    um_per_px: float | None = None,
    seed: int = 0,
    progress=None,
    **options,
) -> SimulatedImage:
    """Simulate a camera image of USAF ``groups`` through ``field`` (module docstring).

    ``field`` defaults to :func:`oapcal.imaging.field.setup1_like_field`.  ``settings``
    (an :class:`ImageSettings`) holds the optics, camera and drawing; any of its fields may
    also be given as a keyword (``sigma_px=0.8, snr=None, ...``), which overrides
    ``settings``.  ``um_per_px`` is the scale of the reference positions ``xy_u``
    (default: the field's paraxial scale, so that ``xy_u`` is the paraxial image of each
    corner); ``seed`` seeds the noise.  Only bar corners are landmarks.
    ``progress(done, total, description)`` (optional) hears of each of the 5 steps
    (:mod:`oapcal.progress`).
    """
    from oapcal.imaging.field import setup1_like_field

    settings = _settings(settings, options)
    if field is None:
        field = setup1_like_field()
    target = usaf_target(groups, settings.layout_name)
    w, h = (int(v) for v in field.image_size)
    q = settings.oversample
    p0, mat = _paraxial_affine(field)
    paraxial_scale = float(np.sqrt(abs(np.linalg.det(mat))))  # px per um
    orientation = nearest_orientation(mat)
    ref_scale = float(um_per_px) if um_per_px is not None else 1.0 / paraxial_scale

    with Stages(progress, 5, "simulating") as stages:
        obj = _object_positions(field, target, q)
        stages.advance(description="mapped pixels through the field")
        sub = _sample_target(target, obj, field, settings)
        stages.advance(description="sampled the target")
        sub = blur(sub, q, settings.sigma_px, settings.na, settings.wavelength_um, field.pixel_size_um)
        stages.advance(description="blurred")
        clean = sub.reshape(h, q, w, q).mean(axis=(1, 3), dtype=np.float64)  # over each camera pixel
        stages.advance(description="integrated over pixels")
        image, peak = expose(clean, settings, seed)
        stages.advance(description="added noise")

    xy_d, visible = _true_corners(target, field)
    return SimulatedImage(
        image=image,
        clean=clean,
        ids=target.corner_ids,
        xy_u=target.reference_px(ref_scale, (w, h), orientation),
        xy_d=xy_d,
        visible=visible,
        um_per_px=ref_scale,
        groups=target.groups,
        peak_electrons=peak,
        orientation=orientation,
    )


def _settings(settings: ImageSettings | None, options: dict) -> ImageSettings:
    """``settings`` (default :class:`ImageSettings`) with the keyword ``options`` of
    :func:`simulate_image` over it; an unknown keyword is a TypeError, as for any function."""
    from dataclasses import fields, replace

    unknown = sorted(set(options) - {f.name for f in fields(ImageSettings)})
    if unknown:
        raise TypeError(f"simulate_image() got an unexpected keyword argument {unknown[0]!r}")
    return replace(settings, **options) if settings is not None else ImageSettings(**options)


def _object_positions(field, target, q: int) -> np.ndarray:
    """Step 1: the object position (target um) of every sub-pixel centre ``(q h, q w, 2)``:
    distorted -> paraxial px through the field's inverse on the pixel grid, interpolated
    bilinearly, then the inverse paraxial affine."""
    w, h = (int(v) for v in field.image_size)
    p0, mat = _paraxial_affine(field)
    gx, gy = np.meshgrid(np.arange(-1.0, w + 1.0), np.arange(-1.0, h + 1.0))
    coarse = np.asarray(field.inverse(np.stack([gx, gy], -1).reshape(-1, 2)), float)
    coarse = coarse.reshape(h + 2, w + 2, 2)
    fine = bilinear_upsample(coarse, q, (h, w))  # (q h, q w, 2) paraxial px
    return (fine - p0) @ np.linalg.inv(mat).T + target.centre_um


def _sample_target(target, obj: np.ndarray, field, settings: ImageSettings) -> np.ndarray:
    """Step 2: the target's relative intensity at the object positions ``obj``, read from
    an area-sampled raster with one cell per sub-pixel, aligned with the sub-pixels."""
    from scipy.ndimage import map_coordinates

    q = settings.oversample
    p0, mat = _paraxial_affine(field)
    mat_inv = np.linalg.inv(mat)
    step = 1.0 / (q * float(np.linalg.svd(mat, compute_uv=False).max()))
    anchor = mat_inv @ (np.array([0.5 / q - 0.5] * 2) - p0) + target.centre_um
    extent = target.full_bbox_um if (settings.squares or settings.digits) else target.bbox_um
    lo = extent[:2] - 4 * step
    hi = extent[2:] + 4 * step
    start = anchor + np.floor((lo - anchor) / step) * step
    n = np.ceil((hi - start) / step).astype(int) + 1
    raster = target_coverage(
        target, (n[1], n[0]), start=tuple(start), step=step, squares=settings.squares, digits=settings.digits
    )
    col = (obj[..., 0] - start[0]) / step
    row = (obj[..., 1] - start[1]) / step
    inside = (col > -1) & (row > -1) & (col < n[0]) & (row < n[1])  # NaN -> False
    cover = np.zeros(obj.shape[:2])
    cover[inside] = map_coordinates(raster, [row[inside], col[inside]], order=1, cval=0.0)
    return intensity(cover, settings.polarity, settings.background).astype(np.float32)


def expose(clean: np.ndarray, settings: ImageSettings, seed: int) -> tuple[np.ndarray, float | None]:
    """Step 5: shot and read noise, then quantization: the image and the electrons at the
    brightest level (None without noise)."""
    rng = np.random.default_rng(seed)
    full = float(2**settings.bits - 1)
    if settings.snr is None:
        electrons, n_peak = clean, 1.0
        peak = None
    else:
        n_peak = peak_electrons_for_snr(settings.snr, settings.read_noise_e)
        electrons = rng.poisson(np.clip(clean, 0, None) * n_peak) + rng.normal(
            0.0, settings.read_noise_e, clean.shape
        )
        peak = float(n_peak)
    dn = np.clip(np.rint(electrons / n_peak * WHITE_FRACTION * full), 0, full)
    return dn.astype(np.uint8 if settings.bits == 8 else np.uint16), peak


def _true_corners(target, field) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth: every bar corner's camera position and whether it lies at least
    :data:`VISIBLE_MARGIN_PX` inside the image."""
    w, h = (int(v) for v in field.image_size)
    xy_d = np.asarray(
        field.forward(field.paraxial_from_object_um(target.corners_um - target.centre_um)), float
    )
    return xy_d, ImageSize(w, h).contains(xy_d, VISIBLE_MARGIN_PX)


def blur(sub, q, sigma_px, na, wavelength_um, pixel_size_um):
    import cv2

    if na is not None:
        kernel = airy_kernel(na, wavelength_um, pixel_size_um / q).astype(np.float32)
        return cv2.filter2D(sub, -1, kernel, borderType=cv2.BORDER_REPLICATE)
    if sigma_px > 0:
        return cv2.GaussianBlur(sub, (0, 0), sigmaX=sigma_px * q, borderType=cv2.BORDER_REPLICATE)
    return sub
