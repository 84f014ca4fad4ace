"""``oapcal simulate image``: a camera image of the USAF-1951 target and its ground truth."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    Finite,
    OutputSet,
    check_output,
    check_work,
    choice_option,
    file_option,
    flag_option,
    out_option,
    parse_size,
    progress_bar,
    range_option,
    sanitize,
)
from oapcal.cli._relay import design_option, design_options

#: Largest Gaussian PSF sigma (camera px): wider blurs every bar of the target into grey.
MAX_SIGMA_PX = 50.0
#: Largest radius of the Airy PSF's first dark ring (camera px), for the same reason.
MAX_AIRY_RADIUS_PX = 50.0
#: Largest side of a simulated image (px).
MAX_SIDE = 16384
#: Bytes of working memory per sub-pixel (coordinates, raster samples, blur; measured peak ~ 90).
BYTES_PER_SUBPIXEL = 100


@click.command("image")
@click.option("--groups", default="4-5", show_default=True, help="USAF groups to draw, e.g. 4-5 or 2,4-5.")
@design_options("image", "setup", "d1_mm")
@choice_option(
    "--field",
    "field_name",
    choices=["setup1-model", "none"],
    default="setup1-model",
    help="Built-in distortion when no relay or calibration is given: an Eq. 1 field like setup 1 (~40 "
    "px), or none.",
)
@file_option("--calibration", help="Distort with a fitted calibration (JSON) instead.")
@click.option(
    "--sigma-px",
    type=Finite(min=0, max=MAX_SIGMA_PX),
    default=0.8,
    show_default=True,
    help="Gaussian PSF sigma (camera px); 0: no blur.",
)
@click.option(
    "--na",
    type=Finite(min=0, max=1, min_open=True, max_open=True),
    default=None,
    help="Airy PSF of this image-space NA (with --wavelength-um) instead of the Gaussian.",
)
@click.option(
    "--wavelength-um",
    type=Finite(min=0.01, max=100),
    default=None,
    help="Wavelength of the Airy PSF (um).",
)
@click.option(
    "--snr",
    type=Finite(min=0, max=1e6, min_open=True),
    default=50.0,
    show_default=True,
    help="Signal-to-noise ratio of the brightest level (shot + read noise).",
)
@flag_option("--no-noise", help="No noise (the image is only quantized).")
@click.option(
    "--read-noise-e",
    type=Finite(min=0, max=1e6),
    default=5.0,
    show_default=True,
    help="Read noise (electrons).",
)
@choice_option("--bits", choices=["8", "16"], default="8", help="Bits per pixel of the output.")
@choice_option(
    "--polarity",
    choices=["bright", "dark"],
    default="bright",
    help="Bright bars on a dark field, or dark bars on a bright field.",
)
@design_option("image", "pixel_size_um")
@click.option("--image-size", default="640x480", show_default=True, help="Camera size WxH (px).")
@click.option(
    "--um-per-px",
    type=Finite(min=1e-6, max=1e6),
    default=None,
    help="Scale of x_u,y_u in the truth file (default: the paraxial scale).",
)
@range_option(
    "--oversample", type=click.IntRange(min=1, max=16), default=4, help="Sub-pixels per pixel side."
)
@range_option("--seed", type=click.IntRange(0, 2**63 - 1), default=0, help="Seed of the noise.")
@choice_option(
    "--layout",
    choices=["compact", "spaced", "whole-target"],
    default="compact",
    help="Layout of the target: makers differ in gaps, square and nesting (docs/usaf.md).",
)
@flag_option("--bars-only", help="Draw only the bars (no reference squares, no printed numbers).")
@out_option("Output image (.png, .tif).", dash=False)
@file_option("--truth", help="Ground-truth CSV: id,x_u,y_u,x_d,y_d,visible.")
# one parameter per command-line option (click)
def simulate_image_command(
    groups, relay_setup, d1_mm, field_name, calibration, sigma_px, na, wavelength_um, snr, no_noise,
    read_noise_e, bits, polarity, pixel_size_um, image_size, um_per_px, oversample, seed, layout, bars_only,
    out, truth,
):  # fmt: skip
    """Simulate a camera image of the USAF-1951 target through a distortion field."""
    from oapcal.imaging.simulate import simulate_image
    from oapcal.imaging.usaf import parse_groups

    _check_options(out, truth, calibration, na, wavelength_um, relay_setup, d1_mm)
    size = parse_size(image_size, max_side=MAX_SIDE)
    _check_cost(size, oversample, sigma_px, na, wavelength_um, pixel_size_um)
    group_list = parse_groups(groups)
    field = _field(relay_setup, d1_mm, calibration, field_name, pixel_size_um, size)
    bar, update = progress_bar("simulating")
    with bar:
        sim = simulate_image(
            group_list, field, sigma_px=sigma_px, na=na, wavelength_um=wavelength_um,
            snr=None if no_noise else snr, read_noise_e=read_noise_e, bits=int(bits), polarity=polarity,
            oversample=oversample, um_per_px=um_per_px, seed=seed,
            squares=not bars_only, digits=not bars_only, layout_name=layout, progress=update,
        )  # fmt: skip
    _write(out, truth, sim, size, bits, groups)
    return 0


def _check_options(out, truth, calibration, na, wavelength_um, relay_setup, d1_mm) -> None:
    """Refuse, before any work, outputs that clash or overwrite an input, an incomplete
    Airy PSF, more than one source of distortion and an image type that is not lossless."""
    from oapcal.errors import DataError

    check_output(out, calibration)
    check_output(truth, calibration, out)
    if truth is not None and truth == out:
        raise DataError(f"{out}: --out and --truth must be different files")
    if (na is None) != (wavelength_um is None):
        raise DataError("an Airy PSF needs both --na and --wavelength-um")
    chosen = [
        o for o, v in (("--relay-setup", relay_setup), ("--d1", d1_mm), ("--calibration", calibration)) if v
    ]
    if len(chosen) > 1:
        raise DataError(f"give only one of {', '.join(chosen)}")
    from pathlib import Path

    from oapcal.errors import OutputError
    from oapcal.io.images import LOSSLESS_SUFFIXES

    if Path(out).suffix.lower() not in LOSSLESS_SUFFIXES:
        raise OutputError(
            f"{out}: unknown image type {Path(out).suffix or '(none)'}; use .png, .tif or .tiff"
        )


def _field(relay_setup, d1_mm, calibration, field_name, pixel_size_um, size):
    """The distortion field the image is simulated through: the traced relay, a
    calibration's model, none, or the setup-1-like model."""
    from oapcal.imaging.field import identity_field, setup1_like_field

    if relay_setup or d1_mm:
        return _relay_field(relay_setup, d1_mm, pixel_size_um, size)
    if calibration:
        from oapcal.imaging.field import ModelDistortionField
        from oapcal.io.calibration import load_calibration

        return ModelDistortionField.from_calibration(load_calibration(calibration, size), size)
    if field_name == "none":
        return identity_field(pixel_size_um, size)
    return setup1_like_field(pixel_size_um, size)


def _write(out, truth, sim, size, bits, groups) -> None:
    """Write the image (and the truth file: both or neither) and say what was written."""
    from oapcal.io.images import write_image
    from oapcal.io.points import write_truth

    with OutputSet() as outputs:  # both or neither
        write_image(outputs.stage(out), sim.image)
        if truth is not None:
            write_truth(outputs.stage(truth), sim)
    click.echo(
        sanitize(
            f"wrote {out}: {size[0]}x{size[1]} px, {bits}-bit, groups {groups}, "
            f"{int(sim.visible.sum())} of {len(sim.ids)} corners fully visible"
        )
    )
    if truth is not None:
        click.echo(
            sanitize(
                f"wrote {truth}: reference x_u,y_u at {sim.um_per_px:.6g} um/px, "
                f"target orientation {sim.orientation}"
            )
        )


def _check_cost(size, oversample, sigma_px, na, wavelength_um, pixel_size_um) -> None:
    """Refuse, before any work, a PSF too wide to mean anything or a job too big for memory."""
    from oapcal.errors import DataError

    w, h = size
    if na is not None:
        radius_px = 0.61 * wavelength_um / na / pixel_size_um
        if radius_px > MAX_AIRY_RADIUS_PX:
            raise DataError(
                f"--na {na:g} at --wavelength-um {wavelength_um:g} gives an Airy disc of radius "
                f"{radius_px:.3g} px, over {MAX_AIRY_RADIUS_PX:g} px (it would blur the whole target); "
                f"give --na {0.61 * wavelength_um / (MAX_AIRY_RADIUS_PX * pixel_size_um):.2g} or more"
            )
        sigma_px = 0.42 * radius_px  # the Airy core's width, for the blur cost below
    if sigma_px > min(w, h) / 4:
        raise DataError(
            f"--sigma-px {sigma_px:g} is over a quarter of the {w}x{h} image; it would blur it to "
            "uniform grey. Give a smaller --sigma-px or a larger --image-size"
        )
    sub = float(w) * h * oversample**2
    # the Airy kernel (sampled 4 x 4 per sub-pixel, out to 4 dark rings) and the image
    kernel = (4 * (2 * 4 * sigma_px / 0.42 * oversample + 1)) ** 2 * 8 * 4 if na is not None else 0.0
    check_work(
        sub * BYTES_PER_SUBPIXEL + kernel, f"a {w}x{h} image at --oversample {oversample}",
        "give a smaller --image-size or --oversample",
    )  # fmt: skip


def _relay_field(setup, d1_mm, pixel_size_um, size):
    from oapcal.errors import DataError

    try:
        from oapcal.optics import relay_distortion
    except ImportError:
        raise DataError(
            "the ray-traced relay (oapcal.optics) is not part of this installation; "
            "use --field setup1-model or --calibration"
        ) from None
    return relay_distortion(
        int(setup) if setup else None, d1_mm=d1_mm, pixel_size_um=pixel_size_um, image_size=size
    )
