"""One call that simulates a relay the way ``oapcal simulate relay`` reports it: grid
distortion, its statistics next to the paper's, the radial-fit residual, spot sizes and
resolution limits.

Compute, then render: :func:`simulate_relay` traces and returns a typed
:class:`RelaySimulation`; :func:`relay_summary` (also ``RelaySimulation.summary``) turns it
into the JSON-ready dict of ``oapcal simulate relay --json`` (``docs/cli.md``).  Files
and figures are made elsewhere (:mod:`oapcal.io.grid`, :mod:`oapcal.report.optics_plots`).

>>> sim = simulate_relay(1)
>>> round(sim.summary["distortion"]["max_um"])  # the paper reports 193 um
192
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from oapcal.errors import GeometrySpecError
from oapcal.optics.quality import (
    Spot,
    hexapolar_pupil,
    numerical_aperture,
    pixel_limit_um,
    rayleigh_limit_um,
    sparrow_limit_um,
    spot_diagram,
    traced_numerical_aperture,
)
from oapcal.optics.relay import GridDistortion, Relay, grid_distortion, radial_fit, resolve_relay

#: The paper's figures for setup 1 (1 mm x 1 mm field, 17 x 17 points, 4.8 um pixels).
PAPER_SETUP1 = {
    "max_um": 193.0,
    "max_px": 40.2,
    "mean_um": 58.3,
    "mean_px": 12.1,
    "radial_fit_mean_um": 33.6,
    "radial_fit_mean_px": 6.99,
    "na": 0.193,
    "sparrow_um": 2.07,
}

#: Rays traced around the stop's rim for the traced numerical aperture.
NA_RAYS = 360

#: The orientations whose spot diagrams are traced, in this order.
SPOT_ORIENTATIONS = ("U", "Z")

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class RadialFitResidual:
    """The second-order radial model fitted to the grid (:func:`~oapcal.optics.relay.radial_fit`):
    whether it converged and its mean forward and correction residuals, in image-plane mm."""

    converged: bool
    mean_residual_mm: float
    mean_correction_residual_mm: float


@dataclass(frozen=True)
class ResolutionLimits:
    """Numerical aperture (paraxial and traced, image side) and the resolution limits (um)
    of a collimated beam of ``beam_diameter_mm`` at ``wavelength_nm``."""

    beam_diameter_mm: float
    wavelength_nm: float
    na: float
    na_traced: float
    sparrow_um: float
    rayleigh_um: float
    pixel_limit_um: float


@dataclass(frozen=True)
class RelaySimulation:
    """What :func:`simulate_relay` computed.

    ``grid`` the traced grid (its ``relay`` the relay traced); ``spots``
    ``{orientation: [Spot per field point]}`` for both orientations, traced with ``rings``
    hexapolar rings; ``radial`` the radial-fit residual; ``limits`` the NA and resolution
    limits; ``pixel_size_um`` the camera pixel that px figures use.
    """

    grid: GridDistortion
    spots: dict[str, list[Spot]]
    radial: RadialFitResidual
    limits: ResolutionLimits
    pixel_size_um: float
    rings: int

    @property
    def relay(self) -> Relay:
        return self.grid.relay

    @property
    def magnification(self) -> float:
        """The paraxial magnification ``sqrt(|det matrix|)``."""
        return paraxial_magnification(self.grid)

    @property
    def paper(self) -> dict | None:
        """The paper's figures when this is the paper's case (setup 1, U, aligned, 17 x 17
        over 1 mm; the px figures only for 4.8 um pixels), else None."""
        relay, grid = self.relay, self.grid
        paper_case = (
            relay.d1_mm == 860.0 and relay.orientation == "U" and grid.n == 17 and grid.field_mm == 1.0
            and relay.focal_length_mm == 50.8 and relay.focal_length_2_mm is None
            and relay.misalignment.is_zero
        )  # fmt: skip
        if not paper_case:
            return None
        if self.pixel_size_um != 4.8:  # the paper's px figures are for 4.8 um pixels
            return {k: v for k, v in PAPER_SETUP1.items() if not k.endswith("_px")}
        return dict(PAPER_SETUP1)

    @property
    def summary(self) -> dict:
        """The JSON-ready dict of :func:`relay_summary`."""
        return relay_summary(self)


def default_spot_fields(field_mm: float) -> list[tuple[float, float]]:
    """The field centre, the middle of two edges and a corner of a square field (mm)."""
    half = 0.5 * float(field_mm)
    return [(0.0, 0.0), (half, 0.0), (0.0, half), (half, half)]


def paraxial_magnification(grid: GridDistortion) -> float:
    """``sqrt(|det M|)`` of the grid's paraxial map ``M``."""
    return float(np.sqrt(abs(np.linalg.det(grid.matrix))))


class _Work:
    """Progress over the steps of :func:`simulate_relay`, counted in traced rays."""

    def __init__(self, total: int, progress: Progress | None):
        self.total = total
        self.done = 0
        self.progress = progress

    def advance(self, k: int) -> None:
        self.done += k
        if self.progress is not None:
            self.progress(self.done, self.total)

    def within(self, done: int, _total: int) -> None:
        """The ``progress`` of a step: its own count added to the steps before it."""
        if self.progress is not None:
            self.progress(self.done + done, self.total)


@dataclass(frozen=True)
class SimulationOptions:
    """What :func:`simulate_relay` traces besides the relay: an ``n`` x ``n`` grid over
    ``field_mm``, px figures for ``pixel_size_um`` (None: the design's, 4.8 for a
    :class:`~oapcal.optics.relay.Relay`), spot diagrams at ``spot_fields`` (object mm,
    ``(M, 2)``; None: :func:`default_spot_fields`) with ``rings`` hexapolar rings, and the
    NA and resolution limits of a collimated beam of ``beam_diameter_mm`` at
    ``wavelength_nm``."""

    n: int = 17
    field_mm: float = 1.0
    pixel_size_um: float | None = None
    beam_diameter_mm: float = 20.0
    wavelength_nm: float = 850.0
    spot_fields: object = None
    rings: int = 8


def simulate_relay(design=1, options: SimulationOptions | None = None, *, misalignment=None,
                   progress: Progress | None = None, **keywords) -> RelaySimulation:  # fmt: skip
    """Trace the relay and summarize it (see the module docstring).

    ``design`` a :class:`~oapcal.optics.relay_model.RelayDesign` (traced with
    ``misalignment``, as :func:`~oapcal.optics.relay.oap_relay` takes it; the spot diagrams
    of the other orientation get the same misalignment), or a
    :class:`~oapcal.optics.relay.Relay` traced as it is; ``options`` a
    :class:`SimulationOptions`.  ``progress(done, total)`` is called as the work advances,
    counted in traced rays (the radial fit counts as one ray per grid point).

    The older form still works: ``design`` the setup (1, 2 or None) and the relay's
    keywords of :func:`~oapcal.optics.relay.oap_relay` (``d1_mm``, ``orientation``,
    ``stop_distance_mm``, ``focal_length_mm``, ``focal_length_2_mm``), with the options'
    fields as keywords (``simulate_relay(1, n=9, pixel_size_um=5.0)``).
    """
    relay, pixel = resolve_relay(design, misalignment, keywords)
    options = dataclasses.replace(options or SimulationOptions(), **keywords)  # unknown names raise
    if options.pixel_size_um is None:
        options = dataclasses.replace(options, pixel_size_um=4.8 if pixel is None else pixel)
    return _simulate(relay, options, progress)


def _simulate(relay: Relay, options: SimulationOptions, progress: Progress | None) -> RelaySimulation:
    """:func:`simulate_relay` of a built relay: the grid, its radial fit, spots and limits."""
    n, field_mm, rings = int(options.n), options.field_mm, options.rings
    field_points = _spot_fields(options.spot_fields, field_mm)
    rays_per_spot = len(hexapolar_pupil(rings)) + 1
    work = _Work(2 * n * n + len(SPOT_ORIENTATIONS) * len(field_points) * rays_per_spot + NA_RAYS, progress)

    grid = trace_grid(relay, n, field_mm, progress=work.within)
    work.advance(n * n)
    fit_result, forward_mm, correction_mm = radial_fit(grid)
    radial = RadialFitResidual(bool(fit_result.converged), forward_mm, correction_mm)
    work.advance(n * n)
    spots = trace_spots(
        relay, field_points, options.beam_diameter_mm, rings, done=lambda: work.advance(rays_per_spot)
    )
    limits = resolution_limits(relay, options.beam_diameter_mm, options.wavelength_nm, options.pixel_size_um,
                               paraxial_magnification(grid))  # fmt: skip
    work.advance(NA_RAYS)
    return RelaySimulation(grid, spots, radial, limits, float(options.pixel_size_um), int(rings))


def _spot_fields(spot_fields, field_mm: float) -> list[tuple[float, float]]:
    """The spot diagrams' object points as ``(x, y)`` mm tuples (default: :func:`default_spot_fields`)."""
    points = default_spot_fields(field_mm) if spot_fields is None else spot_fields
    points = [tuple(float(v) for v in p) for p in np.asarray(points, dtype=float).reshape(-1, 2)]
    if not np.isfinite(points).all():
        raise GeometrySpecError("spot field points must be finite numbers of mm")
    return points


def trace_grid(relay: Relay, n: int, field_mm: float, progress: Progress | None = None) -> GridDistortion:
    """:func:`~oapcal.optics.relay.grid_distortion`, refused with
    :class:`~oapcal.errors.GeometrySpecError` when chief rays are lost or the paraxial map
    near the field centre is not invertible (nothing to compare the real points with)."""
    grid = grid_distortion(relay, n, field_mm, progress=progress)
    lost = int((~np.isfinite(grid.xy_d).all(axis=1)).sum())
    if lost or not (np.isfinite(grid.matrix).all() and abs(np.linalg.det(grid.matrix)) > 1e-9):
        what = (
            f"the chief rays of {lost} of the {n * n} grid points"
            if lost
            else "the rays near the field centre"
        )
        fix = "smaller misalignments" if not relay.misalignment.is_zero else "a smaller field (field_mm)"
        raise GeometrySpecError(
            f"{what} miss a mirror surface or the image plane; give {fix}", param="field_mm"
        )
    return grid


def _with_orientation(relay: Relay, orientation: str) -> Relay:
    """The same design and misalignment with the second mirror in ``orientation``."""
    return relay if orientation == relay.orientation else relay.rebuilt(orientation=orientation)


def trace_spots(relay: Relay, field_points, beam_diameter_mm: float, rings: int,
                done: Callable[[], None] | None = None) -> dict[str, list[Spot]]:  # fmt: skip
    """Spot diagrams of ``relay`` in both orientations (:data:`SPOT_ORIENTATIONS`) at each
    object point of ``field_points`` (mm); ``done()`` is called after each spot."""
    spots = {}
    for key in SPOT_ORIENTATIONS:
        other = _with_orientation(relay, key)
        spots[key] = []
        for p in field_points:
            spots[key].append(spot_diagram(other, p, beam_diameter_mm, rings))
            if done is not None:
                done()
    return spots


def resolution_limits(relay: Relay, beam_diameter_mm: float, wavelength_nm: float, pixel_size_um: float,
                      magnification: float) -> ResolutionLimits:  # fmt: skip
    """The image-side NA (paraxial from the beam and the second focal length, and traced
    with :data:`NA_RAYS` rays) and the Sparrow, Rayleigh and pixel limits."""
    na = numerical_aperture(beam_diameter_mm, relay.focal_lengths_mm[1])
    return ResolutionLimits(
        beam_diameter_mm=float(beam_diameter_mm),
        wavelength_nm=float(wavelength_nm),
        na=na,
        na_traced=traced_numerical_aperture(relay, beam_diameter_mm, NA_RAYS),
        sparrow_um=sparrow_limit_um(na, wavelength_nm),
        rayleigh_um=rayleigh_limit_um(na, wavelength_nm),
        pixel_limit_um=pixel_limit_um(pixel_size_um, magnification),
    )


# --------------------------------------------------------------------------- render


def _distortion_summary(grid: GridDistortion, px: float) -> dict:
    """The grid distortion's statistics in um and px (``px`` camera px per image mm)."""
    disp, dist = grid.displacement, grid.distortion
    return {
        "max_um": float(dist.max() * 1e3),
        "mean_um": float(dist.mean() * 1e3),
        "max_px": float(dist.max() * px),
        "mean_px": float(dist.mean() * px),
        "max_abs_dx_um": float(np.abs(disp[:, 0]).max() * 1e3),
        "max_abs_dy_um": float(np.abs(disp[:, 1]).max() * 1e3),
        "max_abs_dx_px": float(np.abs(disp[:, 0]).max() * px),
        "max_abs_dy_px": float(np.abs(disp[:, 1]).max() * px),
    }


def _quality_summary(sim: RelaySimulation) -> dict:
    """The beam, its NA and resolution limits, and the spots' sizes."""
    q = sim.limits
    return {
        "beam_diameter_mm": q.beam_diameter_mm,
        "wavelength_nm": q.wavelength_nm,
        "rings": sim.rings,
        "na": q.na,
        "na_traced": q.na_traced,
        "sparrow_um": q.sparrow_um,
        "rayleigh_um": q.rayleigh_um,
        "pixel_limit_um": q.pixel_limit_um,
        "spots": [
            {
                "orientation": key,
                "field_mm": list(map(float, s.field_mm)),
                "rms_um": s.rms_um,
                "geo_um": s.geo_um,
            }
            for key in SPOT_ORIENTATIONS
            for s in sim.spots[key]
        ],  # fmt: skip
    }


def relay_summary(sim: RelaySimulation) -> dict:
    """The JSON-ready summary of ``oapcal simulate relay --json`` (``docs/cli.md``): the
    relay, the grid, the paraxial map, the distortion in um and px, the radial fit, the
    resolution limits and spots, and the paper's figures when comparable."""
    relay, grid, radial = sim.relay, sim.grid, sim.radial
    px = 1e3 / sim.pixel_size_um  # px per image mm
    return {
        "relay": {
            "d1_mm": relay.d1_mm,
            "orientation": relay.orientation,
            "stop_distance_mm": relay.stop_distance_mm,
            "focal_length_mm": relay.focal_length_mm,
            "diameter_mm": relay.diameter_mm,
            "focal_length_2_mm": relay.focal_lengths_mm[1],
            "misalignment": relay.misalignment.to_dict(),
        },
        "grid": {
            "n": grid.n,
            "field_mm": grid.field_mm,
            "pixel_size_um": sim.pixel_size_um,
            "n_vignetted": int((~grid.clear).sum()),
        },
        "paraxial_matrix": grid.matrix.round(12).tolist(),
        "paraxial_offset_mm": grid.offset.round(12).tolist(),
        "magnification": sim.magnification,
        "distortion": _distortion_summary(grid, px),
        "radial_fit": {
            "model": "radial",
            "normalize": "grid",
            "converged": radial.converged,
            "mean_residual_um": radial.mean_residual_mm * 1e3,
            "mean_residual_px": radial.mean_residual_mm * px,
            "mean_correction_residual_um": radial.mean_correction_residual_mm * 1e3,
            "mean_correction_residual_px": radial.mean_correction_residual_mm * px,
        },
        "quality": _quality_summary(sim),
        "paper": sim.paper,
    }
