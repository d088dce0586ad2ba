"""Fit a capture: load and calibrate the images, then per colour channel find
the MAP with nlopt and sample the posterior with emcee.

The channels are independent given the data (separate parameters, separate
pixels), so each channel is its own problem; they run in parallel processes.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import project
from ..images import LoadedImage, checks, load_entry
from ..images.noise import entry_noise, noise_summary
from ..memory import default_workers
from ..spec import CHANNELS, Spec
from .likelihood import ChannelProblem, Observation
from .optimize import MapResult, find_map
from .params import G_MAX, G_MIN, ChannelParams, ParameterSpace
from .result import FitOptions
from .sample import (OTHER_MODE_DELTA, Redraw, half_space, mix_modes, mode_log_mass, mode_weights,
                     run_chain)

log = logging.getLogger("fitmedia")


#: The modes' weights are trusted when their standard error (from the bridge sampling of each
#: mode's mass) is below this: an error dw in the weights moves the mixture's CDF by at most dw
#: anywhere, so no interval's coverage by more than 2 dw
MODE_WEIGHT_SE = 0.01
#: |g| below which the polished other-sign optimum counts as the MAP's own region (g = 0)
SAME_MODE_G = 1e-3


@dataclass
class Prepared:
    """Images loaded and calibrated, ready for the per-channel problems."""

    spec: Spec
    images: list[LoadedImage]
    clear: LoadedImage | None
    noise: dict[str, tuple[float, float]]
    noise_source: str
    brightness: dict[str, float | None]
    brightness_source: str
    brightness_rel_sd: dict[str, float | None] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    # per entry ("images[i]", "calibration.clear_water"): the camera's noise (SensorNoise) and
    # its per-pixel maps (gain_map, read_map) of shape (H, W, 3) (LoadedImage.variance_maps)
    sensor_noise: dict = field(default_factory=dict)
    noise_maps: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    noise_per_image: dict[str, dict] = field(default_factory=dict)  # results.json noise.per_image


#: the forward models that ``--model`` names (inference/full.py: full and auto)
MODELS = ("single", "full", "auto")


def _model(spec: Spec, image_index: int | None, channel: str, options: FitOptions,
           forward=None):
    """The model of one image and channel: ``forward(spec, image_index, channels=(channel,))``
    when a forward-model factory is given (``fitmedia.fit(..., model=...)``), else the analytic
    single scattering: every fit starts with it; ``full`` and ``auto`` wrap it in the
    full-transport model after the single-scattering MAP (``auto``: where
    :func:`auto_stays_single` does not keep it single)."""
    if options.model not in MODELS:
        raise InputError(f"--model: {options.model!r} is not one of {', '.join(MODELS)}")
    if forward is not None:
        return forward(spec, image_index, channels=(channel,))
    from ..forward.single import SingleScattering

    return SingleScattering(spec, image_index, channels=(channel,))


def why_bulb_unseen(spec: Spec) -> str:
    """Why no pixel of the camera sees the bulb, judged on the straight line from the camera
    to the bulb's centre (refraction at the wall ignored: the words, not a measurement)."""
    cam, half = spec.camera, spec.tank.half
    d = spec.light.position - cam.position
    z_wall = half[2] + spec.tank.wall_thickness
    at = cam.position + d * (cam.position[2] - z_wall) / (cam.position[2] - spec.light.position[2])
    if np.any(np.abs(at[:2]) > half[:2]):
        return (f"the line of sight to it crosses the front wall's plane at x = {at[0]:.0f}, "
                f"y = {at[1]:.0f} mm, outside the wall's opening |x| < {half[0]:g}, "
                f"|y| < {half[1]:g} mm (it is behind a side wall as seen from the camera)")
    px, py, ahead = project(cam, spec.light.position)  # through camera.distortion, if any
    if not ahead:
        return "it is behind the camera (camera.look_at points away from it)"
    if not (np.isfinite(px) and np.isfinite(py)):
        return "it is outside the image, beyond the fold of camera.distortion"
    if not (0 <= px <= cam.width and 0 <= py <= cam.height):
        return (f"it projects outside the image, near pixel ({px:.0f}, {py:.0f}) of a "
                f"{cam.width} x {cam.height} image (check camera.look_at, fx, fy, cx, cy)")
    return "the model images no pixel of it (check camera and light in the spec)"


def calibrate(spec: Spec, clear: LoadedImage, noise: dict[str, tuple[float, float]]
              ) -> tuple[dict[str, float], dict[str, float]]:
    """The bulb's radiance per channel from the clear-water photo (weighted least squares
    of the photo against the model image of a unit-radiance bulb in clear water), and its
    relative standard error."""
    from ..forward.single import SingleScattering

    # the clear water's own absorption (spec medium.water_kappa_a) attenuates the bulb in the
    # clear-water photo too: the model of the photo includes it, so the radiance is the bulb's
    water = np.array([spec.water_kappa_a[CHANNELS.index(c)] for c in spec.channels])
    unit = SingleScattering(spec, None, channels=spec.channels).render(
        water, np.zeros_like(water), np.zeros_like(water), np.ones_like(water))
    out, rel_sd = {}, {}
    src = spec.clear_water.paths[0]
    for k, ch in enumerate(spec.channels):
        ci = CHANNELS.index(ch)
        m0 = unit[..., k]
        if not m0.max() > 0:  # no pixel sees the bulb: not an exposure problem
            raise InputError(f"calibration.clear_water: {src}: the camera cannot see the bulb: "
                             f"{why_bulb_unseen(spec)}; no calibration is possible")
        use = (m0 > 0.05 * m0.max()) & clear.valid[..., ci]
        core = m0 > 0.9 * m0.max()  # pixels fully covered by the bulb
        if not np.any(use) or np.mean(clear.valid[..., ci][core]) < 0.5:
            raise InputError(f"calibration.clear_water: {src}: the bulb's pixels are saturated or "
                             f"masked in channel {ch}; take a shorter exposure")
        d = clear.data[..., ci][use]
        gain, read = (np.broadcast_to(v, m0.shape)[use] for v in noise[ch])  # maps or scalars
        w = 1.0 / (gain * np.maximum(d, 0) + read)
        fisher = np.sum(w * m0[use] ** 2)
        out[ch] = float(np.sum(w * d * m0[use]) / fisher)
        if not out[ch] > 0:
            raise InputError(f"calibration.clear_water: {src}: the bulb is not brighter than the "
                             f"background in channel {ch} (radiance estimate {out[ch]:.3g})")
        rel_sd[ch] = float(1.0 / np.sqrt(fisher) / out[ch])
    return out, rel_sd


def prepare(spec: Spec, workers: int | None = None) -> Prepared:
    """Load every image, estimate or read the noise, calibrate the light's brightness.
    ``workers``: the channels that will be fitted at once (``FitOptions.workers``; None: the
    default), for the memory check."""
    from ..memory import check_memory

    # before any image is read: a huge camera.size (or too many workers) is refused here
    check_memory(spec, "fit", workers=workers)
    ch_idx = tuple(CHANNELS.index(c) for c in spec.channels)
    images, clear, named = _load_images(spec, ch_idx)
    notes: list[str] = []
    entries = list(spec.images) + ([spec.clear_water] if clear else [])
    sensor, maps, per_image = {}, {}, {}
    for (where, _, im), entry in zip(named, entries):
        first = ("images[0]", sensor["images[0]"]) if "images[0]" in sensor else None
        sensor[where] = entry_noise(spec.noise, spec.noise_exposure, entry, im, ch_idx, where,
                                    first if where == "calibration.clear_water" else None)
        maps[where] = im.variance_maps(sensor[where].a, sensor[where].b)
        per_image[where] = noise_summary(sensor[where], im, maps[where], ch_idx)
    if spec.noise is not None:
        noise = {c: spec.noise for c in spec.channels}
        noise_source = "spec"
    else:  # the first image's typical per-pixel values (its own; each image has its maps)
        first = per_image["images[0]"]["per_channel"]
        noise = {c: (first[c]["gain"], first[c]["read_var"]) for c in spec.channels}
        noise_source = "estimated per image (results.json noise.per_image)"
        notes.append("noise model estimated from each image (no `noise` in the spec)")
    for where, _, im in named:  # each image's largest read variance (brackets vary per pixel)
        read = [float(np.max(maps[where][1][..., ci][im.valid[..., ci]], initial=0.0))
                for ci in ch_idx]
        checks.check_negative(im, ch_idx, spec.channels, read,
                              float(spec.priors.get("background_sd", 0.0)))
        if where != "calibration.clear_water":  # the bulb on black: calibrate() judges it
            checks.check_lit(im, ch_idx, spec.channels, maps[where][1])
    brightness, source, rel_sd = _brightness(spec, clear, maps, notes)
    return Prepared(spec, images, clear, noise, noise_source, brightness, source, rel_sd, notes,
                    sensor, maps, per_image)


def _load_images(spec: Spec, ch_idx: tuple[int, ...]) -> tuple[list, LoadedImage | None, list]:
    """The capture's images and clear-water photo, loaded and checked (values, distinct
    files); and ``(where, paths, image)`` of each for the messages."""
    shape = (spec.camera.height, spec.camera.width)
    images = []
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # checked just below
        for i, entry in enumerate(spec.images):
            cam = spec.camera_for(i)
            images.append(load_entry(entry, expected_shape=(cam.height, cam.width),
                                     channels=ch_idx))
        clear = None
        if spec.clear_water is not None:
            clear = load_entry(spec.clear_water, expected_shape=shape, channels=ch_idx)
    named = [(f"images[{i}]", e.paths, im) for i, (e, im) in enumerate(zip(spec.images, images))]
    named += [("calibration.clear_water", spec.clear_water.paths, clear)] if clear else []
    for _, _, im in named:
        checks.check_values(im, ch_idx, spec.channels)
    checks.check_distinct(named)
    return images, clear, named


def _brightness(spec: Spec, clear: LoadedImage | None, maps: dict, notes: list[str]) -> tuple:
    """The light's brightness per channel (None: a free parameter), where it comes from, and
    its relative standard error per channel (clear-water calibration only); adds notes."""
    light = spec.light
    rel_sd: dict[str, float | None] = {c: None for c in spec.channels}
    if light.type == "bulb" and clear is not None:
        g_c, r_c = maps["calibration.clear_water"]
        brightness, rel_sd = calibrate(spec, clear, {c: (g_c[..., CHANNELS.index(c)],
                                                         r_c[..., CHANNELS.index(c)])
                                                     for c in spec.channels})
        return brightness, ("clear-water photo (prior: normal in log brightness, calibration's "
                            "error)"), rel_sd
    if light.brightness is not None:
        if light.type == "spot" and clear is not None:
            notes.append("clear-water photo not used: a spot (point source) is not visible in it")
        return ({c: light.brightness[CHANNELS.index(c)] for c in spec.channels},
                "spec (light.radiance / light.intensity)", rel_sd)
    why = "a spot is not visible in a clear-water photo" if light.type == "spot" else \
        "no calibration.clear_water"
    notes.append(f"light brightness fitted as a free parameter ({why}): kappa_s is then only "
                 "constrained through its product with the brightness and the glow's shape")
    return {c: None for c in spec.channels}, "free parameter", rel_sd


def _kt_guess(spec: Spec, obs: list[Observation], brightness: float | None) -> float:
    """Undiluted kappa_t from the attenuation of the directly seen bulb (bulb pixels only)."""
    if spec.light.type != "bulb" or brightness is None:
        return 1e-3 / min(o.concentration for o in obs)
    best = []
    for o in obs:
        clear = o.model.render(0.0, 0.0, 0.0, brightness)[..., 0]
        px = (clear > 0.5 * clear.max()) & o.valid if clear.max() > 0 else None
        if px is None or not np.any(px):
            continue
        grid = np.geomspace(1e-5, 10.0, 61)
        cost = [np.sum((np.log(np.maximum(o.data[px], 1e-30)) -
                        np.log(np.maximum(o.model.render(kt, 0.0, 0.0, brightness)[..., 0][px],
                                          1e-300))) ** 2) for kt in grid]
        best.append(grid[int(np.argmin(cost))] / o.concentration)
    return float(np.exp(np.mean(np.log(best)))) if best else 1e-3 / min(o.concentration for o in obs)


@dataclass
class ChannelSetup:
    """One channel's posterior and where its MAP search starts (:func:`channel_problem`)."""

    problem: ChannelProblem
    space: ParameterSpace
    free: bool  # the brightness is a parameter
    guess_b: float  # the brightness's starting value
    kt0: float  # kappa_t from the bulb's attenuation (undiluted, 1/mm)
    x0: np.ndarray  # the search's start in the sampler's coordinates


def fit_channel(spec: Spec, channel: str, data: list[np.ndarray], valid: list[np.ndarray],
                brightness: float | None, brightness_rel_sd: float | None,
                noise: tuple[float, float], options: FitOptions,
                checkpoint: Path | None = None, seed: int = 0, identity: dict | None = None,
                noise_maps: list[tuple[np.ndarray, np.ndarray]] | None = None,
                forward=None) -> dict:
    """MAP and (optionally) posterior samples of one channel; returns plain arrays/dicts.
    ``identity`` (:mod:`fitmedia.inference.identity`) goes into the chains' checkpoints;
    ``forward``: a forward-model factory (:func:`_model`), else single scattering."""
    setup = channel_problem(spec, channel, data, valid, brightness, brightness_rel_sd, noise,
                            options, noise_maps, forward)
    problem, space = setup.problem, setup.space
    rng = np.random.default_rng([seed, CHANNELS.index(channel)])
    res, alt = search_map(setup, options, rng)
    transport: dict = {}  # --model full / auto: what was used (_full_transport)
    stays = auto_stays_single(spec) if options.model == "auto" and forward is None else None
    if options.model != "single" and forward is None and stays is None:
        res, transport = _full_transport(problem, space, res, spec, channel, options, seed, alt)
        if transport["model_used"] == "full":
            # the other sign of g as the full model found it (its log posterior relative to
            # the MAP from local models rebuilt at each point), sampled too where it is close
            alt = transport.pop("full_other_mode_map", None)
    elif forward is None:
        transport = _single_ms_check(problem, space, res, spec, channel, seed)
    if stays is not None:  # auto kept single scattering (a declared single render)
        transport = {"model_used": "single", **transport, "auto_reason": stays}
    other_mode = None if alt is None else {
        "g": float(np.tanh(alt.x[2])), "kappa_t": float(np.exp(alt.x[0])),
        "delta_log_posterior": float(alt.log_posterior - res.log_posterior)}
    out = {"channel": channel, "names": space.names, **_map_fields(problem, space, res, transport),
           "valid_images": [o.valid for o in problem.obs],
           "free_brightness": setup.free, "space": space, "other_g_mode": other_mode, **transport}
    if options.mcmc:
        out.update(_sample_channel(problem, space, res, alt, other_mode, options, rng,
                                   checkpoint, [seed, CHANNELS.index(channel)], channel, identity))
        better = map_from_samples(problem, space, res, out["samples"], out["log_prob"])
        if better is not None:  # the optimizer had stopped short of the posterior's mode
            gain = better.log_posterior - res.log_posterior
            out.update(_map_fields(problem, space, better, transport),
                       map_from_samples={"delta_log_posterior": float(gain),
                                         "optimizer_x": res.x.tolist()})
            if other_mode is not None:
                other_mode["delta_log_posterior"] -= float(gain)
        term = _term_error(transport)
        if term is not None:
            from .full import convolve_samples

            out["samples"] = convolve_samples(out["samples"], term,
                                              np.random.default_rng([seed, CHANNELS.index(channel), 6]))
    return out


#: a posterior sample more than this many log-posterior units above the MAP's says the MAP
#: search stopped short of the mode (``map_from_samples``)
MAP_SAMPLE_TOL = 1.0


def map_from_samples(problem, space: ParameterSpace, res, samples: np.ndarray,
                     log_prob: np.ndarray):
    """The MAP polished from the sampler's best sample on the MAP's side of g, where that ends
    more than ``MAP_SAMPLE_TOL`` above the MAP ``res`` (by ``problem.log_posterior`` itself,
    not the chain's stored values); else None.  A local search can stop on a plateau: the
    albedo's near its upper bound, where kappa_a -> 0 changes nothing and the gradient
    vanishes.  Measured (White Grapefruit Juice 160 ml, R, 100 x 75, --model full): the MAP at
    logit albedo 14.7 (kappa_a 0, kappa_t 0.501 1/mm), the samples' best 7.3 units above it at
    3.52 (kappa_a 0.0138, kappa_t 0.516; truth 0.0138 and 0.519), and the report flagged
    "albedo at the prior's upper bound" for a kappa_a the posterior resolves."""
    if samples is None or log_prob is None or not len(log_prob):
        return None
    same = np.sign(samples[:, 2]) == np.sign(res.x[2])
    lp = np.where(same & np.isfinite(log_prob), log_prob, -np.inf)
    if not np.any(np.isfinite(lp)):
        return None
    best = samples[int(np.argmax(lp))]
    if not problem.log_posterior(best) > res.log_posterior + MAP_SAMPLE_TOL:
        return None
    new = find_map(problem.log_posterior, np.clip(best, space.lower, space.upper), space.lower,
                   space.upper, global_evals=0)
    if not new.log_posterior > res.log_posterior + MAP_SAMPLE_TOL:
        return None
    log.info("the MAP search had stopped %.3g log-posterior units below a posterior sample; "
             "the MAP is polished from there", new.log_posterior - res.log_posterior)
    new.n_evals += res.n_evals
    return new


def _map_fields(problem, space: ParameterSpace, res, transport: dict) -> dict:
    """``fit_channel``'s fields that describe the MAP ``res``."""
    return {"x_map": res.x, "map_logp": res.log_posterior, "n_evals": res.n_evals,
            "laplace_cov": _with_term_error(res.cov, transport),
            "map": {k: float(np.asarray(v)) for k, v in space.physical_samples(res.x).items()},
            "model_images": problem.render(res.x), "chi2": problem.chi2(res.x),
            "chi2_images": problem.chi2_images(res.x),
            "var_images": problem.variance_images(res.x)}


def _term_error(transport: dict) -> np.ndarray | None:
    """The covariance of the full-transport term's error in the values: its realisation (the
    jackknife, inference/full.py: term_jackknife) plus the offset that may remain after the
    last refreshes (``offset_budget``); None where the fit has neither."""
    term, offset = transport.get("ms_term_cov"), transport.get("ms_offset_cov")
    if term is None:
        return offset
    return term if offset is None else term + offset


def _with_term_error(cov: np.ndarray | None, transport: dict) -> np.ndarray | None:
    """The Laplace covariance plus the full-transport term's error (``_term_error``), where
    the fit has one."""
    term = _term_error(transport)
    return cov if cov is None or term is None else cov + term


def channel_problem(spec: Spec, channel: str, data: list[np.ndarray], valid: list[np.ndarray],
                    brightness: float | None, brightness_rel_sd: float | None,
                    noise: tuple[float, float], options: FitOptions,
                    noise_maps: list[tuple[np.ndarray, np.ndarray]] | None = None,
                    forward=None) -> ChannelSetup:
    """One channel's observations (a forward model per image), parameter space and priors,
    posterior, and the MAP search's starting point (kappa_t from the bulb's attenuation)."""
    obs = []
    for i, (d, v) in enumerate(zip(data, valid)):
        model = _model(spec, i, channel, options, forward)
        g, r = noise_maps[i] if noise_maps else (None, None)  # per-pixel noise, when known
        obs.append(Observation(model, d, v & model.support, spec.images[i].concentration, g, r))
    free = brightness is None or brightness_rel_sd is not None
    guess_b = brightness if brightness is not None else float(
        np.max([np.percentile(d[v], 99.9) for d, v in zip(data, valid)]) / 0.5)
    pri = spec.priors
    if brightness_rel_sd is not None and "brightness_rel_sd" in pri:
        brightness_rel_sd = float(pri["brightness_rel_sd"])
    bg_sd = None
    if options.background or "background_sd" in pri:
        bg_sd = float(pri.get("background_sd", 3.0 * np.sqrt(noise[1]) + 1e-12))
    space = ParameterSpace(free_brightness=free, brightness_guess=max(guess_b, 1e-30),
                           brightness_rel_sd=brightness_rel_sd, background_sd=bg_sd, priors=pri)
    problem = ChannelProblem(obs, space, None if free else brightness, noise, robust=options.robust,
                             water_kappa_a=spec.water_kappa_a[CHANNELS.index(channel)])
    kt0 = _kt_guess(spec, obs, guess_b if spec.light.type == "bulb" and brightness else None)
    x0 = space.to_vector(ChannelParams(kt0, 0.5, 0.5, guess_b if free else None))
    if not space.lower[0] <= np.log(kt0) <= space.upper[0]:
        x0[0] = 0.5 * (space.lower[0] + space.upper[0])
    return ChannelSetup(problem, space, free, guess_b, kt0, x0)


def search_map(setup: ChannelSetup, options: FitOptions, rng: np.random.Generator
               ) -> tuple[MapResult, MapResult | None]:
    """The MAP (polished, with its Laplace covariance) and the best optimum scattering the
    other way (forward vs backward g), or None: a global search near the start, local
    searches from several starts, each candidate judged with quadrature nodes of its own."""
    problem, space, x0 = setup.problem, setup.space, setup.x0
    lo, hi = space.lower.copy(), space.upper.copy()
    lo[0], hi[0] = max(lo[0], x0[0] - 3), min(hi[0], x0[0] + 3)  # global search near the guess
    # 1. global search, quadrature nodes adapted at every call (nodes frozen for a broad phase
    #    function misjudge a forward-peaked one and create false modes)
    res = find_map(problem.log_posterior, x0, lo, hi, global_evals=options.global_evals,
                   local_evals=0, seed=int(rng.integers(2**31)))
    # 2. local searches from several starting points with nodes frozen for a narrow peak and
    #    strong attenuation (accurate to < 1e-3 for every g >= 0 and kappa_t up to 3x):
    #    the albedo direction has a plateau when kappa_a << kappa_s, and g has a second,
    #    backward-scattering mode
    kt_hi = 3.0 * setup.kt0  # from the bulb's attenuation, not from a possibly false global mode
    problem.adapt(space.to_vector(ChannelParams(kt_hi, 0.5, 0.97,
                                                setup.guess_b if setup.free else None)))
    starts = [res.x]
    for g0 in (0.6, 0.9, -0.5):  # -0.5: the backward mode, so that it is always looked at
        for la in (0.0, 6.0):
            x = x0.copy()
            x[1], x[2] = np.clip(la, space.lower[1], space.upper[1]), np.clip(
                np.arctanh(g0), space.lower[2], space.upper[2])
            starts.append(x)
    cands, n_evals = [], res.n_evals
    for start in starts:  # loose tolerance: only the basin matters here; polished below
        cand = find_map(problem.log_posterior, start, space.lower, space.upper, global_evals=0,
                        local_evals=500, laplace=False, step=0.3, tol=1e-5)
        n_evals += cand.n_evals
        cands.append(cand)
    best, alt, n_other = _best_and_other(problem, space, cands)
    # 3. nodes tuned at the optimum; polish; Laplace covariance
    problem.adapt(best.x)
    res = find_map(problem.log_posterior, best.x, space.lower, space.upper, global_evals=0)
    res.n_evals += n_evals + n_other
    return res, alt


def _best_and_other(problem: ChannelProblem, space: ParameterSpace, cands: list[MapResult]
                    ) -> tuple[MapResult, MapResult | None, int]:
    """The best candidate, the best one scattering the other way (polished with its own nodes;
    None when there is none or it slides into the best one's region), and the evaluations
    the polish took."""
    # judge the candidates fairly: each with quadrature nodes adapted to its own parameters
    # (the shared nodes above are tuned for forward peaks and misjudge a backward-g mode)
    for cand in cands:
        problem.adapt(cand.x)
        cand.log_posterior = problem.log_posterior(cand.x)
    best = max(cands, key=lambda c: c.log_posterior)
    # the best candidate scattering the other way (forward vs backward g), polished with its own
    # nodes: the sampler explores the best mode only, so a close second mode is reported
    other = [c for c in cands if _opposite_g(c.x, best.x)]
    if not other:
        return best, None, 0
    alt = max(other, key=lambda c: c.log_posterior)
    problem.adapt(alt.x)
    alt = find_map(problem.log_posterior, alt.x, space.lower, space.upper, global_evals=0,
                   laplace=False)
    # the polish runs over the whole range of g: on a posterior that hardly depends on g
    # (dense captures) it slides to g = 0 or across it, into the MAP's own region; that
    # is not a second mode (docs/inference.md)
    if not _opposite_g(alt.x, best.x) or abs(np.tanh(alt.x[2])) < SAME_MODE_G:
        return best, None, alt.n_evals
    return best, alt, alt.n_evals


def _sample_channel(problem: ChannelProblem, space: ParameterSpace, res: MapResult, alt,
                    other_mode: dict | None, options: FitOptions, rng: np.random.Generator,
                    checkpoint: Path | None, seed: list[int], channel: str,
                    identity: dict | None) -> dict:
    """The posterior's chain from the MAP ``res`` (and a second one for the other mode of g,
    :func:`_sample_other_mode`, when its log posterior is within ``OTHER_MODE_DELTA``);
    returns the fields of ``fit_channel``'s result that sampling adds."""
    two = other_mode is not None and other_mode["delta_log_posterior"] > -OTHER_MODE_DELTA
    # with two modes each chain keeps to its own sign of g, so that the modes' masses can
    # be measured separately and the chains mixed by them
    log_post = half_space(problem.log_posterior, 2, res.x[2]) if two else problem.log_posterior
    with problem.tabulated(res.x, res.cov) as table:  # the analytic image interpolated
        chain = run_chain(log_post, res.x, res.cov, space.lower, space.upper, rng=rng,
                          checkpoint=checkpoint, resume=options.resume,
                          n_walkers=options.n_walkers, n_tau=options.n_tau,
                          max_steps=options.max_steps, progress=options.progress, label=channel,
                          redraw=albedo_redraw(space, res.x, res.cov), identity=identity)
    log.info("%s: sampler's image table %s", channel, "not used" if table.logl_error is None
             else f"used for {table.share or 0:.0%} of this run's renders (log-likelihood "
                  f"error at most {table.logl_error:.1e})")
    if table.term_logl_error is not None:
        log.info("%s: the term's table used for %.0f%% of this run's renders (log-likelihood "
                 "error at most %.1e)", channel, 100 * (table.term_share or 0),
                 table.term_logl_error)
    out = dict(samples=chain.samples, log_prob=chain.log_prob_samples, n_steps=chain.n_steps,
               tau=chain.tau, acceptance=chain.acceptance_fraction, converged=chain.converged,
               reason=chain.reason, burn=chain.burn, thin=chain.thin, chain=chain.chain,
               ess=chain.ess, rhat=chain.rhat, table_err=table.logl_error,
               term_table_err=table.term_logl_error)
    if two:
        out.update(_sample_other_mode(problem, space, res, alt, chain, log_post, options,
                                      checkpoint, seed, channel, other_mode, identity))
    return out


def _full_transport(problem: ChannelProblem, space: ParameterSpace, res, spec: Spec,
                    channel: str, options: FitOptions, seed: int, alt=None) -> tuple:
    """``--model full`` / ``auto`` from the single-scattering MAP ``res``: the multiple-
    scattering share there, and (full, or auto: :func:`_auto_choice`) the full-transport MAP
    and its checks (inference/full.py); ``alt``, the single optimum with g of the other sign
    if one was found, refined with the full model too and the better one kept (its MapResult
    ``full_other_mode_map``, its log posterior its measured distance below the MAP's, for
    ``other_g_mode`` and the sampler).  Returns the MAP and ``fit_channel``'s fields."""
    from .full import (more_paths, ms_images, ms_share, offset_budget, refine_map,
                       restart_check, restart_in_loop_units, seed_shift, term_jackknife,
                       use_full_transport, use_single_scattering)

    ms_seed, check_seed = _ms_seeds(seed, channel)
    share, share_se = ms_share(problem, res.x, spec, channel, seed=ms_seed)
    scan = _spot_scan(problem, space, res, spec, channel, ms_seed)  # None for a bulb
    out = {"model_used": "single", "ms_share_single_map": share,
           **({"ms_scan": scan["rows"]} if scan else {})}
    if options.model == "auto":
        above, out["auto_reason"] = _auto_choice(share, scan)
        if not above:
            use_single_scattering(problem, res.x)  # undoes the scan's full model
            out.update(ms_share=share, ms_share_se=share_se)
            return res, out
    use_full_transport(problem, spec, channel, seed=ms_seed)
    single_x = res.x
    start = scan["best"] if scan and scan["best"].log_posterior > res.log_posterior else res
    res, info = refine_map(problem, space, start)
    # the other sign of g, refined with the full model as well
    res, info, single_x, other_g, alt_full = (res, info, single_x, None, None) if alt is None \
        else _full_other_g(problem, space, res, info, single_x, alt)
    # the checks on the loop's fixed point, at the loop's paths (and a bulb's misfit's scan)
    check, out["ms_misfit_scan"] = _misfit_scan(problem, space, restart_check(
        problem, space, res, info, single_x, channel), single_x, channel, scan is not None)
    res, info, restart, adopted, term_cov = check[:5]
    shift = seed_shift(problem, space, res, spec, channel, seed=check_seed)
    # then the last refreshes with more paths, and the values and their term error from there
    loop, loop_term = res, term_cov
    res, last, paths = more_paths(problem, space, res)
    term_cov, offset = term_jackknife(problem, res), offset_budget(res, loop.x)
    share, share_se = ms_share(problem, res.x, spec, channel, seed=ms_seed)
    both = info.followed_by(last)
    out.update(model_used="full", ms_share=share, ms_share_se=share_se,
               full_refreshes=both.refreshes, full_moves_sd=both.moves_sd,
               full_moves_term=both.moves_term, full_midpoints=both.midpoints,
               full_extrapolated=both.extrapolated,
               full_converged=info.converged and last.converged, ms_term_cov=term_cov,
               ms_restart_adopted=adopted, **({} if adopted else {  # adopted: no 2nd
                   "ms_restart_delta": check.delta, "ms_restart_delta_seeds": check.delta_seeds}),
               ms_restart_shift_sd=None if adopted else  # no 2nd
               restart_in_loop_units(problem, loop, restart.x, loop_term, res.x),
               ms_restart_values={"kappa_t": float(np.exp(restart.x[0])), "g": float(np.tanh(restart.x[2]))},
               **_last_refreshes_fields(problem, res, loop, loop_term, term_cov, offset, shift),
               ms_final_paths=paths, ms_images=ms_images(problem, res.x))
    if other_g is not None:  # relative to the final MAP (fit_channel: other_g_mode)
        alt_full.log_posterior = res.log_posterior + other_g["delta_log_posterior"]
        out["full_other_mode_map"] = alt_full
    return res, out


def _last_refreshes_fields(problem: ChannelProblem, res, loop, loop_term, term_cov, offset,
                           shift) -> dict:
    """``_full_transport``'s fields on the last refreshes, from the loop's end ``loop`` (its
    jackknife ``loop_term``) to the MAP ``res`` (its jackknife ``term_cov`` and offset budget
    ``offset``): their move, and the seed shift (``shift``, measured at the loop's end) judged
    against the intervals' whole term error and against the loop's jackknife alone."""
    from .full import distance_sd, seed_shift_units

    return {"ms_seed_shift_sd": seed_shift_units(shift, loop_term, term_cov, offset),
            "ms_seed_shift_jackknife_sd": seed_shift_units(shift, loop_term),
            "ms_offset_cov": offset,
            "ms_final_move_sd": distance_sd(problem, res, loop.x, term_cov),
            "ms_final_move": {"kappa_t": float(np.exp(res.x[0] - loop.x[0]) - 1.0),
                              "g": float(np.tanh(res.x[2]) - np.tanh(loop.x[2]))}}


def _misfit_scan(problem: ChannelProblem, space: ParameterSpace, check, single_x: np.ndarray,
                 channel: str, scanned: bool = False) -> tuple:
    """For a bulb (not ``scanned`` from the start, as a spot is) whose full-transport fit
    ``check`` (``full.RestartCheck``, at the loop's paths) fails the misfit guard there
    (trust.py: ``misfit``): the spot's scan from the single-scattering MAP ``single_x``
    (``full.scan_start``), the loop and the restart check from its best point, and the better
    of the two fits (each log posterior with the local model rebuilt there) kept.  The loop's
    start decides which of its fixed points it ends at, and from the single-scattering MAP of
    dense milk it may end at one that does not describe the images (Regular Milk 60 ml at
    100 x 75 px, G: chi2/pixel 2.83 at the loop's end, the noise allowing 1.23; from the
    scan's best start 1.04 in the end: docs/inference.md, "Dense milk at 100 x 75").  Returns
    the check kept and results.json's ``misfit_scan`` (None where the guard held)."""
    from ..trust import misfit
    from .full import log_posterior_rebuilt, refine_map, restart_check, scan_start

    if scanned:
        return check, None
    lp = log_posterior_rebuilt(problem, check.res.x)
    chi2, n = problem.chi2(check.res.x)
    before = chi2 / max(n, 1)
    if misfit(before, n)["ok"] is not False:
        return check, None
    log.info("full transport, channel %s: chi2/pixel %.3g at the fit does not describe the "
             "images; scanning for another start", channel, before)
    start = MapResult(single_x.copy(), float("nan"), 0, None)  # scan_start reads its x
    best, rows = scan_start(problem, space, start)
    res, info = refine_map(problem, space, best)
    other = restart_check(problem, space, res, info, single_x, channel)
    lp_other = log_posterior_rebuilt(problem, other.res.x)
    chi2_other = problem.chi2(other.res.x)[0] / max(n, 1)
    used = lp_other > lp
    kept = other if used else check
    problem.refresh_models(kept.res.x)
    problem.adapt(kept.res.x)
    return kept, {"rows": rows, "chi2_per_pixel_before": before,
                  "chi2_per_pixel_after": chi2_other, "delta_log_posterior": lp_other - lp,
                  "used": bool(used)}


def _full_other_g(problem: ChannelProblem, space: ParameterSpace, res, info, single_x, alt):
    """The single-scattering optimum ``alt`` with g of the other sign, refined with the full
    model; the better of it and the full MAP ``res`` (each log posterior with the local model
    rebuilt there) becomes the MAP.  Returns the MAP, its refreshes' info, the single-scattering
    point it came from, and the other one (``other_g_mode``'s fields and its MapResult; None,
    None where it is not of the other sign: it slid into the MAP's region)."""
    from .full import log_posterior_rebuilt, refine_map

    alt_full, alt_info = refine_map(problem, space, alt)
    lp_alt = log_posterior_rebuilt(problem, alt_full.x)
    lp_res = log_posterior_rebuilt(problem, res.x)
    if lp_alt > lp_res:
        res, alt_full, info, single_x, lp_res, lp_alt = \
            alt_full, res, alt_info, alt.x, lp_alt, lp_res
        problem.refresh_models(res.x)
        problem.adapt(res.x)
    if not (_opposite_g(alt_full.x, res.x) and abs(np.tanh(alt_full.x[2])) >= SAME_MODE_G):
        return res, info, single_x, None, None
    other = {"g": float(np.tanh(alt_full.x[2])), "kappa_t": float(np.exp(alt_full.x[0])),
             "delta_log_posterior": float(lp_alt - lp_res)}
    return res, info, single_x, other, alt_full


def _auto_choice(share: list[float], scan: dict | None) -> tuple[bool, str]:
    """``--model auto``'s choice from the share at the single-scattering MAP and, on a spot,
    the full model's scan (:func:`_spot_scan`): (full transport?, why in plain words)."""
    from .full import AUTO_SHARE

    above = max(share) > AUTO_SHARE
    why = (f"the multiple-scattering share at the single-scattering MAP, {_pct(max(share))} of "
           f"the glow, is {'above' if above else 'at or below'} {_pct(AUTO_SHARE)} (AUTO_SHARE)")
    if not above and scan is not None and scan["verdict"] is not None:
        return True, why + (f"; but full transport at kappa_t {scan['best_kappa_t']:.4g}, g "
                            f"{scan['best_g']:.3g} fits the images {scan['verdict']} "
                            f"({scan['gain']:+.3g} log-posterior units; a spot: its single-"
                            "scattering fit can take multiple scattering for a thinner medium)")
    return above, why


def _spot_scan(problem: ChannelProblem, space: ParameterSpace, res, spec: Spec, channel: str,
               ms_seed: int) -> dict | None:
    """For a spot capture that does not declare a single-scattering render: the full model
    scanned from the single-scattering MAP ``res`` (inference/full.py: ``scan_start``; the
    problem is left with the full-transport model).  ``verdict`` (``full.scan_verdict``) and
    the point it names (``best_kappa_t``, ``best_g``; ``gain``: its log posterior minus the
    single MAP's); ``best``: the best point's MapResult.  None for a bulb (its direct view
    pins kappa_t) or a declared single render."""
    from .full import scan_start, scan_verdict, use_full_transport

    lights = {spec.light_for(i).type for i in range(len(spec.images))} or {spec.light.type}
    if "spot" not in lights or spec.synthetic_model == "single":  # any image lit by a spot
        return None
    use_full_transport(problem, spec, channel, seed=ms_seed)
    best, rows = scan_start(problem, space, res)
    verdict, named = scan_verdict(rows, res.log_posterior, float(np.exp(res.x[0])))
    return {"best": best, "rows": rows, "verdict": verdict,
            "gain": float(named["log_posterior"] - res.log_posterior),
            "best_kappa_t": named["kappa_t"], "best_g": named["g"]}


def auto_stays_single(spec: Spec) -> str | None:
    """Why ``--model auto`` keeps the single-scattering model for ``spec`` without tracing
    the multiple-scattering term, else None (auto then decides by the term's share at the
    single-scattering MAP, ``_full_transport``):

    * the capture declares a single-scattering render (``synthetic.model: single``, which
      ``fitmedia synth --model single`` writes): its images hold no multiple scattering, so
      the single model is the exact one and the full model would add light that is not
      there.  The single-scattering check still runs and notes the share."""
    if spec.synthetic_model == "single":
        return ("the capture declares a single-scattering render (synthetic.model: single), "
                "whose images hold no multiple scattering")
    return None


def _pct(x: float) -> str:
    """A share as a percentage with two significant figures."""
    return f"{100 * x:.2g} %"


def _ms_seeds(seed: int, channel: str) -> tuple[int, int]:
    """The multiple-scattering term's seeds of one channel's fit (the term's own and the seed-
    shift check's): streams of their own, so the chains' draws do not move."""
    a, b = np.random.default_rng([seed, CHANNELS.index(channel), 5]).integers(2**31, size=2)
    return int(a), int(b)


def _single_ms_check(problem: ChannelProblem, space: ParameterSpace, res, spec: Spec,
                     channel: str, seed: int) -> dict:
    """``--model single``: the multiple-scattering share at the MAP ``res`` and how far chi2/
    pixel would rise were that term in the images (inference/full.py: ``ms_detectability``;
    trust.py judges it).  The same random numbers as ``--model auto``'s share.  On a spot
    capture also the full model's scan from the MAP (:func:`_spot_scan`; ``ms_scan_gain``)."""
    from .full import ms_detectability, use_single_scattering

    ms_seed = _ms_seeds(seed, channel)[0]
    det = ms_detectability(problem, res.x, spec, channel, seed=ms_seed)
    out = {"model_used": "single", "ms_share_single_map": det["share"],
           "ms_share": det["share"], "ms_share_se": det["share_se"],
           "ms_chi2_excess": det["chi2_excess_per_pixel"],
           "ms_declared_single_render": spec.synthetic_model == "single"}
    scan = _spot_scan(problem, space, res, spec, channel, ms_seed)
    if scan is not None:
        use_single_scattering(problem, res.x)
        out.update(ms_scan=scan["rows"], ms_scan_gain=scan["gain"],
                   ms_scan_verdict=scan["verdict"],
                   ms_scan_best={"kappa_t": scan["best_kappa_t"], "g": scan["best_g"]})
    return out


def albedo_redraw(space: ParameterSpace, x_map: np.ndarray, cov: np.ndarray | None) -> Redraw:
    """The chains' albedo move, in 20 % of the steps: a new logit albedo for each walker with
    its kappa_s kept (log kappa_t moves by the change of log albedo), drawn independently of
    the old one from an equal mixture of the albedo's prior and a normal around the MAP twice
    the Laplace sd wide.  Where a thin dilution leaves kappa_a unresolved, the flat-logit half
    of the prior puts a few per cent of the posterior on a plateau (logit albedo ~4-15, kappa_t
    = kappa_s) that differential evolution, its steps scaled by the bulk's spread, crosses in
    hundreds of steps; this move jumps between the two.  The map (log kappa_t, logit albedo)
    -> (log kappa_s, logit albedo) has unit Jacobian, so the acceptance ratio is the posterior
    ratio times q(old) / q(new)."""
    from scipy.special import log_expit
    from scipy.stats import norm

    mu = float(x_map[1])
    sd = 2.0 * float(np.sqrt(cov[1, 1])) if cov is not None and cov[1, 1] > 0 else 1.0

    def log_q(u):
        return np.logaddexp(space.log_albedo_prior(u), norm.logpdf(u, mu, sd)) + np.log(0.5)

    def propose(coords, random):
        n = len(coords)
        new = np.where(random.uniform(0.0, 1.0, n) < 0.5, space.draw_logit_albedo(random, n),
                       random.normal(mu, sd, n))
        q = np.array(coords, float)
        q[:, 0] += log_expit(coords[:, 1]) - log_expit(new)
        q[:, 1] = new
        return q, log_q(coords[:, 1]) - log_q(new)
    return Redraw(propose, weight=0.2)


def _opposite_g(x: np.ndarray, y: np.ndarray) -> bool:
    """Whether two points of the sampler's space scatter opposite ways (g of opposite signs)."""
    return bool(np.tanh(x[2]) * np.tanh(y[2]) < 0)


def _min_ess(chain) -> float | None:
    return None if chain.ess is None else float(np.min(chain.ess))


def _chain_mass(log_prob, chain, space: ParameterSpace, rng: np.random.Generator):
    """The log mass of the mode that ``chain`` sampled (``mode_log_mass``)."""
    return mode_log_mass(log_prob, chain.samples, chain.log_prob_samples, space.lower,
                         space.upper, rng, n_eff=_min_ess(chain))


def _sample_other_mode(problem: ChannelProblem, space: ParameterSpace, res, alt, chain,
                       log_post, options: FitOptions, checkpoint: Path | None,
                       seed: list[int], channel: str, other_mode: dict,
                       identity: dict | None = None) -> dict:
    """Sample the other sign's mode of g with a chain of its own (quadrature nodes adapted to
    it; with full transport, the local model of the multiple-scattering term rebuilt there,
    the same random numbers), measure both modes' posterior masses by bridge sampling, and
    mix the two chains' samples by those masses.  Returns the fields of ``fit_channel``'s
    result that change.

    The second chain and the bridge/mixing draw from random streams of their own (``seed``
    plus 2 and 3): a resumed first chain skips its initial draws, and must not shift them."""
    rng = np.random.default_rng([*seed, 3])
    with problem.tabulated(res.x, res.cov):  # the images its chain's log_prob came from
        mass = [_chain_mass(log_post, chain, space, rng)]
    with problem.models_kept():  # a full-transport model: its local model at res afterwards
        problem.refresh_models(alt.x)  # full transport: the local model rebuilt at this mode
        problem.adapt(alt.x)
        log_alt = half_space(problem.log_posterior, 2, alt.x[2])
        polished = find_map(log_alt, alt.x, space.lower, space.upper, global_evals=0)
        ckpt = None if checkpoint is None else checkpoint.with_name(
            checkpoint.stem + "_mode2" + checkpoint.suffix)
        with problem.tabulated(polished.x, polished.cov):  # as for the first chain
            chain2 = run_chain(log_alt, polished.x, polished.cov, space.lower, space.upper,
                               rng=np.random.default_rng([*seed, 2]), checkpoint=ckpt,
                               resume=options.resume, n_walkers=options.n_walkers,
                               n_tau=options.n_tau, max_steps=options.max_steps,
                               progress=options.progress, label=f"{channel} mode 2",
                               redraw=albedo_redraw(space, polished.x, polished.cov),
                               identity=identity)
            mass.append(_chain_mass(log_alt, chain2, space, rng))
    problem.adapt(res.x)
    w = mode_weights(mass)
    idx = mix_modes([chain.samples, chain2.samples], w, rng)
    parts, logps = (chain.samples, chain2.samples), (chain.log_prob_samples,
                                                     chain2.log_prob_samples)
    samples = np.array([parts[k][r] for k, r in idx])
    log_prob = np.array([logps[k][r] for k, r in idx])
    order = rng.permutation(len(samples))
    modes = []
    for k, (c, m, x) in enumerate(zip((chain, chain2), mass, (res.x, polished.x))):
        modes.append({"g_map": float(np.tanh(x[2])), "weight": float(w[k]),
                      "log_mass": m.log_mass, "mass_rel_se": m.rel_se,
                      "importance_ess": m.ess, "converged": bool(c.converged),
                      "reason": c.reason, "n_steps": int(c.n_steps),
                      "autocorr_time_max": float(np.nanmax(c.tau)),
                      "n_samples_used": int(np.sum(idx[:, 0] == k))})
    weight_se = float(w[0] * w[1] * np.hypot(mass[0].rel_se, mass[1].rel_se))
    trusted = weight_se < MODE_WEIGHT_SE
    converged = chain.converged and chain2.converged and trusted
    reason = (f"two modes of g sampled: g = {modes[0]['g_map']:.3g} (weight {w[0]:.3g}) and "
              f"g = {modes[1]['g_map']:.3g} (weight {w[1]:.3g}); mode 1: {chain.reason}; "
              f"mode 2: {chain2.reason}")
    if not trusted:
        reason += (f"; the modes' weights are uncertain (standard error {weight_se:.2g} > "
                   f"{MODE_WEIGHT_SE:g})")
    other = dict(other_mode, sampled=True, weight=float(w[1]), weight_se=weight_se)
    return {"samples": samples[order], "log_prob": log_prob[order], "converged": converged,
            "reason": reason, "modes": modes, "chain_mode2": chain2.chain,
            "other_g_mode": other}


def _job(args):
    return fit_channel(*args)


def channel_args(prep: Prepared, ch: str, options: FitOptions, checkpoint_dir: Path | None,
                 identity: dict | None = None, forward=None) -> tuple:
    """``fit_channel``'s arguments for channel ``ch`` of a prepared capture."""
    ci = CHANNELS.index(ch)
    ckpt = None if checkpoint_dir is None else Path(checkpoint_dir) / f"checkpoint_{ch}.npz"
    return (prep.spec, ch, [im.data[..., ci] for im in prep.images],
            [im.valid[..., ci] for im in prep.images], prep.brightness[ch],
            prep.brightness_rel_sd.get(ch), prep.noise[ch], options, ckpt, options.seed, identity,
            [(g[..., ci], r[..., ci]) for g, r in
             (prep.noise_maps[f"images[{i}]"] for i in range(len(prep.images)))]
            if prep.noise_maps else None, forward)


def run_channels(prep: Prepared, options: FitOptions, checkpoint_dir: Path | None,
                 identity: dict | None = None, forward=None) -> dict[str, dict]:
    """Fit every channel (in parallel processes when there are cores); one chain file each.
    The worker processes die with this process (:func:`die_with_parent`), even by SIGKILL.
    ``forward``: a forward-model factory (:func:`_model`; picklable for the processes)."""
    jobs = [channel_args(prep, ch, options, checkpoint_dir, identity, forward)
            for ch in prep.spec.channels]
    workers = options.workers or default_workers(len(jobs), prep.spec)
    if workers <= 1 or len(jobs) == 1:
        return {j[1]: fit_channel(*j) for j in jobs}
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("fork"),
                             initializer=die_with_parent, initargs=(os.getpid(),)) as pool:
        results = list(pool.map(_job, jobs))
    return {r["channel"]: r for r in results}


#: prctl(2) option: the signal this process gets when the thread that forked it ends
PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """Worker-process initializer: be killed (SIGKILL) when the parent ends, however it ends,
    so that a `kill -9` of the main process leaves no worker writing checkpoints that a later
    ``--resume`` would race.  Linux only (prctl PR_SET_PDEATHSIG; elsewhere a no-op).  A parent
    that died between the fork and the prctl is caught by its pid: the worker then exits."""
    import ctypes
    import signal
    import sys

    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent_pid:
        os._exit(1)


def prior_g_interval_width(space: ParameterSpace | None = None) -> float:
    lo, hi = space.g_range if space is not None else (G_MIN, G_MAX)
    return 0.9 * (hi - lo)
