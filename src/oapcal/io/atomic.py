"""Outputs that are never half-written and never overwrite an input.

Every file oapcal writes goes through :func:`atomic_write`: the data go to a temporary
file in the destination's directory, which is renamed over the destination only when
writing succeeded; on any error the temporary file is removed and the destination is
untouched.

Temporary names are ``.NAME.XXXXXXXX.tmp`` (:func:`atomic_write`, directories) and
``.STEM.XXXXXXXX.tmp.SUFFIX`` (:func:`atomic_path`); the writing process holds an
exclusive ``flock`` on each while it lives, so :func:`remove_stale_temps` can tell the
leftovers of a killed run (no lock) from a file another run is writing now.

Resume records (:func:`write_resume_record`, :func:`resume_complete`) say what an output
was made from, so that a rerun skips only outputs that match.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import itertools
import json
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from oapcal.errors import OutputError

try:
    import fcntl
except ImportError:  # not on Windows: stale temporary files are then left alone
    fcntl = None


def _read_umask() -> int:
    mask = os.umask(0o22)
    os.umask(mask)
    return mask


# Read once at import: os.umask can only be read by setting it, which is not thread-safe.
_UMASK = _read_umask()


def _publish(tmp: str, path: Path) -> None:
    """Give the temporary file ordinary permissions (mkstemp makes it 0600), then rename
    (after checking again that ``path`` did not become a FIFO or device meanwhile)."""
    check_output_target(path)
    with contextlib.suppress(OSError):
        os.chmod(tmp, 0o666 & ~_UMASK)
    os.replace(tmp, path)


#: The errors of a write that did not fit: a full disk, a file-size limit, a disk quota.
_WRITE_ERRNOS = (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)

_SPECIAL_KINDS = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def check_output_target(path: str | os.PathLike, *, directory: bool = False) -> None:
    """Refuse (:class:`OutputError`, naming ``path``) an output path that exists and is not
    a regular file (a directory when ``directory``): a FIFO, a socket, a character device
    such as ``/dev/null``, a block device, or a symbolic link to one.  Outputs are written
    to a temporary file renamed over the path, which would replace such a file, so none is
    ever written to or replaced; a missing path (or a dangling link) is fine.

    >>> check_output_target("/dev/null")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    oapcal.errors.OutputError: /dev/null: is a character device, not a regular file; oapcal ...
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return
    if stat.S_ISREG(mode) or (directory and stat.S_ISDIR(mode)):
        return
    if stat.S_ISDIR(mode):
        raise OutputError(f"{os.fsdecode(path)}: is a directory; give the path of a file to write")
    for test, kind in _SPECIAL_KINDS:
        if test(mode):
            link = "a link to " if os.path.islink(path) else ""
            raise OutputError(
                f"{os.fsdecode(path)}: is {link}{kind}, not a regular file; oapcal replaces its outputs "
                "whole and never replaces one: give the path of a regular file"
            )


#: Longest file name (bytes) of common file systems.
NAME_MAX = 255


def _temp_prefix(name: str, suffix: str) -> str:
    """``.NAME.``, with NAME cut (at a character boundary) so that the temporary name, with
    tempfile's 8 random characters and ``suffix``, stays within :data:`NAME_MAX` bytes: an
    output name near the limit must not fail because of its temporary name.

    >>> len(_temp_prefix("a" * 250, ".tmp").encode()) + 8 + len(".tmp") <= NAME_MAX
    True
    >>> _temp_prefix("calib.json", ".tmp")
    '.calib.json.'
    """
    room = NAME_MAX - 8 - len(os.fsencode(suffix)) - 2
    raw = os.fsencode(name)
    if len(raw) > room:
        name = raw[:room].decode("utf-8", "ignore")  # a cut multi-byte character is dropped
    return f".{name}."


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", *, clean: bool = True, **open_kwargs) -> Iterator:
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
    directory = _output_directory(path, clean)
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path.name, ".tmp"), suffix=".tmp", dir=directory)
    try:
        with _naming_output(path), os.fdopen(fd, mode, **open_kwargs) as fh:
            _lock(fh.fileno())
            yield fh
            if fcntl is not None:  # rename while still locked (not possible on Windows)
                fh.flush()
                _publish(tmp, path)
        if fcntl is None:
            _publish(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _output_directory(path: Path, clean: bool) -> Path:
    """The existing directory ``path`` is written in (refused if missing, or when ``path``
    may not be replaced), its stale temporary files of ``path`` removed when ``clean``."""
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise OutputError(f"{path}: the output directory {directory} does not exist; create it first")
    check_output_target(path)
    if clean:
        _clean_beside(directory, path)
    return directory


@contextlib.contextmanager
def _naming_output(path: Path) -> Iterator[None]:
    """An :class:`OSError` of a full disk, a file-size limit or a quota that names no file
    (``write`` and ``flush`` say only ``ENOSPC`` / ``EFBIG`` / ``EDQUOT``) raised again
    naming the output ``path``, so that it is not taken for standard output."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None and exc.errno in _WRITE_ERRNOS:
            raise OSError(exc.errno, exc.strerror or os.strerror(exc.errno), os.fspath(path)) from exc
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, clean: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for a library that writes by file name
    (OpenCV, tifffile, Matplotlib); rename it to ``path`` on success, remove it on error.

    The temporary name keeps ``path``'s suffix so writers pick the right format.
    """
    path = Path(path)
    directory = _output_directory(path, clean)
    suffix = f".tmp{path.suffix}"
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path.stem, suffix), suffix=suffix, dir=directory)
    if fcntl is None:  # Windows cannot rename an open file
        os.close(fd)
        fd = None
    _lock(fd)
    try:
        with _naming_output(path):
            yield Path(tmp)
            _publish(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    finally:
        if fd is not None:
            os.close(fd)


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary directory beside ``path`` (for a zarr store), renamed to ``path``
    on success (replacing an older ``path``), removed on error."""
    path = Path(path)
    check_output_target(path, directory=True)
    directory = path.parent if str(path.parent) else Path(".")
    tmp = tempfile.mkdtemp(prefix=_temp_prefix(path.name, ".tmp"), suffix=".tmp", dir=directory)
    fd = os.open(tmp, os.O_RDONLY) if fcntl is not None else None
    _lock(fd)
    try:
        with _naming_output(path):
            yield Path(tmp)
        check_output_target(path, directory=True)
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if fd is not None:
            os.close(fd)


def _clean_beside(directory: Path, path: Path) -> None:
    """Remove what a killed run left while writing ``path`` (a quick look: the first 1000
    entries of the directory)."""
    with contextlib.suppress(OSError):
        remove_stale_temps(directory, [path], limit=1000)


def _lock(fd: int | None) -> None:
    """Hold an exclusive lock on a temporary file for as long as this process writes it."""
    if fcntl is not None and fd is not None:
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)


_TEMP_NAME = re.compile(r"^\.(?P<base>.+)\.[A-Za-z0-9_]{8}\.tmp(?P<suffix>\..*)?$")


def remove_stale_temps(
    directory: str | os.PathLike, outputs: Iterable[str | os.PathLike], limit: int | None = None
) -> list[Path]:
    """Remove the temporary files and directories a killed run left for ``outputs`` (paths
    in ``directory``): names of this module's form, for one of those outputs, that no live
    process holds locked.  At most ``limit`` directory entries are looked at (None: all).
    Returns what was removed."""
    directory = Path(directory)
    if fcntl is None or not directory.is_dir():
        return []
    wanted = set()
    for out in outputs:
        out = Path(out)
        wanted.add((out.name, ""))
        wanted.add((out.stem, out.suffix))
        # the same names as cut by _temp_prefix for outputs near the file-name limit
        wanted.add((_temp_prefix(out.name, ".tmp")[1:-1], ""))
        wanted.add((_temp_prefix(out.stem, f".tmp{out.suffix}")[1:-1], out.suffix))
    removed = []
    with os.scandir(directory) as entries:
        names = [e.name for e in itertools.islice(entries, limit)]
    for name in names:
        entry = directory / name
        match = _TEMP_NAME.match(name)
        if not match or (match["base"], match["suffix"] or "") not in wanted or entry.is_symlink():
            continue
        try:
            fd = os.open(entry, os.O_RDONLY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue  # a live writer holds it
        try:
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed.append(entry)
        finally:
            os.close(fd)
    return removed


# ------------------------------------------------------------------- resume records

#: Directory (inside an output directory) of the resume records.
RESUME_DIR = ".oapcal"


def _tree_stat(path: Path) -> dict:
    """Size and modification time of a file, or total size and file count of a directory."""
    if path.is_dir():
        sizes = [p.stat().st_size for p in path.rglob("*") if p.is_file()]
        return {"size": int(sum(sizes)), "files": len(sizes)}
    st = path.stat()
    return {"size": int(st.st_size), "mtime_ns": int(st.st_mtime_ns)}


def file_fingerprint(path: str | os.PathLike) -> dict:
    """What a rerun compares to know an input is unchanged: size and modification time."""
    return _tree_stat(Path(path))


def resume_record_path(output: str | os.PathLike) -> Path:
    output = Path(output)
    key = hashlib.sha256(os.fsencode(output.name)).hexdigest()[:32]
    return output.parent / RESUME_DIR / f"{key}.json"


def write_resume_record(output: str | os.PathLike, record: dict) -> None:
    """Record what the complete ``output`` was made from (call after it was renamed into
    place): ``record`` (calibration digest, input size and mtime, frame count, ...) and
    the output's own size and mtime."""
    output = Path(output)
    path = resume_record_path(output)
    path.parent.mkdir(exist_ok=True)
    data = {"output": os.fsdecode(output.name), **record, "output_stat": _tree_stat(output)}
    with atomic_write(path, clean=False) as fh:
        fh.write(json.dumps(data, sort_keys=True))


def resume_complete(output: str | os.PathLike, record: dict) -> bool:
    """True if ``output`` exists and was made, complete, from what ``record`` describes;
    False for a missing, replaced, truncated or differently made output."""
    output = Path(output)
    try:
        data = json.loads(resume_record_path(output).read_text(encoding="utf-8"))
        stat = _tree_stat(output)
    except (OSError, ValueError):
        return False
    if not isinstance(data, dict) or data.get("output_stat") != stat:
        return False
    return all(data.get(k) == json.loads(json.dumps(v)) for k, v in record.items())


def check_free_space(directory: str | os.PathLike, n_bytes: int, what: str | os.PathLike) -> None:
    """Refuse, before any work, an output of ``n_bytes`` that cannot fit on the disk."""
    try:
        free = shutil.disk_usage(directory).free
    except OSError:
        return
    if n_bytes > free:
        raise OutputError(
            f"{what}: the output needs {n_bytes / 2**30:.3g} GiB but {directory} has "
            f"{free / 2**30:.3g} GiB free; free some space or choose another output directory",
            param="out_dir",
        )


def check_directory_writable(directory: str | os.PathLike) -> None:
    """Refuse (:class:`OutputError`), before any work, an output directory in which no file
    can be created: tried by creating and removing an empty temporary file in it, or, when
    it does not exist yet, in its nearest existing parent (where it will be made)."""
    directory = Path(directory)
    probe = directory
    while not probe.is_dir() and probe != probe.parent:
        probe = probe.parent
    try:
        fd, tmp = tempfile.mkstemp(prefix=".oapcal-", suffix=".probe", dir=probe)
    except OSError as exc:
        hint = "the file system is read-only" if exc.errno == errno.EROFS else "check its permissions"
        where = "" if probe == directory else f" (it would be made in {probe})"
        raise OutputError(
            f"{directory}: cannot create files in {probe}{where} ({exc.strerror}); {hint} or choose "
            "another output directory",
            param="out_dir",
        ) from None
    os.close(fd)
    os.unlink(tmp)


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
