"""Full light transport in the fit: ``--model full`` and ``--model auto``.

The forward model is the analytic single scattering (orders 0 and 1, exact and cheap)
plus the multiple-scattering term of :class:`fitmedia.forward.multiple.FullTransport`,
a local model of the term (per-order images and their finite differences in
log kappa_t and atanh g, the same random numbers) built around one point.  The
fitter finds the single-scattering MAP first, then alternates: refresh the local
model at the current MAP, polish the MAP with it (within a trust region where the
local model is first-order accurate; its half-width doubles, up to ``TRUST_MAX``, while
the polishes end on its edge), until the MAP moves by less than
``MOVE_TOL_SD`` of its posterior sd, or by less than what two realisations of the term
explain (``term_jackknife``: each refresh at a new point is partly a new realisation, and
that error is in the values' uncertainty).  After the checks on that fixed point (another
seed, a restart beyond it, the other sign of g), the last refreshes trace
``FINAL_PATHS_FACTOR`` times the paths (``more_paths``): the fixed point is offset by the
term's own noise by an amount that falls with the paths.  The sampler then runs on the last
local model.

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
from typing import NamedTuple

import numpy as np
from scipy.special import expit

from .likelihood import ChannelProblem
from .optimize import MapResult, find_map, laplace_covariance
from .params import ParameterSpace
from .sample import OTHER_MODE_DELTA

log = logging.getLogger("fitmedia")

#: the refreshes stop when the MAP moved by less than this many posterior sd (DESIGN.md)
MOVE_TOL_SD = 0.1
#: at most this many refreshes of the local model; a fit that needs more says so
MAX_REFRESH = 8
#: each polish stays within this of the refresh point in log kappa_t and atanh g: the local
#: model is first order there, and FullTransport.needs_refresh's own tolerance is 0.1
TRUST_STEP = 0.25
#: a polish that ends on the trust region's edge doubles the next one's half-width, up to
#: this (the MAP is far away, as for dense milk from its single-scattering MAP: 8 steps of
#: 0.25 reach a factor e^2 in kappa_t); one inside it resets the half-width to TRUST_STEP
TRUST_MAX = 1.0
#: a polish (inside its trust region) whose move, in posterior sd, points back against the
#: previous one (cosine below this) puts the next refresh at the midpoint of its start and
#: end.  The refreshes are a fixed-point iteration x -> F(x); near the fixed point x*,
#: F(x) - x* ~ a (x - x*), and a thin medium (wide posterior, the term's curvature over a
#: move of an sd or more) gave a ~ -0.7: the moves alternate and shrink slowly (measured on a
#: 16 x 12 Espresso 4.1 ml round of docs/validation.md, R: moves of 1.0 and 0.75 sd at 4096
#: paths, "did not settle").  From the midpoint the error is (1 + a) / 2 of the last one,
#: and the next move goes on the same way (a plain refresh), so the error falls by a (1 + a) / 2
#: every two refreshes: 0.1 for a = -0.7 (plain: 0.5), and the loop converges for -2 < a < 0
#: (plain: -1 < a < 0); for 0 < a < 1 the moves do not turn back and nothing changes
REVERSAL_COS = -0.5
#: ... and one whose move goes on the same way as the previous one (cosine above this) but
#: shorter, by a ratio r < 1, puts the next refresh where that geometric series ends: beyond
#: the polish's end by r / (1 - r) times its move, at most ``EXTRAPOLATE_MAX`` times (r = 3/4).
#: For 0 < a < 1 the plain loop creeps (measured on Regular Milk 60 ml at 48 x 36, G: atanh g
#: 0.18, 0.27, 0.38, 0.45, 0.50 in 5 refreshes, truth 0.90, unsettled after 8); from the
#: series' end the error is that of the estimate of a, and the next moves correct it.  Only
#: two plain moves in a row are judged (after a midpoint or an extrapolation the ratio of the
#: moves says nothing of a)
ALIGN_COS = 0.5
EXTRAPOLATE_MAX = 3.0
#: ``--model auto`` switches to full transport above this multiple-scattering share of the
#: glow (sum over the pixels that do not see the bulb); docs/multiple_scattering.md
AUTO_SHARE = 0.02
#: the restart check (restart_shift): its start is at most this far beyond the MAP in log
#: kappa_t and atanh g, and it refreshes the term at most this many times
RESTART_REACH = 0.5
RESTART_REFRESHES = 4
#: a restart that settled where the log posterior, with the local model rebuilt there, is
#: more than this many units from the MAP's is a fixed point the images decide against: below
#: the MAP's it is no second answer (``restart_delta``; trust.py's restart check then holds
#: no reason), above it the refreshes go on from there (``adopt_restart``).  The bound is the
#: one for a second mode of g (inference/sample.py: ``OTHER_MODE_DELTA``): within it the images
#: do not tell two points apart.  Measured on Regular Milk 60 ml at 100 x 75 px (G): from
#: near the answer the loop settled at kappa_t 19.3, g 0.675 (truth 20.4, 0.714) and the
#: restart at kappa_t 34.2, g 0.855 (docs/inference.md, "Dense milk at 100 x 75")
RESTART_DELTA = OTHER_MODE_DELTA
#: ... but the comparison is noisy: the term traced anew at each point, on one seed, moved the
#: log posterior's difference by tens of units between seeds (measured on the bench's 200 x 150
#: Lowfat Milk 16 ml capture, R, 6 seeds: sd 36 units for two points 0.06 posterior sd apart,
#: 104 at 1 sd, 171 at 3 sd; docs/inference.md, "The restart's log posterior: its noise").  So
#: a difference beyond RESTART_DELTA on the fit's own seed is traced again on this many more
#: seeds, and what counts is the one-sided bound of their mean (Student t with their spread:
#: ``delta_beyond_noise``), which must itself lie beyond RESTART_DELTA
DELTA_SEEDS = 2
#: ... and where their mean is beyond RESTART_DELTA but its bound is not (undecided, as 8 of
#: the 90 channels of the 30 rounds at 16 x 12 px were with 3 seeds and t = 6.96: means -10 to
#: -27 and +17 units; docs/validation.md, stop 47), on this many more (since 2026-12-06)
DELTA_SEEDS_MORE = 3
#: the chance that the term's noise alone decides, over both looks (Bonferroni: each look's
#: bound at ``DELTA_LOOK_LEVEL``)
DELTA_LEVEL = 0.99
DELTA_LOOK_LEVEL = 1.0 - (1.0 - DELTA_LEVEL) / 2
#: the other seeds are the term's own plus this step times 1, 2, ...
DELTA_SEED_STEP = 7919
#: the last refreshes trace the term with this many times its paths (``more_paths``): the
#: MAP's offset from the term's own noise falls with the paths (docs/inference.md, "The g
#: offset at the truth"); 1: no such stage.  8 since 2026-12-06 (16 before): with the term
#: built at the truth on the last refreshes' grid (R of a 200 x 150 Lowfat Milk 16 ml capture,
#: docs/studies/ms_shared_error.py) kappa_t was -1.3 % low at 1024 paths per sample pixel,
#: -0.66 +- 0.23 % at 2048 (8 x 256) and -0.19 +- 0.27 % at 4096 (16 x 256), about 1 and 0.3
#: posterior sd; 16 made the bench's full fit 18.5 min against issue 15's 15, its last
#: refreshes 78 % of a channel's full-transport time (docs/inference.md, "Speed")
FINAL_PATHS_FACTOR = 8
#: ... with at most this many refreshes.  4 since 2026-12-07 (3 before): each last refresh
#: at 100 x 75 moves the polish by about a posterior sd of the term's realisation, so three
#: may all stay above 1 term unit at the fixed point.  Regular Milk 60 ml at 100 x 75 (G,
#: seed-62 capture) moved 1.19, 1.88, 1.22 term units and exited 1 ("did not settle") at
#: kappa_t -0.3 %; its fourth moved 0.68 and it exits 0 at kappa_t +0.4 %, g +0.002.  On the
#: 30 rounds at 16 x 12 px the change (the fourth, and the second now extrapolated where two
#: moves line up) moved 5 of 90 channels, none in a fit that exits 0
#: (docs/inference.md, "A fourth last refresh")
FINAL_REFRESHES = 4
#: ... on a grid of about this many sample pixels (``final_bin``; the loop's ``trace_bin``
#: grid is half as fine each way): with the term fixed at the truth (4096 paths per sample
#: pixel) the upsampling from the loop's grid left kappa_t -2.4 % and g -0.002 in R of a Lowfat
#: Milk 16 ml capture, at 200 x 150 (bin 4) and at 100 x 75 (bin 2) alike, 2-4 posterior sd;
#: this grid (bin 2 and bin 1) -0.2 % and +0.1 % (docs/inference.md, "The offset left after
#: the last refreshes")
FINAL_TRACE_WIDTH, FINAL_TRACE_HEIGHT = 96, 72
#: the share of the last refreshes' move that may remain as an offset of the values
#: (``offset_budget``): with the offset falling as paths^-p, F^-p / (1 - F^-p) of the move
#: from the loop's paths to F = ``FINAL_PATHS_FACTOR`` times them remains; p = 1/2
#: (``OFFSET_FALL``) gives 1/3 at F = 16 and 0.55 at F = 8.  Measured (docs/inference.md, "The
#: offset left after the last refreshes"): p about 0.58 (a remainder of about a quarter of
#: the move from 256 to 4096 paths) in R of the bench's 200 x 150 milk capture, no remainder
#: beyond the noise in its G, p about 0.7 at the truth at 100 x 75, and about 1 at the truth
#: on the last refreshes' grid at 200 x 150 (1024 -> 2048 paths); p = 1/2 is below them all
OFFSET_FALL = 0.5
OFFSET_SHARE = FINAL_PATHS_FACTOR ** -OFFSET_FALL / (1.0 - FINAL_PATHS_FACTOR ** -OFFSET_FALL)
#: the jackknife's finite-difference step, in posterior sd of each coordinate
JACKKNIFE_STEP_SD = 0.1
#: the jackknife holds logit albedo where its Laplace sd exceeds this: the albedo on its
#: plateau (albedo -> 1, kappa_a unresolved), where a Newton step along it is meaningless
#: (measured: steps of 10^2-10^5 in logit albedo, which the convolution then put into the
#: samples as albedos of 0 and 1; docs/inference.md)
ALBEDO_HELD_SD = 1.0
#: the term is traced on a grid of about this many sample pixels (camera pixels binned)
TRACE_WIDTH, TRACE_HEIGHT = 48, 36


@dataclass
class FullFitInfo:
    """What the refreshes did, for results.json."""

    refreshes: int = 0
    moves_sd: list[float] = field(default_factory=list)
    #: the same moves in units of what the term's realisation explains (_in_term_units)
    moves_term: list[float] = field(default_factory=list)
    converged: bool = False
    #: refreshes placed at the midpoint of a polish that moved back (``REVERSAL_COS``)
    midpoints: int = 0
    #: refreshes placed beyond a polish that went on the same way (``ALIGN_COS``)
    extrapolated: int = 0
    #: the last polish's move (its end minus its refresh point, sampler coordinates)
    last_step: np.ndarray | None = None

    def followed_by(self, *later: FullFitInfo) -> FullFitInfo:
        """These refreshes and ``later`` ones counted together: the counts summed, the moves
        in order; settled and the last step as the last of them left them."""
        parts = (self, *later)
        return FullFitInfo(refreshes=sum(p.refreshes for p in parts),
                           moves_sd=[m for p in parts for m in p.moves_sd],
                           moves_term=[m for p in parts for m in p.moves_term],
                           converged=parts[-1].converged,
                           midpoints=sum(p.midpoints for p in parts),
                           extrapolated=sum(p.extrapolated for p in parts),
                           last_step=parts[-1].last_step)


def use_full_transport(problem: ChannelProblem, spec, channel: str, *, seed: int) -> None:
    """Give every observation of ``problem`` the full-transport model of its image, built
    around its analytic model (no local model yet: call ``refine_map``); one it has already is
    built anew."""
    from ..forward.multiple import FullTransport

    for i, o in enumerate(problem.obs):
        o.model = FullTransport(spec, i, channels=(channel,), seed=seed,
                                single=getattr(o.model, "single", o.model),
                                bin=trace_bin(spec.camera_for(i)))


#: a spot has no direct view of its light, so nothing pins kappa_t but the glow, and its
#: single-scattering MAP can take multiple-scattering light for a thinner medium with a
#: smaller g (measured on the canonical 200 x 150 spot, Lowfat Milk 4 ml: kappa_t 71-88 %
#: low, g 0.55-0.73 low, chi2/pixel 1.02 in R, where the term's share at that MAP was 0.7 %
#: and auto stayed single).  :func:`scan_start` tries the full model at these multiples of
#: that MAP's kappa_t ...
SCAN_KT_FACTORS = (1.0, 3.0, 10.0, 30.0)
#: ... and at these g (and the single MAP's own)
SCAN_G = (0.5, 0.9)
#: the scan's best full-transport point beats the single-scattering MAP (its log posterior
#: under the single model) by more than this: the images hold multiple scattering that the
#: single fit absorbed into wrong values (the single model's bound for a second mode of g)
SCAN_DELTA = 8.0
#: ... or a scanned point within that many of it at a kappa_t more than this factor away:
#: the images do not tell the two apart (a spot at 32 x 24 px, Lowfat Milk 4 ml, R: the
#: full model at 3.2 x the single MAP's kappa_t within 0.3 units of the scan's best, 4.7
#: above the single MAP)
SCAN_FAR = 2.0


def scan_verdict(rows: list[dict], single_lp: float, single_kt: float
                 ) -> tuple[str | None, dict]:
    """What :func:`scan_start`'s points ``rows`` say of the single-scattering MAP (log
    posterior ``single_lp``, ``single_kt``): ``"better"`` where the best point beats it by
    more than ``SCAN_DELTA``; ``"as well"`` where a point at a kappa_t more than ``SCAN_FAR``
    times away is within ``SCAN_DELTA`` of it (or above); else None (the single MAP stands).
    Returns the verdict and the point it names (the best, or the best far one)."""
    best = max(rows, key=lambda r: r["log_posterior"])
    if best["log_posterior"] - single_lp > SCAN_DELTA:
        return "better", best
    far = [r for r in rows if abs(np.log(r["kappa_t"] / single_kt)) > np.log(SCAN_FAR)]
    near = max(far, key=lambda r: r["log_posterior"], default=None)
    if near is not None and near["log_posterior"] > single_lp - SCAN_DELTA:
        return "as well", near
    return None, best


def scan_start(problem: ChannelProblem, space: ParameterSpace, single: MapResult
               ) -> tuple[MapResult, list[dict]]:
    """The full-transport model (``problem``'s, after :func:`use_full_transport`) on a coarse
    grid from the single-scattering MAP ``single``: kappa_t times ``SCAN_KT_FACTORS``, g at
    ``SCAN_G`` and the MAP's own; at each point the local model is built there and the MAP
    polished inside the trust region (one refresh of :func:`refine_map`).  Returns the best
    polished point and a row per point (``kappa_t``, ``g``, ``log_posterior``)."""
    rows, best = [], None
    for f in SCAN_KT_FACTORS:
        for g in (None, *SCAN_G):
            x = single.x.copy()
            x[0] = np.clip(single.x[0] + np.log(f), space.lower[0], space.upper[0])
            if g is not None:
                x[2] = np.clip(np.arctanh(g), space.lower[2], space.upper[2])
            problem.refresh_models(x)
            problem.adapt(x)
            lo, hi = _trust_region(space, x)
            new = find_map(problem.log_posterior, np.clip(x, lo, hi), lo, hi, global_evals=0,
                           laplace=False)
            rows.append({"kappa_t": float(np.exp(new.x[0])), "g": float(np.tanh(new.x[2])),
                         "log_posterior": float(new.log_posterior)})
            if best is None or new.log_posterior > best.log_posterior:
                best = new
    log.debug("full transport: scan from the single MAP %s: best %s", np.round(single.x, 3),
              np.round(best.x, 3))
    return best, rows


def use_single_scattering(problem: ChannelProblem, x: np.ndarray) -> None:
    """Undo :func:`use_full_transport`: every observation back to its analytic model."""
    for o in problem.obs:
        o.model = getattr(o.model, "single", o.model)
    problem.adapt(x)


def _trust_region(space: ParameterSpace, x: np.ndarray, step: float = TRUST_STEP
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The bounds within which a local model built at ``x`` is used: ``step`` either way in
    log kappa_t and atanh g (the local model's coordinates), the space's bounds else."""
    lo, hi = space.lower.copy(), space.upper.copy()
    for j in (0, 2):
        lo[j], hi[j] = max(lo[j], x[j] - step), min(hi[j], x[j] + step)
    return lo, hi


def _on_edge(space: ParameterSpace, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether ``x`` lies on a trust-region bound ``lo``/``hi`` of log kappa_t or atanh g
    that is not also the space's own bound."""
    tol = 1e-3 * TRUST_STEP
    return any((x[j] - lo[j] < tol and lo[j] > space.lower[j])
               or (hi[j] - x[j] < tol and hi[j] < space.upper[j]) for j in (0, 2))


def trace_bin(cam, width: int = TRACE_WIDTH, height: int = TRACE_HEIGHT) -> int:
    """Camera pixels per traced sample pixel (each way): a grid of about ``width`` x
    ``height`` sample pixels (the loop's, ``TRACE_WIDTH`` x ``TRACE_HEIGHT``, by default)."""
    return max(1, round(min(cam.width / width, cam.height / height)))


def final_bin(cam) -> int:
    """Camera pixels per sample pixel (each way) of the last refreshes (``more_paths``): a
    grid of about ``FINAL_TRACE_WIDTH`` x ``FINAL_TRACE_HEIGHT`` sample pixels."""
    return trace_bin(cam, FINAL_TRACE_WIDTH, FINAL_TRACE_HEIGHT)


def refine_map(problem: ChannelProblem, space: ParameterSpace, start: MapResult, *,
               max_refresh: int = MAX_REFRESH) -> tuple[MapResult, FullFitInfo]:
    """Alternate local-model refreshes and MAP polishes from ``start`` (module docstring).
    Returns the full-transport MAP (Laplace covariance over the whole bounds) and what the
    refreshes did; ``info.converged`` is False when ``MAX_REFRESH`` refreshes did not settle."""
    info = FullFitInfo()
    res, at, step, last = start, start.x, TRUST_STEP, None
    for i in range(max_refresh):
        problem.refresh_models(at)
        problem.adapt(at)
        lo, hi = _trust_region(space, at, step)
        new = off_the_plateau(problem, find_map(problem.log_posterior, np.clip(at, lo, hi),
                                                lo, hi, global_evals=0), lo, hi)
        edge = _on_edge(space, new.x, lo, hi)
        step = min(2.0 * step, TRUST_MAX) if edge else TRUST_STEP
        move = distance_sd(problem, new, at, None)
        cov = _cov_or_ridge(problem, new)  # a Laplace of its own where new.cov is None
        jitter = _in_term_units(at, new.x, cov, term_jackknife(problem, new))
        info.refreshes += 1
        info.moves_sd.append(move)
        info.moves_term.append(jitter)
        info.last_step = new.x - at
        res = new
        if move < MOVE_TOL_SD or jitter < 1.0:
            info.converged = True
            _log_refresh(info, at, new.x, move, jitter, step, "plain")
            break
        d = _move_in_sd(new.x, at, cov)
        # the last refresh is never extrapolated: no refresh after it checks where it landed
        nxt, how = _next_refresh(space, at, new.x, d, last, edge,
                                 extrapolate=i + 2 < max_refresh)
        _log_refresh(info, at, new.x, move, jitter, step, how)
        # the next pair of moves is judged from a plain refresh only (_next_refresh)
        at, last = nxt, ((d, edge) if how == "plain" else None)
        info.midpoints += int(how == "midpoint")
        info.extrapolated += int(how == "extrapolated")
    final = find_map(problem.log_posterior, res.x, space.lower, space.upper, global_evals=0)
    final.n_evals += start.n_evals
    return final, info


#: logit albedo beyond which a polish has ended on the albedo's plateau (kappa_a below
#: 3e-4 kappa_t): kappa_a -> 0 changes nothing there, and a local search stays wherever it
#: started (``off_the_plateau``)
PLATEAU_LOGIT = 8.0
#: the interior albedos ``off_the_plateau`` looks at, in logit albedo (albedo 0.88-0.993)
PLATEAU_PROBES = (2.0, 3.5, 5.0)
#: how far above the plateau's log posterior a polish from the interior must end to be kept
PLATEAU_GAIN = 1.0


def off_the_plateau(problem: ChannelProblem, res: MapResult, lo: np.ndarray, hi: np.ndarray
                    ) -> MapResult:
    """A polish ``res`` that ended on the albedo's plateau (logit albedo above
    ``PLATEAU_LOGIT``), looked at from inside: the log posterior at ``PLATEAU_PROBES`` albedos
    with g held and either kappa_s held (kappa_t = kappa_s / albedo: absorption added,
    scattering kept) or kappa_t held (kappa_s = kappa_t albedo: scattering turned into
    absorption), six evaluations; where one lies above the plateau's, the polish from the best
    of them (within ``lo``/``hi``) replaces ``res`` if it ends more than ``PLATEAU_GAIN``
    above.  The refreshes start from the single-scattering MAP, which is on the plateau
    wherever the missing multiple scattering made absorption look absent; measured on White
    Grapefruit Juice 160 ml (R, 100 x 75): every refresh stayed at logit albedo 14.7 (kappa_t
    -3.4 %), 7.3 log-posterior units below the mode the sampler found at 3.5 (docs/inference.md,
    "A MAP below its own samples").  Where the images pin kappa_t (the attenuation) far more
    tightly than the albedo, every probe that holds kappa_s lies far below the plateau: on
    the noise-free twin of the 100 x 75 px coverage run's round 9 (White Grapefruit Juice
    106.7 ml, R) by 344-161 210 units, where those holding kappa_t at logit albedo 3.5 and 5
    lay 65 and 77 above and the truth 238 above (docs/inference.md, "A MAP below its own
    samples")."""
    if not res.x[1] > PLATEAU_LOGIT:
        return res
    probes = []
    for la in PLATEAU_PROBES:
        for keep_kappa_s in (True, False):
            x = res.x.copy()
            x[1] = la
            if keep_kappa_s:
                x[0] = res.x[0] + np.log(expit(res.x[1])) - np.log(expit(la))
            x = np.clip(x, lo, hi)
            probes.append((problem.log_posterior(x), x))
    lp, x = max(probes, key=lambda p: p[0])
    if not lp > res.log_posterior:
        return res
    cand = find_map(problem.log_posterior, x, lo, hi, global_evals=0)
    cand.n_evals += res.n_evals + len(probes)
    if not cand.log_posterior > res.log_posterior + PLATEAU_GAIN:
        return res
    log.debug("full transport: the polish left the albedo's plateau (logit albedo %.3g -> "
              "%.3g, log posterior +%.3g)", res.x[1], cand.x[1],
              cand.log_posterior - res.log_posterior)
    return cand


def _next_refresh(space: ParameterSpace, at: np.ndarray, x: np.ndarray, d: np.ndarray,
                  last: tuple[np.ndarray, bool] | None, edge: bool, *, extrapolate: bool = True
                  ) -> tuple[np.ndarray, str]:
    """Where the next refresh goes after a polish from ``at`` to ``x`` (move ``d`` in sd,
    ``edge``: it ended on its trust region's edge; ``last``: the previous move and its edge
    flag if that refresh was plain, else None): ``x`` itself (``"plain"``); the midpoint of
    ``at`` and ``x`` where the move turned back (``REVERSAL_COS``, ``"midpoint"``; the fixed
    point lies between, wherever the previous move ended); beyond ``x`` where it went on the
    same way, shorter by a ratio r (``ALIGN_COS``, ``"extrapolated"``: the fixed point of
    x -> x* + r (x - x*), capped at ``EXTRAPOLATE_MAX`` times the move and the space's
    bounds), only where neither move ended on an edge (a move cut short says nothing of r),
    and only where ``extrapolate`` (False for the loop's last refresh: the polish from an
    extrapolated point is then the answer, its move unchecked; measured on Regular Milk 60 ml
    at 48 x 36, G: a last refresh 3 moves beyond, at r = 0.95, ended kappa_t +26 %).
    A polish that ended on its edge is plain."""
    if last is None or edge:
        return x, "plain"
    prev, prev_edge = last
    cos = _cosine(d, prev)
    if cos < REVERSAL_COS:
        return 0.5 * (at + x), "midpoint"
    n_prev = float(np.linalg.norm(prev))
    r = float(np.linalg.norm(d)) / n_prev if n_prev > 0 else 1.0
    if extrapolate and cos > ALIGN_COS and r < 1.0 and not prev_edge:
        k = min(r / (1.0 - r), EXTRAPOLATE_MAX)
        return np.clip(x + k * (x - at), space.lower, space.upper), "extrapolated"
    return x, "plain"


def _log_refresh(info: FullFitInfo, at, x, move: float, jitter: float, step: float,
                 how: str) -> None:
    """One refresh's line in the debug log (``fitmedia -v`` does not show it)."""
    log.debug("full transport: refresh %d at %s -> %s, move %.3g sd, %.3g in term units; "
              "next trust half-width %.2f%s", info.refreshes, np.round(at, 4), np.round(x, 4),
              move, jitter, step, "" if how == "plain" else f"; next refresh {how}")


def _move_in_sd(x: np.ndarray, at: np.ndarray, cov: np.ndarray | None) -> np.ndarray:
    """The move from ``at`` to ``x`` in log kappa_t and atanh g, each in units of its sd in
    ``cov`` (the new point's ``_cov_or_ridge``; unscaled where there is none)."""
    idx = [0, 2]
    sd = np.sqrt(np.diag(cov)[idx]) if cov is not None else np.ones(len(idx))
    return (np.asarray(x)[idx] - np.asarray(at)[idx]) / np.where(sd > 0, sd, 1.0)


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine of the angle between two moves (1 where either is zero)."""
    n = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float(a @ b) / n if n > 0 else 1.0


def term_jackknife(problem: ChannelProblem, res: MapResult) -> np.ndarray | None:
    """Covariance (P, P), in the sampler's coordinates, of the MAP's error that the
    multiple-scattering term's own Monte Carlo realisation causes: the delete-one jackknife
    over the term's independent batches of paths.  Each leave-one-out MAP is one Newton step
    from ``res`` (its Laplace covariance times the gradient of the log posterior with that
    batch left out, central differences at a tenth of a posterior sd), so the whole costs
    ``2 P`` posterior evaluations per batch and no new trace.  Where the Laplace covariance is
    not positive definite, that of log kappa_t and atanh g alone (``_cov_or_ridge``); where
    the albedo is on its plateau, that of the other coordinates with logit albedo held
    (``_newton_covariance``).  None without a Monte Carlo model or either covariance."""
    models = [o.model for o in problem.obs if hasattr(o.model, "leave_out")]
    if not models:
        return None
    cov = _newton_covariance(problem, res)
    if cov is None:
        return None
    lo, hi = problem.space.lower, problem.space.upper
    step = np.where(np.diag(cov) > 0, JACKKNIFE_STEP_SD * np.sqrt(np.diag(cov)), 0.0)
    deltas = []
    try:
        for i in range(min(m.ms.batches for m in models)):
            for m in models:
                m.leave_out = i
            grad = np.zeros(len(res.x))
            for j in range(len(res.x)):
                up, down = res.x.copy(), res.x.copy()
                up[j], down[j] = min(hi[j], res.x[j] + step[j]), max(lo[j], res.x[j] - step[j])
                if up[j] > down[j]:
                    grad[j] = (problem.log_posterior(up) - problem.log_posterior(down)) / (up[j] - down[j])
            deltas.append(cov @ grad)
    finally:
        for m in models:
            m.leave_out = None
    d = np.array(deltas)
    if not np.all(np.isfinite(d)):
        return None
    d -= d.mean(axis=0)
    return (len(d) - 1) / len(d) * d.T @ d


def _newton_covariance(problem: ChannelProblem, res: MapResult) -> np.ndarray | None:
    """The covariance ``term_jackknife``'s Newton steps use: the Laplace covariance
    (``_cov_or_ridge``), except where logit albedo's Laplace sd exceeds ``ALBEDO_HELD_SD``:
    then that of the other coordinates with logit albedo held at the MAP (zero in its row and
    column), so that the term's error moves kappa_t, g and the brightness, not an albedo the
    images do not determine; the ridge covariance if that is not positive definite."""
    if res.cov is None or res.cov[1, 1] <= ALBEDO_HELD_SD ** 2:
        return _cov_or_ridge(problem, res)
    held = _ridge_covariance(problem, res.x, [j for j in range(len(res.x)) if j != 1])
    return held if held is not None else _ridge_covariance(problem, res.x)


def _ridge_covariance(problem: ChannelProblem, x: np.ndarray, idx=(0, 2)) -> np.ndarray | None:
    """Where the full Laplace covariance is not positive definite or the albedo is on its
    plateau: the covariance of the coordinates ``idx`` (log kappa_t and atanh g) with the
    others held at ``x``, embedded in a (P, P) matrix with zeros elsewhere (the term's error
    is then carried by those alone); None if that is not positive definite either."""
    idx = list(idx)

    def sub(y):
        z = x.copy()
        z[idx] = y
        return problem.log_posterior(z)
    small = laplace_covariance(sub, x[idx], problem.space.lower[idx], problem.space.upper[idx])
    if small is None:
        return None
    cov = np.zeros((len(x), len(x)))
    cov[np.ix_(idx, idx)] = small
    return cov


def convolve_samples(samples: np.ndarray, cov: np.ndarray, rng: np.random.Generator
                     ) -> np.ndarray:
    """Posterior samples (N, P) with the term's realisation error added: each moved by an
    independent N(0, ``cov``) draw (the camera's noise and the term's Monte Carlo error are
    independent, so the posterior of the values is the convolution of the two)."""
    val, vec = np.linalg.eigh(0.5 * (cov + cov.T))
    root = vec * np.sqrt(np.clip(val, 0.0, None))
    return samples + rng.standard_normal(samples.shape) @ root.T


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


def ms_detectability(problem: ChannelProblem, u: np.ndarray, spec, channel: str, *,
                     seed: int) -> dict:
    """For a single-scattering fit at its MAP ``u``: would its images show the multiple-
    scattering term that the single model leaves out, were it there?

    The term ``M`` at ``u`` (one trace per image, on the full model's grid) is what a
    photograph of this medium holds beyond the model.  The single model is fitted again
    (local search from ``u``, quadrature re-adapted once) to noise-free what-if images, its
    own images at ``u`` plus ``M``, with the likelihood's noise; what it cannot absorb is the
    rise of chi2/pixel at the MAP that the term would cause: ``excess = (chi2 - sum(se_M^2 /
    var)) / N``, the term's own Monte Carlo variance subtracted, floored at 0.  It is exact
    only where ``u`` is the truth; where the images hold the term, ``u`` has already absorbed
    it and the what-if holds it twice (measured in docs/results.md, "trust"; trust.py allows
    for both: ``MS_DETECT_FACTOR``).  The problem's quadrature is left adapted at ``u``.

    Returns ``share`` and ``share_se`` per image (:meth:`MultipleScattering.share`, 0 where
    the medium does not scatter) and ``chi2_excess_per_pixel``."""
    from ..forward.multiple import MultipleScattering
    from .likelihood import Observation

    p = problem.space.to_params(u)
    b = p.brightness if problem.space.free_brightness else problem.brightness
    shares, errors, whatif, term_var = [], [], [], []
    for i, (o, img0) in enumerate(zip(problem.obs, problem.render(u))):
        ks = o.concentration * p.kappa_s
        term, se = np.zeros_like(img0), np.zeros_like(img0)
        share = err = 0.0
        if ks > 0:
            ms = MultipleScattering(spec, i, channels=(channel,),
                                    bin=trace_bin(spec.camera_for(i)))
            sh, sh_se, img, img_se = ms.share_and_render(
                [o.concentration * p.kappa_a + problem.water_kappa_a], [ks], [p.g], [b],
                seed=seed, single=getattr(o.model, "single", o.model))
            share, err, term, se = float(sh[0]), float(sh_se[0]), img[..., 0], img_se[..., 0]
        shares.append(share)
        errors.append(err)
        whatif.append(Observation(o.model, img0 + term, o.valid, o.concentration, o.gain,
                                  o.read_var))
        term_var.append(se.ravel()[o.flat_idx] ** 2)
    other = ChannelProblem(whatif, problem.space, problem.brightness,
                           (problem.gain, problem.read_var), water_kappa_a=problem.water_kappa_a)
    other._noise = problem._noise  # the real images' variance floors, not the what-if's
    res = find_map(other.log_posterior, u, problem.space.lower, problem.space.upper,
                   global_evals=0, laplace=False)
    other.adapt(res.x)
    res = find_map(other.log_posterior, res.x, problem.space.lower, problem.space.upper,
                   global_evals=0, laplace=False)
    problem.adapt(u)
    chi2, n = other.chi2(res.x)
    mc = sum(float(np.sum(v / other.variance(k, m.ravel()[o.flat_idx])))
             for k, (o, v, m) in enumerate(zip(whatif, term_var, other.render(res.x))))
    return {"share": shares, "share_se": errors,
            "chi2_excess_per_pixel": max(chi2 - mc, 0.0) / max(n, 1)}


class SeedShift(NamedTuple):
    """What ``seed_shift`` measured: the move of the MAP, at the loop's paths, when the term is
    traced with other random numbers (sampler coordinates), the MAP's ``_cov_or_ridge`` there,
    and the move's largest coordinate in posterior sd (``distance_sd``, for fits without the
    term's jackknife)."""

    move: np.ndarray
    cov: np.ndarray | None
    posterior_sd: float


def seed_shift(problem: ChannelProblem, space: ParameterSpace, res: MapResult, spec,
               channel: str, *, seed: int) -> SeedShift:
    """How far the full-transport MAP ``res`` moves when the multiple-scattering term is
    traced with other random numbers (``seed``): a second fit, two refreshes from ``res``
    (``seed_shift_units`` judges the move).  The problem keeps its original term afterwards."""
    with problem.models_kept():
        for o in problem.obs:
            o.model = getattr(o.model, "single", o.model)
        use_full_transport(problem, spec, channel, seed=seed)
        other, _ = refine_map(problem, space, res, max_refresh=2)
    problem.adapt(res.x)
    return SeedShift(other.x - res.x, _cov_or_ridge(problem, res),
                     distance_sd(problem, other, res.x, None))


def seed_shift_units(shift: SeedShift, loop_term: np.ndarray | None,
                     final_term: np.ndarray | None = None, offset: np.ndarray | None = None
                     ) -> float:
    """The seed shift (``seed_shift``, at the loop's paths) in units of the sd such a move has
    if the term's error that the values' intervals state is right: its largest coordinate of
    log kappa_t and atanh g over sqrt(2 C_j rho_j), plus the refreshes' own tolerance
    (``_in_term_units``), with C the loop's jackknife ``loop_term`` and rho_j = (C'_j + O_j) /
    C'_j the intervals' term error at the last refreshes' paths, the jackknife ``final_term``
    (C') plus the offset budget ``offset`` (O), as a multiple of that jackknife.  The shift is
    measured at the loop's paths and the intervals are for the last refreshes' values, so the
    loop's jackknife is scaled by the ratio the intervals apply at theirs (rho = 1 without an
    offset budget: the shift against the loop's jackknife alone, as until 2026-12-07).  Since
    2026-12-07: the bench's 200 x 150 milk capture moved 3.12 times the loop's jackknife in B,
    while its intervals held an offset budget 7 times the final jackknife's sd in log kappa_t
    and 11 times in atanh g (docs/inference.md, "The seed shift against the intervals' whole
    term error").  A large value means the intervals understate the term's error.  Without
    ``loop_term``: the move in posterior sd."""
    if loop_term is None:
        return shift.posterior_sd
    scale = np.ones(len(shift.move))
    if final_term is not None and offset is not None:
        c = np.diag(final_term)
        scale = np.where(c > 0, (c + np.diag(offset)) / np.where(c > 0, c, 1.0), 1.0)
    scaled = loop_term * np.sqrt(np.outer(scale, scale))  # diag: C_j rho_j
    return _in_term_units(np.zeros_like(shift.move), shift.move, shift.cov, scaled)


def _cov_or_ridge(problem: ChannelProblem, res: MapResult) -> np.ndarray | None:
    """The Laplace covariance of ``res``, else that of log kappa_t and atanh g alone."""
    return res.cov if res.cov is not None else _ridge_covariance(problem, res.x)


def _in_term_units(a: np.ndarray, b: np.ndarray, cov: np.ndarray | None,
                   term_cov: np.ndarray | None) -> float:
    """Largest difference of log kappa_t and atanh g between ``a`` and ``b`` in units of the
    sd that two independent realisations of the term give it (sqrt(2 C_jj), ``term_cov`` the
    jackknife's C) plus the refreshes' tolerance (``MOVE_TOL_SD`` Laplace sd at each end);
    inf without ``term_cov`` or ``cov``."""
    if term_cov is None or cov is None:
        return float("inf")
    idx = [0, 2]
    sd = np.sqrt(2.0 * np.diag(term_cov)[idx] + 2.0 * MOVE_TOL_SD**2 * np.diag(cov)[idx])
    return float(np.max(np.abs(b[idx] - a[idx]) / sd))


def restart_shift(problem: ChannelProblem, space: ParameterSpace, res: MapResult,
                  single_x: np.ndarray, term_cov: np.ndarray | None
                  ) -> tuple[float, MapResult, FullFitInfo]:
    """A second full-transport fit of the same images and term, started beyond the MAP on
    the far side from the single-scattering MAP ``single_x`` (as far again along log kappa_t
    and atanh g, the direction in which multiple scattering moved the values): the largest
    distance between the two fits in log kappa_t and atanh g, in units of the values' sd
    (Laplace plus ``term_cov``), the second fit and what its refreshes did.  The refreshes
    stop at fixed points of the local model; where the images hardly distinguish points along
    the kappa_t-g ridge, the term's noise makes more than one, and the two fits end apart.
    The problem's local model is rebuilt at ``res`` afterwards."""
    idx = [0, 2]
    start = res.x.copy()
    start[idx] = np.clip(res.x[idx] + np.clip(res.x[idx] - single_x[idx], -RESTART_REACH,
                                              RESTART_REACH),
                         space.lower[idx], space.upper[idx])
    first = MapResult(start, problem.log_posterior(start), 0, None)
    other, info = refine_map(problem, space, first, max_refresh=RESTART_REFRESHES)
    problem.refresh_models(res.x)
    problem.adapt(res.x)
    return distance_sd(problem, res, other.x, term_cov), other, info


def log_posterior_rebuilt(problem: ChannelProblem, x: np.ndarray) -> float:
    """The full model's log posterior at ``x`` with its local model rebuilt there (the same
    random numbers wherever it is built, so two points compare on one realisation)."""
    problem.refresh_models(x)
    problem.adapt(x)
    return float(problem.log_posterior(x))


def restart_delta(problem: ChannelProblem, res: MapResult, restart: MapResult,
                  restart_info: FullFitInfo) -> tuple[float | None, list[float] | None]:
    """The log posterior at the restart's end minus that at the MAP ``res``, each with the
    local model rebuilt there (``log_posterior_rebuilt``), where the restart settled (a fixed
    point of the loop, as the MAP is); None where it did not (its end is no fixed point, and
    where it would have settled is not known).  Where that difference on the term's own seed
    is beyond ``RESTART_DELTA``, it is traced again on ``DELTA_SEEDS`` more seeds, and where
    that leaves it undecided (``delta_undecided``) on ``DELTA_SEEDS_MORE`` more; the
    difference returned is what lies beyond their spread (``delta_beyond_noise``): a
    difference the term's noise made does not decide.  Returns that difference and the
    per-seed ones (own seed first).  The local model is left rebuilt at ``res`` on its own
    seed."""
    if not restart_info.converged:
        return None, None
    values = [_delta_once(problem, res, restart)]
    models = [o.model for o in problem.obs
              if hasattr(o.model, "seed") and hasattr(o.model, "refresh")]
    if abs(values[0]) <= RESTART_DELTA or not models:
        return values[0], values
    seeds = [m.seed for m in models]
    try:
        for more in (DELTA_SEEDS, DELTA_SEEDS_MORE):
            for j in range(len(values), len(values) + more):
                for m, s in zip(models, seeds):
                    m.seed = s + DELTA_SEED_STEP * j
                values.append(_delta_once(problem, res, restart))
            if not delta_undecided(values):
                break
    finally:
        for m, s in zip(models, seeds):
            m.seed = s
        log_posterior_rebuilt(problem, res.x)
    return delta_beyond_noise(values), values


def _delta_once(problem: ChannelProblem, res: MapResult, restart: MapResult) -> float:
    """One seed's log posterior at the restart's end minus the MAP's, each rebuilt there."""
    there = log_posterior_rebuilt(problem, restart.x)
    return there - log_posterior_rebuilt(problem, res.x)


def delta_beyond_noise(values: list[float]) -> float:
    """The part of the mean of ``values`` (one log-posterior difference per seed of the term)
    that lies beyond its one-sided ``DELTA_LOOK_LEVEL`` confidence bound: sign(m) max(|m| -
    t s / sqrt(n), 0), t Student's with n - 1 degrees of freedom and s the values' spread; the
    mean itself for one value.  Beyond +-``RESTART_DELTA`` exactly where that bound is."""
    v = np.asarray(values, float)
    m = float(v.mean())
    if v.size < 2:
        return m
    from scipy.stats import t as student_t

    t = float(student_t.ppf(DELTA_LOOK_LEVEL, v.size - 1))
    return float(np.sign(m) * max(abs(m) - t * float(v.std(ddof=1)) / np.sqrt(v.size), 0.0))


def delta_undecided(values: list[float]) -> bool:
    """Whether more seeds could decide: the mean of ``values`` is beyond ``RESTART_DELTA``
    but the part of it beyond the noise (``delta_beyond_noise``) is not."""
    return (abs(float(np.mean(values))) > RESTART_DELTA
            and abs(delta_beyond_noise(values)) <= RESTART_DELTA)


def adopt_restart(problem: ChannelProblem, loop: MapResult, loop_info: FullFitInfo,
                  restart: MapResult, restart_info: FullFitInfo, delta: float | None = None
                  ) -> bool:
    """Whether the refreshes go on from the restart's end (``restart_shift``) instead of the
    loop's end: the restart settled where the log posterior is more than ``RESTART_DELTA``
    above the loop's end (``delta``, :func:`restart_delta`), the images prefer it; or the loop
    did not settle and crept (its last move, in the posterior sd at
    its end, points towards the restart's end: cosine above ``ALIGN_COS``), and the restart,
    started beyond, settled or ended with a smaller move than the loop's last.  The fixed
    point is then approached from both sides, and the restart is the nearer to it.  Measured
    on Regular Milk 60 ml at 48 x 36 px (G): the loop crept in atanh g 0.24, 0.28, 0.37,
    0.43, 0.49 (about 0.06 and 3-4 sd a refresh, truth 0.90) and did not settle in
    ``MAX_REFRESH``; the restart from atanh g 0.75 came back to 0.81 with moves of 8, 10, 4
    and 1.7 sd (docs/inference.md, "Dense milk: going on from the restart")."""
    if delta is not None and delta > RESTART_DELTA:
        return True
    if loop_info.converged or loop_info.last_step is None or not loop_info.moves_sd:
        return False
    if not (restart_info.converged
            or (restart_info.moves_sd and restart_info.moves_sd[-1] < loop_info.moves_sd[-1])):
        return False
    cov = _cov_or_ridge(problem, loop)
    ahead = _move_in_sd(restart.x, loop.x, cov)
    step = _move_in_sd(loop.x + loop_info.last_step, loop.x, cov)
    return _cosine(step, ahead) > ALIGN_COS


def go_on_from_restart(problem: ChannelProblem, space: ParameterSpace, info: FullFitInfo,
                       restart: MapResult, restart_info: FullFitInfo
                       ) -> tuple[MapResult, FullFitInfo]:
    """The refreshes gone on from the restart's end (``adopt_restart`` said yes), at most
    ``RESTART_REFRESHES`` more: their MAP, and ``info`` with the restart's refreshes and
    theirs counted in (settled as they are)."""
    res, more = refine_map(problem, space, restart, max_refresh=RESTART_REFRESHES)
    return res, info.followed_by(restart_info, more)


class RestartCheck(NamedTuple):
    """What :func:`restart_check` found: the MAP and its refreshes' ``info`` (gone on from
    the restart where ``adopted``), the restart's MapResult, the term's jackknife at the MAP
    (``term_cov``) and the restart's log posterior relative to the loop's end (``delta``,
    :func:`restart_delta`; None where the restart did not settle)."""

    res: MapResult
    info: FullFitInfo
    restart: MapResult
    adopted: bool
    term_cov: np.ndarray | None
    delta: float | None
    #: the per-seed differences behind ``delta`` (:func:`restart_delta`)
    delta_seeds: list[float] | None = None


def restart_check(problem: ChannelProblem, space: ParameterSpace, res: MapResult,
                  info: FullFitInfo, single_x: np.ndarray, channel: str) -> RestartCheck:
    """The restart check on the loop's end ``res`` (``restart_shift``, with the term's
    jackknife there, and ``restart_delta``), and where ``adopt_restart`` says so the
    refreshes gone on from the restart's end (``go_on_from_restart``)."""
    term_cov = term_jackknife(problem, res)
    _, restart, restart_info = restart_shift(problem, space, res, single_x, term_cov)
    delta, delta_seeds = restart_delta(problem, res, restart, restart_info)
    adopted = adopt_restart(problem, res, info, restart, restart_info, delta)
    if adopted:  # the restart fits better, or the loop crept towards it: go on from there
        log.info("full transport, channel %s: a second fit from beyond ended %s; going on from "
                 "there", channel, "where the images fit better" if delta is not None and
                 delta > RESTART_DELTA else "where the refreshes, which did not settle, crept")
        res, info = go_on_from_restart(problem, space, info, restart, restart_info)
        term_cov = term_jackknife(problem, res)
    return RestartCheck(res, info, restart, adopted, term_cov, delta, delta_seeds)


def restart_in_loop_units(problem: ChannelProblem, loop: MapResult, restart_x: np.ndarray,
                          loop_term_cov: np.ndarray | None, final_x: np.ndarray) -> float:
    """The restart's distance (``restart_shift``: two fixed points of the loop, at the loop's
    paths) in units of the loop's own precision: the values' sd at the loop's fixed point
    ``loop`` (Laplace plus its ``loop_term_cov``) and, per coordinate, the last refreshes' move
    from it to ``final_x``, which measures how far the term at the loop's paths put a fixed
    point from where more paths put it.  Two fixed points closer than that are not told apart
    by the loop (measured at 200 x 150: restarts 3.9-4.8 sd away in those units alone, where
    the last refreshes moved 11-15 sd and ended within 0.2 % of the truth; docs/inference.md)."""
    d = np.asarray(final_x, float) - loop.x
    extra = np.outer(d, d) + (loop_term_cov if loop_term_cov is not None else 0.0)
    return distance_sd(problem, loop, restart_x, extra)


def distance_sd(problem: ChannelProblem, res: MapResult, x: np.ndarray,
                term_cov: np.ndarray | None) -> float:
    """Largest distance of log kappa_t and atanh g (the local model's coordinates) between
    ``x`` and the MAP ``res`` in units of the values' sd there: the Laplace covariance, or
    where that is not positive definite (the albedo on its plateau) ``_cov_or_ridge``'s, plus
    the term's ``term_cov`` (None: the posterior sd alone, as for a refresh's move); inf
    without a covariance."""
    idx = [0, 2]
    cov = _cov_or_ridge(problem, res)
    if cov is None:
        return float("inf")
    sd = np.sqrt(np.diag(cov + (term_cov if term_cov is not None else 0.0))[idx])
    return float(np.max(np.abs(np.asarray(x)[idx] - res.x[idx]) / sd))


def more_paths(problem: ChannelProblem, space: ParameterSpace, res: MapResult, *,
               factor: int = FINAL_PATHS_FACTOR, max_refresh: int = FINAL_REFRESHES
               ) -> tuple[MapResult, FullFitInfo, int]:
    """The last refreshes: every full-transport model of ``problem`` traces ``factor`` times
    its paths from now on, and the MAP is refined from ``res`` with at most ``max_refresh``
    refreshes (``refine_map``).  At the paths of the loop (256 per sample pixel) the refresh
    loop's fixed point is offset by the term's own noise (kappa_t and g low by up to a few
    posterior sd; the offset falls with the paths: at 8 times them, with the term built at the
    truth, about 1 posterior sd and at 16 times 0.3: docs/inference.md); the sampler then
    runs on this local model, whose cost does not depend on the paths.  A term traced on a
    grid coarser than ``final_bin``'s is traced on that finer grid from now on (the coarse
    grid's upsampling leaves a bias).
    Returns the MAP, what the refreshes did, and the paths per sample pixel now traced."""
    paths = 0
    for o in problem.obs:
        ms = getattr(o.model, "ms", None)
        if ms is not None and hasattr(ms, "n_paths"):
            ms.n_paths = int(ms.n_paths * max(int(factor), 1))
            paths = ms.n_paths
            finer = final_bin(ms.camera)
            if hasattr(o.model, "rebin") and finer < ms.bin:
                o.model.rebin(finer)
    new, info = refine_map(problem, space, res, max_refresh=max_refresh)
    return new, info, paths


def offset_budget(res: MapResult, loop_x: np.ndarray) -> np.ndarray:
    """Covariance (P, P), in the sampler's coordinates, of the offset that the term's own
    noise may still give the MAP ``res`` after the last refreshes (``more_paths``) moved it
    from the loop's fixed point ``loop_x``: rank one along that move, its sd ``OFFSET_SHARE``
    of it.  The offset's sign is known (the move's), its size only within the measured fall
    with the paths, so it enters the values' error as a symmetric budget of that size, not as
    a correction.  logit albedo is left out where it is on its plateau (Laplace sd above
    ``ALBEDO_HELD_SD``; its moves there are not the offset: ``_newton_covariance``).
    Its part of the move is the smaller of the move in logit albedo and the move in the albedo
    itself through the slope of logit albedo at ``res`` (1 / (a (1 - a))): a loop that ended on
    the plateau (logit albedo near its bound, kappa_a unresolved at the loop's paths) and
    last refreshes that resolved kappa_a move logit albedo by ~10 for an albedo move of a few
    per cent, which as a budget of half that in logit albedo put albedos of 0 to 1 into the
    samples (measured on White Grapefruit Juice 160 ml, G, 100 x 75: kappa_s 90 % interval
    [0.0005, 0.548] 1/mm around 0.52; docs/inference.md, "The offset budget's albedo part")."""
    x, x0 = np.asarray(res.x, float), np.asarray(loop_x, float)
    d = OFFSET_SHARE * (x - x0)
    if res.cov is None or not res.cov[1, 1] <= ALBEDO_HELD_SD ** 2:
        d[1] = 0.0
    else:
        a, a0 = expit(x[1]), expit(x0[1])
        through_slope = OFFSET_SHARE * abs(a - a0) / max(a * (1.0 - a), 1e-300)
        d[1] = np.sign(d[1]) * min(abs(d[1]), through_slope)
    return np.outer(d, d)


def ms_images(problem: ChannelProblem, u: np.ndarray) -> list[np.ndarray] | None:
    """Per observation, the multiple-scattering part (H, W) of the model image at ``u`` (None
    when the problem's models have none)."""
    out = []
    for o, medium in zip(problem.obs, problem._medium(u)[0]):
        part = getattr(o.model, "ms_part", None)
        if part is None:
            return None
        out.append(part(*medium)[0][..., 0])
    return out
