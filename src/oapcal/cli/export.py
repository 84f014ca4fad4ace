"""``oapcal export-opencv``: the calibration as OpenCV camera parameters."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    allow_unconverged_option,
    check_output,
    load_usable_calibration,
    out_option,
    parse_size,
)
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


def _say_trust(cal, geometry) -> None:
    """Say on stderr how far the exported correction reaches beyond the landmarks' hull and
    with what predicted error: OpenCV corrects the whole frame, trust region or not."""
    from oapcal.cli.correct import trust_message
    from oapcal.imaging.remap import DEFAULT_MAX_ERROR_PX, trust_summary

    summary = trust_summary(cal, geometry, DEFAULT_MAX_ERROR_PX)
    line = trust_message(
        summary, masked=False,
        hint="OpenCV corrects the whole frame; 'oapcal correct' writes only where the predicted error "
        f"is at most {DEFAULT_MAX_ERROR_PX:g} px ('oapcal correct --save-map' writes that map)",
    )  # fmt: skip
    if line:
        click.echo(line, err=True)


def _say_written(out, side, family, export) -> None:
    """Say what was written and, for a family without exact coefficients, how far the
    coefficients (the best Eq. (1) approximation) are from the exact maps."""
    from oapcal.imaging.opencv import EXACT_FAMILIES
    from oapcal.model import BROWN_CONRADY

    approx = export.get("approximation")
    w, h = export["new_image_size"]
    if family is BROWN_CONRADY:
        click.echo(f"wrote {out}: pass new_image_size {w}x{h} to cv2.initUndistortRectifyMap")
    elif family in EXACT_FAMILIES:
        click.echo(
            f"wrote {out} (exact for the {family.name} model): pass R and new_image_size {w}x{h} "
            "to cv2.initUndistortRectifyMap"
        )
    else:
        where = f"{out} and {side}" if side is not None else str(out)
        click.echo(f"wrote {where}: the exact correction is cv2.remap with map_x, map_y ({w}x{h})")
        cal_part = ""
        if approx["calibrated_mean_px"] is not None:
            cal_part = (
                f"; {approx['calibrated_mean_px']:.3g} px mean, {approx['calibrated_max_px']:.3g} px max "
                "over the calibrated region"
            )
        click.echo(
            f"no OpenCV coefficient set is exact for the {family.name} model: camera_matrix, dist_coeffs "
            f"and new_camera_matrix are the best Brown-Conrady approximation, off by {approx['mean_px']:.3g} "
            f"px mean, {approx['max_px']:.3g} px max over the image{cal_part}"
        )


#: The longest image side accepted (the pixel count is limited too).
MAX_SIDE = 2**20


@click.command("export-opencv")
@click.argument("calib", type=click.Path(dir_okay=False))
@out_option("FILE.json, or FILE.yml / FILE.yaml / FILE.xml (OpenCV FileStorage).", dash=False)
@click.option(
    "--image-size",
    default=None,
    help="Input image size WxH in px (default: the calibration's image_size).",
)
@geometry_options
@allow_unconverged_option
def export_opencv_command(calib, out, image_size, extent, um_per_px, out_size, allow_unconverged):
    """Write camera_matrix, dist_coeffs and new_camera_matrix for cv2.initUndistortRectifyMap.

    A relay calibration has no exact OpenCV coefficients: the export then also holds the
    exact maps for cv2.remap (map_x, map_y; beside a .json file in FILE.maps.npz) and says
    how far the coefficients (the best Eq. (1) approximation) are from them.
    """
    import math
    from pathlib import Path

    from oapcal.errors import DataError
    from oapcal.imaging.opencv import EXACT_FAMILIES, opencv_export
    from oapcal.imaging.remap import output_geometry
    from oapcal.io.opencv_export import maps_path, save_opencv
    from oapcal.records import ImageSize

    check_output(out, calib)
    size = parse_size(image_size) or None
    fit_size = parse_size(out_size, "--out-size")
    cal = load_usable_calibration(calib, allow_unconverged)
    family = cal.family
    side = None
    if family not in EXACT_FAMILIES and Path(out).suffix.lower() == ".json":
        side = maps_path(out)
        check_output(str(side), calib)
    size = size or cal.image_size
    if not size:
        raise DataError(f"{calib}: the calibration has no image_size; give --image-size WxH")
    _check_size(size, "--image-size" if image_size else f"{calib}: image_size")
    geometry = output_geometry(
        cal, ImageSize(*size).shape, extent=extent, um_per_px=um_per_px, out_size=fit_size
    )
    export = opencv_export(cal, size, geometry)
    approx = export.get("approximation")
    if approx is not None and not all(math.isfinite(v) for v in (approx["mean_px"], approx["max_px"])):
        click.echo(
            f"oapcal: {calib}: the Eq. (1) approximation of the {family.name} model failed "
            "(no finite coefficients); nothing written",
            err=True,
        )
        return 3
    save_opencv(export, out, cal.name or Path(calib).name)
    _say_trust(cal, geometry)
    _say_written(out, side, family, export)
    return 0
