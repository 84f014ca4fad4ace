"""Named exceptions for bad input.

Numerical failure (a fit that does not converge, a point whose inverse does not
converge) is reported as a *value* (a status and a message on the result); bad
input raises a subclass of :class:`OapcalError`, which is a :class:`ValueError`.
The command-line interface prints ``str(error)`` as one line on stderr and exits
with code 2, so messages must name the file, row or field, say what is wrong and
how to fix it.
"""


class OapcalError(ValueError):
    r"""Base class of every user-facing input error in oapcal.

    Messages name Python parameters, not command-line flags; ``param`` names the parameter
    at fault (when one is; a tuple when the message offers several), and the command line
    adds the flag that sets each.

    A message is always one line: line breaks and other control characters that come
    from the user's data (a quoted CSV header holding the whole file, say) are written as
    escapes.

    >>> err = DataError("fraction must lie strictly between 0 and 1, got 1.5", param="fraction")
    >>> str(err), err.param
    ('fraction must lie strictly between 0 and 1, got 1.5', 'fraction')
    >>> str(InputFileError("f.csv: no column 'x' (columns: a\nb)"))
    "f.csv: no column 'x' (columns: a\\nb)"
    """

    def __init__(self, *args, param: str | tuple[str, ...] | None = None):
        super().__init__(*(_one_line(a) if isinstance(a, str) else a for a in args))
        self.param = param


def _one_line(text: str) -> str:
    """``text`` with C0/C1 control characters (line breaks among them) escaped."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


class InputFileError(OapcalError):
    """A file given by the user is missing, unreadable or malformed."""


class ModelSpecError(OapcalError):
    """A model specification names an unknown parameter or preset."""


class DataError(OapcalError):
    """Point data cannot support the requested operation (too few, collinear, ...)."""


class OutputError(OapcalError):
    """An output path is not allowed (would overwrite an input, escapes its directory, ...)."""


class GeometrySpecError(OapcalError):
    """An optical geometry is invalid (unknown setup or orientation, a negative distance, ...)."""
