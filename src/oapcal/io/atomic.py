"""Outputs that are never half-written and never overwrite an input.

Every file oapcal writes goes through :func:`atomic_write`: the data go to a temporary
file in the destination's directory, which is renamed over the destination only when
writing succeeded; on any error the temporary file is removed and the destination is
untouched.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from oapcal.errors import OutputError


def _read_umask() -> int:
    mask = os.umask(0o22)
    os.umask(mask)
    return mask


# Read once at import: os.umask can only be read by setting it, which is not thread-safe.
_UMASK = _read_umask()


def _publish(tmp: str, path: Path) -> None:
    """Give the temporary file ordinary permissions (mkstemp makes it 0600), then rename."""
    with contextlib.suppress(OSError):
        os.chmod(tmp, 0o666 & ~_UMASK)
    os.replace(tmp, path)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **open_kwargs) -> Iterator:
    """Open a temporary file beside ``path`` and rename it to ``path`` on success.

    ``mode`` is ``"w"`` (text, UTF-8 unless ``encoding`` is given) or ``"wb"``.

    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> with atomic_write(d / "a.txt") as fh:
    ...     _ = fh.write("hello")
    >>> (d / "a.txt").read_text()
    'hello'
    """
    path = Path(path)
    if "b" not in mode:
        open_kwargs.setdefault("encoding", "utf-8")
        open_kwargs.setdefault("newline", "")
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise OutputError(f"{path}: the output directory {directory} does not exist; create it first")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as fh:
            yield fh
        _publish(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for a library that writes by file name
    (OpenCV, tifffile, Matplotlib); rename it to ``path`` on success, remove it on error.

    The temporary name keeps ``path``'s suffix so writers pick the right format.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise OutputError(f"{path}: the output directory {directory} does not exist; create it first")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=directory)
    os.close(fd)
    try:
        yield Path(tmp)
        _publish(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def ensure_not_input(output: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """Raise :class:`OutputError` if ``output`` is the same file as one of ``inputs``."""
    out = Path(output)
    out_resolved = out.resolve()
    for inp in inputs:
        if inp is None or str(inp) == "-":
            continue
        p = Path(inp)
        same = p.resolve() == out_resolved
        if not same and out.exists() and p.exists():
            with contextlib.suppress(OSError):
                same = os.path.samefile(p, out)
        if same:
            raise OutputError(
                f"{output}: this output would overwrite the input {inp}; choose another output path"
            )


def safe_output_path(out_dir: str | os.PathLike, name: str | os.PathLike) -> Path:
    """``out_dir / name``, refusing names that would escape ``out_dir``.

    Refused: absolute names, names with ``..`` or empty parts, and names whose resolved
    path leaves ``out_dir`` (through a symbolic link inside it, for instance).

    >>> str(safe_output_path("out", "a.tif"))
    'out/a.tif'
    >>> try:
    ...     safe_output_path("out", "../a.tif")
    ... except OutputError:
    ...     print("refused")
    refused
    """
    out_dir = Path(out_dir)
    text = os.fspath(name)
    parts = Path(text).parts
    bad = (
        not text
        or os.path.isabs(text)
        or any(part in ("..", "") for part in parts)
        or "\x00" in text
        or text.startswith("~")
    )
    target = out_dir / text
    if not bad:
        bad = not target.resolve().is_relative_to(out_dir.resolve())
        # A link inside out_dir (the file itself or a folder on the way) may point elsewhere.
        probe = target
        while not bad and probe != out_dir and probe != probe.parent:
            bad = probe.is_symlink()
            probe = probe.parent
    if bad:
        raise OutputError(
            f"{text!r}: an output name must stay inside the output directory {out_dir} "
            "(no '..', no absolute path, no link leading out)"
        )
    return target
