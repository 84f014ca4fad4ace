"""The object-space pixel size that a detected target measures (``docs/detection.md``).

Each kept corner has a known position on the target (object um) and a measured one in the
image (camera px).  The least-squares similarity between them (a rotation, one scale, a
shift; mirrored when the image is) gives the mean scale ``s`` (px per um) over the corners;
its uncertainty has three parts, added in quadrature:

* ``statistical``: the standard error of ``s`` from the similarity's residuals (the
  linear least-squares covariance, ``sigma_r / sqrt(sum |u - u_mean|^2)``);
* ``anisotropy``: half the difference of the two principal scales of the least-squares
  affine map (a camera with non-square pixels, a tilted target or a distorted field has
  no single scale; this is how far it is from one);
* ``field``: the spread (standard deviation) of the scales of the single elements, each
  fitted by its own similarity (a distorted field has another scale at every place, so the
  mean scale over the target is known no better than it varies);
* ``estimator``: the difference from the scale reported as ``um_per_px`` when that is
  the pose search's (from the triplet centres only) and not this fit's.

The field of view is the image's width and height times ``um_per_px``.
"""

from __future__ import annotations

import numpy as np

#: Fewer kept corners than this measure no pixel size (one triplet has 12).
MIN_CORNERS = 8


def _similarity_scale(u: np.ndarray, x: np.ndarray):
    """Closed-form least-squares similarity ``x = [[a, -b], [b, a]] u + t``: ``(a, b, uc,
    xc, su)`` with the centred points and ``su = sum |uc|^2``."""
    uc = u - u.mean(axis=0)
    xc = x - x.mean(axis=0)
    su = float((uc**2).sum())
    if not su > 0:
        return None
    a = float((uc[:, 0] * xc[:, 0] + uc[:, 1] * xc[:, 1]).sum()) / su
    b = float((uc[:, 0] * xc[:, 1] - uc[:, 1] * xc[:, 0]).sum()) / su
    return a, b, uc, xc, su


def measure_pixel_size(object_um: np.ndarray, xy_px: np.ndarray, mirrored: bool, labels=None) -> dict | None:
    """The pixel size measured from corners at ``object_um`` (um) seen at ``xy_px`` (px):
    ``um_per_px``, ``statistical``, ``anisotropy``, ``field`` (um per px; ``labels``, one
    per corner, say which corners form one element) and ``corners``; None when fewer than
    :data:`MIN_CORNERS` corners or the points are degenerate."""
    u = np.asarray(object_um, float).reshape(-1, 2)
    x = np.asarray(xy_px, float).reshape(-1, 2)
    n = len(u)
    if n < MIN_CORNERS or len(x) != n:
        return None
    if mirrored:
        u = u * np.array([1.0, -1.0])
    local = []
    if labels is not None:
        labels = np.asarray(labels)
        for lab in np.unique(labels):
            k = labels == lab
            if k.sum() >= MIN_CORNERS:
                fit = _similarity_scale(u[k], x[k])
                if fit is not None and np.hypot(fit[0], fit[1]) > 0:
                    local.append(1.0 / np.hypot(fit[0], fit[1]))
    field_sd = float(np.std(local, ddof=1)) if len(local) >= 2 else 0.0
    whole = _similarity_scale(u, x)
    if whole is None:
        return None
    a, b, uc, xc, su = whole
    s = float(np.hypot(a, b))
    if not s > 0:
        return None
    fit = np.column_stack([a * uc[:, 0] - b * uc[:, 1], b * uc[:, 0] + a * uc[:, 1]])
    rss = float(((xc - fit) ** 2).sum())
    dof = max(2 * n - 4, 1)
    se_s = np.sqrt(rss / dof / su)  # a and b each have variance sigma^2 / su
    affine, *_ = np.linalg.lstsq(uc, xc, rcond=None)
    sv = np.linalg.svd(affine, compute_uv=False)
    return {
        "um_per_px": 1.0 / s,
        "statistical": float(se_s / s**2),
        "anisotropy": float(0.5 * abs(1.0 / sv[1] - 1.0 / sv[0])),
        "field": field_sd,
        "elements": len(local),
        "principal_um_per_px": [float(1.0 / sv[0]), float(1.0 / sv[1])],
        "rms_px": float(np.sqrt(rss / n)),
        "corners": int(n),
    }


def pixel_size_answer(measured: dict | None, um_per_px: float, given: bool, image_size) -> dict:
    """The fields shared by every target's detection: ``um_per_px`` (the scale of the
    reference points: given, or found), ``um_per_px_sigma`` (its 1-sigma uncertainty as a
    pixel size; None when it was given or nothing was measured), ``field_of_view_um``
    (width, height) and ``pixel_size`` (the measurement itself, or None)."""
    w, h = image_size
    sigma = None
    if measured is not None and not given and np.isfinite(um_per_px):
        estimator = abs(um_per_px - measured["um_per_px"])
        measured = dict(measured, estimator=float(estimator))
        parts = (measured["statistical"], measured["anisotropy"], measured["field"], estimator)
        sigma = float(np.sqrt(sum(p**2 for p in parts)))
    fov = [float(w * um_per_px), float(h * um_per_px)] if np.isfinite(um_per_px) else None
    return {
        "um_per_px": float(um_per_px),
        "um_per_px_sigma": sigma,
        "field_of_view_um": fov,
        "pixel_size": measured,
    }
