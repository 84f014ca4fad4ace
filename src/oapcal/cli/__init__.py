"""The ``oapcal`` command line: thin commands over library calls.

Each subcommand lives in a module of this package and is imported only when it runs
(or when ``--help`` lists it), and every module imports only Click at import time, so
``oapcal --help`` stays fast.  :func:`main` turns errors into exit codes:

* 0 success;
* 2 a user error: a Click usage error, or any :class:`oapcal.errors.OapcalError`,
  printed as one line on stderr (no traceback); likewise an error of the environment
  (an :class:`OSError`: permissions, a full disk, stdout that cannot be written), naming the
  user's path rather than a temporary file beside it, and running out of memory;
* 1 an internal error (set ``OAPCAL_DEBUG=1`` to see the traceback);
* 3 the command ran but a numerical result failed (a fit that did not converge);
* 4 a batch (``correct``) finished but some inputs failed (each reported on stderr);
* 130 (Ctrl-C), 143 (SIGTERM), 129 (SIGHUP): interrupted; every output being written is
  removed, as on Ctrl-C.
"""

from __future__ import annotations

import errno
import importlib
import os
import re
import sys
from pathlib import Path

import click

from oapcal import __version__

#: name -> "module:attribute" of every subcommand.
COMMANDS: dict[str, str] = {
    "fit": "oapcal.cli.fit:fit_command",
    "correct-points": "oapcal.cli.correct_points:correct_points_command",
    "demo": "oapcal.cli.demo:demo_command",
    "simulate": "oapcal.cli.simulate:simulate_group",
    "correct": "oapcal.cli.correct:correct_command",
    "export-opencv": "oapcal.cli.export:export_opencv_command",
    "esf": "oapcal.cli.esf:esf_command",
    "report": "oapcal.cli.report:report_command",
    "landmarks": "oapcal.cli.landmarks:landmarks_group",
    "detect": "oapcal.cli.detect:detect_command",
    "select": "oapcal.cli.select:select_command",
    "robustness": "oapcal.cli.select:robustness_command",
    "tolerance": "oapcal.cli.tolerance:tolerance_command",
    "selfcal": "oapcal.cli.selfcal:selfcal_command",
}


class LazyGroup(click.Group):
    """A group that imports each subcommand's module only when it is needed."""

    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | set(COMMANDS))

    def get_command(self, ctx, name):
        if name in COMMANDS:
            from oapcal.cli._common import harden  # every float option finite, seeds >= 0

            module, attr = COMMANDS[name].split(":")
            return harden(getattr(importlib.import_module(module), attr))
        return super().get_command(ctx, name)

    def invoke(self, ctx):
        # Click answers a KeyboardInterrupt with a blank line on stderr and Abort ("two
        # lines" with ours): carry it past Click instead; main() prints the one line.
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:  # Ctrl-C, and SIGTERM/SIGHUP as Terminated
            raise _Interrupted(exc) from None


class _Interrupted(Exception):
    """A KeyboardInterrupt (``args[0]``) carried through Click's main loop."""


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="oapcal")
def cli():
    """Calibrate and remove the distortion of off-axis parabolic mirror relays.

    Typical use: fit a model to labelled point pairs, then correct images with it.

    \b
      oapcal fit points.csv --model paper --out calib.json
      oapcal correct-points calib.json points.csv --out corrected.csv
    """


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised like Ctrl-C so that partial outputs are removed."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_terminated(signum, frame):
    raise Terminated(signum)


def _catch_termination() -> dict:
    """Turn SIGTERM and SIGHUP into :class:`Terminated` (main thread only); returns the
    previous handlers."""
    import signal
    import threading

    previous = {}
    if threading.current_thread() is not threading.main_thread():
        return previous
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            sig = getattr(signal, name)
            previous[sig] = signal.signal(sig, _raise_terminated)
    return previous


def _terminated(exc: Terminated) -> int:
    click.echo(f"oapcal: terminated by signal {exc.signum}; unfinished outputs removed", err=True)
    return 128 + exc.signum


def main(argv: list[str] | None = None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); return the exit code."""
    import signal
    import warnings

    from oapcal.cli._common import quiet_third_party

    previous = _catch_termination()
    # Run as the program (not called with argv by Python code): native libraries' own lines
    # on the stderr file descriptor (libpng warnings, ...) go to /dev/null (kept with OAPCAL_DEBUG).
    restore = _quiet_native_stderr() if argv is None and not os.environ.get("OAPCAL_DEBUG") else None
    try:
        with warnings.catch_warnings():  # the filters are restored for a caller (tests, notebooks)
            quiet_third_party()
            return _main(argv)
    finally:
        if restore is not None:
            restore()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _quiet_native_stderr():
    """Point file descriptor 2 at /dev/null and ``sys.stderr`` at a copy of the real stderr:
    oapcal's own messages (always through ``sys.stderr``) still reach the user, while what C
    libraries write straight to descriptor 2 (``libpng warning: ...``) does not.  Returns the
    function that undoes it, or None when stderr has no descriptor."""
    try:
        fd = sys.stderr.fileno()
        sys.stderr.flush()
        saved = os.dup(fd)
    except (AttributeError, OSError, ValueError):
        return None
    old = sys.stderr
    ours = os.fdopen(
        os.dup(saved), "w", buffering=1, encoding=old.encoding or "utf-8", errors="backslashreplace"
    )
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)
    sys.stderr = ours

    def restore():
        try:
            ours.flush()
        except OSError:
            pass
        os.dup2(saved, fd)
        os.close(saved)
        sys.stderr = old
        ours.close()

    return restore


def _flag_hint(exc, args: list[str]) -> str:
    """`` (set by --flag)`` for an error whose ``param`` is an option of the command run."""
    param = getattr(exc, "param", None)
    if not param:
        return ""
    group, command = cli, None
    ctx = click.Context(cli)
    for word in args:
        if word.startswith("-"):
            continue
        command = group.get_command(ctx, word) if isinstance(group, click.Group) else None
        if not isinstance(command, click.Group):
            break
        group = command
    from oapcal.cli._common import flag_hint

    return flag_hint(command, param)


def _main(argv: list[str] | None) -> int:
    from oapcal.cli._common import sanitize
    from oapcal.errors import OapcalError

    args = sys.argv[1:] if argv is None else list(argv)
    try:
        result = cli.main(args=args, prog_name="oapcal", standalone_mode=False)
    except (click.exceptions.Exit, click.ClickException, click.exceptions.Abort, _Interrupted, OapcalError,
            KeyboardInterrupt, OSError, MemoryError) as exc:  # fmt: skip
        return _error_code(exc, args)
    except Exception as exc:  # an internal error, not the user's
        if os.environ.get("OAPCAL_DEBUG"):
            raise
        click.echo(
            f"oapcal: internal error: {type(exc).__name__}: {sanitize(exc)} "
            "(set OAPCAL_DEBUG=1 for the traceback and please report it)",
            err=True,
        )
        return 1
    code = result if isinstance(result, int) else 0
    try:
        sys.stdout.flush()
    except OSError as exc:
        _silence_stdout()
        click.echo(f"oapcal: error: standard output: cannot be written ({exc.strerror})", err=True)
        return 2
    return code


def _error_code(exc: BaseException, args: list[str]) -> int:
    """Say a user's or the environment's error in one line on stderr; its exit code."""
    from oapcal.cli._common import sanitize
    from oapcal.errors import OapcalError

    if isinstance(exc, click.exceptions.Exit):
        return exc.exit_code
    if isinstance(exc, click.UsageError):
        if type(exc).__name__ == "NoArgsIsHelpError" or exc.ctx is None:
            exc.show()
        else:  # one line, as every other error
            message = sanitize(exc.format_message()).rstrip(".")
            click.echo(f"oapcal: error: {message} (see '{exc.ctx.command_path} --help')", err=True)
        return exc.exit_code
    if isinstance(exc, click.ClickException):
        exc.message = sanitize(exc.message)
        exc.show()
        return exc.exit_code
    if isinstance(exc, click.exceptions.Abort):
        if isinstance(exc.__cause__, Terminated):
            return _terminated(exc.__cause__)
        click.echo("oapcal: aborted", err=True)
        return 130
    if isinstance(exc, _Interrupted):
        if isinstance(exc.args[0], Terminated):
            return _terminated(exc.args[0])
        click.echo("oapcal: interrupted", err=True)
        return 130
    if isinstance(exc, OapcalError):
        click.echo(f"oapcal: error: {sanitize(exc)}{_flag_hint(exc, args)}", err=True)
        return 2
    if isinstance(exc, Terminated):
        return _terminated(exc)
    if isinstance(exc, KeyboardInterrupt):
        click.echo("oapcal: interrupted", err=True)
        return 130
    if isinstance(exc, OSError):  # the environment's: permissions, a full disk, a vanished file
        click.echo(f"oapcal: error: {sanitize(environment_message(exc))}", err=True)
        return 2
    click.echo(  # MemoryError
        "oapcal: error: not enough memory for this command; choose smaller options "
        "(image size, grid, trials) or free memory",
        err=True,
    )
    return 2


def _silence_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush of data that could not
    be written does not print a second error."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass


#: A temporary file of :mod:`oapcal.io.atomic`: ``.NAME.RANDOM.tmp`` or ``.STEM.RANDOM.tmpSUFFIX``.
_TEMP_NAME = re.compile(r"^\.(?P<stem>.+)\.[A-Za-z0-9_]{8}\.tmp(?P<suffix>\.[^.]*)?$")


def environment_message(exc: OSError) -> str:
    """One line for an :class:`OSError` from the environment, naming the user's path (the
    destination, not a hidden temporary file beside it) and what to do."""
    if exc.filename is None and exc.errno in (errno.EPIPE, errno.ENOSPC, errno.EBADF):
        _silence_stdout()
        return f"standard output: cannot be written ({exc.strerror or exc})"
    name = "" if exc.filename is None else os.fsdecode(exc.filename)
    if name:
        path = Path(name)
        m = _TEMP_NAME.match(path.name)
        if m:
            name = str(path.with_name(m["stem"] + (m["suffix"] or "")))
    what = exc.strerror or str(exc)
    hint = {
        errno.EACCES: "check the permissions",
        errno.EPERM: "check the permissions",
        errno.EROFS: "the file system is read-only; choose another place",
        errno.ENOSPC: "the disk is full; free space or choose another place",
        errno.EDQUOT: "the disk quota is exceeded; free space or choose another place",
        errno.EFBIG: "the file is larger than the file system or the file-size limit (ulimit -f) allows; "
        "choose another place or a smaller output",
        errno.ENOENT: "check the path",
        errno.ENAMETOOLONG: "choose a shorter name",
    }.get(exc.errno, "check the path and the disk")
    return f"{name or 'a file'}: {what}; {hint}"
