"""Posterior sampling with emcee, started around the MAP, run until the chain
is at least ``n_tau`` autocorrelation times long (or a step cap, reported as not
converged), checkpointed in emcee's HDF5 backend so a killed run resumes."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .summary import kish_ess

#: A second mode of g (the other sign) whose log posterior is within this of the MAP's is
#: sampled too (a chain of its own) and the two chains are mixed by the modes' posterior masses.
#: 8 units below, the density is 3.4e-4 of the MAP's; the backward mode at g's bound is
#: narrower than the forward one (mass 0.2 x density ratio in a measured case), so a mode left
#: out holds well under 0.1 % of the posterior (docs/inference.md)
OTHER_MODE_DELTA = 8.0


@dataclass
class ChainResult:
    samples: np.ndarray  # (n_samples, ndim), burn-in discarded, thinned
    n_steps: int
    tau: np.ndarray
    acceptance_fraction: float
    converged: bool
    reason: str
    burn: int
    thin: int
    log_prob_samples: np.ndarray = field(default=None, repr=False)
    chain: np.ndarray = field(default=None, repr=False)  # (walkers, steps after burn-in, ndim)
    ess: np.ndarray | None = None  # bulk effective sample size per parameter (ArviZ)
    rhat: np.ndarray | None = None  # rank-normalised split R-hat per parameter, walkers as chains


def initial_ball(x_map: np.ndarray, cov: np.ndarray | None, lower: np.ndarray, upper: np.ndarray,
                 n_walkers: int, rng: np.random.Generator) -> np.ndarray:
    """Walkers around the MAP: from the Laplace covariance when there is one."""
    n = len(x_map)
    if cov is not None:
        p = rng.multivariate_normal(x_map, cov, size=n_walkers)
    else:
        p = x_map + 1e-3 * (upper - lower) * rng.standard_normal((n_walkers, n))
    span = upper - lower
    return np.clip(p, lower + 1e-6 * span, upper - 1e-6 * span)


#: A walker whose starting log posterior is this far below the MAP's starts at the MAP
#: instead: a normal ball puts 4 parameters at most ~17 below (chi-square(4) / 2 at 1e-6)
START_MAX_DROP = 25.0


def start_walkers(log_prob: Callable[[np.ndarray], float], x_map: np.ndarray,
                  cov: np.ndarray | None, lower: np.ndarray, upper: np.ndarray, n_walkers: int,
                  rng: np.random.Generator) -> np.ndarray:
    """The chain's first positions: :func:`initial_ball`, with every walker whose log posterior
    is more than ``START_MAX_DROP`` below the MAP's (or not finite: outside a mode's half of
    g, see :func:`half_space`) moved to the MAP, jittered by 1e-6 of the box.  Such walkers
    come from a Laplace covariance that is wide along a plateau (a thin or milky albedo) and
    are clipped to the prior's bounds far out; an outlier walker can stay out for good, since
    differential-evolution steps are scaled by the other walkers' spread (a Lowfat Milk B
    chain at 200 x 150 kept one at kappa_t / 250, log posterior 2e6 below, with the albedo
    move, whose kappa_s-keeping jumps drag kappa_t along)."""
    start = initial_ball(x_map, cov, lower, upper, n_walkers, rng)
    lp_map = log_prob(x_map)
    bad = ~(np.array([log_prob(p) for p in start]) > lp_map - START_MAX_DROP)
    if np.any(bad):
        span = upper - lower
        start[bad] = x_map + 1e-6 * span * rng.standard_normal((int(bad.sum()), len(x_map)))
        start[bad] = np.clip(start[bad], lower, upper)
    return start


def run_chain(log_prob: Callable[[np.ndarray], float], x_map: np.ndarray, cov: np.ndarray | None,
              lower: np.ndarray, upper: np.ndarray, *, rng: np.random.Generator,
              checkpoint: Path | None = None, resume: bool = False,
              n_walkers: int | None = None, n_tau: float = 50.0, max_steps: int = 20000,
              check_every: int = 100, progress: bool = True, label: str = "",
              redraw: Redraw | None = None, identity: dict | None = None) -> ChainResult:
    """Run emcee until the chain is ``n_tau`` autocorrelation times long.

    Converged means: steps >= n_tau * max(tau), the tau estimate changed by less
    than 5 % since the previous check, the split R-hat across walker groups is
    <= 1.01 and the bulk ESS >= 400 (ArviZ).  With ``resume`` and an existing
    checkpoint, sampling continues from its last state (no steps repeated).  ``identity``
    (:func:`fitmedia.inference.identity.run_identity`) is stored in the checkpoint; a checkpoint
    of another identity is refused with an InputError.
    ``redraw``: an extra Metropolis-Hastings move beside differential evolution (:class:`Redraw`).
    """
    import emcee

    ndim = len(x_map)
    n_walkers = n_walkers or max(4 * ndim, 16)
    backend = emcee.backends.Backend()
    restored = load_checkpoint(checkpoint, backend, identity) \
        if (resume and checkpoint is not None) else None
    if restored is not None and backend.shape != (backend.nwalkers, ndim):
        from ..errors import InputError

        raise InputError(f"{checkpoint}: checkpoint of {backend.ndim} parameters, this fit has "
                         f"{ndim}; remove it to start afresh")
    if restored is None:
        backend.reset(n_walkers, ndim)
        start = start_walkers(log_prob, x_map, cov, lower, upper, n_walkers, rng)
    else:
        n_walkers, start = backend.nwalkers, restored
    # differential evolution only.  emcee <= 3.1.6's DESnookerMove normalises its direction by
    # sqrt(|delta|) instead of |delta| (fixed upstream after 3.1.6, dfm/emcee#531): its stationary
    # distribution is too narrow.  Mixed in at 20 % it made our posteriors 5-9 % narrower than
    # importance sampling and random-walk Metropolis found (docs/inference.md, "Posterior").
    moves = [(emcee.moves.DEMove(), 1.0 - (0.0 if redraw is None else redraw.weight))]
    if redraw is not None:
        moves.append((redraw.move(), redraw.weight))
    sampler = emcee.EnsembleSampler(n_walkers, ndim, log_prob, moves=moves, backend=backend)
    # emcee draws from a numpy RandomState; seed it from our Generator (explicit, reproducible);
    # a resumed chain continues with the random state stored in its checkpoint
    sampler._random = np.random.RandomState(int(rng.integers(2**31 - 1)))
    run = _ChainRun(sampler, backend, checkpoint, json.dumps(identity, sort_keys=True), n_tau,
                    max_steps, check_every, tau=np.full(ndim, np.nan))
    run.sample(start, progress, label)
    return run.result()


@dataclass
class _ChainRun:
    """:func:`run_chain`'s sampling loop and its result: an emcee ``sampler`` stepped until
    the convergence criteria hold or ``max_steps``, checkpointed every ``check_every`` steps."""

    sampler: Any
    backend: Any
    checkpoint: Path | None
    ident: str  # the run identity as stored in the checkpoint (one JSON line)
    n_tau: float
    max_steps: int
    check_every: int
    converged: bool = False
    reason: str = ""
    tau: np.ndarray | None = None

    def sample(self, start, progress: bool, label: str) -> None:
        from tqdm.auto import tqdm

        sampler, n_tau, max_steps = self.sampler, self.n_tau, self.max_steps
        done = sampler.iteration
        old_tau = np.inf
        self.reason = f"step cap {max_steps} reached before {n_tau:g} autocorrelation times"
        bar = tqdm(total=max_steps, initial=done, desc=f"MCMC {label}".strip(), unit="step",
                   disable=not progress, leave=False, mininterval=1.0)
        try:
            remaining = max_steps - done
            for _ in sampler.sample(start, iterations=max(remaining, 0), progress=False,
                                    store=True):
                bar.update(1)
                it = sampler.iteration
                if it % self.check_every:
                    continue
                if self.checkpoint is not None:
                    save_checkpoint(self.checkpoint, self.backend, self.ident)
                tau = self.tau = sampler.get_autocorr_time(tol=0)
                need = n_tau * np.max(tau)
                bar.set_postfix_str(f"tau={np.max(tau):.0f}, need {need:.0f}")
                if it >= need and np.all(np.abs(old_tau - tau) / tau < 0.05) and \
                        self._settled(it):
                    break
                old_tau = tau
        finally:
            bar.close()
        if self.checkpoint is not None:
            save_checkpoint(self.checkpoint, self.backend, self.ident)

    def _settled(self, it: int) -> bool:
        """R-hat and ESS of the chain after burn-in (the tau criteria already hold)."""
        tau = self.tau
        burn_now = int(min(3 * np.max(tau), it // 2))
        ess, rhat = arviz_diagnostics(np.swapaxes(self.sampler.get_chain(discard=burn_now), 0, 1))
        if ess is None or (np.max(rhat) <= RHAT_MAX and np.min(ess) >= ESS_MIN):
            self.converged = True
            self.reason = f"chain {it} steps >= {self.n_tau:g} x tau_max {np.max(tau):.1f}"
            if ess is not None:
                self.reason += f"; split R-hat {np.max(rhat):.3f}, bulk ESS {np.min(ess):.0f}"
            return True
        self.reason = (f"step cap {self.max_steps} reached: split R-hat {np.max(rhat):.3f} "
                       f"(need <= {RHAT_MAX}) or bulk ESS {np.min(ess):.0f} (need >= {ESS_MIN})")
        return False

    def result(self) -> ChainResult:
        """The chain after burn-in (3 tau_max) and thinned (tau_max / 2), with diagnostics."""
        sampler, tau = self.sampler, self.tau
        n_steps = sampler.iteration
        if n_steps >= 2 * self.check_every and not np.all(np.isfinite(tau)):
            tau = sampler.get_autocorr_time(tol=0)
        elif n_steps >= self.check_every:
            tau = sampler.get_autocorr_time(tol=0)
        tmax = float(np.nanmax(tau)) if np.any(np.isfinite(tau)) else 1.0
        burn = int(min(3 * tmax, n_steps // 2))
        thin = max(1, int(tmax / 2))
        samples = sampler.get_chain(discard=burn, thin=thin, flat=True)
        logp = sampler.get_log_prob(discard=burn, thin=thin, flat=True)
        chain = np.swapaxes(sampler.get_chain(discard=burn), 0, 1)
        ess, rhat = arviz_diagnostics(chain)
        return ChainResult(samples, n_steps, np.asarray(tau),
                           float(np.mean(sampler.acceptance_fraction)), self.converged,
                           self.reason, burn, thin, logp, chain, ess, rhat)


@dataclass(frozen=True)
class Redraw:
    """An extra Metropolis-Hastings move for the chains, used in a share ``weight`` of the
    steps beside differential evolution.  ``propose(coords, random)`` returns the proposed
    coordinates (walkers, ndim) and log q(x | x') - log q(x' | x) per walker, as
    ``emcee.moves.MHMove`` expects (:func:`fitmedia.inference.fit.albedo_redraw`)."""

    propose: Callable
    weight: float

    def move(self):
        import emcee

        return emcee.moves.MHMove(self.propose)


def half_space(log_prob: Callable[[np.ndarray], float], index: int, side: float
               ) -> Callable[[np.ndarray], float]:
    """``log_prob`` on the half of the box where ``x[index]`` has the sign of ``side`` (one mode
    of g when ``index`` is atanh g; ``side`` = 0 counts as positive), -inf on the other half."""
    sign = -1.0 if side < 0 else 1.0

    def f(x):
        return log_prob(x) if sign * x[index] > 0 else -np.inf
    return f


@dataclass
class ModeMass:
    """Bridge-sampling estimate of the integral of exp(log_prob) over one mode."""

    log_mass: float
    rel_se: float  # relative standard error of the mass (Fruhwirth-Schnatter 2004)
    ess: float  # effective sample size of the proposal draws' importance weights
    n_draws: int
    n_iter: int  # iterations of the bridge's fixed point


def mode_log_mass(log_prob: Callable[[np.ndarray], float], samples: np.ndarray,
                  log_prob_samples: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                  rng: np.random.Generator, *, n_eff: float | None = None, n_draws: int = 3000,
                  df: float = 5.0, inflate: float = 1.5, max_iter: int = 1000) -> ModeMass:
    """log of the integral of exp(``log_prob``) over the region where it is finite, by bridge
    sampling (Meng & Wong 1996, the optimal bridge; Gronau et al. 2017's recipe).

    The proposal is a multivariate Student-t (``df``) with the mean of a random half of the
    mode's posterior ``samples`` and ``inflate`` times their covariance; the other half, with
    their stored ``log_prob_samples``, is the bridge's posterior side (``n_eff`` of them
    independent, e.g. from the chain's effective sample size).  The bridge stays accurate when
    the proposal matches the mode poorly (a curved or cut mode), where plain importance
    sampling from the same proposal does not.  Proposal draws outside the box or the mode's
    region have density 0: the estimate is the region's integral.
    """
    from scipy.special import logsumexp
    from scipy.stats import multivariate_t

    n, ndim = samples.shape
    perm = rng.permutation(n)
    fit_rows, post_rows = perm[: n // 2], perm[n // 2:]
    fit_s = samples[fit_rows]
    mu = fit_s.mean(axis=0)
    cov = np.atleast_2d(np.cov(fit_s, rowvar=False)) * inflate
    cov = cov + 1e-12 * max(float(np.trace(cov)), 1e-12) * np.eye(ndim)
    q = multivariate_t(mu, cov, df=df, seed=rng)
    x = np.asarray(q.rvs(size=n_draws)).reshape(n_draws, ndim)
    logp2 = np.full(n_draws, -np.inf)
    inside = np.all((x > lower) & (x < upper), axis=1)
    logp2[inside] = [log_prob(xi) for xi in x[inside]]
    l2 = logp2 - np.asarray(q.logpdf(x)).reshape(n_draws)  # log p/q at the proposal's draws
    post = samples[post_rows]
    l1 = np.asarray(log_prob_samples)[post_rows] - np.asarray(q.logpdf(post)).reshape(-1)
    n1 = float(len(post_rows) if n_eff is None else min(len(post_rows), max(n_eff / 2, 2.0)))
    s1, s2 = n1 / (n1 + n_draws), n_draws / (n1 + n_draws)
    if not np.any(np.isfinite(l2)):
        return ModeMass(-np.inf, np.inf, 0.0, n_draws, 0)
    # fixed point of the optimal bridge, in logs: r = mean_q[p/q / (s1 p/q/r + s2)] /
    # mean_p[1 / (s1 p/q/r + s2)] (each term written relative to r)
    log_r = float(logsumexp(l2) - np.log(n_draws))  # start: plain importance sampling
    it = 0
    for it in range(1, max_iter + 1):
        num = logsumexp(l2 - np.logaddexp(np.log(s1) + l2 - log_r, np.log(s2))) - np.log(n_draws)
        den = logsumexp(-np.logaddexp(np.log(s1) + l1 - log_r, np.log(s2))) - np.log(len(l1))
        new = float(num - den)
        if abs(new - log_r) < 1e-10:
            log_r = new
            break
        log_r = new
    # relative mean squared error (Fruhwirth-Schnatter 2004, as in the bridgesampling package)
    f2 = np.exp(l2 - log_r) / (s1 * np.exp(l2 - log_r) + s2)
    f1 = 1.0 / (s1 * np.exp(l1 - log_r) + s2)
    re2 = np.var(f2) / np.mean(f2) ** 2 / n_draws + np.var(f1) / np.mean(f1) ** 2 / n1
    w = np.exp(l2 - np.max(l2))
    ess = kish_ess(w)
    return ModeMass(log_r, float(np.sqrt(re2)), ess, n_draws, it)


def mode_weights(masses: list[ModeMass]) -> np.ndarray:
    """Posterior probability of each mode from the modes' masses."""
    lm = np.array([m.log_mass for m in masses])
    w = np.exp(lm - np.max(lm))
    return w / w.sum()


def mix_modes(parts: list[np.ndarray], weights: np.ndarray, rng: np.random.Generator
              ) -> np.ndarray:
    """Indices (mode, row) of a sample of the mixture: as many draws as the modes' samples
    allow without repeating one, each mode's share equal to its weight (rounded)."""
    sizes = np.array([len(p) for p in parts], float)
    w = np.asarray(weights, float)
    n_total = int(np.min(np.where(w > 0, sizes / np.maximum(w, 1e-300), np.inf)))
    counts = np.floor(w * n_total + 0.5).astype(int)
    counts = np.minimum(counts, sizes.astype(int))
    rows = [(k, r) for k, c in enumerate(counts)
            for r in np.sort(rng.choice(len(parts[k]), size=c, replace=False))]
    return np.array(rows, int).reshape(-1, 2)


RHAT_MAX = 1.01  # Vehtari et al. (2021)
ESS_MIN = 400


RHAT_GROUPS = 4


def walker_groups(chain: np.ndarray, n_groups: int = RHAT_GROUPS) -> np.ndarray:
    """Pool the walkers into ``n_groups`` groups: (walkers, steps, ndim) -> (groups, steps *
    walkers_per_group, ndim), interleaved step by step so each group's halves stay in time order."""
    w, n, d = chain.shape
    k = w // n_groups
    c = chain[: k * n_groups].reshape(n_groups, k, n, d)
    return np.swapaxes(c, 1, 2).reshape(n_groups, n * k, d)


def arviz_diagnostics(chain: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Bulk ESS per parameter (ArviZ, walkers as chains) and rank-normalised split R-hat
    across walker groups (the walkers of an ensemble are individually short chains; pooled in
    groups the split R-hat measures whether parts of the ensemble disagree).  ``chain`` has
    shape (walkers, steps, ndim); None when it is too short."""
    if chain.shape[1] < 8 or chain.shape[0] < 2 * RHAT_GROUPS:
        return None, None
    import arviz as az

    names = [f"p{i}" for i in range(chain.shape[2])]
    ess = az.ess(to_inference_data(chain, names), method="bulk")
    rhat = az.rhat(to_inference_data(walker_groups(chain), names))
    return (np.array([float(ess[n]) for n in names]), np.array([float(rhat[n]) for n in names]))


def to_inference_data(chain: np.ndarray, names: list[str], *, log_prob: np.ndarray | None = None,
                      extra: dict[str, np.ndarray] | None = None):
    """ArviZ InferenceData with walkers as chains; ``extra`` adds derived variables of the
    same (walkers, steps) shape."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # arviz's announcement of its 1.0 API
        import arviz as az

    post = {n: chain[..., i] for i, n in enumerate(names)}
    post.update(extra or {})
    stats = {"lp": log_prob} if log_prob is not None else None
    return az.from_dict(posterior=post, sample_stats=stats)


#: What a checkpoint holds besides the chain: the sampler's random state, the run identity
CHECKPOINT_KEYS = ("chain", "log_prob", "accepted", "iteration", "rs_name", "rs_keys", "rs_pos",
                   "rs_has_gauss", "rs_gauss", "identity")


def save_checkpoint(path: Path, backend, identity: str) -> None:
    """The chain so far, the sampler's random state and the run's identity (one JSON line,
    :mod:`fitmedia.inference.identity`), written atomically (a kill -9 leaves the previous
    checkpoint intact)."""
    from ..util import save_npz

    it = backend.iteration
    name, keys, pos, has_gauss, gauss = backend.random_state
    save_npz(path, {"chain": backend.chain[:it], "log_prob": backend.log_prob[:it],
                    "accepted": backend.accepted, "iteration": np.array(it),
                    "rs_name": np.array(name), "rs_keys": keys, "rs_pos": np.array(pos),
                    "rs_has_gauss": np.array(has_gauss), "rs_gauss": np.array(gauss),
                    "identity": np.array(identity)})


def read_checkpoint(path: Path) -> dict:
    """A checkpoint's arrays, checked for shape and consistency; an InputError naming the
    file when it is empty, truncated, not a checkpoint or inconsistent."""
    import zipfile
    import zlib

    from ..errors import InputError

    def bad(why: str) -> InputError:
        return InputError(f"{path}: not a usable checkpoint ({why}); remove it to start afresh")
    try:
        if Path(path).stat().st_size == 0:
            raise bad("empty file")
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            missing = [k for k in CHECKPOINT_KEYS if k not in z.files and k != "identity"]
            if missing:
                raise bad(f"no {', '.join(missing)}")
            # written before checkpoints held the run's identity: "null", refused by identity
            d = {k: z[k] if k in z.files else np.array("null") for k in CHECKPOINT_KEYS}
    except InputError:
        raise
    except (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error) as exc:
        raise bad(f"{type(exc).__name__}: {str(exc) or 'truncated?'}") from None
    chain, lp, acc = d["chain"], d["log_prob"], d["accepted"]
    if chain.ndim != 3 or chain.shape[1] < 2 or chain.shape[2] < 1:
        raise bad(f"chain of shape {chain.shape}, expected (steps, walkers, parameters)")
    if lp.shape != chain.shape[:2] or acc.shape != chain.shape[1:2]:
        raise bad(f"log_prob {lp.shape} or accepted {acc.shape} do not match chain {chain.shape}")
    if d["iteration"].shape != () or int(d["iteration"]) != len(chain):
        raise bad(f"iteration {d['iteration']} for a chain of {len(chain)} steps")
    if d["identity"].shape != () or d["rs_keys"].shape != (624,):
        raise bad("identity or random state of the wrong shape")
    if not (np.all(np.isfinite(chain)) and not np.any(np.isnan(lp))):
        raise bad("non-finite positions or NaN log posterior")
    return d


def check_checkpoint(path: Path, identity: dict) -> dict:
    """Refuse (InputError) a checkpoint that is unusable (:func:`read_checkpoint`) or was
    written by a run of another identity, naming what differs; else return its arrays."""
    from ..errors import InputError
    from .identity import identity_differences

    d = read_checkpoint(path)
    try:
        stored = json.loads(str(d["identity"]))
    except ValueError:
        stored = None
    diff = identity_differences(stored, identity)
    if diff:
        raise InputError(f"{path}: checkpoint written by another run (what differs: "
                         f"{'; '.join(diff)}); use a new --out folder, or remove the "
                         "checkpoint_*.npz files to start afresh")
    return d


def load_checkpoint(path: Path, backend, identity: dict | None = None):
    """Fill an emcee in-memory backend from a checkpoint; returns the State to continue from,
    or None when there is no checkpoint.  With ``identity``, one of another run is refused
    (:func:`check_checkpoint`)."""
    import emcee

    if not Path(path).exists():
        return None
    d = read_checkpoint(path) if identity is None else check_checkpoint(path, identity)
    chain, lp, acc = d["chain"], d["log_prob"], d["accepted"]
    if len(chain) == 0:
        return None
    rs = (str(d["rs_name"]), d["rs_keys"], int(d["rs_pos"]), int(d["rs_has_gauss"]),
          float(d["rs_gauss"]))
    backend.reset(chain.shape[1], chain.shape[2])
    backend.chain, backend.log_prob = chain.copy(), lp.copy()
    backend.accepted = acc.copy()
    backend.iteration = len(chain)
    backend.random_state = rs
    return emcee.State(chain[-1], log_prob=lp[-1], random_state=rs)
