"""Progress of long library calls, reported through callbacks: the library never draws.

A function that may take more than a second or two takes ``progress``: ``None`` (the
default, nothing reported) or a callable ``progress(done, total)``; functions whose work
has named stages call ``progress(done, total, description)``.  The command line passes
the callback of its Rich bar (``oapcal.cli._common.progress_bar``, which takes both
forms); the napari plugin passes its own; a notebook may pass ``tqdm``'s or a print.

>>> calls = []
>>> with Stages(lambda *a: calls.append(a), total=2, description="start") as s:
...     s.advance(description="half way")
...     s.advance()
>>> calls
[(0, 2, 'start'), (1, 2, 'half way'), (2, 2, 'half way')]
"""

from __future__ import annotations

import threading
from collections.abc import Callable

#: ``progress(done, total)`` or ``progress(done, total, description)``.
ProgressCallback = Callable[..., None]


def progress_callback(progress) -> ProgressCallback | None:
    """``progress`` as a callback or None (for None or False).  A ``True`` is refused: a
    library call does not draw a bar of its own; pass a callback.

    >>> progress_callback(None) is None, progress_callback(print) is print
    (True, True)
    """
    if progress is None or progress is False:
        return None
    if progress is True or not callable(progress):
        raise TypeError(
            f"progress={progress!r}: give a callback progress(done, total, description) or None; "
            "the library draws no progress bar itself (oapcal's commands do)"
        )
    return progress


class Stages:
    """Steps of a task with named stages, each change reported to ``progress(done, total,
    description)`` (nothing when ``progress`` is None).  A context manager: entering
    reports the start.  Threads may share one (files corrected in parallel)."""

    def __init__(self, progress, total: int, description: str = ""):
        self.progress = progress_callback(progress)
        self.total, self.done, self.description = int(total), 0, description
        self._lock = threading.Lock()

    def __enter__(self) -> Stages:
        self._report()
        return self

    def __exit__(self, *exc) -> bool:
        return False

    def stage(self, description: str) -> None:
        """Name the stage now running."""
        self.advance(0, description)

    def advance(self, n: int = 1, description: str | None = None) -> None:
        """``n`` more steps done (and, optionally, the stage now running)."""
        with self._lock:
            self.done += n
            if description is not None:
                self.description = description
            self._report()

    def _report(self) -> None:
        if self.progress is not None:
            # steps may outrun an estimated total (a detection's retries): never report more
            self.progress(min(self.done, self.total), self.total, self.description)
