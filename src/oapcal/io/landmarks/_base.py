"""What every landmark reader shares: the landmark record, file reading, number checks.

Coordinates in a :class:`Landmark` are already in oapcal's convention (origin at the
centre of the top-left pixel, x = column, y = row; ``docs/conventions.md``): each reader
converts from its tool's convention.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

from oapcal.errors import InputFileError
from oapcal.io.userfile import parse_number
from oapcal.io.userfile import read_text as _read_text

#: Landmark files larger than this are refused before they are read (bytes).
#: A coordinate whose magnitude exceeds this (px) is certainly not a pixel position.
MAX_COORD = 1.0e7


@dataclass(frozen=True)
class Landmark:
    """One labelled point: ``x, y`` in px (oapcal convention), its attributes as strings
    (``{"corner": "A3"}``), and ``where`` it came from (``"line 5"``, ``"region 2"``) for
    messages; ``unusable`` the attributes whose values cannot name a landmark (a nested
    object, null, a list), each as a short description of its value, for messages."""

    x: float
    y: float
    attrs: dict = field(default_factory=dict)
    where: str = ""
    unusable: dict = field(default_factory=dict)


def unusable_attributes(values: dict) -> dict:
    """The entries of ``values`` that :func:`attribute_text` cannot read, as ``name ->
    short description`` (``"an object {'a': {'b': 1}}"``, ``"null"``, ``"a list [1, 2]"``)."""
    out = {}
    for key, value in values.items():
        if attribute_text(value) is None:
            kind = ("null" if value is None else "an object" if isinstance(value, dict)
                    else "a list" if isinstance(value, list) else f"a {type(value).__name__}")  # fmt: skip
            out[str(key)] = kind if value is None else f"{kind} {_short(value)}"
    return out


@dataclass(frozen=True)
class LandmarkSet:
    """The landmarks of one image.

    ``source`` names the file (and the image, for files that hold several);
    ``ignored`` holds one line per landmark or region that was read but is not used
    (a disabled BigWarp row, a VIA rectangle, ...), to be reported to the user.
    """

    source: str
    landmarks: tuple[Landmark, ...]
    ignored: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.landmarks)


def read_text(path: str | Path, what: str = "landmark file") -> str:
    """The text of ``path`` (``-`` is stdin): :func:`oapcal.io.userfile.read_text`, and
    an empty file is refused."""
    return _check_text(_read_text(path, what), str(path), what)


def _check_text(text: str, name: str, what: str) -> str:
    if "\x00" in text:
        raise InputFileError(f"{name}: contains binary data (NUL bytes); give a {what} (text)")
    if not text.strip():
        raise InputFileError(f"{name}: is empty; give a {what} with landmarks in it")
    return text


def coordinate(value, source: str, where: str, axis: str) -> float:
    """Check one coordinate read from a file: a real, finite number of sane size.

    ``value`` may be a JSON number or a string from a CSV cell.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise InputFileError(
            f"{source}: {where}: {axis} is {type(value).__name__} {_short(value)}, not a number"
        )
    if isinstance(value, str):
        try:
            number = parse_number(value)
        except ValueError:
            shown = "an empty cell" if not value.strip() else _short(value)
            raise InputFileError(
                f"{source}: {where}: {axis} is {shown}, not a number (give ASCII decimal or scientific "
                "notation, e.g. 47.5)"
            ) from None
    else:
        try:
            number = float(value)
        except OverflowError:
            number = math.inf
    if not math.isfinite(number):
        raise InputFileError(
            f"{source}: {where}: {axis} is {_short(value)}, not a finite number; fix or remove it"
        )
    if abs(number) > MAX_COORD:
        raise InputFileError(
            f"{source}: {where}: {axis} = {number:g} px is far outside any image (limit {MAX_COORD:g}); "
            "fix or remove it"
        )
    return number


def attribute_text(value) -> str | None:
    """A region attribute as text: strings as they are, numbers without a trailing ``.0``,
    checkbox dicts (``{"a": true, "b": false}``) as the sorted ticked keys joined by ``+``;
    None for values that cannot name a landmark (nested objects, null)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value.strip()
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return str(int(value)) if value.is_integer() and abs(value) < 1e15 else repr(value)
    if isinstance(value, dict) and all(isinstance(v, bool) for v in value.values()):
        return "+".join(sorted(str(k) for k, v in value.items() if v))
    return None


def _short(value, limit: int = 30) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def sniff_delimiter(text: str) -> str:
    """Tab if the first line has more tabs than commas, else comma."""
    first = text.splitlines()[0] if text else ""
    return "\t" if first.count("\t") > first.count(",") else ","


def csv_rows(text: str, name: str, delimiter: str = ","):
    """Yield ``(line number, cells)`` of a CSV text, skipping blank lines; malformed CSV
    raises :class:`InputFileError` naming the line."""
    reader = csv.reader(io.StringIO(text), delimiter=delimiter)
    line = 0
    try:
        for row in reader:
            line = reader.line_num
            if not row or all(not c.strip() for c in row):
                continue
            yield line, row
    except csv.Error as exc:
        raise InputFileError(f"{name}: line {line + 1}: malformed CSV ({exc})") from None


def first_row(rows, name: str):
    """The first ``(line, cells)`` of :func:`csv_rows`; a file with no row raises."""
    row = next(rows, None)
    if row is None:
        raise InputFileError(f"{name}: has no header line (only blank or quote-only lines)")
    return row
