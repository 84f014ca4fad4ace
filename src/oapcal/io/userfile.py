"""Opening the files users give: one module, one set of limits, one set of messages.

* **Text and JSON** (point files, landmark exports, calibrations, ROI lists, result files):
  :func:`read_text`, :func:`read_json`.  Refused: a missing file, a directory, a file over
  :data:`MAX_FILE_BYTES` (unread), UTF-16, binary data (NUL bytes), bytes that are not UTF-8
  (a BOM is allowed), and for JSON malformed, absurdly nested or unreadable numbers.
* **Binary files** (images, stacks, correction maps): :func:`check_input_file` checks the
  suffix, that the file is there and that it is a file; their readers
  (:mod:`oapcal.io.images`, :mod:`oapcal.io.maps`) then apply :data:`MAX_PIXELS` per frame
  to the header and, for compressed maps, :data:`MAX_UNPACK_RATIO`, before decoding.

Every message names the file and says what to do; all raise
:class:`~oapcal.errors.InputFileError`.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import sys
from pathlib import Path

from oapcal.errors import InputFileError

#: Text inputs larger than this are refused without being read (64 MiB).
MAX_FILE_BYTES = 64 * 1024 * 1024
#: Default per-frame pixel limit of images and stacks (``max_pixels``): 2**28, e.g.
#: 16384 x 16384, checked on the header before any pixel is decoded.
MAX_PIXELS = 2**28
#: A compressed array (a correction map) that unpacks to more than this many times its
#: stored size, and to more than 64 MiB, is refused as a decompression bomb.
MAX_UNPACK_RATIO = 50


def _read_bounded(fh, name: str, what: str) -> bytes:
    """At most :data:`MAX_FILE_BYTES` from a binary stream, read in chunks: the bound holds
    for devices and pipes whose size ``stat`` cannot tell (``/dev/zero``, ``/dev/urandom``,
    stdin), and binary data is refused at the first chunk."""
    chunks, total = [], 0
    while True:
        chunk = fh.read(min(_CHUNK, MAX_FILE_BYTES + 1 - total))
        if not chunk:
            break
        if not chunks:
            _check_start(chunk, name, what)
        chunks.append(chunk)
        total += len(chunk)
        if total > MAX_FILE_BYTES:
            raise InputFileError(
                f"{name}: is over {MAX_FILE_BYTES // 2**20} MiB; a {what} that large is not read "
                "(is this the right file?)"
            )
    return b"".join(chunks)


#: Bytes read at a time by :func:`_read_bounded`.
_CHUNK = 1 << 20


def _check_start(data: bytes, name: str, what: str) -> None:
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise InputFileError(f"{name}: is UTF-16 text; save it as UTF-8")
    if b"\x00" in data:
        raise InputFileError(
            f"{name}: contains binary data, not UTF-8 text (NUL bytes); give a {what} as text"
        )


def read_text(path: str | Path, what: str = "file", *, missing: str = "no such file; check the path") -> str:
    """The text of ``path`` (``-`` is stdin) decoded as UTF-8.

    ``what`` names the kind of file in messages ("point file", "calibration file", ...);
    ``missing`` is the message for a missing file (after the file name).  Line endings
    come back as ``\\n`` whatever the file used (``\\r\\n``, CR only).  At most
    :data:`MAX_FILE_BYTES` are read, whatever the file is (a device or pipe included).
    """
    name = str(path)
    if name == "-":
        stream = getattr(sys.stdin, "buffer", None)  # a text stream in tests: read it as text
        if stream is None:
            text = sys.stdin.read(MAX_FILE_BYTES + 1)
            _check_start(text.encode("utf-8", "surrogatepass")[:_CHUNK], name, what)
            if len(text) > MAX_FILE_BYTES:
                raise InputFileError(f"{name}: is over {MAX_FILE_BYTES // 2**20} MiB; not read")
            return _unix_newlines(text)
        data = _read_bounded(stream, name, what)
    else:
        p = Path(path)
        if not p.exists():
            raise InputFileError(f"{name}: {missing}")
        if p.is_dir():
            raise InputFileError(f"{name}: is a directory, not a {what}")
        try:
            size = p.stat().st_size
            if size > MAX_FILE_BYTES:
                raise InputFileError(
                    f"{name}: is {size / 2**20:.0f} MiB; a {what} over "
                    f"{MAX_FILE_BYTES // 2**20} MiB is not read (is this the right file?)"
                )
            with open(p, "rb") as fh:
                data = _read_bounded(fh, name, what)
        except OSError as exc:
            raise InputFileError(f"{name}: cannot be read ({exc.strerror}); check its permissions") from None
    _check_start(data, name, what)
    try:
        return _unix_newlines(data.decode("utf-8-sig"))
    except UnicodeDecodeError as exc:
        raise InputFileError(
            f"{name}: is not UTF-8 text (bad byte at offset {exc.start}); save it as UTF-8"
        ) from None


def _unix_newlines(text: str) -> str:
    r"""Line endings as ``\n``: Windows ``\r\n`` and old Mac ``\r`` (CR only) files read like
    any other (Python's csv module would otherwise refuse a lone CR with advice about
    'universal-newline mode').

    >>> _unix_newlines("a,b\r1,2\r\n3,4\n")
    'a,b\n1,2\n3,4\n'
    """
    if "\r" not in text:
        return text
    return text.replace("\r\n", "\n").replace("\r", "\n")


def parse_json(text: str, name: str, what: str = "file"):
    """Parse JSON text; malformed, absurdly nested or unreadable JSON raises
    :class:`InputFileError` naming ``name``."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(f"{name}: line {exc.lineno}: malformed JSON ({exc.msg})") from None
    except RecursionError:
        raise InputFileError(f"{name}: JSON nested too deeply to be a {what}") from None
    except ValueError as exc:  # e.g. an integer literal with thousands of digits
        raise InputFileError(f"{name}: unreadable JSON ({str(exc).splitlines()[0]})") from None


def sniff(path: str | Path, n_bytes: int = 4096) -> str:
    r"""The first ``n_bytes`` (at most) of ``path`` as UTF-8 text (a BOM dropped, a character
    cut at the end ignored), or ``""`` when the file cannot be read or is not text: for
    deciding what a file is (a napari reader) without reading a large or binary file.

    Only a regular file is read: a FIFO, socket, device or directory (under any name, through
    any link) gives ``""`` without being read.  It is opened non-blocking and checked on the
    open descriptor, so a FIFO with no writer cannot block the caller and a file swapped for
    one between a check and the open is still caught.

    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "p.csv"
    >>> _ = f.write_bytes(b"\xef\xbb\xbfx_u,y_u\n" + b"1,2\n" * 10**5)
    >>> sniff(f, 12).splitlines()[0], sniff(f.parent / "missing.csv")
    ('x_u,y_u', '')
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except (OSError, ValueError):  # ValueError: a NUL byte in the name
        return ""
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return ""
        head = os.read(fd, n_bytes)
    except OSError:
        return ""
    finally:
        os.close(fd)
    if b"\x00" in head:
        return ""
    try:
        return head.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 3:  # a bad byte, not a character cut at the end
            return ""
        return head[: exc.start].decode("utf-8-sig")


def read_json(path: str | Path, what: str = "JSON file", *, missing: str = "no such file; check the path"):
    """:func:`read_text` then :func:`parse_json`."""
    return parse_json(read_text(path, what, missing=missing), str(path), what)


def check_input_file(path: str | Path, what: str, suffixes, *, missing: str = "check the path") -> Path:
    """``path`` as a :class:`~pathlib.Path` once it is a file with one of ``suffixes``;
    else :class:`~oapcal.errors.InputFileError` naming the file: an unsupported suffix
    (the suffixes a ``what`` may have), a missing file (``missing`` says what to do), a
    directory.  Every binary input (image, stack, map) comes in through here.

    >>> check_input_file("m.csv", "map file", (".npz", ".npy"))
    Traceback (most recent call last):
    oapcal.errors.InputFileError: m.csv: unsupported file type '.csv'; a map file must end in .npz, .npy
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        article = "an" if what[:1] in "aeiou" else "a"
        raise InputFileError(
            f"{path}: unsupported file type {suffix or '(no suffix)'!r}; {article} {what} must end in "
            f"{', '.join(suffixes)}"
        )
    if path.is_dir():
        raise InputFileError(f"{path}: is a directory, not {'an' if what[:1] in 'aeiou' else 'a'} {what}")
    if not path.is_file():
        raise InputFileError(f"{path}: no such {what}; {missing}")
    return path


#: A number as oapcal reads it from a text file: ASCII decimal or scientific notation
#: (``47.5``, ``-1e-3``, ``.5``, ``3.``), or nan / inf (refused later as not finite).
_NUMBER = re.compile(
    r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf|infinity)", re.I | re.ASCII
)


def parse_number(text: str) -> float:
    """A number from a text cell, surrounding whitespace ignored: ASCII decimal or scientific
    notation only.  Python's ``float`` also reads ``4_7.5`` (47.5), Arabic-Indic and
    full-width digits; a file holding those is more likely wrong than meant, so they raise
    :class:`ValueError`, like any text that is not a number.

    >>> parse_number(" -1.5e3 "), parse_number(".5")
    (-1500.0, 0.5)
    >>> for bad in ("4_7.5", "\u0664\u0667.\u0665", "\uff14\uff17.\uff15", "0x1p3", ""):
    ...     try:
    ...         parse_number(bad)
    ...     except ValueError:
    ...         print("refused", ascii(bad))
    refused '4_7.5'
    refused '\u0664\u0667.\u0665'
    refused '\uff14\uff17.\uff15'
    refused '0x1p3'
    refused ''
    """
    stripped = text.strip()
    if not _NUMBER.fullmatch(stripped):
        raise ValueError(f"not a number in ASCII decimal notation: {text!r}")
    return float(stripped)


def checked_coordinate(
    value: float, limit: float, at: str, shown: str, fix: str, far_fix: str | None = None
) -> float:
    """``value``, a coordinate read at ``at`` (file, line, column) and shown as ``shown``,
    refused (:class:`InputFileError`, ending in ``fix``; ``far_fix`` for a value too large)
    when it is not finite or beyond ``limit`` in size.

    >>> checked_coordinate(2e13, 1e12, "p.csv: line 3", "2e13", "fix it")
    Traceback (most recent call last):
    oapcal.errors.InputFileError: p.csv: line 3: 2e13 is far outside any image (limit 1e+12); fix it
    """
    if not math.isfinite(value):
        raise InputFileError(f"{at}: {shown} is not a finite number; {fix}")
    if abs(value) > limit:
        raise InputFileError(f"{at}: {shown} is far outside any image (limit {limit:g}); {far_fix or fix}")
    return value
