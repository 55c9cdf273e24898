"""A derivative-free minimiser: Nelder-Mead with dimension-adapted coefficients.

The calibration's PSF fit (:mod:`tdfd.calibration.psf_model`) minimises a likelihood whose
kernels are rendered, not differentiated, over a handful of parameters. The simplex method
of Nelder and Mead (Computer Journal 7, 1965) with the coefficients of Gao and Han
(Computational Optimization and Applications 51, 2012: reflection 1, expansion ``1 + 2/n``,
contraction ``0.75 - 1/(2n)``, shrink ``1 - 1/n``), which keep it from stalling above a few
dimensions.

Example:
    >>> import numpy as np
    >>> res = nelder_mead(lambda x: float((x[0] - 1) ** 2 + 10 * (x[1] + 2) ** 2), np.zeros(2), np.ones(2))
    >>> [round(float(v), 3) for v in res.x], res.converged
    ([1.0, -2.0], True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InputError, NonFiniteError

__all__ = ["MinimizeResult", "nelder_mead"]


@dataclass(frozen=True)
class MinimizeResult:
    """The best point a minimiser found.

    Attributes:
        x: the best point.
        value: the objective there.
        evaluations: objective evaluations made.
        converged: the simplex shrank below ``x_tol`` and its values below ``f_tol`` before
            ``max_evaluations``.
    """

    x: np.ndarray
    value: float
    evaluations: int
    converged: bool


def nelder_mead(fun: Callable[[np.ndarray], float], x0: np.ndarray, step: np.ndarray, *,
                max_evaluations: int = 2000, x_tol: float = 1e-4, f_tol: float = 1e-8) -> MinimizeResult:
    """Minimise ``fun`` from ``x0`` by the simplex method (module docstring).

    Args:
        fun: the objective; it may return ``inf`` (a point outside the feasible set), never NaN.
        x0: ``(n,)`` the start.
        step: ``(n,)`` the initial simplex's edge along each axis (non-zero).
        max_evaluations: the budget of objective calls.
        x_tol: stop when every vertex lies within this of the best along every axis...
        f_tol: ... and the vertices' values within this of the best.

    Raises:
        InputError: a start or steps that are not finite, a zero step, or a bad budget.
        NonFiniteError: the objective returned NaN, or is not finite at the start.
    """
    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    step = np.asarray(step, dtype=np.float64).reshape(-1)
    n = x0.size
    if n < 1 or step.shape != x0.shape or not (np.isfinite(x0).all() and np.isfinite(step).all()):
        raise InputError(f"need a finite start and one finite step per coordinate, got {x0} and {step}")
    if (step == 0).any():
        raise InputError(f"every step must be non-zero, got {step}")
    if max_evaluations < n + 1:
        raise InputError(f"max_evaluations must be at least n + 1 = {n + 1}, got {max_evaluations}")
    alpha, gamma, rho, shrink = 1.0, 1.0 + 2.0 / n, 0.75 - 0.5 / n, 1.0 - 1.0 / n
    calls = 0

    def f(x: np.ndarray) -> float:
        nonlocal calls
        calls += 1
        v = float(fun(x))
        if math.isnan(v):
            raise NonFiniteError(f"the objective returned NaN at {x}")
        return v

    simplex = np.vstack([x0] + [x0 + np.eye(n)[i] * step[i] for i in range(n)])
    values = np.array([f(x) for x in simplex])
    if not math.isfinite(values[0]):
        raise NonFiniteError(f"the objective is not finite at the start {x0}")
    converged = False
    while calls < max_evaluations:
        order = np.argsort(values, kind="stable")
        simplex, values = simplex[order], values[order]
        if (np.abs(simplex[1:] - simplex[0]).max() <= x_tol and
                np.abs(values[1:] - values[0]).max() <= f_tol):
            converged = True
            break
        centroid = simplex[:-1].mean(0)
        xr = centroid + alpha * (centroid - simplex[-1])
        fr = f(xr)
        if fr < values[0]:
            xe = centroid + gamma * (xr - centroid)
            fe = f(xe)
            simplex[-1], values[-1] = (xe, fe) if fe < fr else (xr, fr)
        elif fr < values[-2]:
            simplex[-1], values[-1] = xr, fr
        else:
            outside = fr < values[-1]
            xc = centroid + rho * ((xr if outside else simplex[-1]) - centroid)
            fc = f(xc)
            if fc < (fr if outside else values[-1]):
                simplex[-1], values[-1] = xc, fc
            else:
                simplex[1:] = simplex[0] + shrink * (simplex[1:] - simplex[0])
                values[1:] = [f(x) for x in simplex[1:]]
    best = int(np.argmin(values))
    return MinimizeResult(simplex[best].copy(), float(values[best]), calls, converged)
