"""The grid CSV of ``oapcal simulate relay --out``: a traced relay's object points with
their paraxial and real image points (``docs/cli.md``, simulate relay).

Columns ``x_obj,y_obj,x_u,y_u,x_d,y_d,clear``; :func:`oapcal.io.points.read_points` reads
the file back as point pairs (``x_u,y_u`` the reference, ``x_d,y_d`` the distorted points).
"""

from __future__ import annotations

import sys

import numpy as np

from oapcal.io.atomic import atomic_write

#: The header of the grid CSV.
GRID_COLUMNS = ("x_obj", "y_obj", "x_u", "y_u", "x_d", "y_d", "clear")


def grid_values(grid, units: str = "mm", pixel_size_um: float = 4.8, image_size=None) -> np.ndarray:
    """The numeric columns ``x_obj .. y_d`` of the grid CSV, ``(N, 6)``.

    Object points in mm; paraxial and real image points in image-plane mm, or with
    ``units="px"`` in px of ``pixel_size_um`` (axis at 0, 0; with ``image_size`` (w, h)
    camera px with the axis at the image centre, ``((w - 1) / 2, (h - 1) / 2)``).
    """
    scale = 1.0 if units == "mm" else 1e3 / float(pixel_size_um)
    offset = np.zeros(2) if image_size is None else (np.asarray(image_size, float) - 1.0) / 2.0
    return np.concatenate([grid.xy_obj, grid.xy_u * scale + offset, grid.xy_d * scale + offset], axis=1)


def write_grid_csv(grid, path, units: str = "mm", pixel_size_um: float = 4.8,
                   image_size=None, progress=None) -> None:  # fmt: skip
    """Write the grid CSV of a :class:`~oapcal.optics.relay.GridDistortion` (columns and
    units as :func:`grid_values`, then ``clear`` 1 or 0).

    Numbers are written with Python's shortest round-trip ``repr``; atomically, ``-``
    writes to stdout.  ``progress(done, total)`` is called per block of rows.
    """
    values = grid_values(grid, units, pixel_size_um, image_size)
    clear = grid.clear

    def write(fh) -> None:
        fh.write(",".join(GRID_COLUMNS) + "\n")
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
