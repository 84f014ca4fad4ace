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


def default_spot_fields(field_mm: float) -> list[tuple[float, float]]:
    """The field centre, the middle of two edges and a corner of a square field (mm)."""
    half = 0.5 * float(field_mm)
    return [(0.0, 0.0), (half, 0.0), (0.0, half), (half, half)]


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
    spot_fields=None,
    rings: int = 8,
    progress=None,
    focal_length_2_mm: float | None = None,
    misalignment=None,
) -> RelaySimulation:
    """Trace the relay and summarize it (see the module docstring).

    ``spot_fields`` are the object points (mm, ``(M, 2)``) of the spot diagrams, traced
    with ``rings`` hexapolar rings of rays (default: :func:`default_spot_fields`).
    ``progress(done, total)`` is called as the work advances, counted in traced rays
    (the radial fit counts as one ray per grid point).  ``focal_length_2_mm`` and
    ``misalignment`` are as in :func:`~oapcal.optics.relay.oap_relay` (the spot diagrams
    of the other orientation get the same misalignment).
    """
    relay = oap_relay(
        setup, d1_mm=d1_mm, orientation=orientation, stop_distance_mm=stop_distance_mm,
        focal_length_mm=focal_length_mm, focal_length_2_mm=focal_length_2_mm, misalignment=misalignment,
    )  # fmt: skip
    n = int(n)
    field_points = default_spot_fields(field_mm) if spot_fields is None else spot_fields
    field_points = [tuple(float(v) for v in p) for p in np.asarray(field_points, dtype=float).reshape(-1, 2)]
    if not np.isfinite(field_points).all():
        raise GeometrySpecError("spot field points must be finite numbers of mm")
    n_pupil = len(hexapolar_pupil(rings))
    n_na = 360
    total = 2 * n * n + 2 * len(field_points) * (n_pupil + 1) + n_na
    done = 0

    def advance(k: int) -> None:
        nonlocal done
        done += k
        if progress is not None:
            progress(done, total)

    def sub(d: int, _t: int) -> None:
        if progress is not None:
            progress(done + d, total)

    grid = grid_distortion(relay, n, field_mm, progress=sub)
    lost = int((~np.isfinite(grid.xy_d).all(axis=1)).sum())
    if lost or not (np.isfinite(grid.matrix).all() and abs(np.linalg.det(grid.matrix)) > 1e-9):
        what = (
            f"the chief rays of {lost} of the {n * n} grid points"
            if lost
            else "the rays near the field centre"
        )
        fix = "smaller misalignments" if not relay.misalignment.is_zero else "a smaller field (--field)"
        raise GeometrySpecError(f"{what} miss a mirror surface or the image plane; give {fix}")
    advance(n * n)
    px = 1e3 / float(pixel_size_um)  # px per image mm
    disp = grid.displacement
    dist = grid.distortion
    fit_result, forward_mm, correction_mm = radial_fit(grid)
    advance(n * n)
    magnification = float(np.sqrt(abs(np.linalg.det(grid.matrix))))

    spots = {}
    for key in ("U", "Z"):
        other = relay if key == relay.orientation else oap_relay(
            setup, d1_mm=relay.d1_mm, orientation=key, stop_distance_mm=relay.stop_distance_mm,
            focal_length_mm=focal_length_mm, focal_length_2_mm=focal_length_2_mm,
            misalignment=relay.misalignment,
        )  # fmt: skip
        spots[key] = []
        for p in field_points:
            spots[key].append(spot_diagram(other, p, beam_diameter_mm, rings))
            advance(n_pupil + 1)
    na = numerical_aperture(beam_diameter_mm, relay.focal_lengths_mm[1])  # image side
    na_traced = traced_numerical_aperture(relay, beam_diameter_mm, n_na)
    advance(n_na)
    paper_case = (
        relay.d1_mm == 860.0 and relay.orientation == "U" and grid.n == 17 and grid.field_mm == 1.0
        and relay.focal_length_mm == 50.8 and relay.focal_length_2_mm is None and relay.misalignment.is_zero
    )  # fmt: skip
    paper = None
    if paper_case:
        paper = dict(PAPER_SETUP1)
        if float(pixel_size_um) != 4.8:  # the paper's px figures are for 4.8 um pixels
            paper = {k: v for k, v in paper.items() if not k.endswith("_px")}
    summary = {
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
            "pixel_size_um": float(pixel_size_um),
            "n_vignetted": int((~grid.clear).sum()),
        },
        "paraxial_matrix": grid.matrix.round(12).tolist(),
        "paraxial_offset_mm": grid.offset.round(12).tolist(),
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
            "rings": int(rings),
            "na": na,
            "na_traced": na_traced,
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
        "paper": paper,
    }
    return RelaySimulation(grid, summary, spots)


def write_grid_csv(grid: GridDistortion, path, units: str = "mm", pixel_size_um: float = 4.8,
                   image_size=None, progress=None) -> None:  # fmt: skip
    """Write the grid CSV ``x_obj,y_obj,x_u,y_u,x_d,y_d,clear`` (``docs/cli.md``).

    Object points in mm; paraxial and real image points in image-plane mm, or with
    ``units="px"`` in px of ``pixel_size_um`` (axis at 0, 0; with ``image_size`` (w, h)
    camera px with the axis at the image centre).  Numbers are written with Python's
    shortest round-trip ``repr``; atomically, ``-`` writes to stdout.
    ``progress(done, total)`` is called per block of rows.
    """
    import sys

    from oapcal.io.atomic import atomic_write

    scale = 1.0 if units == "mm" else 1e3 / float(pixel_size_um)
    offset = np.zeros(2) if image_size is None else (np.asarray(image_size, float) - 1.0) / 2.0
    values = np.concatenate([grid.xy_obj, grid.xy_u * scale + offset, grid.xy_d * scale + offset], axis=1)
    clear = grid.clear

    def write(fh) -> None:
        fh.write("x_obj,y_obj,x_u,y_u,x_d,y_d,clear\n")
        n = len(values)
        block = 1 << 16
        for lo in range(0, n, block):
            hi = min(n, lo + block)
            rows = values[lo:hi].tolist()
            flags = clear[lo:hi].tolist()
            fh.write(
                "".join(",".join(map(repr, r)) + (",1\n" if ok else ",0\n") for r, ok in zip(rows, flags))
            )
            if progress is not None:
                progress(hi, n)

    if str(path) == "-":
        write(sys.stdout)
        return
    with atomic_write(path) as fh:
        write(fh)
