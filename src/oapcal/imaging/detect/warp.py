"""The 2-D polynomial warp of detection: one helper to fit and evaluate it, and its inverse.

A :class:`PolyWarp` maps points ``x`` ``(N, 2)`` to ``u = sum_k coef[k] * xi^i eta^j`` with
``(xi, eta) = (x - centre) / scale`` and the monomials of total degree up to ``degree`` in
the order of :func:`poly_exponents` (``1, xi, eta, xi^2, xi eta, eta^2, ...``).  Every module
of detection that fits a smooth map (the registration's warp, the pose's correction, the
consistency check, the grid's pixel size, the labelling proposal) builds it here.

The inverse is Newton's method on the rows independently (:func:`newton_invert`): each row is
a 2 x 2 system solved in one batched ``numpy.linalg.solve``, which a general root finder
(``scipy.optimize.root``) would solve one point at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def poly_exponents(degree: int) -> list[tuple[int, int]]:
    """``(i, j)`` of the monomials ``xi^i eta^j`` of total degree up to ``degree``."""
    return [(i, t - i) for t in range(degree + 1) for i in range(t, -1, -1)]


def poly_terms(z: np.ndarray, degree: int) -> np.ndarray:
    """The monomials (:func:`poly_exponents`) at the normalised points ``z`` ``(..., 2)``."""
    z = np.asarray(z, float)
    return np.stack([z[..., 0] ** i * z[..., 1] ** j for i, j in poly_exponents(degree)], -1)


def normalisation(x: np.ndarray) -> tuple[np.ndarray, float]:
    """The default ``(centre, scale)`` of points ``x``: their mean and half their largest
    extent (at least 1)."""
    x = np.asarray(x, float)
    return x.mean(axis=0), max(float(np.ptp(x, axis=0).max()) / 2, 1.0)


@dataclass(frozen=True)
class PolyWarp:
    """``u = sum_k coef[k] * xi^i eta^j`` with ``xi = (x - centre) / scale`` (module docstring)."""

    centre: np.ndarray
    scale: float
    coef: np.ndarray  # (nb, 2)
    degree: int

    @classmethod
    def fit(cls, x, u, degree: int, centre=None, scale=None) -> PolyWarp:
        """The least-squares warp ``x -> u`` of ``degree`` (``centre``, ``scale`` default:
        :func:`normalisation` of ``x``)."""
        x = np.asarray(x, float)
        c0, s0 = normalisation(x)
        centre = c0 if centre is None else np.asarray(centre, float)
        scale = s0 if scale is None else float(scale)
        coef, *_ = np.linalg.lstsq(poly_terms((x - centre) / scale, degree), np.asarray(u, float), rcond=None)
        return cls(centre, scale, coef, degree)

    def basis(self, x: np.ndarray) -> np.ndarray:
        return poly_terms((np.asarray(x, float) - self.centre) / self.scale, self.degree)

    def __call__(self, x):
        return self.basis(x) @ self.coef

    def basis_jacobian(self, x) -> tuple[np.ndarray, np.ndarray]:
        """``d basis / dx`` and ``d basis / dy`` ``(N, nb)`` each."""
        z = (np.asarray(x, float) - self.centre) / self.scale
        dx, dy = [], []
        for i, j in poly_exponents(self.degree):
            dx.append(i * z[:, 0] ** max(i - 1, 0) * z[:, 1] ** j if i else np.zeros(len(z)))
            dy.append(j * z[:, 0] ** i * z[:, 1] ** max(j - 1, 0) if j else np.zeros(len(z)))
        return np.stack(dx, -1) / self.scale, np.stack(dy, -1) / self.scale

    def jacobian(self, x) -> np.ndarray:
        """``du/dx`` ``(N, 2, 2)`` (``[n, u/v, x/y]``)."""
        dbx, dby = self.basis_jacobian(x)
        return np.stack([dbx @ self.coef, dby @ self.coef], -1)

    def with_degree(self, degree: int) -> PolyWarp:
        """The same map with room for the terms of ``degree`` (new terms zero, terms beyond
        it dropped)."""
        new = np.zeros((len(poly_exponents(degree)), 2))
        old = poly_exponents(self.degree)
        for k, e in enumerate(poly_exponents(degree)):
            if e in old:
                new[k] = self.coef[old.index(e)]
        return PolyWarp(self.centre, self.scale, new, degree)

    def with_coef(self, coef: np.ndarray) -> PolyWarp:
        return PolyWarp(self.centre, self.scale, coef, self.degree)

    def tangent(self, x0) -> PolyWarp:
        """The affine map that touches this one at the point ``x0``: the same value and
        Jacobian there, no curvature (degree 1, centred on ``x0``)."""
        x0 = np.asarray(x0, float).reshape(1, 2)
        jac = self.jacobian(x0)[0]  # [u/v, x/y]
        coef = np.stack([self(x0)[0], jac[:, 0] * self.scale, jac[:, 1] * self.scale])
        return PolyWarp(x0[0], self.scale, coef, 1)

    def affine_inverse(self, u: np.ndarray) -> np.ndarray:
        """Points ``x`` from the affine part of the warp at its centre (Newton's start)."""
        c = self.centre[None, :]
        jac = self.jacobian(c)[0]
        return self.centre + np.linalg.solve(jac, (np.asarray(u, float) - self(c)[0]).T).T

    def inverse(self, u: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        """Points ``x`` with ``warp(x) = u`` (Newton from ``x0``, default the affine inverse)."""
        x0 = self.affine_inverse(u) if x0 is None else x0
        return newton_invert(self, self.jacobian, u, x0)


def newton_invert(func, jac, u_target: np.ndarray, x0: np.ndarray, n_iter: int = 30) -> np.ndarray:
    """Solve ``func(x) = u_target`` for x by Newton from ``x0`` (rows independent; module
    docstring for why not ``scipy.optimize.root``)."""
    x = np.array(x0, float)
    for _ in range(n_iter):
        r = func(x) - u_target
        jm = jac(x)
        step = np.linalg.solve(jm, r[..., None])[..., 0]
        x = x - step
        if np.nanmax(np.abs(step), initial=0.0) < 1e-9:
            break
    return x


__all__ = ["PolyWarp", "newton_invert", "normalisation", "poly_exponents", "poly_terms"]
