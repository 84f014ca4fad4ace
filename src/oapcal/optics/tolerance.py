"""Tolerancing a relay: how its grid distortion, and the error of a calibration made on the
aligned relay, respond to misalignment (``oapcal tolerance``, ``docs/optics.md``).

:class:`Tolerancing` traces the aligned relay's grid, fits a Brown-Conrady model to it
(:func:`oapcal.fitting.fit`) as a user would calibrate, and then, for misaligned copies of the
relay, measures in camera px

* the grid distortion ``|real - paraxial|`` (max and mean; the paraxial map of the
  misaligned relay itself, so the image's shift and magnification do not count);
* the *corrected-image error*: the misaligned relay's real points corrected with the
  aligned calibration, compared with the ideal image of the target (the aligned relay's
  paraxial points) after the best rigid motion (rotation and shift: where the target
  lies is arbitrary; a changed magnification stays an error, as it would misscale every
  measurement); for the aligned relay this is the model's own floor;
* the same after the cheap fix of re-measuring where the image lies and its scale
  (*recentred*): the real points shifted back by the image's shift on the sensor before
  the correction, then compared after the best similarity (rotation, shift and scale);
* the shift of the field centre's image on the sensor and the change of magnification.

:meth:`Tolerancing.sensitivity` gives the first-order rates per unit (deg, mm) of every
degree of freedom; :meth:`Tolerancing.monte_carlo` samples random misalignments within
given tolerances and summarizes the metrics by percentiles.

>>> from oapcal.optics.relay import oap_relay
>>> tol = Tolerancing(oap_relay(1), n=9)
>>> round(tol.aligned["max_px"], 1)   # setup 1, 9 x 9 points over 1 mm
40.1
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import GeometrySpecError, OapcalError
from oapcal.optics.misalign import PARAMETERS, Misalignment
from oapcal.optics.relay import Relay, grid_distortion

#: Tolerance groups (the options of ``oapcal tolerance``): name -> the parameters it sets.
GROUPS: dict[str, tuple[str, ...]] = {
    "tilt": ("m1_tilt_x", "m1_tilt_y", "m2_tilt_x", "m2_tilt_y"),
    "decentre": ("m1_decentre_x", "m1_decentre_y", "m2_decentre_x", "m2_decentre_y"),
    "clock": ("m1_clock", "m2_clock"),
    "focal_length": ("m1_focal_length", "m2_focal_length"),
    "d1": ("d1",),
    "stop_decentre": ("stop_decentre_x", "stop_decentre_y"),
    "camera_tilt": ("camera_tilt_x", "camera_tilt_y"),
    "defocus": ("camera_defocus",),
    "object_tilt": ("object_tilt_x", "object_tilt_y"),
}
DISTRIBUTIONS = ("uniform", "normal")
#: Finite-difference steps of :meth:`Tolerancing.sensitivity` per unit.
STEPS = {"deg": 1e-3, "mm": 1e-3}
#: Rates below this (px per unit) are within the noise of the finite differences (the
#: paraxial map's own central differences are good to ~1e-9 mm): tables show them as 0.
RESOLUTION_PX = 1e-3
#: Metrics of every evaluated relay (px, except ``scale_error_ppm``: the magnification's
#: relative change ``|m / m0 - 1|`` in parts per million).
METRICS = ("max_px", "mean_px", "corrected_mean_px", "corrected_max_px", "recentred_mean_px",
           "recentred_max_px", "shift_px", "scale_error_ppm")  # fmt: skip

__all__ = [
    "DISTRIBUTIONS",
    "GROUPS",
    "MAX_TRIALS",
    "METRICS",
    "RESOLUTION_PX",
    "Tolerancing",
    "check_monte_carlo",
    "expand_tolerances",
    "monte_carlo_bytes",
]


def expand_tolerances(groups: dict[str, float] | None = None, parameters: dict[str, float] | None = None):
    """Per-parameter tolerances from group values (:data:`GROUPS`) and per-parameter
    values (which override their group); zero tolerances are dropped."""
    out: dict[str, float] = {}
    for name, value in (groups or {}).items():
        if name not in GROUPS:
            raise GeometrySpecError(f"unknown tolerance group {name!r}: use one of {', '.join(GROUPS)}")
        for key in GROUPS[name]:
            out[key] = _check_tolerance(value, name)
    for key, value in (parameters or {}).items():
        if key not in PARAMETERS:
            raise GeometrySpecError(f"unknown misalignment {key!r}: use one of {', '.join(PARAMETERS)}")
        out[key] = _check_tolerance(value, key)
    return {k: v for k, v in out.items() if v > 0}


#: Most Monte Carlo trials (:meth:`Tolerancing.monte_carlo`, ``oapcal tolerance --trials``).
MAX_TRIALS = 500_000
#: Memory kept per trial (its sample: a dict of the misalignment and the metrics, the metric
#: arrays, and the JSON the command prints): measured 4.9 kB per trial with the 4 tilt
#: parameters (``--grid 9``: 239 MB at 2,000 trials, 287 MB at 12,000); with room.
BYTES_PER_TRIAL = 4096
BYTES_PER_TRIAL_PARAMETER = 512
#: Memory per traced grid point of one block of trials (the real and paraxial points and
#: the residual arrays of the metrics): measured 190 B (``--grid 201``, 103 trials a block:
#: 1.01 GB peak, 0.23 GB of it before the Monte Carlo).
BYTES_PER_BLOCK_POINT = 400
#: Largest memory estimate of a Monte Carlo (4 GiB).
MAX_MONTE_CARLO_BYTES = 4 * 2**30


def monte_carlo_block(n: int) -> int:
    """Trials traced at once for an ``n`` x ``n`` grid: up to 256, and about 2**22 grid points."""
    return int(max(1, min(256, 2**22 // max(1, n * n))))


def monte_carlo_bytes(trials: int, n: int, n_parameters: int) -> int:
    """Memory estimate (bytes) of a Monte Carlo of ``trials`` on an ``n`` x ``n`` grid."""
    kept = int(trials) * (BYTES_PER_TRIAL + BYTES_PER_TRIAL_PARAMETER * n_parameters)
    return kept + min(int(trials), monte_carlo_block(n)) * n * n * BYTES_PER_BLOCK_POINT


def check_monte_carlo(relay: Relay, tolerances: dict[str, float], trials, distribution: str = "uniform",
                      n: int = 17) -> None:  # fmt: skip
    """Refuse, before any tracing, a Monte Carlo that cannot run: ``trials`` not a whole
    number in 1 ... :data:`MAX_TRIALS`, a memory estimate (:func:`monte_carlo_bytes`) over
    4 GiB, or a tolerance whose extreme draw (``+/- tol`` uniform; ``+/- 2.5 tol``, 5 sigma,
    normal) is not a valid misalignment of ``relay`` (a d1 change that leaves no collimated
    path, say).  Each raises :class:`~oapcal.errors.GeometrySpecError` naming the parameter."""
    import operator

    if distribution not in DISTRIBUTIONS:
        raise GeometrySpecError(
            f"unknown distribution {distribution!r}: use uniform or normal", param="distribution"
        )
    try:
        count = operator.index(trials) if not isinstance(trials, bool) else None
    except TypeError:
        count = None
    if count is None or not 1 <= count <= MAX_TRIALS:
        raise GeometrySpecError(
            f"trials must be a whole number from 1 to {MAX_TRIALS:,}, got {trials!r}", param="trials"
        )
    tolerances = expand_tolerances(parameters=tolerances)
    need = monte_carlo_bytes(count, n, len(tolerances))
    if need > MAX_MONTE_CARLO_BYTES:
        raise GeometrySpecError(
            f"{count:,} trials on a grid of {n} x {n} would need about {need / 2**30:.3g} GiB of memory, "
            f"over the {MAX_MONTE_CARLO_BYTES / 2**30:g} GiB limit; give fewer trials or a smaller grid",
            param=("trials", "n"),
        )
    reach = 1.0 if distribution == "uniform" else 2.5
    for name, tol in tolerances.items():
        for sign in (1.0, -1.0):
            try:
                relay.with_misalignment(Misalignment.from_dict({name: sign * reach * tol}))
            except OapcalError as exc:
                raise GeometrySpecError(
                    f"the tolerance {tol:g} of {name} reaches {sign * reach * tol:+g}, where {exc}; give a "
                    "smaller tolerance",
                    param=("tolerances", name),
                ) from None


def _check_tolerance(value, name: str) -> float:
    value = float(value)
    if not (np.isfinite(value) and value >= 0):
        raise GeometrySpecError(f"the tolerance of {name} must be a number >= 0, got {value:g}")
    return value


def _similarity_residuals(points: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``points`` ``(..., N, 2)`` moved by their best rotation, scale and shift onto
    ``truth`` ``(N, 2)`` (complex linear least squares ``t = a p + b``), minus ``truth``."""
    from oapcal.normalize import similarity

    a, pc, tc = similarity(points, truth)
    r = a[..., None] * pc - tc
    return np.stack([r.real, r.imag], axis=-1)


def _rigid_residuals(points: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``points`` ``(..., N, 2)`` moved by their best rotation and shift onto ``truth``
    ``(N, 2)`` (least squares, closed form), minus ``truth``."""
    pc = points - points.mean(axis=-2, keepdims=True)
    tc = truth - truth.mean(axis=0)
    cross = (pc[..., 0] * tc[:, 1] - pc[..., 1] * tc[:, 0]).sum(-1)
    dot = (pc * tc).sum(-1).sum(-1)
    angle = np.arctan2(cross, dot)[..., None]
    c, s = np.cos(angle), np.sin(angle)
    moved = np.stack([c * pc[..., 0] - s * pc[..., 1], s * pc[..., 0] + c * pc[..., 1]], axis=-1)
    return moved - tc


@dataclass(frozen=True)
class _Traced:
    xy_u: np.ndarray  # (N, 2) paraxial px of the misaligned relay itself
    xy_d: np.ndarray  # (N, 2) real px on the sensor
    offset: np.ndarray  # (2,) px
    scale: float  # sqrt |det J|
    clear: bool


def _percentile_summary(values: np.ndarray, pct: list[float]) -> dict:
    """``mean``, ``std``, ``max`` and ``p<q>`` of the finite ``values`` (None for none)."""
    ok = values[np.isfinite(values)]
    entry = {"mean": None, "std": None, "max": None, **{f"p{q:g}": None for q in pct}}
    if ok.size:
        entry.update(mean=float(ok.mean()), std=float(ok.std()), max=float(ok.max()))
        entry.update({f"p{q:g}": float(v) for q, v in zip(pct, np.percentile(ok, pct))})
    return entry


class Tolerancing:
    """The aligned relay, its grid and calibration; evaluates misaligned copies.

    ``relay`` the aligned design (:func:`~oapcal.optics.relay.oap_relay`), ``n`` x ``n``
    object points over ``field_mm``, camera px of ``pixel_size_um`` (the axis at the
    centre of an ``image_size`` camera), ``model`` the Brown-Conrady model of the
    calibration (:func:`oapcal.model.parse_model`).  ``calibration`` is the aligned fit
    (:class:`oapcal.fitting.FitResult`); ``aligned`` the metrics of the aligned relay.
    """

    def __init__(self, relay: Relay, *, n: int = 17, field_mm: float = 1.0, pixel_size_um: float = 4.8,
                 model="paper", image_size=(640, 480)) -> None:  # fmt: skip
        from oapcal.fitting import fit

        if not float(pixel_size_um) > 0:
            raise GeometrySpecError(f"the pixel size must be a positive number of um, got {pixel_size_um:g}")
        self.relay = relay
        self.n, self.field_mm = int(n), float(field_mm)
        self.pixel_size_um = float(pixel_size_um)
        self.model = model
        self.px = 1e3 / self.pixel_size_um
        self.centre = (np.asarray(image_size, dtype=float) - 1.0) / 2.0
        base = self._trace(relay)
        self.truth = base.xy_u
        self.scale0 = base.scale
        self.calibration = fit(base.xy_u, base.xy_d, model)
        metrics = self._metrics([base])
        if metrics["lost"][0]:
            raise GeometrySpecError(
                "chief rays of the aligned relay's grid miss a mirror: give a smaller field"
            )
        self.aligned = {k: float(metrics[k][0]) for k in METRICS}

    # -------------------------------------------------------------- evaluation

    def _trace(self, relay: Relay) -> _Traced:
        grid = grid_distortion(relay, self.n, self.field_mm)
        with np.errstate(all="ignore"):  # a relay whose rays miss gives NaN, reported as lost
            return _Traced(grid.xy_u * self.px + self.centre, grid.xy_d * self.px + self.centre,
                       grid.offset * self.px, float(np.sqrt(abs(np.linalg.det(grid.matrix)))),
                       bool(grid.clear.all()))  # fmt: skip

    def relay_for(self, misalignment: Misalignment | dict) -> Relay:
        """The design with ``misalignment`` applied."""
        return self.relay.with_misalignment(
            misalignment if isinstance(misalignment, Misalignment) else Misalignment.from_dict(misalignment)
        )

    def _corrected(self, traced: list[_Traced]) -> tuple[np.ndarray, np.ndarray]:
        """Residuals ``(T, N, 2)`` of the corrected real points after the best rigid motion,
        and of the recentred ones after the best similarity (NaN where the aligned
        calibration's inverse fails)."""
        xy_d = np.stack([t.xy_d for t in traced])
        shift = np.stack([t.offset for t in traced])[:, None, :]
        both = self.calibration.model.inverse(np.concatenate([xy_d, xy_d - shift])).xy
        k = len(traced)
        with np.errstate(all="ignore"):
            return _rigid_residuals(both[:k], self.truth), _similarity_residuals(both[k:], self.truth)

    def _metrics(self, traced: list[_Traced]) -> dict[str, np.ndarray]:
        disp = np.stack([t.xy_d - t.xy_u for t in traced])
        dist = np.hypot(disp[..., 0], disp[..., 1])
        rigid, similar = self._corrected(traced)
        res = np.hypot(rigid[..., 0], rigid[..., 1])
        rec = np.hypot(similar[..., 0], similar[..., 1])
        lost = ~np.array([np.isfinite(t.xy_d).all() and np.isfinite(t.scale) for t in traced])
        out = {
            "max_px": dist.max(-1),
            "mean_px": dist.mean(-1),
            "corrected_mean_px": res.mean(-1),
            "corrected_max_px": res.max(-1),
            "recentred_mean_px": rec.mean(-1),
            "recentred_max_px": rec.max(-1),
            "shift_px": np.array([np.hypot(*t.offset) for t in traced]),
            "scale_error_ppm": np.array([abs(t.scale / self.scale0 - 1.0) * 1e6 for t in traced]),
            "clear": np.array([t.clear for t in traced]),
        }
        for key in METRICS:  # a relay whose chief rays miss has no metrics
            out[key] = np.where(lost, np.nan, out[key])
        out["lost"] = lost
        return out

    def evaluate(self, misalignment: Misalignment | dict) -> dict[str, float]:
        """The :data:`METRICS` of one misaligned relay (and ``clear``: no chief ray of the
        grid is vignetted)."""
        m = self._metrics([self._trace(self.relay_for(misalignment))])
        return {k: (bool(v[0]) if k in ("clear", "lost") else float(v[0])) for k, v in m.items()}

    # -------------------------------------------------------------- sensitivity

    def sensitivity(self, names=None, progress=None) -> list[dict]:
        """First-order rates per unit (deg or mm) of each degree of freedom ``names``
        (default: all of :data:`~oapcal.optics.misalign.PARAMETERS`), by differences
        with steps :data:`STEPS` (``d1``: 0.1 mm):

        * ``max_plus_px`` / ``max_minus_px``: change of the max distortion for +1 / -1
          unit (one-sided: the max is a kink where mirrored points tie, so a
          symmetric-breaking perturbation raises it either way), the same for ``mean``;
        * ``field_change_mean_px`` / ``_max_px``: mean and max over the grid of
          ``|d(real - paraxial) / dp|``, how fast the distortion pattern itself changes;
        * ``corrected_mean_px`` / ``_max_px``: mean and max over the grid of the rate of
          the corrected-image error vector (the aligned calibration applied): the error
          grows by about this much per unit of misalignment, on top of the aligned floor;
          ``recentred_mean_px`` / ``_max_px`` the same after recentring (module docstring);
        * ``shift_px``: rate of the image shift on the sensor; ``scale_ppm``: of the
          magnification (ppm per unit).

        ``progress(done, total)`` is called after each parameter.
        """
        names = list(PARAMETERS) if names is None else list(names)
        for name in names:
            if name not in PARAMETERS:
                raise GeometrySpecError(f"unknown misalignment {name!r}: use one of {', '.join(PARAMETERS)}")
        base = self._trace(self.relay)
        base_disp = base.xy_d - base.xy_u
        base_dist = np.hypot(*base_disp.T)
        rows = []
        for i, name in enumerate(names):
            unit = PARAMETERS[name][0]
            h = 0.1 if name == "d1" else STEPS[unit]
            plus, minus = (self._trace(self.relay_for({name: s * h})) for s in (1.0, -1.0))
            rigid, similar = self._corrected([plus, minus])
            rate = (rigid[0] - rigid[1]) / (2 * h)
            rate_recentred = (similar[0] - similar[1]) / (2 * h)
            field_rate = ((plus.xy_d - plus.xy_u) - (minus.xy_d - minus.xy_u)) / (2 * h)
            d_plus = np.hypot(*(plus.xy_d - plus.xy_u).T)
            d_minus = np.hypot(*(minus.xy_d - minus.xy_u).T)
            rows.append({
                "parameter": name,
                "unit": unit,
                "step": h,
                "max_plus_px": float((d_plus.max() - base_dist.max()) / h),
                "max_minus_px": float((d_minus.max() - base_dist.max()) / h),
                "mean_plus_px": float((d_plus.mean() - base_dist.mean()) / h),
                "mean_minus_px": float((d_minus.mean() - base_dist.mean()) / h),
                "field_change_mean_px": float(np.hypot(*field_rate.T).mean()),
                "field_change_max_px": float(np.hypot(*field_rate.T).max()),
                "corrected_mean_px": float(np.hypot(*rate.T).mean()),
                "corrected_max_px": float(np.hypot(*rate.T).max()),
                "recentred_mean_px": float(np.hypot(*rate_recentred.T).mean()),
                "recentred_max_px": float(np.hypot(*rate_recentred.T).max()),
                "shift_px": float(np.hypot(*(plus.offset - minus.offset)) / (2 * h)),
                "scale_ppm": float((plus.scale - minus.scale) / (2 * h) / self.scale0 * 1e6),
            })  # fmt: skip
            if progress is not None:
                progress(i + 1, len(names))
        return rows

    # -------------------------------------------------------------- Monte Carlo

    def sample(self, tolerances: dict[str, float], trials: int, seed: int = 0,
               distribution: str = "uniform") -> list[Misalignment]:  # fmt: skip
        """``trials`` random misalignments: each parameter of ``tolerances`` (name -> tol)
        drawn independently, uniform in ``[-tol, tol]`` or normal with ``sigma = tol / 2``
        (the tolerance as a 2-sigma value); seeded (:func:`numpy.random.default_rng`)."""
        if distribution not in DISTRIBUTIONS:
            raise GeometrySpecError(f"unknown distribution {distribution!r}: use uniform or normal")
        if int(trials) < 1:
            raise GeometrySpecError(f"the Monte Carlo needs at least 1 trial, got {trials}")
        tolerances = expand_tolerances(parameters=tolerances)
        rng = np.random.default_rng(seed)
        names = list(tolerances)
        tol = np.array([tolerances[k] for k in names])
        if distribution == "uniform":
            values = rng.uniform(-1.0, 1.0, size=(int(trials), len(names))) * tol
        else:
            values = rng.normal(0.0, 0.5, size=(int(trials), len(names))) * tol
        return [Misalignment.from_dict(dict(zip(names, row.tolist()))) for row in values]

    def monte_carlo(self, tolerances: dict[str, float], trials: int = 500, *, seed: int = 0,
                    distribution: str = "uniform", percentiles=(50, 90, 95), refit: bool = False,
                    progress=None) -> dict:  # fmt: skip
        """Evaluate ``trials`` random misalignments (:meth:`sample`).

        Returns a JSON-ready dict: ``trials``, ``seed``, ``distribution``, ``tolerances``,
        ``percentiles``, ``summary`` (per metric: ``mean``, ``std``, ``max`` and ``p<q>``
        for each percentile ``q``, over the trials where it is finite), ``n_lost`` (trials
        where chief rays miss a mirror or the image plane: no metrics, left out of the
        summary), ``n_failed`` (trials where the aligned calibration's inverse failed at
        some grid point),
        ``n_vignetted`` (trials with a vignetted chief ray) and ``samples`` (each trial's
        misalignment values and metrics).  With ``refit`` each trial also refits the model
        to its own grid: ``refit_mean_px`` / ``refit_max_px``, the model's floor on that
        relay.  ``progress(done, total)`` counts trials.
        """
        pct = [float(q) for q in percentiles]
        if not all(0 <= q <= 100 for q in pct):
            raise GeometrySpecError(f"percentiles must lie in 0..100, got {', '.join(f'{q:g}' for q in pct)}")
        check_monte_carlo(self.relay, tolerances, trials, distribution, self.n)
        samples = self.sample(tolerances, trials, seed, distribution)
        total = len(samples)
        metrics = self._streamed_metrics(samples, refit, progress)
        clear = metrics.pop("clear")
        lost = metrics.pop("lost")
        summary = {key: _percentile_summary(values, pct) for key, values in metrics.items()}
        names = list(expand_tolerances(parameters=tolerances))
        return {
            "trials": total,
            "seed": int(seed),
            "distribution": distribution,
            "tolerances": expand_tolerances(parameters=tolerances),
            "percentiles": pct,
            "summary": summary,
            "n_lost": int(lost.sum()),
            "n_failed": int((~np.isfinite(metrics["corrected_mean_px"]) & ~lost).sum()),
            "n_vignetted": int((~clear & ~lost).sum()),
            "samples": [
                {
                    "misalignment": {k: getattr(m, k) for k in names},
                    **{k: (float(v[i]) if np.isfinite(v[i]) else None) for k, v in metrics.items()},
                }
                for i, m in enumerate(samples)
            ],  # fmt: skip
        }

    def _streamed_metrics(self, samples, refit: bool, progress) -> dict[str, np.ndarray]:
        """The metrics of every misalignment of ``samples`` (and ``clear``, ``lost``).
        Streamed: each block of trials is traced, measured and dropped, so memory holds the
        metrics and samples of every trial but the traced grids of one block only."""
        total = len(samples)
        block = monte_carlo_block(self.n)
        metrics: dict[str, list] = {}
        for lo in range(0, total, block):
            traced = []
            for i in range(lo, min(lo + block, total)):
                traced.append(self._trace(self.relay.with_misalignment(samples[i])))
                if progress is not None and (i % 8 == 7 or i + 1 == total):
                    progress(i + 1, total)
            part = self._metrics(traced)
            if refit:
                part.update(self._refit(traced))
            for k, v in part.items():
                metrics.setdefault(k, []).append(v)
            del traced
        return {k: np.concatenate(v) for k, v in metrics.items()}

    def _refit(self, traced: list[_Traced]) -> dict[str, np.ndarray]:
        from oapcal.fitting import fit

        mean, worst = np.full(len(traced), np.nan), np.full(len(traced), np.nan)
        for i, t in enumerate(traced):
            if not (np.isfinite(t.xy_d).all() and np.isfinite(t.xy_u).all()):
                continue  # a lost relay
            result = fit(t.xy_u, t.xy_d, self.model)
            if result.converged:
                err = np.hypot(*(result.model.inverse(t.xy_d).xy - t.xy_u).T)
                mean[i], worst[i] = err.mean(), err.max()
        return {"refit_mean_px": mean, "refit_max_px": worst}
