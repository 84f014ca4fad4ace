"""The fields of a relay's design, their units, defaults and ranges: the one table that
:class:`oapcal.optics.relay_model.RelayDesign` checks itself against, a stored design is
checked against (:func:`oapcal.optics.relay_model.design_from_record`), and the design
options of the commands are built from (:func:`oapcal.cli._relay.design_options`).

Imports nothing (the commands' ``--help`` reads it without loading NumPy).

>>> FIELDS["pixel_size_um"].describe_range()
'(0, 1000]'
>>> FIELDS["stop_distance_mm"].default
0.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class DesignField:
    """One field of a relay design: its ``name`` (the :class:`RelayDesign` attribute),
    ``unit``, ``default``, and for a number its range ``low .. high`` (``low_open``: the low
    end excluded; ``nullable``: None allowed, meaning the field is not given), or the range
    ``abs_range`` of its absolute value; ``choices`` for a field that takes one of a few
    values; ``help`` what it is, in a phrase."""

    name: str
    unit: str
    default: object
    help: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    nullable: bool = False
    choices: tuple = ()
    #: For the microscope's magnification: the range of its absolute value.
    abs_range: tuple | None = None

    @property
    def numeric(self) -> bool:
        """Whether the field is a number with a range (not a choice or a point)."""
        return self.low is not None

    def describe_range(self) -> str:
        """``(0, 1000]``: the range in words for messages."""
        return f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}]"

    def accepts(self, value) -> bool:
        """Whether ``value`` is a number (not a bool) in the range, or None when nullable."""
        if value is None:
            return self.nullable
        if isinstance(value, bool) or not _is_number(value):
            return False
        x = float(value)
        above = x > self.low if self.low_open else x >= self.low
        return math.isfinite(x) and above and x <= self.high


def _is_number(value) -> bool:
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return not isinstance(value, str | bytes)


#: The paper's OAPs (reflected focal length, mm) and camera (pixel pitch, um).
DEFAULT_FOCAL_LENGTH_MM = 50.8
DEFAULT_PIXEL_SIZE_UM = 4.8
#: The microscope's magnification, in absolute value (its sign says whether it inverts).
MICROSCOPE_MAGNIFICATION_RANGE = (0.01, 1000.0)

#: The design's fields, in :class:`RelayDesign`'s order (bounds written as the commands'
#: ``--help`` shows them; the numbers' ranges are those
#: ``oapcal fit --model relay`` accepts; the microscope's magnification is checked by its
#: absolute value, its sign saying whether it inverts).
DESIGN_FIELDS: tuple[DesignField, ...] = (
    DesignField("setup", "", 1, "the paper's setup 1 (d1 = 860 mm) or 2 (660 mm)", nullable=True,
                choices=(1, 2)),
    DesignField("d1_mm", "mm", None, "collimated path length (overrides the setup)", 0, 100_000,
                low_open=True, nullable=True),
    DesignField("focal_length_mm", "mm", DEFAULT_FOCAL_LENGTH_MM, "reflected focal length of the mirrors",
                0, 10_000, low_open=True),
    DesignField("focal_length_2_mm", "mm", None, "the second mirror's (default: the first's)", 0, 10_000,
                low_open=True, nullable=True),
    DesignField("orientation", "", "U", "U (parent axes coincide) or Z (second mirror turned 180 deg)",
                choices=("U", "Z")),
    DesignField("stop_distance_mm", "mm", 0.0, "aperture stop, after the first mirror (0: at it)", 0,
                100_000),
    DesignField("pixel_size_um", "um", DEFAULT_PIXEL_SIZE_UM, "camera pixel size", 0, 1000, low_open=True),
    DesignField("centre", "px", None, "the point of the reference frame on the relay's axis", nullable=True),
    DesignField("microscope_magnification", "", None, "a finite-conjugate microscope's magnification "
                "(negative: it inverts the image)", nullable=True, abs_range=MICROSCOPE_MAGNIFICATION_RANGE),
)  # fmt: skip
FIELDS: dict[str, DesignField] = {f.name: f for f in DESIGN_FIELDS}
