"""How the commands spell the relay design's fields (:data:`OPTION_STYLES`), and the
Python names of those options (:data:`DESIGN_OPTIONS`), which an error about the design
names (``param="design"``, :func:`oapcal.cli._common.flag_hint`).

Plain data, importing nothing of the CLI: :mod:`oapcal.cli._common` reads the names and
:mod:`oapcal.cli._relay` builds the options (:func:`oapcal.cli._relay.design_options`)
from the same table, without importing each other in a circle.
"""

from __future__ import annotations

from oapcal.optics.design import DESIGN_FIELDS

#: An option that no design error comes from (``design_hint`` False): the orientation is a
#: choice the command line checks itself.
_NO_HINT = {"design_hint": False}

_W = "With --model relay: "
#: How each command spells the design's fields (:data:`oapcal.optics.design.DESIGN_FIELDS`):
#: style -> field -> (flag, Python name, help[, changes]).  Types, ranges and defaults come
#: from the table; ``changes`` replace some for that style: ``simulate relay`` and
#: ``tolerance`` leave the low end of d1, the second focal length and the pixel size to the
#: tracer and the command, whose messages name the geometry ("d1 (the collimated path
#: length) must be a positive number of mm"), and put the stop at the first mirror by
#: None; ``simulate image`` traces a relay only when a setup or d1 is given.
OPTION_STYLES: dict[str, dict[str, tuple]] = {
    # fit, select, selfcal, robustness: with --model relay
    "relay": {
        "setup": ("--relay-setup", "relay_setup", _W + "the paper's setup 1 (d1 = 860 mm) or 2 (660 mm)."),
        "d1_mm": ("--d1", "relay_d1", _W + "collimated path length, mm (overrides --relay-setup)."),
        "focal_length_mm": ("--focal-length", "relay_focal_length",
                            _W + "reflected focal length of the mirrors, mm."),
        "focal_length_2_mm": ("--focal-length-2", "relay_focal_length_2",
                              _W + "the second mirror's, mm (default: --focal-length)."),
        "orientation": ("--orientation", "relay_orientation", _W + "U or Z.", _NO_HINT),
        "stop_distance_mm": ("--stop-distance", "relay_stop",
                             _W + "aperture stop, mm after the first mirror."),
        "pixel_size_um": ("--pixel-size", "relay_pixel_size", _W + "camera pixel size, um."),
        "centre": ("--relay-centre", "relay_centre", _W + "the point (px) on the relay's axis (default: the "
                   "image centre with --image-size, else the middle of the reference points)."),
        "microscope_magnification": ("--microscope-magnification", "microscope_magnification", _W + "a "
                                     "finite-conjugate microscope between the relay and the camera, its "
                                     "magnification; negative when it inverts the image (-5: a 5x objective "
                                     "forming a real image). The model is then relay+microscope "
                                     "(docs/models.md)."),
    },
    # simulate relay, tolerance: the relay traced
    "simulate": {
        "setup": ("--setup", "setup", "The paper's setup: 1 (d1 = 860 mm) or 2 (d1 = 660 mm)."),
        "d1_mm": ("--d1", "d1", "Collimated path length in mm (overrides --setup).", {"low": None}),
        "orientation": ("--orientation", "orientation",
                        "U: parent axes coincide (cancels astigmatism); Z: rotated 180 degrees.", _NO_HINT),
        "stop_distance_mm": ("--stop-distance", "stop_distance",
                             "Aperture stop on the collimated path, mm after the first mirror "
                             "(default: at it).",
                             {"default": None}),
        "focal_length_mm": ("--focal-length", "focal_length", "Reflected focal length of both mirrors, mm."),
        "focal_length_2_mm": ("--focal-length-2", "focal_length_2",
                              "Reflected focal length of the second mirror, mm (default: --focal-length).",
                              {"low": None, "high": None}),
        "pixel_size_um": ("--pixel-size", "pixel_size", "Camera pixel size, um.", {"low": None}),
        "microscope_magnification": ("--microscope-magnification", "microscope_magnification", "The grid "
                                     "CSV's image points (x_u..y_d) behind an ideal microscope of this "
                                     "magnification (negative: it inverts the image, -5 for a 5x objective), "
                                     "as "
                                     "'oapcal fit --model relay --microscope-magnification' takes them; the "
                                     "tables and figures stay at the relay's image."),
    },
    # simulate image: a ray-traced relay only when asked for
    "image": {
        "setup": ("--relay-setup", "relay_setup", "Ray-traced relay of the paper's setup 1 or 2.",
                  {"default": None}),
        "d1_mm": ("--d1", "d1_mm", "Ray-traced relay with this OAP 2 - OAP 3 distance (mm).",
                  {"low": 1, "low_open": False}),
        "pixel_size_um": ("--pixel-size-um", "pixel_size_um", "Camera pixel size (um).",
                          {"low": 0.01, "low_open": False, "design_hint": False}),
    },
}  # fmt: skip


def _design_option_names() -> tuple[str, ...]:
    """The Python names of every style's design options, each once, style by style in the
    table's field order (:data:`oapcal.optics.design.DESIGN_FIELDS`), leaving out those
    marked ``design_hint`` False."""
    names: list[str] = []
    for style in OPTION_STYLES.values():
        for field in DESIGN_FIELDS:
            flag, dest, _help, *changes = style.get(field.name, (None, None, None))
            if (
                flag is not None
                and (changes[0] if changes else {}).get("design_hint", True)
                and dest not in names
            ):
                names.append(dest)
    return tuple(names)


#: The Python names of the options that give a relay's design (``fit``, ``select``,
#: ``selfcal`` and ``robustness`` spell them ``relay_*``, ``simulate relay`` and
#: ``tolerance`` without the prefix, ``simulate image`` its own): an error whose ``param``
#: is ``"design"`` names those the command has.
DESIGN_OPTIONS: tuple[str, ...] = _design_option_names()
