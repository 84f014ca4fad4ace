"""Reading the text and JSON files users give: one set of checks and messages.

Every message names the file and says what to do: a missing file, a directory, a file
over :data:`MAX_FILE_BYTES` (refused unread), UTF-16, binary data (NUL bytes), bytes that
are not UTF-8 (a BOM is allowed), and for JSON malformed, absurdly nested or unreadable
numbers.  All raise :class:`~oapcal.errors.InputFileError`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from oapcal.errors import InputFileError

#: Text inputs larger than this are refused without being read (64 MiB).
MAX_FILE_BYTES = 64 * 1024 * 1024


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
    ``missing`` is the message for a missing file (after the file name).  At most
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
            return text
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
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputFileError(
            f"{name}: is not UTF-8 text (bad byte at offset {exc.start}); save it as UTF-8"
        ) from None


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


def read_json(path: str | Path, what: str = "JSON file", *, missing: str = "no such file; check the path"):
    """:func:`read_text` then :func:`parse_json`."""
    return parse_json(read_text(path, what, missing=missing), str(path), what)
