"""Image quality of a relay: spot diagrams, RMS spot radius, diffraction and pixel limits.

Diffraction limits for a circular pupil with image-space numerical aperture ``NA`` at
wavelength ``lambda``: Rayleigh ``0.61 lambda / NA`` (the Airy radius), Sparrow
``0.47 lambda / NA``.  For the paper's NA 0.193 at 850 nm:

>>> round(sparrow_limit_um(0.193, 850.0), 2), round(rayleigh_limit_um(0.193, 850.0), 2)
(2.07, 2.69)
>>> round(numerical_aperture(20.0, 50.8), 4)  # a 20 mm beam on f = 50.8 mm
0.1931
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import GeometrySpecError
from oapcal.optics.relay import Relay, chief_rays, trace_through_stop

SPARROW_FACTOR = 0.47
RAYLEIGH_FACTOR = 0.61


def numerical_aperture(beam_diameter_mm: float, focal_length_mm: float) -> float:
    """``sin(atan(D / 2f))``: the NA of a collimated beam of diameter ``D`` focused by a
    mirror of (reflected) focal length ``f``."""
    return float(np.sin(np.arctan(0.5 * float(beam_diameter_mm) / float(focal_length_mm))))


def sparrow_limit_um(na: float, wavelength_nm: float) -> float:
    """Sparrow two-point resolution ``0.47 lambda / NA`` in um."""
    return SPARROW_FACTOR * float(wavelength_nm) * 1e-3 / float(na)


def rayleigh_limit_um(na: float, wavelength_nm: float) -> float:
    """Rayleigh two-point resolution (Airy radius) ``0.61 lambda / NA`` in um."""
    return RAYLEIGH_FACTOR * float(wavelength_nm) * 1e-3 / float(na)


def pixel_limit_um(pixel_size_um: float, magnification: float = 1.0) -> float:
    """Pixel-limited resolution in object space, ``2 p / |m|``: two points are resolved only
    with a pixel between them, i.e. the finest period the sensor samples (Nyquist)."""
    return 2.0 * float(pixel_size_um) / abs(float(magnification))


def hexapolar_pupil(rings: int = 8) -> np.ndarray:
    """Pupil samples ``(1 + 3 rings (rings + 1), 2)`` in the unit disc: the centre and
    ``6 k`` equally spaced points on ring ``k / rings`` (``k = 1 .. rings``)."""
    if int(rings) < 1:
        raise GeometrySpecError(f"the pupil needs at least 1 ring of rays, got {rings}")
    pts = [np.zeros((1, 2))]
    for k in range(1, int(rings) + 1):
        phi = 2 * np.pi * np.arange(6 * k) / (6 * k)
        pts.append((k / rings) * np.stack([np.cos(phi), np.sin(phi)], axis=-1))
    return np.concatenate(pts)


@dataclass(frozen=True)
class Spot:
    """A spot diagram at one field point.

    ``field_mm`` (2,) object point; ``chief_mm`` (2,) its chief-ray image point;
    ``xy_um`` ``(M, 2)`` ray hits relative to the chief ray (um, image-plane axes);
    ``clear`` ``(M,)`` rays not vignetted; ``centroid_um`` (2,) their centroid;
    ``rms_um`` RMS radius about the centroid; ``rms_chief_um`` about the chief ray;
    ``geo_um`` the largest distance from the centroid.
    """

    field_mm: np.ndarray
    chief_mm: np.ndarray
    xy_um: np.ndarray
    clear: np.ndarray
    centroid_um: np.ndarray
    rms_um: float
    rms_chief_um: float
    geo_um: float


def spot_diagram(relay: Relay, field_mm, beam_diameter_mm: float = 20.0, rings: int = 8) -> Spot:
    """Trace a hexapolar bundle filling a stop of ``beam_diameter_mm`` from the object
    point ``field_mm`` (2,) to the image plane (rays aimed through the stop by Newton)."""
    if not float(beam_diameter_mm) > 0:
        raise GeometrySpecError(f"the beam diameter must be a positive number of mm, got {beam_diameter_mm}")
    field_mm = np.asarray(field_mm, dtype=float)
    pupil = hexapolar_pupil(rings) * (0.5 * float(beam_diameter_mm))
    chief = chief_rays(relay, field_mm).xy_mm
    rays = trace_through_stop(relay, np.broadcast_to(field_mm, pupil.shape), pupil)
    xy_um = (rays.xy_mm - chief) * 1e3
    ok = rays.clear & np.isfinite(xy_um).all(axis=-1)
    if not ok.any():
        x, y = (float(v) for v in np.broadcast_to(field_mm, (2,)))
        fix = "a smaller field (field_mm) or a shorter d1"
        if not relay.misalignment.is_zero:
            fix = "smaller misalignments, " + fix
        raise GeometrySpecError(
            f"no ray of the {float(beam_diameter_mm):g} mm beam from the field point ({x:g}, {y:g}) mm "
            f"passes both mirrors (d1 = {relay.d1_mm:g} mm); give {fix}",
            param=("field_mm", "spot_fields", "d1"),
        )
    use = xy_um[ok]
    centroid = use.mean(axis=0)
    r2 = ((use - centroid) ** 2).sum(axis=-1)
    return Spot(
        field_mm=field_mm,
        chief_mm=chief,
        xy_um=xy_um,
        clear=ok,
        centroid_um=centroid,
        rms_um=float(np.sqrt(r2.mean())),
        rms_chief_um=float(np.sqrt((use**2).sum(axis=-1).mean())),
        geo_um=float(np.sqrt(r2.max())),
    )


def traced_numerical_aperture(relay: Relay, beam_diameter_mm: float = 20.0, n: int = 360) -> float:
    """Image-space NA from real rays: the mean over the marginal ring of the sine of the
    angle between a marginal ray and the central chief ray (both meet at the focus)."""
    phi = 2 * np.pi * np.arange(n) / n
    ring = 0.5 * float(beam_diameter_mm) * np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    rays = trace_through_stop(relay, np.zeros_like(ring), ring)
    axis = np.asarray(relay.image_plane.normal)
    cos = np.clip(rays.trace.direction @ axis, -1.0, 1.0)
    return float(np.sqrt(1.0 - cos**2).mean())
