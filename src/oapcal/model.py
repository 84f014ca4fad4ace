"""The distortion model of the paper's Eq. (1): parameter layout, presets, forward map,
analytic Jacobians and the Newton inverse.

The map goes from *undistorted* (reference, ideal, paraxial) coordinates ``(x_u, y_u)``
to *distorted* (observed) coordinates ``(x_d, y_d)``; see ``docs/models.md``::

    xb = m (x_u + x_off),  yb = m (y_u + y_off),  r2 = xb^2 + yb^2
    xb_d = xb (1 + k1 r2 + k2 r2^2) + 2 p1 xb yb + p2 (r2 + 2 xb^2) + s1 r2 + s2 r2^2
    yb_d = yb (1 + k1 r2 + k2 r2^2) + p1 (r2 + 2 yb^2) + 2 p2 xb yb + s3 r2 + s4 r2^2
    x_d = xb_d + c_x,  y_d = yb_d + c_y

The tangential terms follow OpenCV's convention (``docs/models.md`` explains why).

Shapes and broadcasting
-----------------------
Points are ``(..., N, 2)`` arrays with x = column, y = row (``docs/conventions.md``).
Parameters are ``(..., 13)`` arrays in the order of :data:`PARAM_NAMES`; their leading
dimensions broadcast against the points' leading dimensions, so ``params`` of shape
``(B, 13)`` with points ``(N, 2)`` evaluates B models on the same points, and with
points ``(B, N, 2)`` evaluates each model on its own points.

A *model* (a subset of free parameters) is a boolean mask of shape ``(13,)``; ``m`` is
always free, every other parameter is free or fixed at 0.  The 12 other flags form the
*bits* of the subset: bit ``i`` is parameter ``PARAM_NAMES[i]`` for ``i < 12``.

Example
-------
>>> import numpy as np
>>> p = params_from_dict({"k1": 1e-2, "m": 1.0})
>>> distort(np.array([[1.0, 0.0]]), p)
array([[1.01, 0.  ]])
>>> inv = undistort(np.array([[1.01, 0.0]]), p)
>>> bool(inv.converged[0]), bool(np.allclose(inv.xy, [[1.0, 0.0]]))
(True, True)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError, ModelSpecError

#: The 13 parameters of Eq. (1), in the one order used everywhere in oapcal.
PARAM_NAMES: tuple[str, ...] = (
    "k1", "k2", "p1", "p2", "s1", "s2", "s3", "s4", "x_off", "y_off", "c_x", "c_y", "m",
)  # fmt: skip
N_PARAMS = len(PARAM_NAMES)
INDEX: dict[str, int] = {name: i for i, name in enumerate(PARAM_NAMES)}
#: Number of optional parameters (all but ``m``); there are ``2**N_OPTIONAL`` models.
N_OPTIONAL = N_PARAMS - 1

#: Named models. ``paper`` is the paper's Eq. (2) plus ``x_off``.
PRESETS: dict[str, tuple[str, ...]] = {
    "full": PARAM_NAMES,
    "paper": ("k1", "p1", "s3", "x_off", "y_off", "c_x", "c_y", "m"),
    "radial": ("k1", "x_off", "y_off", "c_x", "c_y", "m"),
}

#: How each parameter scales when all coordinates are divided by a factor ``f``:
#: the parameter is multiplied by ``f ** SCALE_EXPONENTS[i]``.  This reparametrization is
#: exact (the model in the new units gives the old distorted points divided by ``f``).
SCALE_EXPONENTS = np.array([2, 4, 1, 1, 1, 3, 1, 3, -1, -1, -1, -1, 0], dtype=float)


# --------------------------------------------------------------------------- models


def parse_model(spec: str | Mapping | np.ndarray | tuple | list) -> np.ndarray:
    """Return the free-parameter mask ``(13,) bool`` of a model specification.

    ``spec`` is a preset name (``full``, ``paper``, ``radial``), a comma-separated list of
    parameter names (``"k1,p1,s3,y_off,c_x,c_y"``; ``m`` is added if missing), a sequence
    of names, a mapping ``{name: True/False}`` (the names marked True), or a boolean mask.

    >>> names_from_mask(parse_model("k1, c_x"))
    ('k1', 'c_x', 'm')
    """
    if isinstance(spec, np.ndarray) and spec.dtype == bool:
        if spec.shape != (N_PARAMS,):
            raise ModelSpecError(f"a model mask must have shape ({N_PARAMS},), got {spec.shape}")
        mask = spec.copy()
    else:
        if isinstance(spec, str):
            key = spec.strip()
            if key in PRESETS:
                names = PRESETS[key]
            else:
                names = tuple(n.strip() for n in key.split(",") if n.strip())
                if not names:
                    raise ModelSpecError(
                        "empty model specification: give a preset "
                        f"({', '.join(PRESETS)}) or a comma list of parameter names"
                    )
        elif isinstance(spec, Mapping):  # {name: True/False}: the names marked free
            for name, free in spec.items():
                if not isinstance(free, bool | np.bool_):
                    raise ModelSpecError(
                        f"a model given as a mapping marks each parameter free with True or False, "
                        f"got {name!r}: {free!r}",
                        param="model",
                    )
            names = tuple(name for name, free in spec.items() if free)
        elif isinstance(spec, np.ndarray | tuple | list):
            names = tuple(spec)
        else:
            raise ModelSpecError(
                f"a model specification is a preset ({', '.join(PRESETS)}), a comma list of parameter "
                f"names, a sequence of names or a ({N_PARAMS},) boolean mask, not {type(spec).__name__}",
                param="model",
            )
        mask = np.zeros(N_PARAMS, dtype=bool)
        for name in names:
            if name not in INDEX:
                raise ModelSpecError(
                    f"unknown parameter or preset {name!r} in model specification: use a preset "
                    f"({', '.join(PRESETS)}) or names from {' '.join(PARAM_NAMES)}"
                )
            mask[INDEX[name]] = True
    mask[INDEX["m"]] = True
    return mask


#: A model specification ending in this adds the target's in-plane rotation to Eq. (1)
#: (:data:`BROWN_CONRADY_POSE`): ``"paper+rotation"``.
ROTATION_SUFFIX = "+rotation"


#: A specification ending in this adds the perspective (keystone) terms ``tilt_x, tilt_y``
#: to Eq. (1) (:data:`BROWN_CONRADY_TILT`): ``"paper+tilt"``, or with the target's rotation
#: as well ``"paper+rotation+tilt"``.
TILT_SUFFIX = "+tilt"


def parse_any_model(spec) -> np.ndarray:
    """The free-parameter mask of a model of any family: :func:`parse_model`'s specs
    (Eq. 1), the same with :data:`ROTATION_SUFFIX` (``"paper+rotation"``: ``(14,)``, Eq. 1
    with the target's rotation), with :data:`TILT_SUFFIX` (``"paper+tilt"``,
    ``"paper+rotation+tilt"``: ``(16,)``, Eq. 1 with the perspective terms), or a boolean
    mask of any family's length (returned as is).  Relay subsets are parsed by
    :func:`oapcal.optics.relay_model.relay_mask`.

    >>> names_from_mask(parse_any_model("k1+rotation"))
    ('k1', 'm', 'rotation')
    >>> names_from_mask(parse_any_model("k1+tilt"))
    ('k1', 'm', 'tilt_x', 'tilt_y')
    """
    if isinstance(spec, np.ndarray) and spec.dtype == bool and spec.shape != (N_PARAMS,):
        if spec.ndim != 1 or spec.shape[0] not in _BY_SIZE:
            sizes = ", ".join(str(n) for n in sorted(_BY_SIZE))
            raise ModelSpecError(f"a model mask must have {sizes} entries, got shape {spec.shape}")
        return spec.copy()
    if isinstance(spec, str) and spec.strip().endswith(TILT_SUFFIX):
        base = spec.strip()[: -len(TILT_SUFFIX)]
        rotation = base.endswith(ROTATION_SUFFIX)
        base = base[: -len(ROTATION_SUFFIX)] if rotation else base
        return np.concatenate([parse_model(base or "paper"), [rotation, True, True]])
    if isinstance(spec, str) and spec.strip().endswith(ROTATION_SUFFIX):
        base = spec.strip()[: -len(ROTATION_SUFFIX)]
        return np.append(parse_model(base or "paper"), True)
    return parse_model(spec)


def family_of_spec(spec) -> ModelFamily:
    """The family a specification of :func:`parse_any_model` names: Eq. (1) with the
    target's rotation for ``"...+rotation"``, with the perspective terms for ``"...+tilt"``,
    Eq. (1) for its other specs; a bare boolean
    mask carries nothing but its length (:func:`family_of`).

    >>> family_of_spec("paper+rotation").name
    'brown-conrady+rotation'
    """
    if isinstance(spec, np.ndarray) and spec.dtype == bool:
        return family_of(spec)
    if isinstance(spec, str) and spec.strip().endswith(TILT_SUFFIX):
        return BROWN_CONRADY_TILT
    if isinstance(spec, str) and spec.strip().endswith(ROTATION_SUFFIX):
        return BROWN_CONRADY_POSE
    return BROWN_CONRADY


def names_from_mask(mask: np.ndarray) -> tuple[str, ...]:
    """The names of the free parameters of a mask, in :data:`PARAM_NAMES` order (or the
    order of the family whose vector has the mask's length, :func:`family_of`)."""
    mask = np.asarray(mask, bool)
    return tuple(name for name, free in zip(family_of(mask).param_names, mask) if free)


def mask_from_bits(bits: int | np.ndarray) -> np.ndarray:
    """Masks ``(..., 13)`` from 12-bit subset numbers (bit i = ``PARAM_NAMES[i]``; m free)."""
    bits = np.asarray(bits, dtype=np.int64)
    mask = np.ones(bits.shape + (N_PARAMS,), dtype=bool)
    mask[..., :N_OPTIONAL] = (bits[..., None] >> np.arange(N_OPTIONAL)) & 1 == 1
    return mask


def bits_from_mask(mask: np.ndarray) -> np.ndarray:
    """Inverse of :func:`mask_from_bits`: the 12-bit subset numbers of masks ``(..., 13)``."""
    mask = np.asarray(mask, dtype=bool)
    return (mask[..., :N_OPTIONAL].astype(np.int64) << np.arange(N_OPTIONAL)).sum(axis=-1)


def all_masks() -> np.ndarray:
    """All ``2**12 = 4096`` models as masks ``(4096, 13)``, ordered by their bits."""
    return mask_from_bits(np.arange(2**N_OPTIONAL))


# ------------------------------------------------------------------- parameter vectors


def params_from_dict(values: Mapping[str, float], base: np.ndarray | None = None) -> np.ndarray:
    """A full ``(13,)`` parameter vector from a name -> value mapping.

    Unnamed parameters come from ``base`` (default: all 0 with ``m = 1``).
    """
    params = identity_params() if base is None else np.array(base, dtype=float)
    for name, value in values.items():
        if name not in INDEX:
            raise ModelSpecError(f"unknown parameter {name!r}: use names from {' '.join(PARAM_NAMES)}")
        params[INDEX[name]] = float(value)
    return params


def params_to_dict(params: np.ndarray) -> dict[str, float]:
    """Name -> value for a ``(13,)`` parameter vector."""
    return {name: float(v) for name, v in zip(PARAM_NAMES, np.asarray(params, float))}


def identity_params() -> np.ndarray:
    """The identity model: all parameters 0 and ``m = 1``."""
    params = np.zeros(N_PARAMS)
    params[INDEX["m"]] = 1.0
    return params


def pack(params: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The free values ``(..., k)`` of full parameter vectors ``(..., 13)`` under one mask."""
    return np.asarray(params, float)[..., np.asarray(mask, bool)]


def unpack(free: np.ndarray, mask: np.ndarray, fixed: np.ndarray | None = None) -> np.ndarray:
    """Full vectors ``(..., 13)`` from free values ``(..., k)``; fixed ones from ``fixed`` (0)."""
    free = np.asarray(free, float)
    mask = np.asarray(mask, bool)
    out = np.zeros(free.shape[:-1] + (N_PARAMS,)) if fixed is None else np.array(fixed, float)
    out = np.broadcast_to(out, free.shape[:-1] + (N_PARAMS,)).copy()
    out[..., mask] = free
    return out


def scale_params(params: np.ndarray, factor: float) -> np.ndarray:
    """Parameters for coordinates divided by ``factor`` (an exact reparametrization).

    ``distort(xy / f, scale_params(p, f)) == distort(xy, p) / f``.  Used to fit in
    well-conditioned units whatever the units of the data.
    """
    return np.asarray(params, float) * float(factor) ** SCALE_EXPONENTS


# ---------------------------------------------------------------------- model families


@dataclass(frozen=True)
class ModelFamily:
    """A family of distortion models as the solver sees it (``docs/architecture.md``).

    ``code`` selects the family's point function in the compiled core (the family's copy
    of the kernels, :func:`oapcal._kernels.family_kernels`); ``param_names`` is the flat parameter vector;
    ``always_free`` the parameters every model of the family fits; ``scale_exponents``
    the exact reparametrization for coordinates divided by ``f`` (``p * f**e``; None when
    there is none: the solver then fits in the data's units); ``moves`` says for each
    parameter whether it moves the distorted ``"x"`` only, ``"y"`` only or ``"xy"``
    (the solver skips the zero halves of the Jacobian); ``analytic_jacobian`` False
    makes the solver use central differences of the point function (relative step
    ``fd_step``); ``never_free`` the parameters no model of the family fits (constants
    of a design carried in the vector); ``zero_when_fixed``: a parameter a model does not
    fit is 0 (Eq. 1: the term is absent) or, when False, keeps its starting value;
    ``map_step``: a correction map evaluates the model at every pixel (0) or every
    ``map_step`` px with bicubic splines in between (a costly point function).
    """

    name: str
    code: int
    param_names: tuple[str, ...]
    always_free: tuple[str, ...]
    scale_exponents: np.ndarray | None
    moves: tuple[str, ...]
    analytic_jacobian: bool = True
    fd_step: float = 1e-6
    never_free: tuple[str, ...] = ()
    zero_when_fixed: bool = True
    map_step: int = 0

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def half(self) -> np.ndarray:
        """``moves`` as codes for the kernels: 0 both, 1 x only, 2 y only."""
        return np.array([{"xy": 0, "x": 1, "y": 2}[v] for v in self.moves], dtype=np.int64)


#: Eq. (1), the Brown-Conrady model (the family of every preset and subset above).
BROWN_CONRADY = ModelFamily(
    name="brown-conrady",
    code=0,
    param_names=PARAM_NAMES,
    always_free=("m",),
    scale_exponents=SCALE_EXPONENTS,
    moves=("xy", "xy", "xy", "xy", "x", "x", "y", "y", "xy", "xy", "x", "y", "xy"),
)


#: Eq. (1) after an in-plane rotation of the reference points by ``rotation`` degrees
#: (counter-clockwise about the origin of the fit's coordinates): with Eq. (1)'s own
#: scale ``m`` and shift ``x_o, y_o``, the target's whole in-plane pose.  Its models are
#: Eq. (1)'s with ``rotation`` free as well (one more parameter in AICc).
BROWN_CONRADY_POSE = ModelFamily(
    name="brown-conrady+rotation",
    code=1,
    param_names=PARAM_NAMES + ("rotation",),
    always_free=("m", "rotation"),
    scale_exponents=np.append(SCALE_EXPONENTS, 0.0),
    moves=BROWN_CONRADY.moves + ("xy",),
)

#: The perspective (keystone) terms of :data:`BROWN_CONRADY_TILT`, in 1 / (units of the
#: reference points).
TILT_NAMES = ("tilt_x", "tilt_y")

#: Eq. (1) of the reference points seen in perspective (a tilted target or camera: the
#: keystone): ``s = x_r + x_off``, ``t = y_r + y_off`` (``(x_r, y_r)`` the reference point
#: turned by ``rotation``, which a model may fix at 0), ``w = 1 + tilt_x s + tilt_y t``, and
#: Eq. (1) of the point whose offset coordinates are ``(s / w, t / w)``: a projective map of
#: the reference plane about the distortion centre before the distortion
#: (``docs/conventions.md``, ``docs/models.md``).  Its models are Eq. (1)'s with ``tilt_x``
#: and ``tilt_y`` free (two more parameters in AICc), ``"paper+tilt"``, and optionally the
#: rotation, ``"paper+rotation+tilt"``.
BROWN_CONRADY_TILT = ModelFamily(
    name="brown-conrady+tilt",
    code=3,
    param_names=PARAM_NAMES + ("rotation",) + TILT_NAMES,
    always_free=("m",),
    scale_exponents=np.append(SCALE_EXPONENTS, [0.0, 1.0, 1.0]),
    moves=BROWN_CONRADY.moves + ("xy",) * 3,
)

#: Names of the physical relay family's parameters (:mod:`oapcal._relay_kernel` has the
#: model): the target's pose, the relay's 20 misalignment values
#: (:data:`oapcal.optics.misalign.PARAMETERS`), and the design's constants.
RELAY_POSE_NAMES = ("scale", "rotation", "shift_x", "shift_y")
RELAY_MISALIGNMENT_NAMES = (
    "m1_tilt_x", "m1_tilt_y", "m1_decentre_x", "m1_decentre_y", "m1_clock", "m1_focal_length",
    "m2_tilt_x", "m2_tilt_y", "m2_decentre_x", "m2_decentre_y", "m2_clock", "m2_focal_length",
    "d1", "stop_decentre_x", "stop_decentre_y", "camera_tilt_x", "camera_tilt_y", "camera_defocus",
    "object_tilt_x", "object_tilt_y",
)  # fmt: skip
RELAY_DESIGN_NAMES = ("d1_mm", "f1_mm", "f2_mm", "orientation", "stop_mm", "pixel_mm", "cx", "cy",
                      "a11", "a12", "a21", "a22")  # fmt: skip

#: The physical relay (``docs/models.md``): central differences for the parameter
#: columns (step 1e-3 deg, mm or px: the aimed chief rays are exact to ~1e-13 mm, so a
#: smaller step loses digits on the weakly-acting d1), fitted in the data's px.
RELAY = ModelFamily(
    name="relay",
    code=2,
    param_names=RELAY_POSE_NAMES + RELAY_MISALIGNMENT_NAMES + RELAY_DESIGN_NAMES,
    always_free=(),
    scale_exponents=None,
    moves=("xy",) * (len(RELAY_POSE_NAMES) + len(RELAY_MISALIGNMENT_NAMES) + len(RELAY_DESIGN_NAMES)),
    analytic_jacobian=False,
    fd_step=1e-3,
    never_free=RELAY_DESIGN_NAMES,
    zero_when_fixed=False,
    map_step=8,
)

#: The microscope behind the relay (``relay+microscope``): its magnification (signed,
#: negative inverts) and radial term, fitted; the design's magnification, a constant.
MICROSCOPE_NAMES = ("microscope_magnification", "microscope_k1")
MICROSCOPE_DESIGN_NAMES = ("microscope_design_magnification",)

#: The physical relay with a finite-conjugate microscope behind it (``docs/models.md``):
#: the relay's 36 values in the same order, then the microscope's.  It shares the relay's
#: point function (``code``): the vector's length tells it that there is a microscope.
RELAY_MICROSCOPE = ModelFamily(
    name="relay+microscope",
    code=RELAY.code,
    param_names=RELAY.param_names + MICROSCOPE_NAMES + MICROSCOPE_DESIGN_NAMES,
    always_free=(),
    scale_exponents=None,
    moves=RELAY.moves + ("xy",) * (len(MICROSCOPE_NAMES) + len(MICROSCOPE_DESIGN_NAMES)),
    analytic_jacobian=False,
    fd_step=RELAY.fd_step,
    never_free=RELAY_DESIGN_NAMES + MICROSCOPE_DESIGN_NAMES,
    zero_when_fixed=False,
    map_step=RELAY.map_step,
)

#: The relay families (the physical relay, with or without a microscope behind it).
RELAY_FAMILIES = (RELAY, RELAY_MICROSCOPE)

FAMILIES = {
    f.name: f for f in (BROWN_CONRADY, BROWN_CONRADY_POSE, BROWN_CONRADY_TILT, RELAY, RELAY_MICROSCOPE)
}
_BY_SIZE = {f.n_params: f for f in FAMILIES.values()}


def family_of(params, family: ModelFamily | None = None) -> ModelFamily:
    """The family of a *bare* parameter vector ``(..., P)``, for the legacy calls that pass
    one (``distort(xy, params)``): ``family`` if given, else the built-in family whose
    vector has ``P`` entries (13 Eq. 1, 14 Eq. 1 with rotation, 16 Eq. 1 with the
    perspective terms, 36 the relay, 39 the relay
    with a microscope; the sizes are distinct).  Any other size raises
    :class:`ModelSpecError` naming the sizes.  Code that knows its family passes it (a
    :class:`Model`, or ``family=``): a registered family (:func:`register_family`) is never
    found by length."""
    if family is not None:
        return family
    size = int(np.shape(params)[-1]) if np.ndim(params) else None
    try:
        return _BY_SIZE[size]
    except KeyError:
        sizes = ", ".join(f"(..., {f.n_params}) {f.name}" for f in _BY_SIZE.values())
        raise ModelSpecError(
            f"parameters must have shape {sizes}, got {np.shape(params)}: a vector of no model "
            "family (or give a Model, oapcal.model.Model, that names its family)",
            param="params",
        ) from None


def register_family(family: ModelFamily, point, inverse_start=None, rounding_scale=None) -> ModelFamily:
    """Add a model family: its entry in :data:`FAMILIES` (found by name) and its compiled
    point function in the kernels' dispatch table (``oapcal._kernels._POINT``, with its
    Newton start and rounding scale; defaults: start at the distorted point, no rounding
    magnitudes).  ``point`` is a ``numba.njit`` function with :func:`oapcal._kernels.bc_point`'s
    contract.  Everything that takes a :class:`Model` (distort, inverse, fits, correction
    maps, simulation) then works for it; nothing else changes (``docs/architecture.md``,
    "Where a new model family goes"; ``tests/model/test_toy_family.py``)."""
    k = _kernels()
    taken = {f.code for f in FAMILIES.values()} | set(k._POINT)
    if family.name in FAMILIES or family.code in taken:
        raise ModelSpecError(
            f"a model family named {family.name!r} or with code {family.code} exists already", param="family"
        )
    k._POINT[family.code] = point
    k._START[family.code] = inverse_start or k.identity_start
    if rounding_scale is not None:
        k._ROUNDING[family.code] = rounding_scale
    # the point function lives outside _kernels.py: its source names the cached kernels
    k._DEPENDS[family.code] = (point,) + tuple(f for f in (inverse_start, rounding_scale) if f is not None)
    FAMILIES[family.name] = family
    return family


def _kernels():
    from oapcal import _kernels  # numba loads on first use, not on ``import oapcal``

    return _kernels


def kernel_array(a, dtype=float) -> np.ndarray:
    """``a`` as a C-contiguous, writeable array of ``dtype``: the one layout the compiled
    kernels are compiled (and cached) for, so that a read-only or strided input does not
    trigger another compilation."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


def _as_batches(xy: np.ndarray, params: np.ndarray, n_params: int):
    """Flatten points ``(..., N, 2)`` and parameters ``(..., P)`` to ``(Bx, N, 2)`` and
    ``(Bp, P)`` (each of ``Bx, Bp`` 1 or B) plus the broadcast leading shape."""
    try:
        xy = np.asarray(xy, dtype=float)
    except (TypeError, ValueError):
        raise DataError(f"points must be numbers of shape (..., N, 2), got {type(xy).__name__}") from None
    try:
        params = np.asarray(params, dtype=float)
    except (TypeError, ValueError):
        raise DataError(f"parameters must be numbers, got {type(params).__name__}") from None
    if xy.ndim < 2 or xy.shape[-1] != 2:
        raise ModelSpecError(f"points must have shape (..., N, 2), got {xy.shape}")
    if params.shape[-1:] != (n_params,):
        raise ModelSpecError(f"parameters must have shape (..., {n_params}), got {params.shape}")
    lead = np.broadcast_shapes(xy.shape[:-2], params.shape[:-1])
    n_items = int(np.prod(lead, dtype=np.int64))

    def flat(a, tail):
        if a.shape[: a.ndim - len(tail)] == lead:
            return kernel_array(a.reshape((n_items,) + tail))
        if a.size == int(np.prod(tail, dtype=np.int64)):
            return kernel_array(a.reshape((1,) + tail))
        return kernel_array(np.broadcast_to(a, lead + tail).reshape((n_items,) + tail))

    return flat(xy, xy.shape[-2:]), flat(params, (n_params,)), lead, n_items


def _evaluate(xy_u, params, need: int, family: ModelFamily | None, finite_difference: bool = False):
    family = family_of(params, family)
    k = _kernels()
    u, p, lead, n_items = _as_batches(xy_u, params, family.n_params)
    n = u.shape[1]
    out = np.empty((n_items, n, 2))
    jpt = np.empty((n_items, n, 2, 2) if need >= k.POINT_JAC else (1, 1, 2, 2))
    jpar = np.empty((n_items, n, 2, family.n_params) if need == k.PARAM_JAC else (1, 1, 2, family.n_params))
    fd = float(family.fd_step) if (finite_difference or not family.analytic_jacobian) else None
    total = n_items * n
    k.run_blocks(k.evaluate, total, k.block_size(total, 65536), family.code, p, u, need, fd, out, jpt, jpar)
    return out.reshape(lead + (n, 2)), jpt, jpar, lead + (n,)


# ------------------------------------------------------------------------- forward map


def distort(xy_u: np.ndarray, params: np.ndarray, *, family: ModelFamily | None = None) -> np.ndarray:
    """Eq. (1): distorted points ``(..., N, 2)`` from undistorted points ``(..., N, 2)``."""
    return _evaluate(xy_u, params, 0, family)[0]


def jacobian_point(xy_u: np.ndarray, params: np.ndarray, *, family: ModelFamily | None = None) -> np.ndarray:
    """d(x_d, y_d) / d(x_u, y_u), shape ``(..., N, 2, 2)`` (row = output, column = input)."""
    _, jpt, _, shape = _evaluate(xy_u, params, 1, family)
    return jpt.reshape(shape + (2, 2))


def jacobian_params(
    xy_u: np.ndarray,
    params: np.ndarray,
    *,
    family: ModelFamily | None = None,
    finite_difference: bool = False,
) -> np.ndarray:
    """d(x_d, y_d) / d(params), shape ``(..., N, 2, P)``, columns in :data:`PARAM_NAMES` order.

    Analytic, or central differences with ``finite_difference=True`` (step
    ``family.fd_step * max(|p_i|, 1)``; what the solver uses for a family without
    analytic columns).
    """
    family = family_of(params, family)
    _, _, jpar, shape = _evaluate(xy_u, params, 2, family, finite_difference)
    return jpar.reshape(shape + (2, family.n_params))


def jacobian_determinant(
    xy_u: np.ndarray, params: np.ndarray, *, family: ModelFamily | None = None
) -> np.ndarray:
    """``det d(x_d, y_d)/d(x_u, y_u)`` at each point, ``(..., N)``; <= 0 where the map folds."""
    jac = jacobian_point(xy_u, params, family=family)
    return jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]


def min_jacobian_determinant(
    params: np.ndarray, xy_u: np.ndarray, *, family: ModelFamily | None = None
) -> np.ndarray:
    """The smallest Jacobian determinant of each model ``params (B, P)`` over the points
    ``xy_u (M, 2)``, ``(B,)``: <= 0 where a model folds over among the points, NaN where a
    determinant is not finite."""
    params = kernel_array(np.atleast_2d(params))
    family = family_of(params, family)
    out = np.empty(len(params))
    k = _kernels()
    xy = kernel_array(np.asarray(xy_u, dtype=float).reshape(-1, 2).T)
    k.run_blocks(k.min_det, len(params), k.CHUNK, family.code, params, xy, out)
    return out


# ------------------------------------------------------------------------- the inverse


@dataclass(frozen=True)
class InverseResult:
    """Result of :func:`undistort`.

    Attributes
    ----------
    xy : (..., N, 2) undistorted points; NaN where ``converged`` is False.
    converged : (..., N) bool, the residual ``|distort(xy) - xy_d|`` reached ``tol``, or
        the model's own rounding level where that is coarser (:func:`undistort`), and the
        map is locally one-to-one there.
    folded : (..., N) bool, Newton stopped where the Jacobian determinant is <= 0: the
        fitted map folds over near this point, so no trustworthy inverse exists.
    n_iter : the largest number of Newton iterations any point took.
    """

    xy: np.ndarray
    converged: np.ndarray
    folded: np.ndarray
    n_iter: int


def undistort(
    xy_d: np.ndarray,
    params: np.ndarray,
    *,
    tol: float = 1e-10,
    max_iter: int = 50,
    xy_start: np.ndarray | None = None,
    family: ModelFamily | None = None,
) -> InverseResult:
    """Correct observed points: solve ``distort(xy_u, params) = xy_d`` for ``xy_u``.

    Newton iteration with the analytic 2x2 point Jacobian and step halving (up to 10
    halvings a step when the residual grows), started from the inverse of the linear part
    of the model, ``xy_u = (xy_d - c) / m - off``, unless ``xy_start`` is given.

    A point converges when ``|distort(xy_u) - xy_d| <= tol`` (Euclidean, in the units of
    the points) within ``max_iter`` iterations *and* the Jacobian determinant there is
    positive.  Where the model's evaluation cannot be that exact, the point also converges
    when its residual is within the evaluation's rounding level and a full Newton step no
    longer reduces it: ``16 eps`` times the
    magnitudes the evaluation adds up, the points' own and the family's (the relay's
    mm-scale ray geometry in px, ``(d1 + f1 + f2 + stop) / pixel``; Eq. (1)'s centre and
    offsets); ``docs/models.md`` has the numbers.  Where ``tol`` is met first (Eq. 1 in px
    coordinates, the relay at 4.8 um pixels) the result is the one of the absolute test
    alone.  Where the determinant is <= 0 the map folds over: the point is reported as
    ``folded`` and not converged.  Points that do not converge come back as NaN.  A point
    whose residual stops decreasing above the rounding level is stopped (not converged).

    Shapes follow :func:`distort`: ``xy_d`` ``(..., N, 2)`` with ``params`` ``(..., 13)``;
    each point is solved independently (compiled, in parallel).
    """
    family = family_of(params, family)
    k = _kernels()
    d, p, lead, n_items = _as_batches(xy_d, params, family.n_params)
    n = d.shape[1]
    start = None
    if xy_start is not None:
        start = np.asarray(xy_start, dtype=float)
        start = kernel_array(np.broadcast_to(start, lead + (n, 2)).reshape(n_items, n, 2))
    out = np.empty((n_items, n, 2))
    converged = np.zeros((n_items, n), dtype=np.bool_)
    folded = np.zeros((n_items, n), dtype=np.bool_)
    iters = np.zeros((n_items, n), dtype=np.int64)
    total = n_items * n
    k.run_blocks(k.invert_batch, total, k.block_size(total, 4096), family.code, p, d, start, float(tol),
                 int(max_iter), out, converged, folded, iters)  # fmt: skip
    return InverseResult(
        xy=out.reshape(lead + (n, 2)),
        converged=converged.reshape(lead + (n,)),
        folded=folded.reshape(lead + (n,)),
        n_iter=int(iters.max()) if iters.size else 0,
    )


def correction_errors(params: np.ndarray, xy_d: np.ndarray, xy_u: np.ndarray, *, tol: float = 1e-10,
                      max_iter: int = 50, family: ModelFamily | None = None):  # fmt: skip
    """Correct all points ``xy_d (N, 2)`` through each model ``params (B, P)`` (as
    :func:`undistort`) and compare with ``xy_u (N, 2)`` without storing the points.

    Returns ``(rss, mean_dist, n_bad, n_folded)``, each ``(B,)``: the sum of squared and
    the mean Euclidean corrected-minus-reference distances over the points whose inverse
    converged (the test of :func:`undistort`, with its allowance for the model's rounding),
    the number of points whose inverse failed, and how many of those fold.
    """
    k = _kernels()
    params = kernel_array(np.atleast_2d(params))
    family = family_of(params, family)
    n_items = len(params)
    rss = np.empty(n_items)
    mean_dist = np.empty(n_items)
    n_bad = np.zeros(n_items, dtype=np.int64)
    n_folded = np.zeros(n_items, dtype=np.int64)
    d = kernel_array(xy_d)
    u = kernel_array(xy_u)
    k.run_blocks(k.invert_score, n_items, k.CHUNK, family.code, params, d, u, float(tol), int(max_iter), rss,
                 mean_dist, n_bad, n_folded)  # fmt: skip
    return rss, mean_dist, n_bad, n_folded


# ----------------------------------------------------------------------- the value


def family_named(name: str | ModelFamily) -> ModelFamily:
    """The family of :data:`FAMILIES` called ``name`` (a :class:`ModelFamily` is returned
    as it is): the one way a family is found, by its name, never by a vector's length."""
    if isinstance(name, ModelFamily):
        return name
    try:
        return FAMILIES[str(name)]
    except KeyError:
        raise ModelSpecError(
            f"unknown model family {name!r}: use one of {', '.join(FAMILIES)}", param="family"
        ) from None


@dataclass(frozen=True, eq=False)
class Model:
    """A distortion model as a value: its family (carried by name), its whole parameter
    vector and the names of its free parameters.

    Calling it distorts (undistorted -> distorted px, :func:`distort`); :meth:`inverse`
    corrects (:func:`undistort`, an :class:`InverseResult`); :meth:`jacobian` is the 2x2
    point Jacobian; :meth:`with_pose` composes the model with the target's in-plane pose.
    Every function that evaluates a model takes one (``docs/architecture.md``).

    >>> m = Model("brown-conrady", params_from_dict({"k1": 1e-2}), ("k1", "m"))
    >>> m(np.array([[1.0, 0.0]]))
    array([[1.01, 0.  ]])
    >>> bool(np.allclose(m.inverse(np.array([[1.01, 0.0]])).xy, [[1.0, 0.0]]))
    True
    """

    family: ModelFamily
    params: np.ndarray
    free: tuple[str, ...] = ()

    def __post_init__(self):
        family = family_named(self.family)
        try:
            params = np.array(self.params, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise DataError(f"parameters must be numbers, got {type(self.params).__name__}") from None
        if params.shape != (family.n_params,):
            raise ModelSpecError(
                f"a {family.name} model has {family.n_params} parameters, got {np.shape(self.params)}",
                param="params",
            )
        free = tuple(self.free)
        unknown = [n for n in free if n not in family.param_names]
        if unknown:
            raise ModelSpecError(
                f"unknown parameter(s) {', '.join(unknown)} of the {family.name} family", param="free"
            )
        params.setflags(write=False)
        object.__setattr__(self, "family", family)
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "free", tuple(n for n in family.param_names if n in free))

    # ---- construction
    @classmethod
    def identity(cls, family: str | ModelFamily = BROWN_CONRADY) -> Model:
        """The identity of Eq. (1) (all terms 0, ``m = 1``), with or without the rotation;
        the relay families have no identity (their design sets the map)."""
        family = family_named(family)
        if family not in (BROWN_CONRADY, BROWN_CONRADY_POSE, BROWN_CONRADY_TILT):
            raise ModelSpecError(f"the {family.name} family has no identity model", param="family")
        params = np.append(identity_params(), np.zeros(family.n_params - N_PARAMS))  # extra terms 0
        return cls(family, params, family.always_free)

    @classmethod
    def from_mask(cls, family: str | ModelFamily, params, mask) -> Model:
        """A model from a parameter vector and a free-parameter mask of its family."""
        family = family_named(family)
        mask = np.asarray(mask, bool)
        return cls(family, params, tuple(n for n, f in zip(family.param_names, mask) if f))

    def with_params(self, params) -> Model:
        """The same family and free parameters with other values."""
        return Model(self.family, params, self.free)

    # ---- what it is
    @property
    def mask(self) -> np.ndarray:
        """The free-parameter mask ``(P,)`` in the family's order."""
        return np.array([n in self.free for n in self.family.param_names])

    @property
    def params_dict(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.family.param_names, self.params)}

    def value(self, name: str) -> float:
        """One parameter's value, by name."""
        if name not in self.family.param_names:
            raise ModelSpecError(f"the {self.family.name} family has no parameter {name!r}", param="name")
        return float(self.params[self.family.param_names.index(name)])

    # ---- what it does
    def __call__(self, xy_u: np.ndarray) -> np.ndarray:
        """Distorted points ``(..., N, 2)`` from undistorted ones (:func:`distort`)."""
        return distort(xy_u, self.params, family=self.family)

    def inverse(self, xy_d: np.ndarray, **options) -> InverseResult:
        """Corrected (undistorted) points of observed ones: :func:`undistort` with its
        ``tol``, ``max_iter`` and ``xy_start``."""
        return undistort(xy_d, self.params, family=self.family, **options)

    def jacobian(self, xy_u: np.ndarray) -> np.ndarray:
        """``d(x_d, y_d) / d(x_u, y_u)``, ``(..., N, 2, 2)`` (:func:`jacobian_point`)."""
        return jacobian_point(xy_u, self.params, family=self.family)

    def jacobian_params(self, xy_u: np.ndarray, *, finite_difference: bool = False) -> np.ndarray:
        """``d(x_d, y_d) / d(params)``, ``(..., N, 2, P)`` (:func:`jacobian_params`)."""
        return jacobian_params(xy_u, self.params, family=self.family, finite_difference=finite_difference)

    def with_pose(self, rotation_deg: float) -> Model:
        """This Eq. (1) model after the target's in-plane rotation by ``rotation_deg``
        (counter-clockwise about the origin of the model's coordinates): a model of
        :data:`BROWN_CONRADY_POSE`, whose own ``m`` and offsets carry the pose's scale and
        shift.  A model that already has the rotation gets the rotations added."""
        if self.family is BROWN_CONRADY:
            params = np.append(self.params, float(rotation_deg))
            return Model(BROWN_CONRADY_POSE, params, self.free + ("rotation",))
        if self.family in (BROWN_CONRADY_POSE, BROWN_CONRADY_TILT):
            params = self.params.copy()
            params[N_PARAMS] += float(rotation_deg)
            return Model(self.family, params, tuple(dict.fromkeys(self.free + ("rotation",))))
        raise ModelSpecError(
            f"the {self.family.name} family carries the target's pose in its own parameters "
            "(scale, rotation, shift_x, shift_y): set them with with_params",
            param="rotation_deg",
        )

    def __repr__(self) -> str:
        values = ", ".join(f"{n}={self.value(n):.6g}" for n in self.free)
        return f"Model({self.family.name!r}, {values})"


def as_model(value, family: str | ModelFamily | None = None) -> Model:
    """``value`` as a :class:`Model`: a Model as it is; a fitted record with a ``model``
    (a :class:`~oapcal.calibration.Calibration`) its model; a record with ``params`` and
    ``free`` (a calibration or fit written before ``model`` existed) the model of its
    family (its ``family`` when it carries one); a bare parameter vector ``(P,)`` the model
    of ``family``, or for a legacy call without one, of the built-in family of its length
    (:func:`family_of`, which refuses any other length), with no free parameters named.

    The one adapter of the functions that take "a calibration, a Model or a vector"."""
    if isinstance(value, Model):
        return value if family is None or family_named(family) is value.family else _mismatch(value, family)
    inner = getattr(value, "model", None)
    if isinstance(inner, Model):
        return as_model(inner, family)
    if hasattr(value, "params") and hasattr(value, "free"):
        carried = getattr(value, "family", None)
        if family is None and isinstance(carried, ModelFamily | str):
            family = carried
        return Model(family_of(value.params, None if family is None else family_named(family)),
                     value.params, tuple(value.free))  # fmt: skip
    try:
        params = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise DataError(
            f"a model is a Model, a calibration or a parameter vector, not {type(value).__name__}",
            param="model",
        ) from None
    if params.ndim != 1:
        raise ModelSpecError(f"one model's parameter vector is 1-D, got shape {params.shape}", param="params")
    fam = family_of(params, None if family is None else family_named(family))
    return Model(fam, params, ())


def _mismatch(model: Model, family) -> Model:
    raise ModelSpecError(
        f"a {model.family.name} model was given where a {family_named(family).name} model is needed",
        param="family",
    )
