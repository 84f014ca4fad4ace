"""Helpers shared by the commands: point-file input, output checks, printing.

Imports nothing heavy at module level (see :mod:`oapcal.cli`).
"""

from __future__ import annotations

import contextlib
import functools
import json
import re
import sys
from dataclasses import dataclass

import click

from oapcal.cli._design_flags import DESIGN_OPTIONS

#: Characters that must not reach a terminal raw: C0 and C1 controls (escape sequences can
#: set the title, move the cursor, rewrite the screen), DEL, and Unicode line separators and
#: bidirectional overrides (which can make text read differently than it is).
_UNSAFE = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")


def sanitize(text) -> str:
    r"""``text`` with every character unsafe for a terminal written as a Python escape, so a
    landmark label or file name from a hostile file prints as visible text on one line.

    >>> print(sanitize("corner\x1b]0;pwned\x07 1\n"))
    corner\x1b]0;pwned\x07 1\n
    """
    return _UNSAFE.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), str(text))


def flag_hint(command, param) -> str:
    """`` (set by --flag)`` for the options of ``command`` whose Python names are ``param``
    (a name or a tuple of names, as :class:`oapcal.errors.OapcalError` ``.param``); ``""``
    when the command has none of them.

    >>> @click.command()
    ... @click.option("--um-per-px", type=float)
    ... @click.option("--out-size")
    ... def cmd(um_per_px, out_size): ...
    >>> flag_hint(cmd, ("out_size", "extent", "um_per_px"))
    ' (set by --out-size, --um-per-px)'
    """
    names = (param,) if isinstance(param, str) else tuple(param or ())
    names = tuple(n for name in names for n in (DESIGN_OPTIONS if name == "design" else (name,)))
    options = {p.name: p for p in getattr(command, "params", []) if isinstance(p, click.Option)}
    flags = []
    for name in names:
        option = options.get(name)
        if option is not None:
            flags.append(option.opts[-1] if option.opts[-1].startswith("--") else option.opts[0])
    return f" (set by {', '.join(flags)})" if flags else ""


def with_flag_hint(message: str, param) -> str:
    """``message`` with the flags of the running command that set ``param`` (:func:`flag_hint`)."""
    ctx = click.get_current_context(silent=True)
    return message + (flag_hint(ctx.command, param) if ctx is not None else "")


def markup_safe(text) -> str:
    """:func:`sanitize` and escape Rich markup (``[bold]`` in a file name prints as is)."""
    from rich.markup import escape

    return escape(sanitize(text))


class PointsUsageError(click.ClickException):
    """A one-line usage error (exit 2) about how point data were given."""

    exit_code = 2

    def show(self, file=None):
        click.echo(f"oapcal: error: {sanitize(self.format_message())}", err=True)


# One declaration per kind of option; each command gives its flag, Python name and help.


def file_option(*decls: str, help: str, dash: bool = False, required: bool = False):
    """An option naming a file (``click.Path(dir_okay=False)``; ``dash``: ``-`` means
    stdin/stdout), ``required`` or else None by default."""
    given = {"required": True} if required else {"default": None}
    return click.option(*decls, type=click.Path(dir_okay=False, allow_dash=dash), **given, help=help)


def out_option(help: str, *, required: bool = True, dash: bool = True):
    """``--out FILE`` (Python name ``out``)."""
    return file_option("--out", "out", help=help, dash=dash, required=required)


def json_option(help: str = "Print one JSON object instead of tables."):
    """The ``--json`` flag (Python name ``as_json``)."""
    return click.option("--json", "as_json", is_flag=True, help=help)


def positive_option(*decls: str, help: str, **given):
    """A positive number (``FloatRange(min=0, min_open=True)``), None by default."""
    given.setdefault("default", None)
    return click.option(*decls, type=click.FloatRange(min=0, min_open=True), **given, help=help)


def count_option(*decls: str, help: str, least: int, default: int):
    """A whole number of at least ``least`` (``IntRange(min=least)``), its default shown."""
    return click.option(*decls, type=click.IntRange(min=least), default=default, show_default=True, help=help)


def range_option(*decls: str, type, default, help: str):
    """A number within the bounds of ``type`` (``click.IntRange``, ``click.FloatRange``),
    its default shown."""
    return click.option(*decls, type=type, default=default, show_default=True, help=help)


def choice_option(*decls: str, choices, default, help: str):
    """One of ``choices`` (``click.Choice``), its default shown."""
    return click.option(*decls, type=click.Choice(choices), default=default, show_default=True, help=help)


def flag_option(*decls: str, help: str):
    """An on/off flag, off by default."""
    return click.option(*decls, is_flag=True, help=help)


#: ``--init`` of ``fit`` and ``select``.
INIT_HELP = (
    "Starting values: 'auto' (default: the data's own centre, scale and turn; a fit also "
    "tries the next two and keeps the best), 'zero' (all 0, m = 1; the paper's choice for "
    "normalized data), 'pixel' (the paper's pixel-scale guesses), or name=value pairs such "
    "as 'k1=1e-6,m=1'."
)


#: ``correct``, ``correct-points`` and ``export-opencv``: use a calibration whose fit did not
#: converge (written by ``oapcal fit --keep-unconverged``).
allow_unconverged_option = click.option(
    "--allow-unconverged",
    is_flag=True,
    help="Use the calibration even though its fit did not converge (refused by default).",
)


def load_usable_calibration(path: str, allow_unconverged: bool = False):
    """The calibration in ``path`` (:func:`oapcal.io.calibration.load_calibration`), refused
    (exit 2, one line) when its fit did not converge unless ``allow_unconverged``."""
    from oapcal.io.calibration import load_calibration

    cal = load_calibration(path)
    if not cal.fit.converged and not allow_unconverged:
        why = cal.fit.message.removeprefix("not converged: ") or "not converged"
        raise PointsUsageError(
            f"{path}: the calibration's fit did not converge ({why}), so its correction is not "
            "reliable; refit it (oapcal fit), or give --allow-unconverged to use it anyway"
        )
    return cal


@dataclass(frozen=True)
class PointsSource:
    """Where a command's point pairs come from: a point-pair CSV (``points``) or a
    distorted and a reference landmark file (``distorted``, ``reference``) with the options
    that read and pair them (:func:`oapcal.io.landmarks.read_landmark_pairs`)."""

    points: str | None = None
    distorted: str | None = None
    reference: str | None = None
    fmt: str = "auto"
    pair_by: str | None = None
    pair_by_order: bool = False
    distorted_image: str | None = None
    reference_image: str | None = None
    x_column: str = "x"
    y_column: str = "y"
    pixel_origin: str = "center"

    @property
    def paths(self) -> tuple[str, ...]:
        """The input files (for output checks)."""
        return tuple(p for p in (self.points, self.distorted, self.reference) if p is not None)

    def __str__(self) -> str:
        if self.points is not None:
            return self.points
        return " + ".join(self.paths)


_LANDMARK_DEFAULTS = {
    "distorted": None, "reference": None, "landmark_format": "auto", "pair_by": None,
    "pair_by_order": False, "distorted_image": None, "reference_image": None,
    "x_column": "x", "y_column": "y", "pixel_origin": "center",
}  # fmt: skip


def _landmark_decorators():
    path = click.Path(dir_okay=False, allow_dash=True)
    return [
        click.option("--distorted", type=path, default=None,
                     help="Landmarks labelled on the distorted (camera) image, instead of POINTS."),
        click.option("--reference", type=path, default=None,
                     help="Landmarks of the reference image (not needed for a BigWarp file, or a "
                     "VIA file holding both images)."),
        click.option("--format", "landmark_format", default="auto", show_default=True,
                     type=click.Choice(["auto", "csv", "via", "napari", "bigwarp"]),
                     help="Landmark file format; 'auto' detects it from the content."),
        click.option("--pair-by", "pair_by", metavar="ATTR", default=None,
                     help="Pair landmarks by this attribute / column (e.g. a corner id)."),
        click.option("--pair-by-order", is_flag=True, default=False,
                     help="Pair landmarks by their order in the two files."),
        click.option("--distorted-image", metavar="NAME", default=None,
                     help="VIA: the image whose regions are the distorted landmarks."),
        click.option("--reference-image", metavar="NAME", default=None,
                     help="VIA: the image whose regions are the reference landmarks."),
        click.option("--x-column", default="x", show_default=True,
                     help="Plain CSV/TSV landmarks: the x (column) coordinate's column."),
        click.option("--y-column", default="y", show_default=True,
                     help="Plain CSV/TSV landmarks: the y (row) coordinate's column."),
        click.option("--pixel-origin", type=click.Choice(["center", "corner"]), default="center",
                     show_default=True,
                     help="Plain CSV/TSV landmarks: 'corner' if the top-left pixel's centre is at "
                     "(0.5, 0.5) (e.g. ImageJ measurements)."),
    ]  # fmt: skip


def _source(points, options: dict) -> PointsSource:
    given = {k: v for k, v in options.items() if v != _LANDMARK_DEFAULTS[k]}
    if points is not None and options["distorted"] is not None:
        raise PointsUsageError("give either POINTS or --distorted/--reference landmark files, not both")
    if points is None and options["distorted"] is None:
        if options["reference"] is not None:
            raise PointsUsageError("--reference needs --distorted FILE too")
        raise PointsUsageError(
            "give a point-pair file POINTS, or landmark files --distorted FILE --reference FILE"
        )
    if points is not None and given:
        flag = "--" + next(iter(given)).replace("landmark_format", "format").replace("_", "-")
        raise PointsUsageError(f"{flag} applies to --distorted/--reference landmark files, not to POINTS")
    if options["pair_by"] is not None and options["pair_by_order"]:
        raise PointsUsageError("give either --pair-by ATTR or --pair-by-order, not both")
    return PointsSource(
        points=points, distorted=options["distorted"], reference=options["reference"],
        fmt=options["landmark_format"], pair_by=options["pair_by"], pair_by_order=options["pair_by_order"],
        distorted_image=options["distorted_image"], reference_image=options["reference_image"],
        x_column=options["x_column"], y_column=options["y_column"], pixel_origin=options["pixel_origin"],
    )  # fmt: skip


def points_options(func):
    """Point-pair input shared by commands: a ``POINTS`` file, or ``--distorted`` and
    ``--reference`` landmark files with ``--format``, ``--pair-by``, ... (exactly one of the
    two ways).  The command receives one :class:`PointsSource` as ``points``; give it to
    :func:`load_pairs` and :func:`check_output`."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        points = kwargs.pop("points")
        options = {k: kwargs.pop(k) for k in _LANDMARK_DEFAULTS}
        return func(*args, points=_source(points, options), **kwargs)

    for decorate in reversed(_landmark_decorators()):
        wrapper = decorate(wrapper)
    return click.argument("points", required=False, type=click.Path(dir_okay=False, allow_dash=True))(wrapper)


def landmark_options(func):
    """``--distorted/--reference/--format/--pair-by/...`` (no ``POINTS``), given to the
    command as one :class:`PointsSource` named ``source``."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        options = {k: kwargs.pop(k) for k in _LANDMARK_DEFAULTS}
        if options["distorted"] is None:
            raise PointsUsageError("give the landmark files: --distorted FILE [--reference FILE]")
        return func(*args, source=_source(None, options), **kwargs)

    for decorate in reversed(_landmark_decorators()):
        wrapper = decorate(wrapper)
    return wrapper


def load_pairs(points, require=("x_u", "y_u", "x_d", "y_d")):
    """Read point pairs given on the command line: a POINTS path or a :class:`PointsSource`
    (see :func:`oapcal.io.points.read_points`, :func:`oapcal.io.landmarks.read_landmark_pairs`).
    What was read but not used (unpaired landmarks, ...) is reported on stderr."""
    from oapcal.io.points import read_points

    if isinstance(points, PointsSource) and points.points is not None:
        points = points.points
    if not isinstance(points, PointsSource):
        return read_points(points, require=require)
    from oapcal.io.landmarks import read_landmark_pairs

    pairs = read_landmark_pairs(
        points.distorted, points.reference, fmt=points.fmt, pair_by=points.pair_by,
        pair_by_order=points.pair_by_order, distorted_image=points.distorted_image,
        reference_image=points.reference_image, x_column=points.x_column, y_column=points.y_column,
        origin=points.pixel_origin, require=tuple(require),
    )  # fmt: skip
    for line in pairs.warnings:
        click.echo(f"oapcal: warning: {sanitize(line)}", err=True)
    return pairs


def check_output(out: str | None, *inputs) -> None:
    """Refuse, before any work, an output path that would overwrite one of the inputs, whose
    directory does not exist, or in which no file can be created (permissions, a read-only
    file system: tried by creating and removing an empty temporary file)."""
    if out is None or out == "-":
        return
    from oapcal.io.atomic import ensure_not_input

    paths = []
    for item in inputs:
        paths.extend(item.paths if isinstance(item, PointsSource) else [item])
    ensure_not_input(out, paths)
    check_writable(out)


def check_writable(out) -> None:
    """Raise :class:`~oapcal.errors.OutputError` naming ``out`` unless a file can be created
    in its directory, and ``out`` is not a directory nor a FIFO, socket or device
    (:func:`oapcal.io.atomic.check_output_target`)."""
    import errno
    import os
    import tempfile
    from pathlib import Path

    from oapcal.errors import OutputError
    from oapcal.io.atomic import check_output_target

    path = Path(out)
    directory = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise OutputError(f"{out}: is a directory; give a file name for this output")
    check_output_target(path)
    if not directory.is_dir():
        what = "is not a directory" if directory.exists() else "does not exist; create it first"
        raise OutputError(f"{out}: the output directory {directory} {what}")
    if len(os.fsencode(path.name)) > 255:
        raise OutputError(f"{out}: the file name is longer than 255 bytes; choose a shorter name")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".oapcal-", suffix=".probe", dir=directory)
    except OSError as exc:
        hint = "the file system is read-only" if exc.errno == errno.EROFS else "check its permissions"
        raise OutputError(
            f"{out}: cannot create files in {directory} ({exc.strerror}); {hint} or choose another place"
        ) from None
    os.close(fd)
    os.unlink(tmp)


class OutputSet:
    """Several outputs of one command written all or nothing.

    ``stage(path)`` gives a hidden temporary name beside ``path`` (same suffix, so writers
    pick the format) for a writer to write to; when the ``with`` block ends without error
    every staged file is renamed to its destination, else all are removed and no destination
    is touched.  ``-`` (stdout) and None pass through.

    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> try:
    ...     with OutputSet() as outputs:
    ...         _ = outputs.stage(d / "a.csv").write_text("a")
    ...         raise ValueError("the second output failed")
    ... except ValueError:
    ...     pass
    >>> sorted(p.name for p in d.iterdir())
    []
    """

    def __init__(self):
        self._staged: list[tuple[object, object]] = []

    def stage(self, path):
        import os
        import tempfile
        from pathlib import Path

        from oapcal.io.atomic import check_output_target

        if path is None or str(path) == "-":
            return path
        dest = Path(path)
        check_output_target(dest)
        directory = dest.parent if str(dest.parent) else Path(".")
        fd, tmp = tempfile.mkstemp(prefix=".oapcal-", suffix=f".stage{dest.suffix}", dir=directory)
        os.close(fd)
        os.unlink(tmp)  # the writer creates it (some refuse an existing file)
        self._staged.append((Path(tmp), dest))
        return Path(tmp)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        import contextlib
        import errno
        import os

        from oapcal.io.atomic import check_output_target

        if exc_type is None:
            try:
                for _, dest in self._staged:  # none renamed unless all may be
                    check_output_target(dest)
            except BaseException:
                for tmp, _ in self._staged:
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(tmp)
                raise
            for tmp, dest in self._staged:
                os.replace(tmp, dest)
            return False
        for tmp, _ in self._staged:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is not None:
            name = os.path.basename(os.fsdecode(exc.filename))
            for tmp, dest in self._staged:  # name the user's file, not the staged one
                if tmp.stem in name:
                    raise OSError(exc.errno, exc.strerror, str(dest)) from None
        if (
            isinstance(exc, OSError)
            and exc.filename is None
            and exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)
            and self._staged
        ):  # a full disk or a size limit while writing one of them: name them, not stdout
            names = " or ".join(str(dest) for _, dest in self._staged)
            raise OSError(exc.errno, exc.strerror or os.strerror(exc.errno), names) from None
        return False


def check_plot_suffix(path, option: str = "--plot", allowed=None) -> None:
    """Refuse, before any work, a figure file name whose suffix Matplotlib cannot write."""
    from pathlib import Path

    if path is None:
        return
    allowed = allowed or ("png", "pdf", "svg", "jpg", "jpeg", "tif", "tiff", "eps", "ps", "webp")
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in allowed:
        raise click.BadParameter(
            f"{str(path)!r}: unsupported figure type {('.' + suffix) if suffix else '(no suffix)'}; "
            f"use one of {', '.join('.' + a for a in allowed)}",
            param_hint=option,
        )


def print_json(obj) -> None:
    """Print one JSON object on stdout."""
    from oapcal.io.jsonfile import json_safe

    sys.stdout.write(json.dumps(json_safe(obj), indent=2, allow_nan=False, default=_json_default) + "\n")


def _json_default(value):
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def console():
    """A Rich console on stdout that never passes a control character through (every string
    it renders, table cells included, goes through :func:`sanitize`, keeping line breaks)."""
    from rich.console import Console

    class SafeConsole(Console):
        def render_str(self, text, **kwargs):
            lines = str(text).split("\n")
            return super().render_str("\n".join(sanitize(line) for line in lines), **kwargs)

    # Off a terminal Rich assumes 80 columns and wraps tables; files and pipes get 120.
    width = None if sys.stdout.isatty() else 120
    return SafeConsole(file=sys.stdout, highlight=False, width=width)


class Finite(click.FloatRange):
    """A float option that must be finite (no nan, inf) and within ``[min, max]``; click's
    own FloatRange lets NaN through (every comparison with NaN is false).

    >>> Finite(0, 10, min_open=True).convert("nan", None, None)
    Traceback (most recent call last):
    ...
    click.exceptions.BadParameter: 'nan' is not a finite number.
    """

    name = "finite float"

    def convert(self, value, param, ctx):
        import math

        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(number, param, ctx)

    def _describe_range(self) -> str:
        """The range shown in ``--help``; nothing for an unbounded option (click would
        print ``x<=None``)."""
        if self.min is None and self.max is None:
            return ""
        return super()._describe_range()


#: Float options that may be NaN or infinite on purpose: none (correct's --border, the fill
#: value of pixels outside the input, is a finite number like every other float option).
NON_FINITE_OK: frozenset[str] = frozenset()
#: Largest seed (NumPy takes any non-negative integer; this keeps it one 64-bit word).
MAX_SEED = 2**63 - 1


def harden(command):
    """Make every float option of ``command`` (and of its subcommands) refuse NaN and
    infinity (:class:`Finite`, keeping its range), and every ``--seed`` refuse a negative
    number, so no command of any module can forget it.  Returns ``command``.

    >>> @click.command()
    ... @click.option("--x", type=float)
    ... @click.option("--seed", type=int)
    ... def c(x, seed): pass
    >>> [type(p.type).__name__ for p in harden(c).params]
    ['Finite', 'IntRange']
    """
    if getattr(command, "_oapcal_hardened", False):
        return command
    for param in command.params:
        kind = param.type
        if param.name in NON_FINITE_OK or isinstance(kind, Finite):
            pass
        elif isinstance(kind, click.FloatRange):
            param.type = Finite(kind.min, kind.max, kind.min_open, kind.max_open, kind.clamp)
        elif kind is click.FLOAT:
            param.type = Finite()
        elif param.name == "seed" and kind is click.INT:
            param.type = click.IntRange(0, MAX_SEED)
    for sub in getattr(command, "commands", {}).values():
        harden(sub)
    command._oapcal_hardened = True
    return command


def check_work(estimate_bytes: float, what: str, fix: str, limit: float | None = None) -> None:
    """Refuse, before any work, a job whose memory estimate exceeds ``limit`` bytes (default
    :data:`MAX_WORK_BYTES`): one line saying what it would need and which option to change."""
    from oapcal.errors import DataError

    limit = MAX_WORK_BYTES if limit is None else limit
    if not estimate_bytes <= limit:
        raise DataError(
            f"{what} would need about {estimate_bytes / 2**30:.3g} GiB of memory, over the "
            f"{limit / 2**30:.3g} GiB limit; {fix}"
        )


#: Largest memory estimate of one command's work (4 GiB).
MAX_WORK_BYTES = 4 * 2**30


def parse_size(text: str | None, option: str = "--image-size", max_side: int | None = 1_000_000):
    """``"640x480"`` -> ``(640, 480)``; raises a usage error naming ``option`` (also for a side
    over ``max_side`` px)."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise click.BadParameter(f"{text!r} is not a size like 640x480", param_hint=option) from None
    if max_side is not None and max(w, h) > max_side:
        raise click.BadParameter(f"{text!r}: a side over {max_side} px is not supported", param_hint=option)
    return (w, h)


def quiet_third_party() -> None:
    """Keep libraries' own chatter off the terminal, so an error is the one ``oapcal:`` line:
    OpenCV's native log (``[ WARN:0@...]``, read before cv2 is first imported), and NumPy's
    RuntimeWarnings (overflow, invalid value) with their source paths; oapcal checks the
    numbers it produces instead."""
    import os
    import warnings

    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
    if "cv2" in sys.modules:
        with contextlib.suppress(Exception):
            sys.modules["cv2"].setLogLevel(0)
    warnings.filterwarnings("ignore", category=RuntimeWarning)


def stderr_is_terminal() -> bool:
    """Whether a progress display may be drawn: stderr is a terminal (``isatty``; Rich's own
    test also says yes when ``FORCE_COLOR`` or ``TTY_COMPATIBLE`` is set, as in many CI
    systems, and would then draw the bar into a log file)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


class _NoBar(contextlib.nullcontext):
    """What :func:`progress_bar` gives off a terminal: a context that draws nothing."""

    disable = True


def _ignore_progress(done: int, total: int, description: str | None = None) -> None:
    """The progress callback off a terminal."""


def progress_bar(description: str = "", enabled: bool = True):
    """A Rich progress bar on stderr (drawn only when stderr is a terminal, removed when done) and its
    callback ``update(done, total, description=None)``, which library functions take as
    their ``progress`` argument.  Use the bar as a context manager around the work.
    Off a terminal, or not ``enabled`` (``--quiet``, ``--json``), nothing is drawn and Rich
    is not even imported (a null context and a callback that does nothing)."""
    if not enabled or not stderr_is_terminal():
        return _NoBar(), _ignore_progress
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    err = Console(file=sys.stderr)
    bar = Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        console=err, transient=True,
    )  # fmt: skip
    task = bar.add_task(description, total=None)

    def update(done: int, total: int, description: str | None = None) -> None:
        if description is None:
            bar.update(task, completed=done, total=total)
        else:
            bar.update(task, completed=done, total=total, description=description)

    return bar, update


def write_detected_points(out, det, plot, draw) -> None:
    """Write a detection's point pairs to ``out`` and, with ``plot``, its picture
    (``draw(path)``): both or neither (the picture is published only with the points)."""
    from oapcal.io.points import write_point_pairs

    if not plot:
        write_point_pairs(out, det.xy_u, det.xy_d, ids=det.ids)
        return
    from oapcal.io.atomic import atomic_path

    with atomic_path(plot) as tmp_plot:
        draw(tmp_plot)
        write_point_pairs(out, det.xy_u, det.xy_d, ids=det.ids)
