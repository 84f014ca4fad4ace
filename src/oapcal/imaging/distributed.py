"""Correct stacks too big for memory with Dask: lazy reads, chunks of frames, bounded memory.

:func:`correct_stack_dask` reads a multi-page TIFF or a zarr array lazily as a Dask array
chunked along frames (``chunk_frames`` frames per chunk), corrects each chunk with
``map_blocks`` and writes a zarr array (each chunk written by the worker that corrected
it) or a multi-page TIFF (chunks gathered in order and appended).  It runs on a
``dask.distributed`` ``LocalCluster`` by default, on an existing scheduler given its
address, or on Dask's local ``threads`` / ``synchronous`` schedulers.

Memory stays bounded however long the stack is: chunks are computed a window at a time
(a few per worker), and nothing keeps a reference to finished chunks.  Workers build the
correction map themselves from the parameters and the output geometry (cached per
process), so the task graph stays small; with a map file they load it (workers must see
the file).  Workers must also see the input and output paths (a shared file system).
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError, OutputError
from oapcal.imaging.remap import CorrectionMap, OutputGeometry, correct_image, correction_map, load_map
from oapcal.io.images import MAX_PIXELS, TIFF_SUFFIXES, FrameWriter, check_frame, probe

ZARR_SUFFIX = ".zarr"
LOCAL_SCHEDULERS = ("threads", "synchronous", "processes")


@dataclass(frozen=True)
class DaskResult:
    """``frames`` corrected from ``input`` into ``output`` (``skipped`` if it existed)."""

    input: str
    output: str
    frames: int
    chunks: int
    skipped: bool = False


# ------------------------------------------------------------------------ lazy input


def _read_tiff_frames(
    path: str, start: int, stop: int, frame_shape: tuple[int, ...], layout: tuple
) -> np.ndarray:
    """Frames ``start:stop`` of a TIFF stack: straight from the file when its pixel data are
    one contiguous uncompressed block (what cameras and tifffile write), else page by page."""
    offset, dtype = layout
    if offset is not None:
        frame_size = int(np.prod(frame_shape))
        count = (stop - start) * frame_size
        data = np.fromfile(
            path,
            dtype=np.dtype(dtype),
            count=count,
            offset=offset + start * frame_size * np.dtype(dtype).itemsize,
        )
        if data.size != count:
            raise InputFileError(f"{path}: the file is truncated (frames {start}-{stop - 1} are missing)")
        return data.reshape((stop - start, *frame_shape)).astype(
            np.dtype(dtype).newbyteorder("="), copy=False
        )
    import tifffile

    with tifffile.TiffFile(path) as tif:
        pages = tif.series[0].pages
        return np.stack([pages[i].asarray().reshape(frame_shape) for i in range(start, stop)])


def lazy_stack(path: str | Path, chunk_frames: int = 16, max_pixels: int = MAX_PIXELS):
    """A Dask array ``(frames, rows, cols[, ch])`` over a TIFF stack or zarr array, one
    chunk per ``chunk_frames`` frames; nothing is read until it is computed."""
    from oapcal.extras import require

    dask = require("dask")
    da = require("dask.array")
    require("zarr")

    path = Path(path)
    if chunk_frames < 1:
        raise InputFileError(f"{path}: --chunk-frames must be at least 1, got {chunk_frames}")
    if path.suffix.lower() == ZARR_SUFFIX:
        import zarr

        try:
            z = zarr.open_array(str(path), mode="r")
        except Exception as exc:  # zarr raises several types for a missing or bad store
            raise InputFileError(
                f"{path}: cannot be opened as a zarr array ({type(exc).__name__}: {exc})"
            ) from None
        if z.ndim == 2:
            arr = da.from_zarr(z)[None]
        elif z.ndim in (3, 4):
            arr = da.from_zarr(z)
        else:
            raise InputFileError(
                f"{path}: a zarr stack must be (frames, rows, cols[, ch]), got shape {z.shape}"
            )
        if arr.shape[1] * arr.shape[2] > max_pixels:
            raise InputFileError(
                f"{path}: frames of {arr.shape[2]}x{arr.shape[1]} px exceed --max-pixels {max_pixels}"
            )
        check_frame(path, np.empty((1, 1) + arr.shape[3:], arr.dtype))
        return arr.rechunk({0: chunk_frames, 1: -1, 2: -1})
    if path.suffix.lower() not in TIFF_SUFFIXES:
        raise InputFileError(f"{path}: --dask reads TIFF stacks and zarr arrays ({ZARR_SUFFIX} directories)")
    info = probe(path, max_pixels)
    import tifffile

    with tifffile.TiffFile(path) as tif:
        series = tif.series[0]
        if len(series.pages) != info.n_frames:
            raise InputFileError(f"{path}: --dask needs one frame per TIFF page; correct it without --dask")
        offset = series.dataoffset
        layout = (offset, tif.byteorder + np.dtype(series.dtype).str[1:])
    check_frame(path, np.empty((1, 1) + info.frame_shape[2:], info.dtype))
    blocks = []
    for start in range(0, info.n_frames, chunk_frames):
        stop = min(info.n_frames, start + chunk_frames)
        task = dask.delayed(_read_tiff_frames, pure=True)(str(path), start, stop, info.frame_shape, layout)
        blocks.append(da.from_delayed(task, (stop - start, *info.frame_shape), dtype=info.dtype))
    return da.concatenate(blocks, axis=0)


# ----------------------------------------------------------------- the work per chunk


@functools.lru_cache(maxsize=8)
def _worker_map(source: tuple) -> CorrectionMap:
    """The map, built (or loaded) once per worker process and reused for every chunk."""
    if source[0] == "file":
        return load_map(source[1])
    _, params, shape, x0, y0, scale, um = source
    geometry = OutputGeometry(shape, x0, y0, scale, um)
    return correction_map(np.array(params), shape, geometry=geometry)


def _correct_block(block: np.ndarray, source: tuple, interp: str, border: float) -> np.ndarray:
    cmap = _worker_map(source)
    out = np.empty((block.shape[0], *cmap.shape, *block.shape[3:]), block.dtype)
    for i, frame in enumerate(block):
        out[i] = correct_image(frame, cmap, interp, border).reshape(out.shape[1:])
    return out


def _write_zarr_block(block: np.ndarray, path: str, block_info=None) -> np.ndarray:
    """Write one corrected chunk into the zarr array at ``path``; return its frame count."""
    import zarr

    start = block_info[0]["array-location"][0][0]
    z = zarr.open_array(path, mode="r+")
    z[start : start + len(block)] = block
    return np.array([len(block)])


# ------------------------------------------------------------------------ schedulers


@contextlib.contextmanager
def dask_scheduler(scheduler: str | None = None, workers: int | None = None):
    """Yield what ``dask.compute(..., scheduler=...)`` takes, and the number of chunks to
    keep in flight: a new ``LocalCluster`` (default), a ``Client`` of the scheduler at an
    address (``tcp://host:8786``), or a local scheduler name (threads, synchronous,
    processes)."""
    if scheduler in LOCAL_SCHEDULERS:
        yield scheduler, max(2, workers or os.cpu_count() or 1)
        return
    from oapcal.extras import require

    require("distributed")
    from distributed import Client, LocalCluster

    if scheduler is None:
        n = workers or 1
        with LocalCluster(n_workers=n, threads_per_worker=1, dashboard_address=None) as cluster:
            with Client(cluster) as client:
                yield client, 2 * n
        return
    try:
        client = Client(scheduler, timeout="10s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputFileError(f"--scheduler {scheduler}: cannot connect to a Dask scheduler ({exc})") from None
    with client:
        n_threads = sum(client.nthreads().values()) or 1
        yield client, 2 * n_threads


# ---------------------------------------------------------------------- the pipeline


def correct_stack_dask(
    calibration,
    input_path: str | Path,
    out_dir: str | Path,
    *,
    output_format: str = "zarr",
    chunk_frames: int = 16,
    interp: str = "linear",
    border: float = 0,
    extent: str = "input",
    um_per_px: float | None = None,
    out_size: tuple[int, int] | None = None,
    map_path: str | Path | None = None,
    allow_size_mismatch: bool = False,
    max_pixels: int = MAX_PIXELS,
    scheduler: str | None = None,
    workers: int | None = None,
    calibration_name: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> DaskResult:
    """Correct one TIFF or zarr stack with Dask into ``out_dir/STEM.zarr`` (or ``.tif``).

    The output appears atomically (written under a temporary name, then renamed); an
    existing output is skipped unless ``overwrite``.  Output arrays are chunked like the
    input (``chunk_frames`` frames) and carry the calibration's name and the pixel size
    (zarr attributes ``oapcal_calibration``, ``um_per_px``; TIFF metadata).
    """
    input_path = Path(input_path)
    if output_format not in ("zarr", "tiff"):
        raise OutputError(f"unknown output format {output_format!r}: use zarr or tiff")
    suffix = ZARR_SUFFIX if output_format == "zarr" else ".tif"
    out_dir = Path(out_dir)
    out_path = out_dir / (input_path.name.removesuffix(input_path.suffix) + suffix)
    if out_path.resolve() == input_path.resolve():
        raise OutputError(
            f"{out_path}: the output would overwrite the input {input_path}; choose another --out-dir"
        )
    stack = lazy_stack(input_path, chunk_frames, max_pixels)
    if out_path.exists() and not overwrite:
        return DaskResult(str(input_path), str(out_path), 0, 0, skipped=True)
    rows, cols = stack.shape[1:3]
    cal_size = getattr(calibration, "image_size", None)
    if cal_size and tuple(cal_size) != (cols, rows) and not allow_size_mismatch:
        raise InputFileError(
            f"{input_path}: frames are {cols}x{rows} px but the calibration is for "
            f"{cal_size[0]}x{cal_size[1]} px; give --allow-size-mismatch to correct them anyway"
        )
    if map_path is not None:
        cmap = load_map(map_path)
        if cmap.input_shape and cmap.input_shape != (rows, cols) and not allow_size_mismatch:
            raise InputFileError(
                f"{input_path}: frames are {cols}x{rows} px but the map {map_path} was built for "
                f"{cmap.input_shape[1]}x{cmap.input_shape[0]} px input"
            )
        source = ("file", str(Path(map_path).resolve()))
        geometry = cmap.geometry
    else:
        params = np.asarray(getattr(calibration, "params", calibration), float)
        geometry = correction_map(
            calibration, (rows, cols), extent=extent, um_per_px=um_per_px, out_size=out_size, geometry=None
        ).geometry
        source = (
            "params",
            tuple(float(v) for v in params),
            geometry.shape,
            geometry.x0,
            geometry.y0,
            geometry.scale,
            geometry.um_per_px,
        )
    out_shape = (stack.shape[0], *geometry.shape, *stack.shape[3:])
    corrected = stack.map_blocks(
        _correct_block,
        source,
        interp,
        border,
        dtype=stack.dtype,
        chunks=(stack.chunks[0], (geometry.shape[0],), (geometry.shape[1],), *stack.chunks[3:]),
    )
    name = calibration_name or getattr(calibration, "name", None)
    starts = np.concatenate([[0], np.cumsum(stack.chunks[0])[:-1]]).astype(int)
    n_chunks = len(starts)
    out_dir.mkdir(parents=True, exist_ok=True)
    bar = _bar(progress, n_chunks, out_shape[0], input_path.name)
    with dask_scheduler(scheduler, workers) as (sched, window), bar:
        if output_format == "zarr":
            import zarr

            tmp = tempfile.mkdtemp(prefix=f".{out_path.name}.", suffix=".tmp", dir=out_dir)
            try:
                z = zarr.create_array(
                    tmp,
                    shape=out_shape,
                    chunks=(chunk_frames, *out_shape[1:]),
                    dtype=stack.dtype,
                    overwrite=True,
                )
                z.attrs.update(
                    {
                        "oapcal_calibration": name,
                        "um_per_px": geometry.um_per_px,
                        "axes": "TYX" + "C" * (len(out_shape) == 4),
                    }
                )
                drop = list(range(1, corrected.ndim))
                written = corrected.map_blocks(
                    _write_zarr_block, tmp, dtype=int, chunks=((1,) * n_chunks,), drop_axis=drop
                )
                for j in range(0, n_chunks, window):
                    counts = written[j : j + window].compute(scheduler=sched)
                    bar.advance(len(counts), int(counts.sum()))
                if out_path.exists():
                    shutil.rmtree(out_path)
                os.replace(tmp, out_path)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        else:
            from oapcal.io.atomic import atomic_path

            with atomic_path(out_path) as tmp, FrameWriter(tmp, "tiff", name, geometry.um_per_px) as writer:
                for j in range(0, n_chunks, window):
                    lo, hi = (
                        int(starts[j]),
                        int(
                            starts[min(n_chunks - 1, j + window - 1)]
                            + corrected.chunks[0][min(n_chunks - 1, j + window - 1)]
                        ),
                    )
                    block = corrected[lo:hi].compute(scheduler=sched)
                    for frame in block:
                        writer.write(frame)
                    bar.advance(min(window, n_chunks - j), len(block))
                    del block
    return DaskResult(str(input_path), str(out_path), out_shape[0], n_chunks)


class _NoBar:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def advance(self, chunks, frames):
        pass


class _RichBar(_NoBar):
    def __init__(self, n_chunks, n_frames, label):
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.bar = Progress(
            TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
            console=Console(stderr=True),
        )  # fmt: skip
        self.frames = self.bar.add_task(f"{label} frames", total=n_frames)

    def __enter__(self):
        self.bar.start()
        return self

    def __exit__(self, *exc):
        self.bar.stop()
        return False

    def advance(self, chunks, frames):
        self.bar.advance(self.frames, frames)


def _bar(enabled, n_chunks, n_frames, label):
    return _RichBar(n_chunks, n_frames, label) if enabled else _NoBar()
