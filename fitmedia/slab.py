"""Total reflectance and transmittance of a plane-parallel slab, by Mitsuba 3.

A check of the medium code path that the tank model uses (``homogeneous``
medium, ``hg`` phase function, smooth ``dielectric`` boundaries, ``volpath``)
against published adding-doubling and Monte Carlo tables.

Method (reciprocity, see ``docs/mitsuba.md``): the total reflectance of a slab
for a collimated beam arriving from direction w0 equals the radiance that
leaves the slab towards w0 when the slab is lit by radiance 1 from the whole
hemisphere on the beam's side; the total transmittance equals the same
radiance when the slab is lit from the other hemisphere only.  So a
``radiancemeter`` just above the slab looking along -w0, a ``constant``
environment of radiance 1 and one black plane that hides the unwanted
hemisphere (below the slab for R, above the meter for T) measure R or T
directly, specular reflection and unscattered transmission included.

Units: the slab's extinction is 1 (per mm) and its thickness is the optical
thickness.  The slab's top face is at z = 0 (Mitsuba's ray epsilons grow with
the coordinates, so the region that matters is kept near the origin).
"""

from __future__ import annotations

import math

import numpy as np

from .errors import InputError

#: Extra optical depth (in diffusion lengths) that stands in for "infinitely thick".
SEMI_INFINITE_DIFFUSION_LENGTHS = 40.0
#: Largest optical thickness used for a semi-infinite slab.
MAX_SEMI_INFINITE = 1e5
#: Samples per batch (one ``mi.render`` call); batches give the standard error.
BATCH_SPP = 1 << 13
MIN_BATCHES = 8
#: Most samples an adaptive call (``spp=None``) takes for each of R and T.
MAX_SPP = 1 << 21


def diffusion_length(albedo: float, g: float) -> float:
    """Diffusion length in mean free paths, 1 / sqrt(3 ka (ka + ks (1 - g))) with kt = 1."""
    ka, ks = 1.0 - albedo, albedo
    if ka <= 0:
        return math.inf
    return 1.0 / math.sqrt(3.0 * ka * (ka + ks * (1.0 - g)))


def semi_infinite_thickness(albedo: float, g: float) -> float:
    """Optical thickness that behaves as infinite for R at 1e-6 precision or better.

    The diffuse light decays as exp(-tau / L_d) with the diffusion length L_d,
    so 40 L_d (plus 100 mean free paths for the unscattered and near-surface
    light) leaves a relative change of R below exp(-40) ~ 4e-18.
    """
    tau = 100.0 + SEMI_INFINITE_DIFFUSION_LENGTHS * diffusion_length(albedo, g)
    if not tau <= MAX_SEMI_INFINITE:
        raise InputError(f"albedo: got {albedo!r} with g {g!r}: a semi-infinite slab this close to "
                         f"albedo 1 needs an optical thickness above {MAX_SEMI_INFINITE:g}; "
                         f"give a finite optical_thickness")
    return tau


def _check(albedo, optical_thickness, g, n, mu0, spp, rel_err, abs_err) -> float:
    if not 0.0 <= albedo <= 1.0:
        raise InputError(f"albedo: got {albedo!r}, expected 0 <= albedo <= 1")
    if not (optical_thickness > 0):  # also rejects NaN
        raise InputError(f"optical_thickness: got {optical_thickness!r}, expected > 0 or inf")
    if not -1.0 < g < 1.0:
        raise InputError(f"g: got {g!r}, expected -1 < g < 1")
    if not 1.0 <= n < 10.0:
        raise InputError(f"n: got {n!r}, expected 1 <= n < 10")
    if not 0.0 < mu0 <= 1.0:
        raise InputError(f"mu0: got {mu0!r}, expected 0 < mu0 <= 1 (cosine of the incidence angle)")
    if spp is not None and not int(spp) >= 2 * BATCH_SPP:
        raise InputError(f"spp: got {spp}, expected None (adaptive) or >= {2 * BATCH_SPP} "
                         f"(two batches of {BATCH_SPP})")
    if not (rel_err > 0 and abs_err > 0):
        raise InputError(f"rel_err {rel_err!r} and abs_err {abs_err!r} must be > 0")
    if math.isinf(optical_thickness):
        return semi_infinite_thickness(albedo, g)
    return float(optical_thickness)


def _scene(mi, albedo: float, tau: float, g: float, n: float, mu0: float, which: str) -> dict:
    T = mi.ScalarTransform4f
    width = max(1e4, 100.0 * min(diffusion_length(albedo, g), tau) + 10.0 * tau)
    w0 = np.array([math.sqrt(max(0.0, 1.0 - mu0 * mu0)), 0.0, mu0])
    origin = 1e-3 * w0 / mu0  # just above the top face (z = 0), on the ray through the origin
    boundary = {"type": "null"} if n == 1.0 else {"type": "dielectric", "int_ior": n,
                                                  "ext_ior": 1.0}
    # R: hide the lower hemisphere below the slab; T: hide the upper one above the meter
    block_z = -tau - 1.0 if which == "R" else 1e-3 + 1.0
    return {
        "type": "scene",
        # no Russian roulette: absorption is already sampled analogously
        "integrator": {"type": "volpath", "max_depth": -1, "rr_depth": 1 << 30},
        "sensor": {"type": "radiancemeter", "origin": origin.tolist(), "direction": (-w0).tolist(),
                   "sampler": {"type": "independent"},
                   "film": {"type": "hdrfilm", "width": 1, "height": 1,
                            "rfilter": {"type": "box"}, "pixel_format": "luminance"}},
        "sky": {"type": "constant", "radiance": 1.0},
        "medium": {"type": "homogeneous", "sigma_t": 1.0, "albedo": float(albedo), "scale": 1.0,
                   "phase": {"type": "hg", "g": float(g)}},
        "slab": {"type": "cube", "bsdf": boundary, "interior": {"type": "ref", "id": "medium"},
                 "to_world": T().translate([0.0, 0.0, -tau / 2]).scale([width, width, tau / 2])},
        "blocker": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": 0.0},
                    "to_world": T().translate([0.0, 0.0, block_z]).scale([1e3 * width,
                                                                          1e3 * width, 1.0])},
    }


def _measure(mi, scene_d: dict, *, spp: int | None, seed: int, stream: int,
             rel_err: float, abs_err: float) -> tuple[float, float]:
    """Mean radiance of the meter and its standard error, from batches of BATCH_SPP samples.

    With ``spp`` None: MIN_BATCHES batches first, then as many more as the
    observed batch-to-batch spread says are needed for a standard error below
    max(rel_err * value, abs_err), at most MAX_SPP samples in all.
    """
    scene = mi.load_dict(scene_d)
    max_batches = max(MIN_BATCHES, -(-(spp or MAX_SPP) // BATCH_SPP))
    seeds = np.random.SeedSequence([seed, stream]).generate_state(max_batches, dtype=np.uint32)
    vals: list[float] = []

    def run(k_total: int) -> None:
        while len(vals) < k_total:
            v = float(np.asarray(mi.render(scene, spp=BATCH_SPP, seed=int(seeds[len(vals)])))
                      .ravel()[0])
            if not math.isfinite(v):
                raise FloatingPointError(f"Mitsuba returned a non-finite slab radiance {v!r}")
            vals.append(v)

    if spp is not None:
        run(max_batches)
    else:
        run(MIN_BATCHES)
        for _ in range(4):  # the spread estimate firms up as batches accumulate
            spread = float(np.std(vals, ddof=1))
            target = max(rel_err * abs(float(np.mean(vals))), abs_err)
            need = min(max_batches, math.ceil(1.1 * (spread / target) ** 2))
            if need <= len(vals):
                break
            run(need)
    a = np.asarray(vals)
    return float(a.mean()), float(a.std(ddof=1) / math.sqrt(len(a)))


def slab_rt(albedo: float, optical_thickness: float, g: float, n: float, *, mu0: float = 1.0,
            spp: int | None = None, seed: int = 0, rel_err: float = 0.003, abs_err: float = 2e-4,
            variant: str | None = None) -> dict[str, float]:
    """Total R and T of a homogeneous slab in air lit by a collimated beam.

    Parameters
    ----------
    albedo : float
        Single-scattering albedo kappa_s / kappa_t.
    optical_thickness : float
        kappa_t times the thickness; ``math.inf`` for a semi-infinite slab
        (rendered as a slab of :func:`semi_infinite_thickness`, T = 0).
    g : float
        Henyey–Greenstein anisotropy.
    n : float
        Refractive index of the slab (smooth boundaries); 1 means index matched
        (Mitsuba ``null`` boundary).
    mu0 : float
        Cosine of the angle of incidence.
    spp : int, optional
        Monte Carlo samples for each of R and T (rounded up to whole batches
        of :data:`BATCH_SPP`).  Default None: adaptive, until the standard
        error is below max(rel_err * value, abs_err) or :data:`MAX_SPP`
        samples are spent; that takes about 0.5-3 s on 2 CPU cores for the
        reference cases in ``tests/data/slab_references.csv``.
    seed : int
        Seed of the sampler (the result is reproducible for a given seed).
    rel_err, abs_err : float
        Target standard errors (relative and absolute) of the adaptive mode.
    variant : str, optional
        Mitsuba variant (default: :func:`fitmedia.mitsuba_env.choose_variant`).

    Returns
    -------
    dict
        ``R``, ``T`` (unitless fractions of the incident power) and their Monte
        Carlo standard errors ``R_err``, ``T_err`` (standard deviation of the
        batch means over sqrt(number of batches)).
    """
    from .mitsuba_env import import_mitsuba

    albedo, g, n, mu0 = float(albedo), float(g), float(n), float(mu0)
    tau = _check(albedo, float(optical_thickness), g, n, mu0, spp, rel_err, abs_err)
    mi = import_mitsuba(variant)
    opts = dict(spp=None if spp is None else int(spp), seed=int(seed), rel_err=float(rel_err),
                abs_err=float(abs_err))
    r, r_err = _measure(mi, _scene(mi, albedo, tau, g, n, mu0, "R"), stream=0, **opts)
    if math.isinf(optical_thickness):
        t, t_err = 0.0, 0.0
    else:
        t, t_err = _measure(mi, _scene(mi, albedo, tau, g, n, mu0, "T"), stream=1, **opts)
    return {"R": r, "T": t, "R_err": r_err, "T_err": t_err}
