"""Correct stacks too big for memory with Dask: lazy reads, chunks of frames, bounded memory.

:func:`correct_stack_dask` reads a multi-page TIFF or a zarr array lazily as a Dask array
chunked along frames (``chunk_frames`` frames per chunk), corrects each chunk with
``map_blocks`` and writes a zarr array (each chunk written by the worker that corrected
it) or a multi-page TIFF (chunks gathered in order and appended).  It runs on a
``dask.distributed`` ``LocalCluster`` by default, on an existing scheduler given its
address, or on Dask's local ``threads`` / ``synchronous`` schedulers.

Memory stays bounded however long the stack is: chunks are computed a window at a time
(a few per worker), and nothing keeps a reference to finished chunks; a chunk never holds
more frames than the stack.  TIFF inputs are read like :mod:`oapcal.io.images` reads them
(every page of every series, planar colour, ImageJ hyperstacks in one page memory-mapped).  Workers build the
correction map themselves from the parameters and the output geometry (cached per
process), so the task graph stays small; a prebuilt map given with its file is loaded by
them (workers must see the file), one given without travels in the task graph.  Workers
must also see the input and output paths (a shared file system).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import os
import signal
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from oapcal.batch.stack import ZARR_SUFFIX, dask_output_name  # noqa: F401 (named here as before)
from oapcal.errors import DataError, InputFileError, OutputError
from oapcal.imaging.remap import CorrectionMap, OutputGeometry, correct_image, correction_map
from oapcal.io.images import (
    MAX_PIXELS,
    TIFF_SUFFIXES,
    FrameWriter,
    check_frame,
    info_slice,
    output_kind,
    probe,
    read_tiff_frames,
)
from oapcal.io.maps import load_map
from oapcal.progress import Stages

LOCAL_SCHEDULERS = ("threads", "synchronous", "processes")
#: ``DaskSettings.output_format``: a zarr array, an OME-Zarr (NGFF 0.4) group, a TIFF.
OUTPUT_FORMATS = ("zarr", "ome-zarr", "tiff")
#: The most chunks one stack may have (a header claiming 1e9 frames would otherwise build a
#: task graph larger than memory); raise --chunk-frames for longer stacks.
MAX_CHUNKS = 1_000_000
#: Seconds to wait for a scheduler given by address to answer.
CONNECT_TIMEOUT = 10
#: Seconds to wait, once connected, for a scheduler to have at least one worker.
WORKER_TIMEOUT = 30
#: Protocols of a ``dask.distributed`` scheduler address.
SCHEDULER_PROTOCOLS = ("tcp", "tls", "ws", "wss", "ucx")


@dataclass(frozen=True)
class DaskResult:
    """``frames`` corrected from ``input`` into ``output`` (``skipped`` if it existed)."""

    input: str
    output: str
    frames: int
    chunks: int
    skipped: bool = False
    #: What the run decided for the user (streamed in this process; a scheduler that is
    #: slower than streaming on one machine), for the command to print; "" when nothing.
    note: str = ""


# ------------------------------------------------------------------------ lazy input


def _read_tiff_frames(info) -> np.ndarray:
    """The frames of a TIFF that ``info`` (an :func:`oapcal.io.images.info_slice`) describes."""
    return read_tiff_frames(info, 0, info.n_frames)


def lazy_stack(path: str | Path, chunk_frames: int = 16, max_pixels: int = MAX_PIXELS):
    """A Dask array ``(frames, rows, cols[, ch])`` over a TIFF stack or zarr array, one
    chunk per ``chunk_frames`` frames (at most the stack's length); nothing is read until
    it is computed."""
    from oapcal.extras import require

    dask = require("dask")
    da = require("dask.array")
    require("zarr")

    path = Path(path)
    if chunk_frames < 1:
        raise InputFileError(
            f"{path}: chunk_frames must be at least 1, got {chunk_frames}", param="chunk_frames"
        )
    if path.suffix.lower() == ZARR_SUFFIX:
        return _lazy_zarr(path, chunk_frames, max_pixels, da)
    if path.suffix.lower() not in TIFF_SUFFIXES:
        raise InputFileError(
            f"{path}: the Dask correction reads TIFF stacks and zarr arrays ({ZARR_SUFFIX} directories)"
        )
    return _lazy_tiff(path, chunk_frames, max_pixels, dask, da)


def _lazy_zarr(path: Path, chunk_frames: int, max_pixels: int, da):
    """:func:`lazy_stack` of a zarr array (or OME-Zarr image): checked, frames first."""
    import zarr

    from oapcal.io.ome import ome_zarr_array_path

    ngff = ome_zarr_array_path(path) if path.is_dir() else None
    try:
        z = zarr.open_array(str(ngff or path), mode="r")
    except Exception as exc:  # zarr raises several types for a missing or bad store
        raise InputFileError(
            f"{path}: cannot be opened as a zarr array ({type(exc).__name__}: {exc})"
        ) from None
    if z.ndim not in (2, 3, 4):
        raise InputFileError(f"{path}: a zarr stack must be (frames, rows, cols[, ch]), got shape {z.shape}")
    shape = (1, *z.shape) if z.ndim == 2 else tuple(z.shape)
    if min(shape) < 1:
        raise InputFileError(f"{path}: the zarr array is empty (shape {z.shape})")
    if shape[1] * shape[2] > max_pixels:
        raise InputFileError(
            f"{path}: frames of {shape[2]}x{shape[1]} px exceed max_pixels {max_pixels}",
            param="max_pixels",
        )
    _check_chunks(path, shape[0], chunk_frames)
    if z.nchunks_initialized == 0:
        raise InputFileError(
            f"{path}: the zarr header claims {shape[0]} frames of {shape[2]}x{shape[1]} px but "
            "the store holds no data; the array is empty or its header is corrupt"
        )
    arr = da.from_zarr(z)
    if ngff is not None and z.ndim == 4:  # NGFF stores colour as (t, c, y, x)
        arr = arr.transpose(0, 2, 3, 1)
        shape = tuple(arr.shape)
    if z.ndim == 2:
        arr = arr[None]
    check_frame(path, np.empty((1, 1) + arr.shape[3:], arr.dtype))
    return arr.rechunk({0: min(chunk_frames, shape[0]), 1: -1, 2: -1})


def _lazy_tiff(path: Path, chunk_frames: int, max_pixels: int, dask, da):
    """:func:`lazy_stack` of a TIFF stack: one delayed read per chunk of frames."""
    info = probe(path, max_pixels)
    check_frame(path, np.empty((1, 1) + info.frame_shape[2:], info.dtype))
    _check_chunks(path, info.n_frames, chunk_frames)
    chunk_frames = min(chunk_frames, info.n_frames)
    blocks = []
    for start in range(0, info.n_frames, chunk_frames):
        stop = min(info.n_frames, start + chunk_frames)
        task = dask.delayed(_read_tiff_frames, pure=True)(info_slice(info, start, stop))
        blocks.append(da.from_delayed(task, (stop - start, *info.frame_shape), dtype=info.dtype))
    return da.concatenate(blocks, axis=0)


def _check_chunks(path: Path, n_frames: int, chunk_frames: int) -> None:
    n_chunks = -(-n_frames // chunk_frames)
    if n_chunks > MAX_CHUNKS:
        raise InputFileError(
            f"{path}: {n_frames} frames in chunks of {chunk_frames} make {n_chunks} chunks, more than "
            f"{MAX_CHUNKS}; give a larger chunk_frames (if the frame count is genuine)",
            param="chunk_frames",
        )


# ----------------------------------------------------------------- the work per chunk


@functools.lru_cache(maxsize=8)
def _worker_map(source: tuple) -> CorrectionMap:
    """The map, built (or loaded) once per worker process and reused for every chunk."""
    if source[0] == "file":
        return load_map(source[1])
    _, params, shape, x0, y0, scale, um = source
    geometry = OutputGeometry(shape, x0, y0, scale, um)
    return correction_map(np.array(params), shape, geometry=geometry)


def _correct_block(block: np.ndarray, source, interp: str, border: float, allow: bool = False) -> np.ndarray:
    cmap = source if isinstance(source, CorrectionMap) else _worker_map(source)
    out = np.empty((block.shape[0], *cmap.shape, *block.shape[3:]), block.dtype)
    for i, frame in enumerate(block):
        out[i] = correct_image(frame, cmap, interp, border, allow_size_mismatch=allow).reshape(out.shape[1:])
    return out


def _write_zarr_block(block: np.ndarray, path: str, ngff: bool = False, block_info=None) -> np.ndarray:
    """Write one corrected chunk into the zarr array at ``path`` (with ``ngff``, colour as
    NGFF's ``(t, c, y, x)``); return its frame count."""
    import zarr

    start = block_info[0]["array-location"][0][0]
    z = zarr.open_array(path, mode="r+")
    z[start : start + len(block)] = np.moveaxis(block, -1, 1) if ngff and block.ndim == 4 else block
    return np.array([len(block)])


# ------------------------------------------------------------------------ schedulers


#: ``DaskSettings.engine``: ``auto`` streams the chunks in this process when no scheduler is
#: given and at most one worker (see :func:`streams_locally`), ``dask`` always runs Dask's
#: scheduler (a new ``LocalCluster`` when none is given).
ENGINES = ("auto", "dask")
#: What :func:`dask_scheduler` yields for a run that streams in this process.
STREAM = "stream"


def streams_locally(scheduler: str | None, workers: int | None, engine: str = "auto") -> bool:
    """Whether a run streams its frames in this process (read, remapped and written one at a
    time, as ``oapcal correct`` without ``--dask`` does, into the same output) instead of
    starting a ``LocalCluster``: with ``engine="auto"``, no
    scheduler and at most one worker, the default of ``oapcal correct --dask``.  On one
    machine that is the fastest way (``docs/benchmarks.md``, "Dask against streaming"):
    a local cluster only adds its start-up and the transfer of frames between processes.

    >>> streams_locally(None, None), streams_locally(None, 2), streams_locally("tcp://h:8786", 1)
    (True, False, False)
    """
    if engine not in ENGINES:
        raise InputFileError(f"engine {engine!r}: use one of {', '.join(ENGINES)}", param="engine")
    return engine == "auto" and scheduler is None and (workers or 1) <= 1


def max_local_workers() -> int:
    """The most worker processes a local cluster may start: four per core (at least 8).
    Each is a Python process of about 100 MB; more than the cores only queue."""
    return max(8, 4 * (os.cpu_count() or 1))


def dask_note(scheduler: str | None, workers: int | None, engine: str = "auto") -> str:
    """What to tell the user about where a ``--dask`` run goes, from the measurements in
    ``docs/benchmarks.md``; "" for a cluster given by address.

    >>> dask_note("tcp://10.0.0.5:8786", None)
    ''
    """
    if streams_locally(scheduler, workers, engine):
        return (
            "streamed in this process, frame by frame: on one machine a local cluster of Dask workers "
            "is slower than streaming (docs/benchmarks.md); give workers > 1 or a scheduler address "
            "to run Dask workers"
        )
    if scheduler is None or scheduler in LOCAL_SCHEDULERS:
        return (
            "Dask on this machine alone is slower than correcting without Dask, which streams the "
            "frames in one process (docs/benchmarks.md); Dask pays on a cluster (a scheduler address) "
            "whose workers see the files"
        )
    return ""


@contextlib.contextmanager
def dask_scheduler(
    scheduler: str | None = None, workers: int | None = None, worker_timeout: float | None = None,
    *, engine: str = "auto",
):  # fmt: skip
    """Yield what ``dask.compute(..., scheduler=...)`` takes, and the number of chunks to
    keep in flight: :data:`STREAM` and 1 when the frames stream in this process without
    Dask (:func:`streams_locally`: the default without a scheduler and with at most one
    worker, unless ``engine="dask"``), else a new ``LocalCluster`` of ``workers`` processes,
    a ``Client`` of the scheduler at an address (``tcp://host:8786``), or a local scheduler
    name (threads, synchronous, processes).  Open it once for a batch of stacks.

    An address is checked before any connection (:func:`parse_scheduler_address`); a
    scheduler that has no worker within ``worker_timeout`` seconds (default
    :data:`WORKER_TIMEOUT`) is refused rather than waited for forever.

    Dask's own log messages (tracebacks of workers stopped by Ctrl-C, a full disk) are kept
    off the terminal; oapcal reports the problem in one line.  The local cluster's worker
    processes ignore Ctrl-C (the main process stops them).
    """
    if streams_locally(scheduler, workers, engine):
        yield STREAM, 1
        return
    if scheduler in LOCAL_SCHEDULERS:
        yield scheduler, max(2, workers or os.cpu_count() or 1)
        return
    if scheduler is not None:
        scheduler = parse_scheduler_address(scheduler)
    from oapcal.extras import require

    require("distributed")
    with _quiet_distributed():
        if scheduler is None:
            from distributed import Client, LocalCluster

            n = workers or 1
            most = max_local_workers()
            if n > most:
                raise DataError(
                    f"a local cluster of {n:,} worker processes on a machine with {os.cpu_count() or 1} "
                    f"cores: give at most {most} workers (or a scheduler address for a cluster)",
                    param="workers",
                )
            with _workers_ignore_sigint():
                cluster = LocalCluster(
                    n_workers=n, threads_per_worker=1, dashboard_address=None, silence_logs=logging.CRITICAL
                )
            with cluster, Client(cluster) as client:
                yield client, 2 * n
            return
        client = connect_scheduler(scheduler)
        with client:
            _wait_for_workers(client, scheduler, WORKER_TIMEOUT if worker_timeout is None else worker_timeout)
            n_threads = sum(client.nthreads().values()) or 1
            yield client, 2 * n_threads


def parse_scheduler_address(address: str) -> str:
    """``address`` once it has the form of a scheduler address, ``PROTOCOL://HOST:PORT``
    (:data:`SCHEDULER_PROTOCOLS`) or ``HOST:PORT`` (tcp), with a port 1-65535; else
    :class:`InputFileError` saying what to give (no connection is tried).

    >>> parse_scheduler_address("tcp://127.0.0.1:8786"), parse_scheduler_address("[::1]:8786")
    ('tcp://127.0.0.1:8786', 'tcp://[::1]:8786')
    >>> parse_scheduler_address("THREADS")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    oapcal.errors.InputFileError: scheduler 'THREADS': not a scheduler name; give tcp://HOST:PORT ...
    """
    import re

    text = str(address).strip()
    usage = (
        "give tcp://HOST:PORT of a running dask scheduler, or threads, synchronous or processes (lower case)"
    )
    protocol, sep, rest = text.partition("://")
    if not sep:
        protocol, rest = "tcp", text
    protocol = protocol.lower()
    match = re.fullmatch(r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):([0-9]{1,5})", rest)
    if protocol not in SCHEDULER_PROTOCOLS:
        why = f"protocol {protocol}:// is not one of a dask scheduler ({', '.join(SCHEDULER_PROTOCOLS)})"
        raise InputFileError(f"scheduler {address!r}: {why}; {usage}", param="scheduler")
    if not match:
        why = (
            "has no port" if re.fullmatch(r"\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+", rest) else "is not HOST:PORT"
        )
        if not sep and not match and text.lower() in {*LOCAL_SCHEDULERS, "sync", "thread", "process"}:
            why = "not a scheduler name"
        elif not sep:
            why = "not a scheduler name or address"
        raise InputFileError(f"scheduler {address!r}: {why}; {usage}", param="scheduler")
    port = int(match[2])
    if not 1 <= port <= 65535:
        raise InputFileError(f"scheduler {address!r}: port {port} is not 1-65535; {usage}", param="scheduler")
    return f"{protocol}://{match[1]}:{port}"


def _wait_for_workers(client, address: str, timeout: float) -> None:
    """Refuse (InputFileError) a scheduler that has no worker after ``timeout`` seconds."""
    try:
        client.wait_for_workers(1, timeout=timeout)
    except Exception:  # TimeoutError (distributed's or asyncio's)
        if client.nthreads():
            return
        raise InputFileError(
            f"scheduler {address}: has no workers after {timeout:g} s; start workers "
            f"('dask worker {address}') or leave the scheduler out for a local cluster",
            param="scheduler",
        ) from None


def connect_scheduler(address: str, timeout: float | None = None):
    """A ``distributed.Client`` of the scheduler at ``address``; refuses (InputFileError)
    an address that does not answer as a Dask scheduler within ``timeout`` seconds (a
    server that accepts the connection and says nothing, or answers with other bytes)."""
    from distributed import Client

    timeout = CONNECT_TIMEOUT if timeout is None else timeout
    box: dict = {}

    def connect():
        try:
            box["client"] = Client(address, timeout=f"{timeout}s", set_as_default=False)
        except BaseException as exc:  # MemoryError from a server answering with garbage, ...
            box["error"] = exc

    thread = threading.Thread(target=connect, name="oapcal-connect", daemon=True)
    thread.start()
    thread.join(timeout + 1)
    hint = "check the address (tcp://HOST:PORT of a running dask scheduler) or leave the scheduler out"
    if thread.is_alive():
        raise InputFileError(
            f"scheduler {address}: no answer from a Dask scheduler within {timeout:g} s; {hint}",
            param="scheduler",
        )
    if "error" in box:
        exc = box["error"]
        if isinstance(exc, KeyboardInterrupt):
            raise exc
        what = "not a Dask scheduler" if isinstance(exc, MemoryError) else f"{type(exc).__name__}: {exc}"
        raise InputFileError(
            f"scheduler {address}: cannot connect to a Dask scheduler ({what}); {hint}", param="scheduler"
        )
    return box["client"]


@contextlib.contextmanager
def _quiet_distributed():
    names = ("distributed", "distributed.nanny", "distributed.worker", "distributed.scheduler", "tornado")
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


@contextlib.contextmanager
def _workers_ignore_sigint():
    """Start worker processes with Ctrl-C ignored (they inherit it); only from the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


# ---------------------------------------------------------------------- the pipeline


@dataclass(frozen=True)
class DaskSettings:
    """The output and scheduler options of :func:`correct_stack_dask`.

    ``extent``, ``um_per_px`` and ``out_size`` shape the map built for each stack's size
    when no prebuilt map is given (see :func:`oapcal.imaging.remap.correction_map`).
    """

    #: ``zarr`` (a plain array), ``ome-zarr`` (NGFF 0.4, :mod:`oapcal.io.ome`) or ``tiff``.
    output_format: str = "zarr"
    chunk_frames: int = 16
    interp: str = "linear"
    border: float = 0
    extent: str = "input"
    um_per_px: float | None = None
    out_size: tuple[int, int] | None = None
    allow_size_mismatch: bool = False
    max_pixels: int = MAX_PIXELS
    scheduler: str | None = None
    workers: int | None = None
    calibration_name: str | None = None
    overwrite: bool = False
    #: ``progress(done, total, description)`` over the frames written (:mod:`oapcal.progress`).
    progress: object = None
    #: :data:`ENGINES`: ``auto`` streams in this process when no scheduler and at most one
    #: worker are given (:func:`streams_locally`), ``dask`` always uses Dask's scheduler.
    engine: str = "auto"


@dataclass(frozen=True)
class _MapPlan:
    """What the workers build (or load) the map from, its geometry, and the resume digest."""

    source: object
    geometry: OutputGeometry
    digest: str


def correct_stack_dask(
    calibration,
    input_path: str | Path,
    out_dir: str | Path,
    cmap: CorrectionMap | None = None,
    settings: DaskSettings = DaskSettings(),
    *,
    map_path: str | Path | None = None,
    session: tuple | None = None,
) -> DaskResult:
    """Correct one TIFF or zarr stack with Dask into ``out_dir/STEM.zarr`` (or ``.tif``).

    ``cmap`` is a prebuilt map (``--map``), which the stack's frames must fit unless
    ``settings.allow_size_mismatch``; ``map_path``, the file it was loaded from, lets the
    workers load it themselves (otherwise it travels in the task graph).  Without ``cmap``
    the map is built for the stack's frame size from the calibration and the settings'
    geometry, by each worker (so the graph stays small).

    The output appears atomically (written under a temporary name, then renamed); an
    existing output is skipped, unless ``overwrite``, when its resume record (see
    :mod:`oapcal.batch.stack`) matches the calibration, settings and input.  Output
    arrays are chunked like the input (``chunk_frames`` frames, at most the stack) and
    carry the calibration's name and the pixel size (zarr attributes
    ``oapcal_calibration``, ``um_per_px``; TIFF metadata; a BigTIFF when over 4 GiB).
    ``session`` is an open :func:`dask_scheduler` ``(scheduler, window)`` to run on
    (default: open ``settings.scheduler`` for this stack alone).
    """
    from oapcal.io.atomic import file_fingerprint, resume_complete, write_resume_record

    shown_in = Path(input_path)
    shown_out = _plan_output(shown_in, Path(out_dir), settings.output_format)
    # Workers of a distributed cluster run in their own directories: they get absolute paths.
    input_path, out_path = shown_in.absolute(), shown_out.absolute()
    stack = _open_input(calibration, input_path, settings)
    plan = _plan_map(calibration, input_path, stack.shape[1:3], cmap, map_path, settings)
    record = {
        "calibration": plan.digest,
        "input": file_fingerprint(input_path),
        "frames": int(stack.shape[0]),
    }
    if out_path.exists() and not settings.overwrite and resume_complete(out_path, record):
        return DaskResult(str(shown_in), str(shown_out), 0, 0, skipped=True)
    name = settings.calibration_name or getattr(calibration, "name", None)
    own = (
        contextlib.nullcontext(session)
        if session is not None
        else dask_scheduler(settings.scheduler, settings.workers, engine=settings.engine)
    )
    with own as opened:
        if opened[0] == STREAM:
            n_chunks = _stream_and_write(stack, input_path, plan, out_path, name, settings, calibration)
        else:
            corrected = _build_graph(stack, plan, settings)
            n_chunks = _run_and_write(corrected, out_path, plan.geometry, name, input_path.name, settings,
                                      opened, calibration)  # fmt: skip
    write_resume_record(out_path, {**record})
    note = dask_note(settings.scheduler, settings.workers, settings.engine)
    return DaskResult(str(shown_in), str(shown_out), int(stack.shape[0]), n_chunks, note=note)


def correct_stacks_dask(
    calibration,
    plan,
    out_dir: str | Path,
    cmap: CorrectionMap | None = None,
    settings: DaskSettings = DaskSettings(),
    *,
    map_path: str | Path | None = None,
):
    """Correct every stack of ``plan`` (:func:`oapcal.batch.stack.plan_batch` with a
    ``dask_format``) with :func:`correct_stack_dask` on one scheduler, opened once for the
    batch (:func:`dask_scheduler`); the library form of ``oapcal correct --dask``.

    Returns a :class:`~oapcal.batch.stack.StackReport`: the plan's failures, then one
    :class:`~oapcal.batch.stack.FileResult` per stack (a stack the correction refuses, or
    that fails to read or write, is a failed result naming the file, and the batch goes on);
    its ``notes`` say where the run went, once.  Temporary outputs that workers leave after
    an interruption are removed.  Dask's own log messages are kept off the terminal.
    """
    from oapcal.batch.stack import FileResult, StackReport
    from oapcal.errors import OapcalError
    from oapcal.extras import EXTRAS, require
    from oapcal.io.atomic import remove_stale_temps

    for module in EXTRAS["dask"]:  # before any work: a missing extra is one clear error
        require(module, "dask")
    # Dask's event loop reports the tasks a Ctrl-C cancelled when they are garbage collected,
    # at exit; the caller reports the interruption itself, in one line.
    for logger in ("asyncio", "distributed", "tornado"):
        logging.getLogger(logger).setLevel(logging.CRITICAL)
    results = list(plan.failures)
    notes: list[str] = []
    try:
        with dask_scheduler(settings.scheduler, settings.workers) as session:
            for path in plan.files:
                try:
                    r = correct_stack_dask(
                        calibration, path, out_dir, cmap, settings, map_path=map_path, session=session
                    )
                except (OapcalError, OSError, MemoryError) as exc:
                    results.append(_failed(path, out_dir, exc))
                    continue
                if r.note and r.note not in notes:
                    notes.append(r.note)
                status = "skipped" if r.skipped else "corrected"
                results.append(FileResult(r.input, r.output, status, r.frames))
    finally:
        # Workers may have written into a temporary store after an interruption: now that
        # they are gone, remove what is left.
        if Path(out_dir).is_dir():
            remove_stale_temps(out_dir, plan.outputs)
    return StackReport(tuple(results), notes=tuple(notes))


def _failed(path: Path, out_dir, exc: BaseException):
    """The failed :class:`~oapcal.batch.stack.FileResult` of a stack, its message naming
    the file (``output`` None, as nothing was written)."""
    from oapcal.batch.stack import FileResult
    from oapcal.errors import OapcalError

    if isinstance(exc, MemoryError):
        message = f"{path}: not enough memory; lower chunk_frames or workers"
        return FileResult(str(path), None, "failed", 0, message, ("chunk_frames", "workers"), "out_of_memory")
    message = str(exc)
    if str(path) not in message and str(out_dir) not in message:  # name the file
        message = f"{path}: {message}"
    reason = "refused" if isinstance(exc, OapcalError) else "os_error"
    return FileResult(str(path), None, "failed", 0, message, getattr(exc, "param", None), reason)


def _plan_output(input_path: Path, out_dir: Path, output_format: str) -> Path:
    """The output path of ``input_path``; refuses an unknown format or overwriting the input."""
    if output_format not in OUTPUT_FORMATS:
        raise OutputError(f"unknown output format {output_format!r}: use {', '.join(OUTPUT_FORMATS)}")
    out_path = out_dir / dask_output_name(input_path, output_format)
    if out_path.resolve() == input_path.resolve():
        raise OutputError(
            f"{out_path}: the output would overwrite the input {input_path}; choose another out_dir",
            param="out_dir",
        )
    from oapcal.io.atomic import check_output_target

    check_output_target(out_path, directory=output_format != "tiff")
    return out_path


def _open_input(calibration, input_path: Path, settings: DaskSettings):
    """The stack as a lazy Dask array; refuses frames of another size than the calibration's."""
    stack = lazy_stack(input_path, settings.chunk_frames, settings.max_pixels)
    rows, cols = stack.shape[1:3]
    cal_size = getattr(calibration, "image_size", None)
    if cal_size and tuple(cal_size) != (cols, rows) and not settings.allow_size_mismatch:
        raise InputFileError(
            f"{input_path}: frames are {cols}x{rows} px but the calibration is for "
            f"{cal_size[0]}x{cal_size[1]} px; give allow_size_mismatch=True to correct them anyway",
            param="allow_size_mismatch",
        )
    return stack


def _plan_map(calibration, input_path: Path, frame_shape, cmap, map_path, settings: DaskSettings) -> _MapPlan:
    """How the workers get the map for frames of ``frame_shape = (rows, cols)``."""
    from oapcal.batch.stack import correction_digest

    rows, cols = frame_shape
    interp, border = settings.interp, float(settings.border)
    if cmap is not None:
        if cmap.input_shape and cmap.input_shape != (rows, cols) and not settings.allow_size_mismatch:
            where = f" {map_path}" if map_path is not None else ""
            raise InputFileError(
                f"{input_path}: frames are {cols}x{rows} px but the map{where} was built for "
                f"{cmap.input_shape[1]}x{cmap.input_shape[0]} px input"
            )
        from oapcal.imaging.remap import check_map_samples

        check_map_samples(cmap, (rows, cols))
        source = ("file", str(Path(map_path).resolve())) if map_path is not None else None
        if source is None:
            import dask

            source = dask.delayed(cmap, pure=True)
        digest = correction_digest(calibration, cmap, interp=interp, border=border)
        return _MapPlan(source, cmap.geometry, digest)
    params = np.asarray(getattr(calibration, "params", calibration), float)
    # the frame size was checked against the calibration's when the stack was opened
    geometry = correction_map(calibration, (rows, cols), extent=settings.extent, um_per_px=settings.um_per_px,
                              out_size=settings.out_size, allow_size_mismatch=True).geometry  # fmt: skip
    source = ("params", tuple(float(v) for v in params), geometry.shape, geometry.x0, geometry.y0,
              geometry.scale, geometry.um_per_px)  # fmt: skip
    fit_size = None if settings.out_size is None else list(settings.out_size)
    digest = correction_digest(calibration, None, interp=interp, border=border, extent=settings.extent,
                               um_per_px=settings.um_per_px, out_size=fit_size)  # fmt: skip
    return _MapPlan(source, geometry, digest)


def _build_graph(stack, plan: _MapPlan, settings: DaskSettings):
    """The corrected stack as a lazy Dask array, one task per chunk of frames."""
    shape = plan.geometry.shape
    return stack.map_blocks(
        _correct_block,
        plan.source,
        settings.interp,
        settings.border,
        settings.allow_size_mismatch,
        dtype=stack.dtype,
        chunks=(stack.chunks[0], (shape[0],), (shape[1],), *stack.chunks[3:]),
    )


def _run_and_write(
    corrected, out_path: Path, geometry, name, label, settings: DaskSettings, session, calibration=None
) -> int:
    """Compute ``corrected`` a window of chunks at a time into ``out_path``, atomically;
    return the number of chunks."""
    from oapcal.io.atomic import check_free_space, remove_stale_temps

    out_dir = out_path.parent
    out_shape = corrected.shape
    out_bytes = int(np.prod(out_shape, dtype=np.int64)) * corrected.dtype.itemsize
    n_chunks = len(corrected.chunks[0])
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out_dir, [out_path])
    if settings.output_format == "tiff":
        check_free_space(out_dir, out_bytes, out_path)
    bar = Stages(settings.progress, out_shape[0], f"{label} frames")
    own = (
        contextlib.nullcontext(session)
        if session is not None
        else dask_scheduler(settings.scheduler, settings.workers, engine=settings.engine)
    )
    try:
        with own as (sched, window), bar:
            if settings.output_format in ("zarr", "ome-zarr"):
                from oapcal.io.ome import provenance

                ngff = None
                if settings.output_format == "ome-zarr":
                    ngff = provenance(name, geometry.um_per_px, label, calibration)
                _write_zarr(corrected, out_path, geometry, name, sched, window, bar, ngff)
            else:
                _write_tiff(corrected, out_path, geometry, name, out_bytes, sched, window, bar, label,
                            calibration)  # fmt: skip
    except OSError as exc:
        raise _os_error(out_path, exc) from None
    return n_chunks


def _stream_and_write(stack, input_path: Path, plan: _MapPlan, out_path: Path, name, settings: DaskSettings,
                      calibration) -> int:  # fmt: skip
    """The frames of ``stack`` read, remapped and written one at a time in this process,
    into the output :func:`_run_and_write` would write (the same store, chunks and
    metadata); return the number of chunks of the input."""
    from oapcal.io.atomic import atomic_dir, atomic_path, check_free_space, remove_stale_temps
    from oapcal.io.images import open_frames

    source = plan.source
    if isinstance(source, tuple):
        cmap = _worker_map(source)
    else:
        cmap = source if isinstance(source, CorrectionMap) else source.compute(scheduler="synchronous")
    n, chunk = int(stack.shape[0]), int(stack.chunks[0][0])
    out_shape = (n, *plan.geometry.shape, *stack.shape[3:])
    dtype = np.dtype(stack.dtype)
    out_bytes = int(np.prod(out_shape, dtype=np.int64)) * dtype.itemsize
    out_dir = out_path.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out_dir, [out_path])
    fmt = settings.output_format
    if fmt == "tiff":
        check_free_space(out_dir, out_bytes, out_path)

    def frames():
        if input_path.suffix.lower() in TIFF_SUFFIXES:
            with open_frames(input_path, settings.max_pixels) as (_, pages):
                yield from pages
            return
        for lo in range(0, n, chunk):  # a zarr input: one chunk at a time
            yield from stack[lo : lo + chunk].compute(scheduler="synchronous")

    label = input_path.name
    meta = dict(expected_bytes=out_bytes, n_frames=n, source=label, calibration=calibration)
    try:
        with Stages(settings.progress, n, f"{label} frames") as bar:
            temporary = atomic_path(out_path) if fmt == "tiff" else atomic_dir(out_path)
            with temporary as tmp:
                if fmt == "zarr":
                    writer = _ZarrSlabs(tmp, out_shape, chunk, dtype, name, plan.geometry.um_per_px)
                else:
                    kind = output_kind(out_path) if fmt == "tiff" else "ome-zarr"
                    writer = FrameWriter(tmp, kind, name, plan.geometry.um_per_px, **meta)
                with writer:
                    buffer = None
                    for frame in frames():
                        buffer = correct_image(frame, cmap, settings.interp, settings.border, out=buffer,
                                               allow_size_mismatch=settings.allow_size_mismatch)  # fmt: skip
                        writer.write(buffer.reshape(out_shape[1:]))
                        bar.advance()
                if writer.n != n:
                    raise OutputError(f"{out_path}: {writer.n} of {n} frames were written")
    except OSError as exc:
        raise _os_error(out_path, exc) from None
    return len(stack.chunks[0])


class _ZarrSlabs:
    """Frames gathered into slabs of ``chunk`` frames and written to a new zarr array at
    ``path`` as :func:`_write_zarr` makes it (its chunks and attributes).  A slab is
    encoded and written by one background thread while the next is filled (zarr's
    compression releases the GIL), at most two slabs in memory."""

    def __init__(self, path, shape, chunk: int, dtype, name, um_per_px):
        import zarr

        chunks = (chunk, *shape[1:])
        from oapcal.io.ome import zarr_compressors

        self.z = zarr.create_array(str(path), shape=shape, chunks=chunks, dtype=dtype, overwrite=True,
                                   compressors=zarr_compressors())  # fmt: skip
        self.z.attrs.update({"oapcal_calibration": name, "um_per_px": um_per_px,
                             "axes": "TYX" + "C" * (len(shape) == 4)})  # fmt: skip
        self.chunk, self.shape, self.dtype = chunk, shape, dtype
        self.slab = np.empty((chunk, *shape[1:]), dtype)
        self.n = 0
        self._k = 0
        self._pool = None
        self._pending = None

    def __enter__(self):
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="oapcal-zarr")
        return self

    def write(self, frame: np.ndarray) -> None:
        self.slab[self._k] = frame
        self._k += 1
        self.n += 1
        if self._k == self.chunk:
            self._flush()

    def _flush(self) -> None:
        if not self._k:
            return
        if self._pending is not None:
            self._pending.result()  # the previous slab is written: at most two in memory
        lo, slab = self.n - self._k, self.slab[: self._k]
        self._pending = self._pool.submit(self.z.__setitem__, slice(lo, self.n), slab)
        self.slab = np.empty((self.chunk, *self.shape[1:]), self.dtype)
        self._k = 0

    def __exit__(self, exc_type, *exc):
        try:
            if exc_type is None:
                self._flush()
            if self._pending is not None:
                self._pending.result()
        finally:
            self._pool.shutdown(wait=True)
        return False


def _write_zarr(corrected, out_path: Path, geometry, name, sched, window: int, bar, ngff=None) -> None:
    """Each chunk written into a temporary zarr store by the worker that corrected it; with
    ``ngff`` (the provenance) an OME-Zarr group whose array ``0`` the workers write."""
    import zarr

    from oapcal.io.atomic import atomic_dir

    out_shape = corrected.shape
    n_chunks = len(corrected.chunks[0])
    with atomic_dir(out_path) as tmp:
        try:
            target = str(tmp)
            if ngff is not None:
                from oapcal.io.ome import create_ome_zarr

                create_ome_zarr(tmp, out_shape[0], out_shape[1:], corrected.dtype, geometry.um_per_px, ngff,
                                Path(ngff["source"] or out_path.name).name)  # fmt: skip
                target = str(tmp / "0")
            else:
                from oapcal.io.ome import zarr_compressors

                z = zarr.create_array(
                    str(tmp), shape=out_shape, chunks=(corrected.chunks[0][0], *out_shape[1:]),
                    dtype=corrected.dtype, overwrite=True, compressors=zarr_compressors(),
                )  # fmt: skip
                z.attrs.update(
                    {
                        "oapcal_calibration": name,
                        "um_per_px": geometry.um_per_px,
                        "axes": "TYX" + "C" * (len(out_shape) == 4),
                    }
                )
            drop = list(range(1, corrected.ndim))
            written = corrected.map_blocks(
                _write_zarr_block, target, ngff is not None, dtype=int, chunks=((1,) * n_chunks,),
                drop_axis=drop,
            )  # fmt: skip
            total = 0
            for j in range(0, n_chunks, window):
                counts = written[j : j + window].compute(scheduler=sched)
                total += int(counts.sum())
                bar.advance(int(counts.sum()))
        except BaseException:
            _settle(sched)
            raise
        if total != out_shape[0]:
            raise OutputError(f"{out_path}: {total} of {out_shape[0]} frames were written")


def _write_tiff(
    corrected, out_path: Path, geometry, name, out_bytes: int, sched, window: int, bar, source=None,
    calibration=None,
) -> None:  # fmt: skip
    """Chunks gathered in order, a window at a time, and appended to a temporary TIFF (an
    OME-TIFF when ``out_path`` is named ``.ome.tif``)."""
    from oapcal.io.atomic import atomic_path

    n_frames = corrected.shape[0]
    sizes = corrected.chunks[0]
    n_chunks = len(sizes)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)
    with (
        atomic_path(out_path) as tmp,
        FrameWriter(
            tmp,
            output_kind(out_path),
            name,
            geometry.um_per_px,
            expected_bytes=out_bytes,
            n_frames=n_frames,
            source=source,
            calibration=calibration,
        ) as writer,  # fmt: skip
    ):
        for j in range(0, n_chunks, window):
            last = min(n_chunks - 1, j + window - 1)
            lo, hi = int(starts[j]), int(starts[last] + sizes[last])
            block = corrected[lo:hi].compute(scheduler=sched)
            for frame in block:
                writer.write(frame)
            bar.advance(len(block))
            del block
        if writer.n != n_frames:
            raise OutputError(f"{out_path}: {writer.n} of {n_frames} frames were written")


def _os_error(out_path: Path, exc: OSError) -> OutputError:
    """A failed write (a full disk, lost permissions) as one line naming the output."""
    reason = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
        reason = f"{reason}: the disk is full or the file too large"
    return OutputError(f"{out_path}: cannot be written ({reason}); nothing was written")


def _settle(sched) -> None:
    """After an interruption, let chunks still running on a distributed scheduler finish
    (they write into the temporary store) before it is removed; a few seconds at most."""
    import time

    if isinstance(sched, str):
        return
    with contextlib.suppress(Exception):
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(sched.processing().values()):
            time.sleep(0.1)
