"""The typed records a :class:`~oapcal.imaging.detect.core.Detection` carries.

Each is a frozen dataclass whose fields are named as the keys of the dict it replaced, and
reads like that dict too (``rec["key"]``, ``rec.get``, ``dict(rec)``, ``rec == {...}``:
:class:`Record`), so every caller of the dicts, and the JSON that ``oapcal detect`` writes,
are unchanged.  Fields listed in ``_OPTIONAL`` are left out of the keys while they are
None (the dict did not have them then).

``Detection.orientation_scores`` (orientation name -> correlation score, best first) and
``Detection.predicted`` (corner id -> predicted camera px) stay dicts: their keys are data
(names such as ``flip-x``, every corner id), not fields.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any


class Record(Mapping):
    """A frozen dataclass read like the dict of its fields (module docstring)."""

    _OPTIONAL: tuple[str, ...] = ()

    def _keys(self) -> list[str]:
        return [
            f.name for f in fields(self) if not (f.name in self._OPTIONAL and getattr(self, f.name) is None)
        ]

    def __getitem__(self, key: str) -> Any:
        if not isinstance(key, str) or key not in self._keys():
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self):
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={self[k]!r}' for k in self)})"


def with_changes(rec, **changes):
    """``rec`` with ``changes``: a new record, or (a plain dict given) a new dict."""
    return replace(rec, **changes) if isinstance(rec, Record) else dict(rec, **changes)


@dataclass(frozen=True, eq=False, repr=False)
class WorkEstimate(Record):
    """What detection of an image needs (:func:`~oapcal.imaging.detect.core.work_estimate`):
    its pixels and the bound of the memory (MB)."""

    pixels: int
    memory_bound_mb: int


@dataclass(frozen=True, eq=False, repr=False)
class PoseInfo(Record):
    """The pose search's outcome: ``method`` (``triplets``, ``dense``, ``correlation``: what
    placed the target kept), its ``status`` and ``message``, the ``best`` and ``runner_up``
    poses' summaries (when found), the scores of the slipped poses, the number of bar
    triplets in the image and the target's ``layout``; ``mirror_from_digits`` (only when the
    printed numbers decided a mirror the bars left open, :mod:`.digits`): the mirror read and
    the correlation of each hypothesis' numbers with the image; ``layout_from_corners``
    (only when the corners found decided another layout than the pose search's,
    :mod:`.layouts`): the pose's layout and the rms (px) of each layout's cubic map;
    ``outvoted`` (only when the triplet path disagreed with a dense registration and had put
    the disputed corners on another element's bars, :func:`~oapcal.imaging.detect.checks.outvoted`):
    the registration left out (``triplets``) with the disagreement."""

    _OPTIONAL = ("best", "runner_up", "mirror_from_digits", "layout_from_corners", "outvoted")

    method: str
    status: int
    message: str
    best: dict | None = None
    runner_up: dict | None = None
    slip_scores: dict | None = None
    image_triplets: int = 0
    layout: str | None = None
    mirror_from_digits: dict | None = None
    layout_from_corners: dict | None = None
    outvoted: list | None = None


@dataclass(frozen=True, eq=False, repr=False)
class ConsistencySummary(Record):
    """The global consistency check (:class:`~oapcal.imaging.detect.checks.Consistency`)
    as reported: the model fitted (None: not checked), the rms and largest residual (px),
    the number of inconsistent pairs, its status and message, the pairs off the model
    that a cubic map kept (``rescued``) and, only when the model's rms exceeded the limit,
    the cubic map's (``cubic_rms_px``)."""

    _OPTIONAL = ("cubic_rms_px",)

    model: str | None
    rms_px: float
    max_px: float
    inconsistent: int
    status: int
    message: str
    rescued: int = 0
    cubic_rms_px: float | None = None


@dataclass(frozen=True, eq=False, repr=False)
class DroppedCounts(Record):
    """Corners dropped, by reason (:data:`~oapcal.imaging.detect.core.DROP_REASONS`, in that
    order); a reason with none is left out of the keys."""

    _OPTIONAL = (
        "not_converged", "contrast", "moved", "ambiguous", "uncertain", "outside", "inconsistent",
        "unresolved",
    )  # fmt: skip

    not_converged: int | None = None
    contrast: int | None = None
    moved: int | None = None
    ambiguous: int | None = None
    uncertain: int | None = None
    outside: int | None = None
    inconsistent: int | None = None
    unresolved: int | None = None

    @classmethod
    def from_counts(cls, counts: Mapping) -> DroppedCounts:
        """The non-zero ``counts`` (reason -> corners)."""
        return cls(**{k: int(v) for k, v in counts.items() if v})


@dataclass(frozen=True, eq=False, repr=False)
class DetectionDebug(Record):
    """What the detection pictures draw: the image's bar triplets, the reference triplets
    and the best and rival poses."""

    image_triplets: Any = None
    ref: Any = None
    pose: Any = None
    runner_up: Any = None


__all__ = [
    "ConsistencySummary",
    "DetectionDebug",
    "DroppedCounts",
    "PoseInfo",
    "Record",
    "WorkEstimate",
    "with_changes",
]
