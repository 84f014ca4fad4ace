"""Correct many images and long stacks: expand inputs, plan outputs, loop over frames.

:func:`correct_stack` is the library form of ``oapcal correct``:

* inputs are image files, directories (their image files, not recursive) and glob patterns
  (``**`` recurses);
* each input ``NAME`` is written as ``OUT_DIR/NAME`` in the same format (a multi-page TIFF
  stays one multi-page TIFF, every page of every series corrected), atomically: frames
  stream through a temporary file that is renamed when the file is complete and its frame
  count checked against the input's;
* resume: a record in ``OUT_DIR/.oapcal/`` keeps what each output was made from (digest of
  the calibration and correction settings, input size and mtime, frame count, the output's
  size and mtime); a rerun skips an output only when all of these match, and redoes it
  otherwise (a zero-byte or replaced output, another calibration, a changed input);
  temporary files left by a killed run are removed;
* the output directory must not be, or contain, any input, and no two inputs (nor an input
  and another output such as ``--save-map``) may map to the same output name;
* a corrupt or unreadable input is reported in the result and skipped; the batch goes on.

Frames are read, corrected and written one at a time, so a stack never sits in memory
whole.  One correction map is built per input frame size and reused.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import itertools
import json
import threading
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from oapcal.errors import DataError, InputFileError, OapcalError, OutputError
from oapcal.imaging.remap import (
    CorrectionMap,
    check_map_samples,
    correct_image,
    correction_map,
    mask_untrusted,
    output_geometry,
)
from oapcal.io.atomic import (
    atomic_dir,
    atomic_path,
    check_directory_writable,
    check_free_space,
    check_output_target,
    ensure_not_input,
    file_fingerprint,
    remove_stale_temps,
    resume_complete,
    safe_output_path,
    write_resume_record,
)
from oapcal.io.images import (
    BGR_KINDS,
    IMAGE_SUFFIXES,
    MAX_PIXELS,
    FrameWriter,
    count_frames,
    open_frames,
    output_kind,
    probe,
)
from oapcal.io.ome import OME_TIFF_SUFFIXES, OME_ZARR_SUFFIX
from oapcal.progress import Stages

_GLOB_CHARS = set("*?[")
#: ``output_format`` of :func:`correct_stack`: None keeps each input's format (a video stays
#: a video, an ``.ome.tif`` an OME-TIFF); ``ome-tiff`` writes ``STEM.ome.tif``, ``ome-zarr``
#: ``STEM.ome.zarr`` (NGFF 0.4), ``tiff`` ``STEM.tif``, whatever the input.
OUTPUT_FORMATS = (None, "tiff", "ome-tiff", "ome-zarr")


#: The suffix of a zarr array (a directory), read and written by ``--dask``.
ZARR_SUFFIX = ".zarr"


def output_name(path: str | Path, output_format: str | None = None) -> str:
    """The output name of an input for ``output_format`` (:data:`OUTPUT_FORMATS`).

    >>> [output_name("a/run.avi", f) for f in OUTPUT_FORMATS]
    ['run.avi', 'run.tif', 'run.ome.tif', 'run.ome.zarr']
    >>> output_name("cells.ome.tif", "ome-zarr")
    'cells.ome.zarr'
    """
    if output_format not in OUTPUT_FORMATS:
        raise DataError(
            f"output_format {output_format!r}: use one of {', '.join(str(f) for f in OUTPUT_FORMATS)}",
            param="output_format",
        )
    name = Path(path).name
    if output_format is None:
        return name
    lower = name.lower()
    stem = next((name[: -len(s)] for s in OME_TIFF_SUFFIXES if lower.endswith(s)), Path(name).stem)
    return stem + {"tiff": ".tif", "ome-tiff": ".ome.tif", "ome-zarr": OME_ZARR_SUFFIX}[output_format]


def dask_output_name(input_path: str | Path, output_format: str = "zarr") -> str:
    """The output name of a stack corrected with Dask: ``STEM.zarr``, ``STEM.tif`` or
    ``STEM.ome.zarr``.

    >>> dask_output_name("a/run.ome.tif", "ome-zarr"), dask_output_name("run.tif")
    ('run.ome.zarr', 'run.zarr')
    """
    input_path = Path(input_path)
    if output_format == "ome-zarr":
        return output_name(input_path, "ome-zarr")
    suffix = ZARR_SUFFIX if output_format == "zarr" else ".tif"
    return input_path.name.removesuffix(input_path.suffix) + suffix


@dataclass(frozen=True)
class FileResult:
    """What happened to one input: ``status`` is ``corrected``, ``skipped`` (its complete
    output already existed) or ``failed`` (``message`` says why, ``reason`` is its code, one
    of :data:`FAILURE_REASONS`; ``param`` names the parameter of :func:`correct_stack` that
    the message suggests changing, if any, as :class:`~oapcal.errors.OapcalError` does)."""

    input: str
    output: str | None
    status: str
    frames: int = 0
    message: str = ""
    param: str | tuple[str, ...] | None = None
    reason: str = ""

    @property
    def ok(self) -> bool:
        """Whether the input is done (corrected now or before; docs/conventions.md)."""
        return self.status != "failed"


#: Codes of a failed input (``FileResult.reason``): not found (no such path, a pattern or
#: directory without images), not an image oapcal reads (type, a zarr array without Dask),
#: the file or the correction refused it (an :class:`~oapcal.errors.OapcalError`: bad or
#: changed file, map or geometry), out of memory, and an error of the operating system
#: (disk full, permissions).
FAILURE_REASONS = ("not_found", "unsupported", "refused", "out_of_memory", "os_error")


@dataclass(frozen=True)
class StackReport:
    """Per-input results of :func:`correct_stack` (or
    :func:`oapcal.batch.distributed.correct_stacks_dask`), in input order; ``notes`` what the
    run decided for the user, each once (where a Dask run went)."""

    results: tuple[FileResult, ...]
    geometries: dict = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)

    @property
    def frames(self) -> int:
        return sum(r.frames for r in self.results if r.status == "corrected")

    @property
    def ok(self) -> bool:
        return self.count("failed") == 0

    def summary(self) -> str:
        return (
            f"{self.count('corrected')} corrected ({self.frames} frames), "
            f"{self.count('skipped')} skipped (complete output exists), {self.count('failed')} failed"
        )


def is_zarr_array(path: str | Path) -> bool:
    """Whether the directory ``path`` is a zarr array (its suffix or its metadata file)."""
    path = Path(path)
    return path.is_dir() and (
        path.suffix.lower() == ".zarr" or any((path / marker).exists() for marker in (".zarray", "zarr.json"))
    )


def expand_inputs(
    inputs: Iterable[str], suffixes: Sequence[str] = IMAGE_SUFFIXES
) -> tuple[list[Path], list[FileResult], list[Path]]:
    """Expand files, directories and glob patterns.

    Returns ``(files, failures, directories)``: the image files in order (duplicates
    dropped), a failed :class:`FileResult` for every input that names nothing usable, and
    the directories given (whose images were taken).  Hidden files (``.name``) in
    directories and glob matches are ignored: oapcal's temporary files are hidden.
    """
    files: list[Path] = []
    failures: list[FileResult] = []
    dirs: list[Path] = []
    seen: set[Path] = set()

    def add(path: Path) -> None:
        key = path.resolve()
        if key not in seen:
            seen.add(key)
            files.append(path)

    for text in inputs:
        found, failure, directory = _expand_one(text, suffixes)
        if directory is not None:
            dirs.append(directory)
        if failure is not None:
            failures.append(failure)
        for p in found:
            add(p)
    return files, failures, dirs


def _usable(path: Path, suffixes: Sequence[str]) -> bool:
    """An image file of a type oapcal reads, not hidden."""
    return path.is_file() and path.suffix.lower() in suffixes and not path.name.startswith(".")


def _expand_one(text: str, suffixes: Sequence[str]) -> tuple[list[Path], FileResult | None, Path | None]:
    """One input of :func:`expand_inputs`: the image files it names, in order, the failure
    when it names nothing usable (None: it does) and the directory when it is one."""
    path = Path(text)
    if path.is_dir() and path.suffix.lower() not in suffixes:
        found = sorted(p for p in path.iterdir() if _usable(p, suffixes))
        failure = None
        if not found:
            why = (
                "is a zarr array, which is corrected with Dask (oapcal.batch.distributed.correct_stack_dask)"
                if is_zarr_array(path)
                else ("the directory holds no images")
            )
            reason = "unsupported" if is_zarr_array(path) else "not_found"
            failure = FileResult(text, None, "failed", message=f"{text}: {why}", reason=reason)
        return found, failure, path
    if path.exists():
        if path.suffix.lower() not in suffixes:
            failure = FileResult(
                text,
                None,
                "failed",
                message=f"{text}: unsupported file type {path.suffix or '(no suffix)'!r}; "
                f"oapcal reads {', '.join(suffixes)}",
                reason="unsupported",
            )
            return [], failure, None
        return [path], None, None
    if _GLOB_CHARS & set(text):
        found = sorted(Path(p) for p in glob.glob(text, recursive=True))
        found = [p for p in found if _usable(p, suffixes) or (p.is_dir() and p.suffix.lower() in suffixes)]
        failure = None
        if not found:
            failure = FileResult(
                text,
                None,
                "failed",
                message=f"{text}: the pattern matches no images",
                reason="not_found",
            )  # fmt: skip
        return found, failure, None
    missing = f"{text}: no such file or directory"
    return [], FileResult(text, None, "failed", message=missing, reason="not_found"), None


def plan_outputs(
    files: Sequence[Path],
    out_dir: str | Path,
    dirs: Sequence[Path] = (),
    protect=(),
    *,
    output_name=None,
    reserved: Sequence[tuple[str | Path, str]] = (),
) -> list[Path]:
    """The output path of every input file (``out_dir / output_name(path)``, by default
    ``out_dir / name``), after checking, before any work, that the output directory is not,
    and does not contain, an input (file or directory), that no two inputs map to the same
    output, that no output is a protected file (the calibration) and that no output is one
    of the ``reserved`` ``(path, what)`` outputs (``--save-map``)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: the output directory is an existing file; choose a directory")
    base = out_dir.resolve()
    for d in dirs:
        if d.resolve() == base or d.resolve().is_relative_to(base):
            raise OutputError(
                f"{out_dir}: the output directory is or contains the input directory {d}; "
                "choose an output directory outside the inputs"
            )
    taken = {Path(p).resolve(): what for p, what in reserved if p is not None}
    outputs = []
    names: dict[str, Path] = {}
    for path in files:
        if path.resolve().is_relative_to(base):
            raise OutputError(
                f"{out_dir}: the output directory contains the input {path}; "
                "choose an output directory outside the inputs"
            )
        name = output_name(path) if output_name else path.name
        if name in names:
            raise OutputError(
                f"{path}: the input {names[name]} would be written to the same output "
                f"{out_dir / name}; correct them into separate output directories"
            )
        names[name] = path
        out = safe_output_path(out_dir, name)
        if out.resolve() in taken:
            raise OutputError(
                f"{out}: the output of {path} would be the same file as {taken[out.resolve()]}; "
                "choose another path for it"
            )
        ensure_not_input(out, [*files, *protect])
        check_output_target(out, directory=out.suffix.lower() == ".zarr")
        outputs.append(out)
    return outputs


@dataclass(frozen=True)
class BatchPlan:
    """What a batch will correct (:func:`plan_batch`): the input ``files`` in order, their
    ``outputs``, and a failed :class:`FileResult` for every input that names nothing usable."""

    files: tuple[Path, ...]
    failures: tuple[FileResult, ...]
    outputs: tuple[Path, ...]


def plan_batch(
    inputs: Iterable[str | Path],
    out_dir: str | Path,
    *,
    dask_format: str | None = None,
    output_format: str | None = None,
    protect: Sequence[str | Path] = (),
    reserved: Sequence[tuple[str | Path, str]] = (),
) -> BatchPlan:
    """Expand the inputs and check every output path before any work
    (:func:`expand_inputs`, :func:`plan_outputs`): for :func:`correct_stack` with its
    ``output_format``, or, with ``dask_format`` (:data:`oapcal.batch.distributed.OUTPUT_FORMATS`),
    for the Dask correction (TIFF stacks and zarr arrays, named by
    :func:`dask_output_name`).  Raises
    :class:`~oapcal.errors.OutputError` for two inputs with one output name, an output that
    is an input or a ``protect`` file, and an output that is one of the ``reserved``."""
    from oapcal.io.images import TIFF_SUFFIXES

    if dask_format is not None:
        files, failures, dirs = expand_inputs(
            [str(p) for p in inputs], suffixes=(*TIFF_SUFFIXES, ZARR_SUFFIX)
        )
        naming = lambda p: dask_output_name(p, dask_format)  # noqa: E731
    else:
        files, failures, dirs = expand_inputs([str(p) for p in inputs])
        naming = None if output_format is None else (lambda p: output_name(p, output_format))
    outputs = plan_outputs(files, out_dir, dirs, protect, output_name=naming, reserved=reserved)
    return BatchPlan(tuple(files), tuple(failures), tuple(outputs))


def correction_digest(calibration, cmap: CorrectionMap | None = None, **settings) -> str:
    """A digest of everything that decides a corrected image: the model parameters (or the
    map's values), the output geometry options, interpolation and border value."""
    h = hashlib.sha256()
    if cmap is not None:
        h.update(np.ascontiguousarray(cmap.map_x).tobytes())
        h.update(np.ascontiguousarray(cmap.map_y).tobytes())
        settings["geometry"] = cmap.geometry.to_dict()
    else:
        params = np.asarray(getattr(calibration, "params", calibration), float)
        settings["params"] = [float(v).hex() for v in params]
        settings["calibration_um_per_px"] = getattr(calibration, "um_per_px", None)
        bounds = getattr(calibration, "bounds", None)
        settings["bounds"] = None if bounds is None else [float(v) for v in bounds]
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return h.hexdigest()


class MapCache:
    """One correction map per input frame size, built on first use (thread-safe).

    With a fixed ``cmap`` (a loaded map) every input must have the map's input size.
    ``image_size`` ``(width, height)`` is the calibration's camera size: a frame of another
    size is an error unless ``allow_size_mismatch``.
    """

    def __init__(
        self,
        calibration,
        *,
        cmap: CorrectionMap | None = None,
        image_size=None,
        allow_size_mismatch: bool = False,
        predicted_errors=None,
        **geometry_options,
    ):
        self.calibration = calibration
        self.cmap = cmap
        self.image_size = tuple(image_size) if image_size else None
        self.allow = allow_size_mismatch
        self.options = geometry_options
        self.predicted = dict(predicted_errors or {})
        self._maps: dict[tuple[int, int], CorrectionMap] = {}
        self._checked: set[tuple[int, int]] = set()
        self._lock = threading.Lock()

    def get(self, frame_shape, source) -> CorrectionMap:
        rows, cols = int(frame_shape[0]), int(frame_shape[1])
        if self.image_size and (cols, rows) != self.image_size and not self.allow:
            raise InputFileError(
                f"{source}: image is {cols}x{rows} px but the calibration is for "
                f"{self.image_size[0]}x{self.image_size[1]} px; give allow_size_mismatch=True "
                "to correct it anyway",
                param="allow_size_mismatch",
            )
        if self.cmap is not None:
            shape = self.cmap.input_shape
            if shape and shape != (rows, cols) and not self.allow:
                raise InputFileError(
                    f"{source}: image is {cols}x{rows} px but the map was built for {shape[1]}x{shape[0]} "
                    "px input; build a map for this size or give allow_size_mismatch=True",
                    param="allow_size_mismatch",
                )
            with self._lock:
                if (rows, cols) not in self._checked:  # a map file made for another camera
                    check_map_samples(self.cmap, (rows, cols))
                    self._checked.add((rows, cols))
            return self.cmap
        with self._lock:
            if (rows, cols) not in self._maps:
                self._maps[(rows, cols)] = self._build((rows, cols))
            return self._maps[(rows, cols)]

    def _build(self, shape) -> CorrectionMap:
        """The map for frames of ``shape`` (the size was checked by :meth:`get`); its trust
        region from a predicted error already computed for this size and geometry, if given."""
        seed, limit = self.predicted.get(shape), self.options.get("max_error_px")
        if seed is None or limit is None or not hasattr(self.calibration, "covariance"):
            return correction_map(self.calibration, shape, allow_size_mismatch=True, **self.options)
        options = {k: v for k, v in self.options.items() if k != "max_error_px"}
        geometry, predicted = seed
        # the output is written only where trusted (a fold beyond the landmarks is allowed)
        if output_geometry(self.calibration, shape, **options, trust_region=True) != geometry:
            return correction_map(self.calibration, shape, allow_size_mismatch=True, **self.options)
        cmap = correction_map(self.calibration, shape, allow_size_mismatch=True, geometry=geometry)
        return mask_untrusted(cmap, predicted, limit)  # what correction_map(max_error_px=...) does


@dataclass(frozen=True)
class StackSettings:
    """The options of :func:`correct_stack` as one record (each keyword of
    :func:`correct_stack` is a field of the same name and default).

    ``extent``, ``um_per_px``, ``out_size`` and ``max_error_px`` shape the map built for each
    input frame size (:func:`~oapcal.imaging.remap.correction_map`), unless ``cmap`` is a
    prebuilt map.
    """

    interp: str = "linear"
    border: float = 0
    workers: int = 1
    extent: str = "input"
    um_per_px: float | None = None
    out_size: tuple[int, int] | None = None
    cmap: CorrectionMap | None = None
    allow_size_mismatch: bool = False
    max_pixels: int = MAX_PIXELS
    overwrite: bool = False
    calibration_name: str | None = None
    protect: Sequence[str | Path] = ()
    reserved: Sequence[tuple[str | Path, str]] = ()
    #: ``progress(done, total, description)`` over the frames corrected (:mod:`oapcal.progress`).
    progress: object = None
    output_format: str | None = None
    max_error_px: float | None = None
    #: ``{(rows, cols): (geometry, predicted)}``: predicted-error maps already computed.
    predicted_errors: object = None


def correct_stack(
    calibration,
    inputs: Iterable[str | Path],
    out_dir: str | Path,
    settings: StackSettings | None = None,
    **options,
) -> StackReport:
    """Correct every image and stack of ``inputs`` into ``out_dir`` (see the module doc).

    The options are a :class:`StackSettings` ``settings``, or its fields as keywords (both:
    the keywords replace the settings' fields; an unknown keyword is a ``TypeError``).

    ``calibration`` is a :class:`~oapcal.io.calibration.Calibration` (or a parameter vector);
    the output geometry options are those of :func:`~oapcal.imaging.remap.output_geometry`,
    or ``cmap`` is a prebuilt map.  ``workers`` files are corrected at once (threads;
    OpenCV's remap is itself multi-threaded).  ``protect`` lists further files that no
    output may overwrite, ``reserved`` further outputs ``(path, description)`` no image
    output may coincide with.  ``output_format`` (:data:`OUTPUT_FORMATS`) writes every
    input as OME-TIFF, OME-Zarr or TIFF (:func:`output_name`) instead of its own format;
    video inputs (AVI, MP4, MOV, MKV) stream frame by frame like TIFF stacks and, in their
    own format, are written as video.  ``progress(done, total, description)`` (optional) hears of
    every frame corrected (:mod:`oapcal.progress`).  Raises
    :class:`~oapcal.errors.OutputError` before writing anything when the output directory
    is not allowed; per-file problems are results.  ``max_error_px`` builds each map with
    that trust region (:func:`~oapcal.imaging.remap.correction_map`); ``predicted_errors``
    ``{(rows, cols): (geometry, predicted)}`` are predicted-error maps the caller already
    computed (:func:`~oapcal.imaging.remap.predicted_error_map`), used for frames of that
    size when their output geometry is the same instead of computing them again.
    """
    opts = dataclasses.replace(settings or StackSettings(), **options)
    files, failures, outputs = _prepare_outputs(inputs, out_dir, opts)
    cache = _map_cache(calibration, opts)
    digest = _stack_digest(calibration, opts)
    results, jobs, n_frames = _plan_jobs(files, outputs, digest, opts)
    name = opts.calibration_name or getattr(calibration, "name", None)
    _run_jobs(jobs, results, n_frames, cache, name, opts)
    ordered = tuple(failures) + tuple(results[i] for i in sorted(results))
    geometries = {shape: m.geometry for shape, m in cache._maps.items()}
    return StackReport(ordered, geometries)


def _prepare_outputs(inputs, out_dir, opts: StackSettings):
    """The input files, the failed inputs and each file's output path, checked; the output
    directory made and cleared of a killed run's temporary files."""
    files, failures, dirs = expand_inputs([str(p) for p in inputs])
    output_name(".", opts.output_format)  # an unknown format is refused before any work
    fmt = opts.output_format
    naming = None if fmt is None else (lambda p: output_name(p, fmt))
    outputs = plan_outputs(files, out_dir, dirs, opts.protect, reserved=opts.reserved, output_name=naming)
    check_directory_writable(out_dir)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out_dir, outputs)
    return files, failures, outputs


def _trust_option(opts: StackSettings) -> dict:
    """``max_error_px`` as a keyword when it is set (absent otherwise, as before)."""
    return {} if opts.max_error_px is None else {"max_error_px": opts.max_error_px}


def _map_cache(calibration, opts: StackSettings) -> MapCache:
    return MapCache(
        calibration,
        cmap=opts.cmap,
        image_size=getattr(calibration, "image_size", None),
        allow_size_mismatch=opts.allow_size_mismatch,
        extent=opts.extent,
        um_per_px=opts.um_per_px,
        out_size=opts.out_size,
        predicted_errors=opts.predicted_errors,
        **_trust_option(opts),
    )


def _stack_digest(calibration, opts: StackSettings) -> str:
    """The resume digest of the calibration (or map) and every setting that decides an output."""
    return correction_digest(
        calibration, opts.cmap, interp=opts.interp, border=float(opts.border), extent=opts.extent,
        um_per_px=opts.um_per_px, out_size=None if opts.out_size is None else list(opts.out_size),
        **({} if opts.output_format is None else {"output_format": opts.output_format}),
        **_trust_option(opts),
    )  # fmt: skip


def _plan_jobs(files, outputs, digest: str, opts: StackSettings):
    """Probe each input: ``(results, jobs, n_frames)``, the failed and skipped (complete)
    inputs by index, the ``(i, src, dst, info, record)`` to correct and their frame count."""
    jobs = []
    results: dict[int, FileResult] = {}
    n_frames = 0
    for i, (src, dst) in enumerate(zip(files, outputs)):
        try:
            info = probe(src, opts.max_pixels)
            record = {"calibration": digest, "input": file_fingerprint(src), "frames": info.n_frames}
        except (OapcalError, OSError) as exc:
            results[i] = FileResult(
                str(src), str(dst), "failed", message=str(exc), param=getattr(exc, "param", None),
                reason="refused" if isinstance(exc, OapcalError) else "os_error",
            )  # fmt: skip
            continue
        if dst.exists() and not opts.overwrite and resume_complete(dst, record):
            results[i] = FileResult(str(src), str(dst), "skipped")
            continue
        n_frames += info.n_frames
        jobs.append((i, src, dst, info, record))
    return results, jobs, n_frames


def _run_jobs(jobs, results: dict, n_frames: int, cache: MapCache, name, opts: StackSettings) -> None:
    """Correct the ``jobs`` (``opts.workers`` files at once), their results into ``results``."""

    def run(job):
        i, src, dst, info, record = job
        results[i] = _correct_file(src, dst, info, record, cache, opts.interp, opts.border, name, bar)
        bar.stage(f"files {next(finished)}/{len(jobs)}")  # next() of a count: atomic under the GIL

    finished = itertools.count(1)
    with Stages(opts.progress if jobs else None, n_frames, f"files 0/{len(jobs)}") as bar:
        if opts.workers > 1 and len(jobs) > 1:
            with ThreadPoolExecutor(max_workers=opts.workers) as pool:
                list(pool.map(run, jobs))
        else:
            for job in jobs:
                run(job)


def _correct_file(src: Path, dst: Path, info, record, cache, interp, border, name, bar) -> FileResult:
    n = 0
    try:
        with open_frames(src, info=info) as (info, frames):
            cmap = cache.get(info.frame_shape, src)
            pixels_in = info.frame_shape[0] * info.frame_shape[1]
            out_bytes = info.n_frames * info.frame_bytes * cmap.shape[0] * cmap.shape[1] // pixels_in
            kind = output_kind(dst)
            meta = dict(
                planar=info.planar and kind == "tiff", expected_bytes=out_bytes, n_frames=info.n_frames,
                source=src.name, fps=info.fps, bgr=info.kind in BGR_KINDS, calibration=cache.calibration,
            )  # fmt: skip
            if kind in ("tiff", "ome-tiff"):  # uncompressed: the size is known; PNG etc. compress
                check_free_space(dst.parent, out_bytes, dst)
            # cleaned for the whole batch
            temporary = atomic_dir(dst) if kind == "ome-zarr" else atomic_path(dst, clean=False)
            with temporary as tmp:
                with FrameWriter(tmp, kind, name, cmap.geometry.um_per_px, **meta) as writer:
                    out = None
                    for frame in frames:
                        out = correct_image(
                            frame, cmap, interp, border, out=out, allow_size_mismatch=cache.allow
                        )
                        writer.write(out.reshape(cmap.shape + frame.shape[2:]))
                        n += 1
                        bar.advance()
                written = count_frames(tmp)
                # a video's header count is the container's estimate (exact for AVI, checked on reading)
                expected = n if info.kind == "video" and kind == "video" else info.n_frames
                if n != expected or written != expected:
                    raise InputFileError(
                        f"{src}: {info.n_frames} frames were expected but {n} were read and {written} "
                        "written; the input may have changed while it was corrected; nothing was written"
                    )
            write_resume_record(dst, record)
    except OapcalError as exc:
        message = str(exc)
        if not message.startswith(str(src)):  # map and geometry errors do not know the file
            message = f"{src}: {message}"
        return FileResult(str(src), str(dst), "failed", n, message, exc.param, "refused")
    except MemoryError:
        return FileResult(str(src), str(dst), "failed", n,
                          f"{src}: not enough memory to correct it; free memory or correct fewer files at "
                          "once (fewer workers)", "workers", "out_of_memory")  # fmt: skip
    except OSError as exc:
        return FileResult(str(src), str(dst), "failed", n, _os_message(src, dst, exc), reason="os_error")
    return FileResult(str(src), str(dst), "corrected", n)


def _os_message(src: Path, dst: Path, exc: OSError) -> str:
    """One line for a failed read or write, naming the user's file (not a temporary one)."""
    import errno

    reason = exc.strerror or str(exc)
    if exc.filename is not None and Path(exc.filename) == Path(src):
        return f"{src}: cannot be read ({reason})"
    if exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
        reason = f"{reason}: the disk is full or the file too large"
    return f"{dst}: cannot be written ({reason}); nothing was written"


def correct_frames(
    frames: np.ndarray,
    cmap: CorrectionMap,
    interp: str = "linear",
    border: float = 0,
    *,
    allow_size_mismatch: bool = False,
) -> np.ndarray:
    """Correct an in-memory stack ``(frames, rows, cols[, ch])`` with one map (each frame
    checked as :func:`~oapcal.imaging.remap.correct_image` checks an image)."""
    frames = np.asarray(frames)
    if frames.ndim not in (3, 4):
        raise DataError(f"a stack must be (frames, rows, cols[, ch]), got shape {frames.shape}")
    out = np.empty((len(frames), *cmap.shape, *frames.shape[3:]), frames.dtype)
    for i, frame in enumerate(frames):
        corrected = correct_image(frame, cmap, interp, border, allow_size_mismatch=allow_size_mismatch)
        out[i] = corrected.reshape(out.shape[1:])
    return out
