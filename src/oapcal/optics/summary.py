"""One call that simulates a relay the way ``oapcal simulate relay`` reports it: grid
distortion, its statistics next to the paper's, the radial-fit residual, spot sizes and
resolution limits.

>>> sim = simulate_relay(1)
>>> round(sim.summary["distortion"]["max_um"])  # the paper reports 193 um
192
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.optics.quality import (
    Spot,
    numerical_aperture,
    pixel_limit_um,
    rayleigh_limit_um,
    sparrow_limit_um,
    spot_diagram,
    traced_numerical_aperture,
)
from oapcal.optics.relay import GridDistortion, grid_distortion, oap_relay, radial_fit

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


@dataclass(frozen=True)
class RelaySimulation:
    """``grid`` the traced grid, ``summary`` a JSON-ready dict (``docs/cli.md``), ``spots``
    ``{orientation: [Spot per field point]}`` for both orientations."""

    grid: GridDistortion
    summary: dict
    spots: dict[str, list[Spot]]


def simulate_relay(
    setup: int | None = 1,
    *,
    d1_mm: float | None = None,
    orientation: str = "U",
    stop_distance_mm: float | None = None,
    focal_length_mm: float = 50.8,
    n: int = 17,
    field_mm: float = 1.0,
    pixel_size_um: float = 4.8,
    beam_diameter_mm: float = 20.0,
    wavelength_nm: float = 850.0,
) -> RelaySimulation:
    """Trace the relay and summarize it (see the module docstring)."""
    relay = oap_relay(
        setup, d1_mm=d1_mm, orientation=orientation, stop_distance_mm=stop_distance_mm,
        focal_length_mm=focal_length_mm,
    )  # fmt: skip
    grid = grid_distortion(relay, n, field_mm)
    px = 1e3 / float(pixel_size_um)  # px per image mm
    disp = grid.displacement
    dist = grid.distortion
    fit_result, forward_mm, correction_mm = radial_fit(grid)
    magnification = float(np.sqrt(abs(np.linalg.det(grid.matrix))))

    half = 0.5 * grid.field_mm
    field_points = [(0.0, 0.0), (half, 0.0), (0.0, half), (half, half)]
    spots = {}
    for key in ("U", "Z"):
        other = relay if key == relay.orientation else oap_relay(
            setup, d1_mm=relay.d1_mm, orientation=key, stop_distance_mm=relay.stop_distance_mm,
            focal_length_mm=focal_length_mm,
        )  # fmt: skip
        spots[key] = [spot_diagram(other, p, beam_diameter_mm) for p in field_points]
    na = numerical_aperture(beam_diameter_mm, relay.focal_length_mm)
    paper_case = (
        relay.d1_mm == 860.0 and relay.orientation == "U" and grid.n == 17 and grid.field_mm == 1.0
        and relay.focal_length_mm == 50.8
    )  # fmt: skip
    summary = {
        "relay": {
            "d1_mm": relay.d1_mm,
            "orientation": relay.orientation,
            "stop_distance_mm": relay.stop_distance_mm,
            "focal_length_mm": relay.focal_length_mm,
            "diameter_mm": relay.diameter_mm,
        },
        "grid": {
            "n": grid.n,
            "field_mm": grid.field_mm,
            "pixel_size_um": float(pixel_size_um),
            "n_vignetted": int((~grid.clear).sum()),
        },
        "paraxial_matrix": grid.matrix.round(12).tolist(),
        "magnification": magnification,
        "distortion": {
            "max_um": float(dist.max() * 1e3),
            "mean_um": float(dist.mean() * 1e3),
            "max_px": float(dist.max() * px),
            "mean_px": float(dist.mean() * px),
            "max_abs_dx_um": float(np.abs(disp[:, 0]).max() * 1e3),
            "max_abs_dy_um": float(np.abs(disp[:, 1]).max() * 1e3),
            "max_abs_dx_px": float(np.abs(disp[:, 0]).max() * px),
            "max_abs_dy_px": float(np.abs(disp[:, 1]).max() * px),
        },
        "radial_fit": {
            "model": "radial",
            "normalize": "grid",
            "converged": bool(fit_result.converged),
            "mean_residual_um": forward_mm * 1e3,
            "mean_residual_px": forward_mm * px,
            "mean_correction_residual_um": correction_mm * 1e3,
            "mean_correction_residual_px": correction_mm * px,
        },
        "quality": {
            "beam_diameter_mm": float(beam_diameter_mm),
            "wavelength_nm": float(wavelength_nm),
            "na": na,
            "na_traced": traced_numerical_aperture(relay, beam_diameter_mm),
            "sparrow_um": sparrow_limit_um(na, wavelength_nm),
            "rayleigh_um": rayleigh_limit_um(na, wavelength_nm),
            "pixel_limit_um": pixel_limit_um(pixel_size_um, magnification),
            "spots": [
                {
                    "orientation": key,
                    "field_mm": list(map(float, s.field_mm)),
                    "rms_um": s.rms_um,
                    "geo_um": s.geo_um,
                }
                for key in ("U", "Z")
                for s in spots[key]
            ],  # fmt: skip
        },
        "paper": dict(PAPER_SETUP1) if paper_case else None,
    }
    return RelaySimulation(grid, summary, spots)
