"""``oapcal simulate relay``: ray-traced grid distortion of the OAP relay."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    Finite,
    OutputSet,
    check_output,
    check_plot_suffix,
    choice_option,
    console,
    file_option,
    json_option,
    parse_size,
    print_json,
    progress_bar,
    range_option,
)
from oapcal.cli._relay import check_microscope, design_option, design_options, field_option

#: Largest grid (points per side) and number of hexapolar rings: beyond them tracing takes
#: minutes and gigabytes and shows nothing new.
MAX_GRID = 1001
MAX_RINGS = 200

#: Misalignment options: name -> unit (mirrors ``oapcal.optics.misalign.PARAMETERS``, without
#: ``d1``, which ``--d1`` sets; kept here so that ``--help`` imports nothing heavy).
MISALIGNMENT_UNITS = {
    **{f"m{i}_{k}": u for i in (1, 2) for k, u in (("tilt_x", "deg"), ("tilt_y", "deg"), ("decentre_x", "mm"),
                                                    ("decentre_y", "mm"), ("clock", "deg"),
                                                    ("focal_length", "mm"))},
    "stop_decentre_x": "mm", "stop_decentre_y": "mm", "camera_tilt_x": "deg", "camera_tilt_y": "deg",
    "camera_defocus": "mm", "object_tilt_x": "deg", "object_tilt_y": "deg",
}  # fmt: skip
#: Misalignment angles beyond this (deg) are refused: not a misalignment any more.
MAX_ANGLE_DEG = 45.0
_MISALIGNMENT_HELP = {
    "tilt_x": "tip about its tangent-plane x axis (perpendicular to the fold plane)",
    "tilt_y": "tilt about its tangent-plane y axis (in the fold plane)",
    "decentre_x": "decentre along its tangent-plane x axis",
    "decentre_y": "decentre along its tangent-plane y axis",
    "clock": "clocking about its normal",
    "focal_length": "focal-length change (centre fixed)",
    "stop_decentre_x": "aperture stop moved along its x axis",
    "stop_decentre_y": "aperture stop moved along its y axis",
    "camera_tilt_x": "camera (image plane) tilted about its x axis",
    "camera_tilt_y": "camera (image plane) tilted about its y axis",
    "camera_defocus": "camera moved along its normal, + away from the mirror",
    "object_tilt_x": "object (target) plane tilted about its x axis",
    "object_tilt_y": "object (target) plane tilted about its y axis",
}


def misalignment_options(func):
    """``--m1-tilt-x DEG`` ... ``--object-tilt-y DEG`` (``docs/optics.md``, Misalignment),
    given to the command as one dict ``misalignment`` of the non-zero values."""
    import functools

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        values = {name: kwargs.pop(name) for name in MISALIGNMENT_UNITS}
        return func(*args, misalignment={k: v for k, v in values.items() if v}, **kwargs)

    for name, unit in reversed(MISALIGNMENT_UNITS.items()):
        mirror = name[:2] in ("m1", "m2")
        what = _MISALIGNMENT_HELP[name[3:] if mirror else name]
        which = "First" if name[1] == "1" else "Second"
        text = f"{which} mirror {what}, {unit}." if mirror else f"{what.capitalize()}, {unit}."
        flag = "--" + name.replace("_", "-")
        kind = click.FloatRange(-MAX_ANGLE_DEG, MAX_ANGLE_DEG) if unit == "deg" else float
        wrapper = click.option(flag, name, type=kind, default=0.0, metavar=unit.upper(), help=text)(wrapper)
    return wrapper


@click.command("relay")
@design_options("simulate", "setup", "d1_mm", "orientation", "stop_distance_mm", "focal_length_mm")
@range_option("--grid", "n", type=click.IntRange(max=MAX_GRID), default=17, help="Grid points per side.")
@field_option("Full width of the square object field, mm.")
@choice_option(
    "--units", choices=["mm", "px"], default="mm", help="Units of x_u,y_u,x_d,y_d in the CSV (image plane)."
)
@design_option("simulate", "pixel_size_um")
@click.option(
    "--image-size",
    default=None,
    help="With --units px: write camera px (axis at the image centre) for a WxH image.",
)
@click.option("--beam-diameter", type=Finite(min=0, max=1000, min_open=True), default=20.0, show_default=True,
              help="Collimated beam (stop) diameter for spots and NA, mm.")  # fmt: skip
@click.option(
    "--wavelength", type=Finite(max=100_000), default=850.0, show_default=True, help="Wavelength, nm."
)
@click.option(
    "--spot-field",
    "spot_fields",
    multiple=True,
    metavar="X,Y",
    help="Object point (mm) of a spot diagram; repeat for more (default: centre, edges, corner).",
)
@range_option(
    "--rings", type=click.IntRange(max=MAX_RINGS), default=8, help="Hexapolar rings of rays per spot diagram."
)
@file_option("--out", help="Write the grid CSV (x_obj,y_obj,x_u,y_u,x_d,y_d,clear).", dash=True)
@file_option("--plot", help="Grid distortion figure (PNG).")
@file_option("--spots", help="Spot diagrams of both orientations (PNG).")
@json_option()
@design_option("simulate", "focal_length_2_mm")
@misalignment_options
@choice_option(
    "--reference",
    choices=["paraxial", "design"],
    default="paraxial",
    help="x_u,y_u of the CSV: the paraxial image through this (misaligned) relay, or through the aligned "
    "design (the ideal image of the target, as an experiment's reference points are; what 'oapcal "
    "fit --model relay' takes).",
)
@file_option(
    "--layout", help="Figure of the relay in its fold plane with the frames of the misalignment conventions."
)
@design_option("simulate", "microscope_magnification")
# The command's options, one parameter each (click); the body calls helpers.
def relay_command(setup, d1, orientation, stop_distance, focal_length, n, field_mm, units, pixel_size,
                  image_size, beam_diameter, wavelength, spot_fields, rings, out, plot, spots,
                  as_json, focal_length_2=None, misalignment=None, layout=None,
                  reference="paraxial", microscope_magnification=None):  # fmt: skip
    """Trace the OAP relay: grid distortion (paraxial vs real chief rays), spots, limits."""
    from oapcal.cli._relay import traced_relay
    from oapcal.optics.summary import SimulationOptions, simulate_relay

    size = _check_options(n, rings, units, image_size, pixel_size, beam_diameter, wavelength,
                          microscope_magnification, (out, plot, spots, layout))  # fmt: skip
    points = [_parse_point(text) for text in spot_fields] or None
    bar, update = progress_bar("tracing")
    with bar:
        update(0, 1, f"tracing {n}x{n} grid and spots")
        relay = traced_relay({"setup": setup, "d1_mm": d1, "orientation": orientation,
                              "stop_distance_mm": stop_distance, "focal_length_mm": focal_length,
                              "focal_length_2_mm": focal_length_2}, misalignment)  # fmt: skip
        options = SimulationOptions(n=n, field_mm=field_mm, pixel_size_um=pixel_size,
                                    beam_diameter_mm=beam_diameter, wavelength_nm=wavelength,
                                    spot_fields=points, rings=rings)  # fmt: skip
        sim = simulate_relay(relay, options, progress=update)
        files = {"out": out, "plot": plot, "spots": spots, "layout": layout}
        _write_outputs(sim, files, update, units, pixel_size, size, reference, microscope_magnification)
    if as_json:
        print_json(sim.summary)
    elif out != "-":
        print_summary(sim.summary)
    return 0


def _check_options(n, rings, units, image_size, pixel_size, beam_diameter, wavelength, microscope, files):
    """Refuse bad option values before any tracing (usage errors naming the option);
    returns the parsed --image-size.  (Nine arguments: the options it checks.)"""
    from oapcal.errors import GeometrySpecError

    size = parse_size(image_size)
    if n < 3:
        raise GeometrySpecError(
            f"--grid {n}: a grid needs at least 2 points per side and the radial fit at least 3; "
            "give --grid 3 or more"
        )
    if rings < 1:
        raise GeometrySpecError(f"--rings must be at least 1, got {rings}")
    check_microscope(microscope)
    if size is not None and units != "px":
        raise GeometrySpecError("--image-size needs --units px (camera px); drop it or add --units px")
    for value, name in ((pixel_size, "--pixel-size"), (beam_diameter, "--beam-diameter"),
                        (wavelength, "--wavelength")):  # fmt: skip
        if not value > 0:
            raise GeometrySpecError(f"{name} must be positive, got {value:g}")
    outputs = [p for p in files if p not in (None, "-")]
    if len(set(outputs)) < len(outputs):
        raise GeometrySpecError("--out, --plot, --spots and --layout must be different files")
    for path in outputs:
        check_output(path)
    out, plot, spots, layout = files
    check_plot_suffix(plot, "--plot")
    check_plot_suffix(spots, "--spots")
    check_plot_suffix(layout, "--layout")
    return size


def _write_outputs(sim, files: dict, update, units, pixel_size, size, reference, microscope):
    """The grid CSV and the figures asked for (all of them or none: :class:`OutputSet`)."""
    from oapcal.io.grid import write_grid_csv

    with OutputSet() as outputs:
        if files["out"] is not None:
            update(0, 1, "writing the grid CSV")
            grid = sim.grid if reference == "paraxial" else _design_reference(sim.grid)
            if microscope is not None:
                grid = _behind_microscope(grid, microscope)
            write_grid_csv(grid, outputs.stage(files["out"]), units, pixel_size, size, progress=update)
        if files["plot"] is not None:
            from oapcal.report.optics_plots import plot_grid

            update(0, 1, "plotting")
            plot_grid(sim.grid, outputs.stage(files["plot"]), units=units, pixel_size_um=pixel_size)
        if files["spots"] is not None:
            from oapcal.report.optics_plots import plot_spots

            airy = sim.summary["quality"]["rayleigh_um"]
            plot_spots(sim.spots, outputs.stage(files["spots"]), airy_radius_um=airy)
        if files["layout"] is not None:
            from oapcal.report.optics_plots import plot_layout

            plot_layout(sim.grid.relay, outputs.stage(files["layout"]))


def _design_reference(grid):
    """``grid`` with its paraxial points ``xy_u`` those of the aligned design (no offset)."""
    import dataclasses

    from oapcal.optics.relay import apply_matrix, paraxial_matrix

    design = grid.relay.with_misalignment(None)
    return dataclasses.replace(grid, xy_u=apply_matrix(paraxial_matrix(design), grid.xy_obj))


def _behind_microscope(grid, magnification: float):
    """``grid`` with its image points (paraxial and real, mm) magnified by an ideal
    microscope: the relay's image plane imaged onto the camera, ``M`` times."""
    import dataclasses

    return dataclasses.replace(grid, xy_u=grid.xy_u * magnification, xy_d=grid.xy_d * magnification)


def _parse_point(text: str) -> tuple[float, float]:
    """``"0.5,-0.25"`` -> ``(0.5, -0.25)`` (a --spot-field value)."""
    from oapcal.cli._relay import parse_xy

    return parse_xy(text, "--spot-field", "0.5,0.5 (mm)")


def print_summary(s: dict) -> None:
    from rich.table import Table

    out = console()
    r, g = s["relay"], s["grid"]
    out.print(
        f"OAP relay: d1 = {r['d1_mm']:g} mm, orientation {r['orientation']}, stop "
        f"{r['stop_distance_mm']:g} mm after the first mirror, f = {r['focal_length_mm']:g} mm; "
        f"{g['n']}x{g['n']} grid over {g['field_mm']:g} mm, {g['pixel_size_um']:g} um pixels; "
        f"paraxial magnification {s['magnification']:.6f}"
    )
    if r.get("focal_length_2_mm", r["focal_length_mm"]) != r["focal_length_mm"]:
        out.print(f"second mirror f = {r['focal_length_2_mm']:g} mm")
    moved = {k: v for k, v in (r.get("misalignment") or {}).items() if v}
    if moved:
        from oapcal.optics.misalign import PARAMETERS

        out.print("Misaligned: " + ", ".join(f"{k} {v:+g} {PARAMETERS[k][0]}" for k, v in moved.items()))
        off = s["paraxial_offset_mm"]
        out.print(f"field centre imaged at ({off[0] * 1e3:+.2f}, {off[1] * 1e3:+.2f}) um on the sensor")
    if g["n_vignetted"]:
        out.print(f"[yellow]{g['n_vignetted']} chief rays fall outside a mirror's diameter[/yellow]")
    paper = s["paper"] or {}
    d, f = s["distortion"], s["radial_fit"]
    table = Table(title="Grid distortion |real - paraxial|", title_justify="left")
    for col in ("", "oapcal um", "oapcal px", "paper um", "paper px"):
        table.add_column(col, justify="right")

    def cell(key):
        return f"{paper[key]:g}" if key in paper else "-"

    table.add_row("max", f"{d['max_um']:.1f}", f"{d['max_px']:.2f}", cell("max_um"), cell("max_px"))
    table.add_row("mean", f"{d['mean_um']:.1f}", f"{d['mean_px']:.2f}", cell("mean_um"), cell("mean_px"))
    table.add_row("max |dx|", f"{d['max_abs_dx_um']:.1f}", f"{d['max_abs_dx_px']:.2f}", "-", "-")
    table.add_row("max |dy|", f"{d['max_abs_dy_um']:.1f}", f"{d['max_abs_dy_px']:.2f}", "-", "-")
    table.add_row(
        "radial fit, mean residual", f"{f['mean_residual_um']:.1f}", f"{f['mean_residual_px']:.2f}",
        cell("radial_fit_mean_um"), cell("radial_fit_mean_px"),
    )  # fmt: skip
    out.print(table)
    q = s["quality"]
    out.print(
        f"Beam {q['beam_diameter_mm']:g} mm at {q['wavelength_nm']:g} nm: NA {q['na']:.4f} "
        f"(traced {q['na_traced']:.4f}; paper 0.193), Sparrow {q['sparrow_um']:.2f} um (paper 2.07), "
        f"Rayleigh {q['rayleigh_um']:.2f} um, pixel limit {q['pixel_limit_um']:.2f} um"
    )
    spots = Table(title="RMS spot radius (um)", title_justify="left")
    spots.add_column("field (mm)")
    spots.add_column("U", justify="right")
    spots.add_column("Z", justify="right")
    by_field: dict = {}
    for spot in q["spots"]:
        by_field.setdefault(tuple(spot["field_mm"]), {})[spot["orientation"]] = spot["rms_um"]
    for field, values in by_field.items():
        spots.add_row(f"({field[0]:g}, {field[1]:g})", f"{values['U']:.2f}", f"{values['Z']:.2f}")
    out.print(spots)
