"""MAP with nlopt (a global method, then a local one) and a Laplace approximation."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class MapResult:
    x: np.ndarray
    log_posterior: float
    n_evals: int
    cov: np.ndarray | None  # Laplace covariance in the unconstrained coordinates


def find_map(log_post: Callable[[np.ndarray], float], x0: np.ndarray, lower: np.ndarray,
             upper: np.ndarray, *, global_evals: int = 400, local_evals: int = 2000,
             seed: int = 0, laplace: bool = True, step: float = 0.05,
             tol: float = 1e-9) -> MapResult:
    """Maximise ``log_post`` inside the box: GN_CRS2_LM from ``x0``, then LN_BOBYQA.

    ``step`` is BOBYQA's initial trust-region size (per coordinate, clipped to a quarter of
    the box): too small a start lets it stop on a poor quadratic model far from the optimum.

    The same function the sampler uses is maximised (lmfit's rule: one objective).
    """
    import nlopt

    n = len(x0)
    count = [0]
    best = [np.array(x0, float), log_post(np.asarray(x0, float))]

    def objective(x, grad):
        count[0] += 1
        v = log_post(np.asarray(x))
        if not np.isfinite(v):
            return -1e300
        if v > best[1]:
            best[0], best[1] = np.array(x), v
        return v

    nlopt.srand(int(seed))
    x = np.clip(np.asarray(x0, float), lower, upper)
    if global_evals > 0:
        opt = nlopt.opt(nlopt.GN_CRS2_LM, n)
        opt.set_lower_bounds(lower)
        opt.set_upper_bounds(upper)
        opt.set_max_objective(objective)
        opt.set_maxeval(int(global_evals))
        opt.set_population(max(10 * (n + 1), 20))
        try:
            opt.optimize(x)
        except nlopt.RoundoffLimited:
            pass
        x = best[0]
    if local_evals <= 0:
        return MapResult(best[0], float(best[1]), count[0], None)
    opt = nlopt.opt(nlopt.LN_BOBYQA, n)
    opt.set_lower_bounds(lower)
    opt.set_upper_bounds(upper)
    opt.set_max_objective(objective)
    opt.set_maxeval(int(local_evals))
    # x tolerance relative to each coordinate's box (the background offset lives on a scale of
    # 1e-4 image units, log kappa_t on a scale of 1); no f tolerance: BOBYQA stops on the first
    # iteration that fails to improve when one is set
    opt.set_xtol_abs(tol * (upper - lower))
    opt.set_initial_step(np.minimum(step, 0.25 * (upper - lower)))
    try:
        opt.optimize(np.clip(x, lower, upper))
    except nlopt.RoundoffLimited:
        pass
    x = best[0]
    cov = laplace_covariance(log_post, x, lower, upper) if laplace else None
    return MapResult(x, float(best[1]), count[0], cov)


def laplace_covariance(log_post: Callable[[np.ndarray], float], x: np.ndarray, lower: np.ndarray,
                       upper: np.ndarray, *, step: float = 1e-3) -> np.ndarray | None:
    """Inverse of the negative Hessian by central differences; None if not positive definite
    (e.g. a parameter at its bound)."""
    n = len(x)
    h = np.full(n, step)
    f0 = log_post(x)
    hess = np.zeros((n, n))

    def f(dx):
        return log_post(np.clip(x + dx, lower, upper))

    for i in range(n):
        ei = np.zeros(n)
        ei[i] = h[i]
        hess[i, i] = (f(ei) - 2 * f0 + f(-ei)) / h[i] ** 2
        for j in range(i + 1, n):
            ej = np.zeros(n)
            ej[j] = h[j]
            hess[i, j] = hess[j, i] = (f(ei + ej) - f(ei - ej) - f(-ei + ej) + f(-ei - ej)) / (
                4 * h[i] * h[j])
    if not np.all(np.isfinite(hess)):
        return None
    try:
        cov = np.linalg.inv(-hess)
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None
    return cov
