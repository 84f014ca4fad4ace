"""The digest of a file a user gives (``oapcal detect`` reports the image's, so a result can be
matched to the exact file it came from)."""

from __future__ import annotations

import hashlib
from pathlib import Path


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of the file's bytes, in hex (as ``sha256sum`` prints it)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


__all__ = ["file_sha256"]
