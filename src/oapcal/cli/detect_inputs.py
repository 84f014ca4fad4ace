"""The inputs that ``oapcal detect`` reads for every target (USAF, dots, chessboard): the image's
size checked against what detection handles, and the truth file of a simulated image."""

from __future__ import annotations


def check_image_size(path) -> None:
    """Refuse an image larger than detection handles, with a message for this command."""
    from oapcal.errors import InputFileError
    from oapcal.imaging.detect.core import MAX_IMAGE_PIXELS
    from oapcal.io.images import probe

    try:
        info = probe(path)
    except InputFileError as exc:
        if exc.param == "max_pixels":
            raise InputFileError(
                f"{path}: too large for detection (at most {MAX_IMAGE_PIXELS} px); "
                f"crop it to the target or bin it"
            ) from None
        raise
    rows, cols = info.frame_shape[:2]
    if rows * cols > MAX_IMAGE_PIXELS:
        raise InputFileError(
            f"{path}: {cols} x {rows} px is too large for detection (at most {MAX_IMAGE_PIXELS} px); "
            f"crop it to the target or bin it"
        )


def read_truth(path):
    """A simulated image's truth file ``id,x_d,y_d,visible``: ``(ids, xy_d, visible)``."""
    import numpy as np

    from oapcal.errors import InputFileError
    from oapcal.io.points import read_points

    pairs = read_points(path, require=("x_d", "y_d"), check_geometry=False)
    if pairs.ids is None or "visible" not in pairs.fieldnames:
        raise InputFileError(f"{path}: line 1: a truth file needs the columns id,x_d,y_d,visible")
    visible = []
    for row, line in zip(pairs.rows, pairs.lines):
        v = row["visible"].strip()
        if v not in ("0", "1"):
            raise InputFileError(f"{path}: line {line}, column 'visible': {v!r} is not 0 or 1")
        visible.append(v == "1")
    return pairs.ids, pairs.xy_d, np.array(visible)
