"""``oapcal simulate image``: a camera image of the USAF-1951 target and its ground truth."""

from __future__ import annotations

import click

from oapcal.cli._common import check_output, parse_size


@click.command("image")
@click.option("--groups", default="4-5", show_default=True, help="USAF groups to draw, e.g. 4-5 or 2,4-5.")
@click.option(
    "--relay-setup",
    type=click.Choice(["1", "2"]),
    default=None,
    help="Ray-traced relay of the paper's setup 1 or 2.",
)
@click.option(
    "--d1",
    "d1_mm",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Ray-traced relay with this OAP 2 - OAP 3 distance (mm).",
)
@click.option(
    "--field",
    "field_name",
    type=click.Choice(["setup1-model", "none"]),
    default="setup1-model",
    show_default=True,
    help="Built-in distortion when no relay or calibration is given: an Eq. 1 field like "
    "setup 1 (~40 px), or none.",
)
@click.option(
    "--calibration",
    type=click.Path(dir_okay=False),
    default=None,
    help="Distort with a fitted calibration (JSON) instead.",
)
@click.option(
    "--sigma-px",
    type=click.FloatRange(min=0),
    default=0.8,
    show_default=True,
    help="Gaussian PSF sigma (camera px); 0: no blur.",
)
@click.option(
    "--na",
    type=click.FloatRange(min=0, max=1, min_open=True, max_open=True),
    default=None,
    help="Airy PSF of this image-space NA (with --wavelength-um) instead of the Gaussian.",
)
@click.option(
    "--wavelength-um",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Wavelength of the Airy PSF (um).",
)
@click.option(
    "--snr",
    type=click.FloatRange(min=0, min_open=True),
    default=50.0,
    show_default=True,
    help="Signal-to-noise ratio of the brightest level (shot + read noise).",
)
@click.option("--no-noise", is_flag=True, help="No noise (the image is only quantized).")
@click.option(
    "--read-noise-e",
    type=click.FloatRange(min=0),
    default=5.0,
    show_default=True,
    help="Read noise (electrons).",
)
@click.option(
    "--bits",
    type=click.Choice(["8", "16"]),
    default="8",
    show_default=True,
    help="Bits per pixel of the output.",
)
@click.option(
    "--polarity",
    type=click.Choice(["bright", "dark"]),
    default="bright",
    show_default=True,
    help="Bright bars on a dark field, or dark bars on a bright field.",
)
@click.option(
    "--pixel-size-um",
    type=click.FloatRange(min=0, min_open=True),
    default=4.8,
    show_default=True,
    help="Camera pixel size (um).",
)
@click.option("--image-size", default="640x480", show_default=True, help="Camera size WxH (px).")
@click.option(
    "--um-per-px",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Scale of x_u,y_u in the truth file (default: the paraxial scale).",
)
@click.option(
    "--oversample",
    type=click.IntRange(min=1, max=16),
    default=4,
    show_default=True,
    help="Sub-pixels per pixel side.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the noise.")
@click.option(
    "--out", "out", type=click.Path(dir_okay=False), required=True, help="Output image (.png, .tif)."
)
@click.option(
    "--truth",
    type=click.Path(dir_okay=False),
    default=None,
    help="Ground-truth CSV: id,x_u,y_u,x_d,y_d,visible.",
)
def simulate_image_command(
    groups, relay_setup, d1_mm, field_name, calibration, sigma_px, na, wavelength_um, snr, no_noise,
    read_noise_e, bits, polarity, pixel_size_um, image_size, um_per_px, oversample, seed, out, truth,
):  # fmt: skip
    """Simulate a camera image of the USAF-1951 target through a distortion field."""
    from oapcal.errors import DataError
    from oapcal.imaging.field import identity_field, setup1_like_field
    from oapcal.imaging.simulate import simulate_image, write_truth
    from oapcal.imaging.usaf import parse_groups
    from oapcal.io.images import write_image

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
    size = parse_size(image_size)
    group_list = parse_groups(groups)
    if relay_setup or d1_mm:
        field = _relay_field(relay_setup, d1_mm, pixel_size_um, size)
    elif calibration:
        from oapcal.imaging.field import ModelDistortionField
        from oapcal.io.calibration import load_calibration

        field = ModelDistortionField.from_calibration(load_calibration(calibration, size), size)
    elif field_name == "none":
        field = identity_field(pixel_size_um, size)
    else:
        field = setup1_like_field(pixel_size_um, size)
    sim = simulate_image(
        group_list, field, sigma_px=sigma_px, na=na, wavelength_um=wavelength_um,
        snr=None if no_noise else snr, read_noise_e=read_noise_e, bits=int(bits), polarity=polarity,
        oversample=oversample, um_per_px=um_per_px, seed=seed, progress=True,
    )  # fmt: skip
    write_image(out, sim.image)
    if truth is not None:
        write_truth(truth, sim)
    click.echo(
        f"wrote {out}: {size[0]}x{size[1]} px, {bits}-bit, groups {groups}, "
        f"{int(sim.visible.sum())} of {len(sim.ids)} corners fully visible"
    )
    if truth is not None:
        click.echo(
            f"wrote {truth}: reference x_u,y_u at {sim.um_per_px:.6g} um/px, "
            f"target orientation {sim.orientation}"
        )
    return 0


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
