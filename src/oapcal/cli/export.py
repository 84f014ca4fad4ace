"""``oapcal export-opencv``: the calibration as OpenCV camera parameters."""

from __future__ import annotations

import click

from oapcal.cli._common import check_output, parse_size
from oapcal.cli.correct import geometry_options


def _check_size(size, what) -> None:
    """Refuse an image size no camera has (the map OpenCV would build could not be stored)."""
    from oapcal.errors import DataError
    from oapcal.io.images import MAX_PIXELS

    w, h = size
    if w * h > MAX_PIXELS or max(w, h) > MAX_SIDE:
        raise DataError(
            f"{what} {w}x{h} is larger than any image oapcal corrects ({MAX_PIXELS} px, sides up to "
            f"{MAX_SIDE} px); give the camera's size in px"
        )


#: The longest image side accepted (the pixel count is limited too).
MAX_SIDE = 2**20


@click.command("export-opencv")
@click.argument("calib", type=click.Path(dir_okay=False))
@click.option(
    "--out",
    "out",
    type=click.Path(dir_okay=False),
    required=True,
    help="FILE.json, or FILE.yml / FILE.yaml / FILE.xml (OpenCV FileStorage).",
)
@click.option(
    "--image-size",
    default=None,
    help="Input image size WxH in px (default: the calibration's image_size).",
)
@geometry_options
def export_opencv_command(calib, out, image_size, extent, um_per_px, out_size):
    """Write camera_matrix, dist_coeffs and new_camera_matrix for cv2.initUndistortRectifyMap."""
    from pathlib import Path

    from oapcal.errors import DataError
    from oapcal.imaging.remap import output_geometry
    from oapcal.io.calibration import load_calibration
    from oapcal.io.opencv_export import opencv_parameters, save_opencv

    check_output(out, calib)
    size = parse_size(image_size) or None
    fit_size = parse_size(out_size, "--out-size")
    cal = load_calibration(calib)
    size = size or cal.image_size
    if not size:
        raise DataError(f"{calib}: the calibration has no image_size; give --image-size WxH")
    _check_size(size, "--image-size" if image_size else f"{calib}: image_size")
    geometry = output_geometry(cal, (size[1], size[0]), extent=extent, um_per_px=um_per_px, out_size=fit_size)
    export = opencv_parameters(cal.params, size, geometry)
    save_opencv(export, out, cal.name or Path(calib).name)
    w, h = export["new_image_size"]
    click.echo(f"wrote {out}: pass new_image_size {w}x{h} to cv2.initUndistortRectifyMap")
    return 0
