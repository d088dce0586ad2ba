"""Full light transport in the fit: ``--model full`` and ``--model auto``.

The forward model is the analytic single scattering (orders 0 and 1, exact and cheap)
plus the multiple-scattering term of :class:`fitmedia.forward.multiple.FullTransport`,
a local model of the term (per-order images and their finite differences in
log kappa_t and atanh g, the same random numbers) built around one point.  The
fitter finds the single-scattering MAP first, then alternates: refresh the local
model at the current MAP, polish the MAP with it (within a trust region where the
local model is first-order accurate), until the MAP moves by less than
``MOVE_TOL_SD`` of its posterior sd.  The sampler then runs on the last local model.

The term's Monte Carlo error enters the likelihood's variance (``ChannelProblem.
refresh_models``): the per-pixel variance of the estimate at the refresh point, times
the number of camera pixels that share one traced sample pixel (``bin**2``), because
those pixels share one error, which independent variances would count ``bin**2``
times over (docs/inference.md, "Full transport").

``--model auto`` fits single scattering, estimates the multiple-scattering share of
the glow at that MAP, and switches to the full model when the share exceeds
``AUTO_SHARE`` (docs/multiple_scattering.md gives the measurement behind it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .likelihood import ChannelProblem
from .optimize import MapResult, find_map, laplace_covariance
from .params import ParameterSpace

log = logging.getLogger("fitmedia")

#: the refreshes stop when the MAP moved by less than this many posterior sd (DESIGN.md)
MOVE_TOL_SD = 0.1
#: at most this many refreshes of the local model; a fit that needs more says so
MAX_REFRESH = 8
#: each polish stays within this of the refresh point in log kappa_t and atanh g: the local
#: model is first order there, and FullTransport.needs_refresh's own tolerance is 0.1
TRUST_STEP = 0.25
#: ``--model auto`` switches to full transport above this multiple-scattering share of the
#: glow (sum over the pixels that do not see the bulb); docs/multiple_scattering.md
AUTO_SHARE = 0.02
#: the term is traced on a grid of about this many sample pixels (camera pixels binned)
TRACE_WIDTH, TRACE_HEIGHT = 48, 36


@dataclass
class FullFitInfo:
    """What the refreshes did, for results.json."""

    refreshes: int = 0
    moves_sd: list[float] = field(default_factory=list)
    converged: bool = False


def use_full_transport(problem: ChannelProblem, spec, channel: str, *, seed: int) -> None:
    """Give every observation of ``problem`` the full-transport model of its image, built
    around its existing analytic model (no local model yet: call ``refine_map``)."""
    from ..forward.multiple import FullTransport

    for i, o in enumerate(problem.obs):
        cam = spec.camera_for(i)
        b = max(1, round(min(cam.width / TRACE_WIDTH, cam.height / TRACE_HEIGHT)))
        o.model = FullTransport(spec, i, channels=(channel,), seed=seed, single=o.model, bin=b)


def _move_in_sd(problem: ChannelProblem, space: ParameterSpace, old: np.ndarray,
                new: MapResult) -> float:
    """Largest move of log kappa_t and atanh g (the local model's coordinates) between two
    MAPs, in units of their posterior sd at the new one: the Laplace sd, or where the full
    Laplace covariance is not positive definite (the albedo on its plateau), the sd of the
    two with the other parameters held at the MAP."""
    idx = [0, 2]
    if new.cov is not None:
        sd = np.sqrt(np.diag(new.cov)[idx])
    else:
        def sub(y):
            x = new.x.copy()
            x[idx] = y
            return problem.log_posterior(x)
        cov = laplace_covariance(sub, new.x[idx], space.lower[idx], space.upper[idx])
        if cov is None:
            return float("inf")
        sd = np.sqrt(np.diag(cov))
    return float(np.max(np.abs(new.x[idx] - old[idx]) / sd))


def refine_map(problem: ChannelProblem, space: ParameterSpace, start: MapResult, *,
               max_refresh: int = MAX_REFRESH) -> tuple[MapResult, FullFitInfo]:
    """Alternate local-model refreshes and MAP polishes from ``start`` (module docstring).
    Returns the full-transport MAP (Laplace covariance over the whole bounds) and what the
    refreshes did; ``info.converged`` is False when ``MAX_REFRESH`` refreshes did not settle."""
    info = FullFitInfo()
    res = start
    for _ in range(max_refresh):
        problem.refresh_models(res.x)
        problem.adapt(res.x)
        lo, hi = space.lower.copy(), space.upper.copy()
        for j in (0, 2):  # log kappa_t, atanh g: the local model's coordinates
            lo[j], hi[j] = max(lo[j], res.x[j] - TRUST_STEP), min(hi[j], res.x[j] + TRUST_STEP)
        new = find_map(problem.log_posterior, np.clip(res.x, lo, hi), lo, hi, global_evals=0)
        move = _move_in_sd(problem, space, res.x, new)
        log.debug("full transport: refresh %d at %s -> %s, move %.3g sd", info.refreshes + 1,
                  np.round(res.x, 4), np.round(new.x, 4), move)
        info.refreshes += 1
        info.moves_sd.append(move)
        res = new
        if move < MOVE_TOL_SD:
            info.converged = True
            break
    final = find_map(problem.log_posterior, res.x, space.lower, space.upper, global_evals=0)
    final.n_evals += start.n_evals
    return final, info


def ms_share(problem: ChannelProblem, u: np.ndarray, spec, channel: str, *, seed: int
             ) -> tuple[list[float], list[float]]:
    """Per observation: the multiple-scattering share of the glow at parameters ``u`` and its
    Monte Carlo standard error (:meth:`fitmedia.forward.multiple.MultipleScattering.share`);
    0 where the medium does not scatter."""
    from ..forward.multiple import MultipleScattering

    p = problem.space.to_params(u)
    shares, errors = [], []
    for i, o in enumerate(problem.obs):
        ks = o.concentration * p.kappa_s
        if not ks > 0:
            shares.append(0.0)
            errors.append(0.0)
            continue
        share, err = MultipleScattering(spec, i, channels=(channel,)).share(
            [o.concentration * p.kappa_a + problem.water_kappa_a], [ks], [p.g], seed=seed,
            single=getattr(o.model, "single", o.model))
        shares.append(float(share[0]))
        errors.append(float(err[0]))
    return shares, errors


def seed_shift(problem: ChannelProblem, space: ParameterSpace, res: MapResult, spec,
               channel: str, *, seed: int) -> float:
    """How far the full-transport MAP moves when the multiple-scattering term is traced with
    other random numbers (``seed``), in posterior sd of log kappa_t and atanh g.  The
    intervals hold the camera's noise and the term's per-pixel variance but not the term's
    own realisation, which is shared by every pixel; a shift above 1 sd means they are too
    narrow.  The problem keeps its original term afterwards."""
    models = [o.model for o in problem.obs]
    saved = list(problem._model_var)
    for o in problem.obs:
        o.model = getattr(o.model, "single", o.model)
    use_full_transport(problem, spec, channel, seed=seed)
    other, _ = refine_map(problem, space, res, max_refresh=2)
    for o, m in zip(problem.obs, models):
        o.model = m
    problem._model_var = saved
    problem.adapt(res.x)
    return _move_in_sd(problem, space, res.x, other)


def ms_images(problem: ChannelProblem, u: np.ndarray) -> list[np.ndarray] | None:
    """Per observation, the multiple-scattering part (H, W) of the model image at ``u`` (None
    when the problem's models have none)."""
    p = problem.space.to_params(u)
    b = p.brightness if problem.space.free_brightness else problem.brightness
    out = []
    for o in problem.obs:
        part = getattr(o.model, "ms_part", None)
        if part is None:
            return None
        out.append(part([o.concentration * p.kappa_a + problem.water_kappa_a],
                        [o.concentration * p.kappa_s], [p.g], [b])[0][..., 0])
    return out
