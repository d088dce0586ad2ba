"""Synthetic captures: render a dilution series with a forward model, add
Poisson–Gaussian camera noise from a seeded generator, and write float TIFFs,
a capture spec that points at them, and truth.json."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .images import write_float_tiff
from .medium import Medium
from .spec import CHANNELS, Spec, dump_spec
from .util import make_rng, staged_output_dir, write_json

DEFAULT_BRIGHTNESS = 1.0      # bulb radiance in the water, image units
DEFAULT_SPOT_INTENSITY = 2.0e4  # spot radiant intensity, image units x mm^2
DEFAULT_GAIN = 2.0e-5         # variance per unit value (a full well of 5e4 e- at value 1)
DEFAULT_READ_VAR = 1.0e-9
SATURATION = 4.0              # the synthetic camera clips here (written into the spec)
#: a hybrid capture's multiple-scattering term is a Monte Carlo estimate, and its error is in
#: the images but not in their noise model: a fit's chi2/pixel at the truth rises by the mean,
#: over the pixels the term reaches, of (term error / camera noise sd)^2.  Where that mean
#: square exceeds this in some channel, synth says so (truth.json ``notes``, printed): it is
#: half the misfit guard's model-error allowance (trust.MODEL_ERROR_ALLOWANCE, 0.1), the rest
#: being the fit's own term error.  Measured (docs/multiple_scattering.md, "Test captures
#: with this term"): the bench's 200 x 150 Lowfat Milk 16 ml capture at 256 paths per pixel
#: had a median ratio of only 0.09 in R (the paths are heavy-tailed) but a mean square of 0.18
#: (0.21 against the fit's own variance), and its full fit's chi2/pixel was 1.16 against 1.15
#: with the values within 0.7 % of the truth; the median (the note's statistic until
#: 2026-12-07, bound 0.3) did not see it
HYBRID_TERM_CHI2 = 0.05


#: truth.json's note for a capture made with ``--gain 0 --read-var 0`` (since 2026-12-07)
NOISE_FREE_NOTE = ("the images are noise-free (gain and read_var 0): capture.yaml's noise block "
                   "has zero variance, which fit refuses; give it the variance to fit with "
                   "(docs/spec.md, noise)")


@dataclass(frozen=True)
class CameraNoise:
    gain: float = DEFAULT_GAIN
    read_var: float = DEFAULT_READ_VAR

    def apply(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Poisson photo-electrons (mean image / gain) times gain, plus Gaussian read noise."""
        mean = np.clip(image, 0.0, None)
        shot = rng.poisson(mean / self.gain) * self.gain if self.gain > 0 else mean
        return shot + rng.normal(0.0, np.sqrt(self.read_var), size=image.shape)

    def is_zero(self) -> bool:
        """Whether this adds no noise at all (a noise-free capture)."""
        return self.gain == 0 and self.read_var == 0


def _render(spec: Spec, index: int | None, medium: Medium, brightness: np.ndarray, model: str,
            spp: int, seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The clean image (H, W, 3) and, for ``hybrid``, the standard error of its Monte Carlo
    multiple-scattering term (else None)."""
    if model == "single":
        from .forward.single import SingleScattering

        m = SingleScattering(spec, index, channels=CHANNELS, supersample=2)
    elif model == "full":
        from .forward.mitsuba import MitsubaModel

        m = MitsubaModel(spec, 0 if index is None else index, spp=spp, seed=seed, channels=CHANNELS)
    elif model == "hybrid":  # analytic single scattering + fitmedia's own multiple-scattering term
        from .forward.multiple import MultipleScattering
        from .forward.single import SingleScattering

        ss = SingleScattering(spec, index, channels=CHANNELS, supersample=2)
        ms = MultipleScattering(spec, index, channels=CHANNELS, bin=1, n_paths=max(spp, 16))
        term, err = ms.render(medium.kappa_a, medium.kappa_s, medium.g, brightness, seed=seed)
        return ss.render(medium.kappa_a, medium.kappa_s, medium.g, brightness) + term, err
    else:
        raise InputError(f"--model: expected 'single', 'full' or 'hybrid', got {model!r}")
    return m.render(medium.kappa_a, medium.kappa_s, medium.g, brightness), None


def term_noise(clean: np.ndarray, err: np.ndarray, noise: CameraNoise) -> dict:
    """Per channel, the Monte Carlo error ``err`` of a hybrid capture's term against the
    camera noise's sd at the clean image ``clean``, over the pixels the term reaches:
    ``median`` and ``p90`` of the ratio, and ``mean_square``, the mean of its square (what it
    adds to a fit's chi2/pixel at the truth); 0 where it reaches none."""
    sd = np.sqrt(noise.gain * np.clip(clean, 0.0, None) + noise.read_var)
    out = {}
    for k, ch in enumerate(CHANNELS):
        reach = err[..., k] > 0
        r = err[..., k][reach] / sd[..., k][reach] if reach.any() else np.zeros(1)
        out[ch] = {"median": float(np.median(r)), "p90": float(np.percentile(r, 90)),
                   "mean_square": float(np.mean(r ** 2))}
    return out


def _image_notes(k: int, img: np.ndarray, clean: np.ndarray, err: np.ndarray | None,
                 noise: CameraNoise, spp: int, notes: list[str]) -> dict:
    """truth.json's extra fields for image ``k`` (``img``, rendered ``clean`` with the term's
    error ``err``); appends its notes (term error, saturated pixels) to ``notes``."""
    extra = {}
    # hybrid: how large the term's own error is, in camera noise (none to compare with in a
    # noise-free capture: until 2026-12-07 its ratio was inf and its note said so)
    if err is not None and not noise.is_zero():
        extra["ms_term_error_to_camera_noise"] = ratio = term_noise(clean, err, noise)
        notes += _term_noise_note(k, ratio, max(spp, 16))
    n_sat = int(np.sum(np.any(img >= SATURATION, axis=-1)))
    if n_sat:
        notes.append(f"image {k}: {n_sat} pixels saturated")
    return extra


def _term_noise_note(k: int, ratio: dict, paths: int) -> list[str]:
    """truth.json's note for image ``k`` where its term's error (:func:`term_noise`'s
    ``ratio``) adds more than ``HYBRID_TERM_CHI2`` to chi2/pixel in some channel; else none."""
    ch = max(ratio, key=lambda c: ratio[c]["mean_square"])
    if not ratio[ch]["mean_square"] > HYBRID_TERM_CHI2:
        return []
    return [f"image {k}: the multiple-scattering term's own Monte Carlo error adds "
            f"{ratio[ch]['mean_square']:.2g} to chi2/pixel at the truth in channel {ch} (the "
            f"mean square of its ratio to the camera noise over the water; median ratio "
            f"{ratio[ch]['median']:.2g}, 90th percentile {ratio[ch]['p90']:.2g}) at {paths} paths "
            f"per pixel, above {HYBRID_TERM_CHI2:g}: the images hold that noise and their noise "
            "model does not, so a fit's chi2/pixel rises by as much (the misfit guard allows "
            "0.1 for all model error) and its values scatter more than their intervals say; "
            "render with more --spp (in a typical pixel the error falls more slowly than "
            "1/sqrt(spp): docs/multiple_scattering.md)"]


def _with_water(tank: Medium, water_kappa_a: np.ndarray) -> Medium:
    """The tank's medium plus the clear water's absorption (spec ``medium.water_kappa_a``)."""
    return Medium(tank.kappa_a + water_kappa_a, tank.kappa_s, tank.g, tank.channels, tank.name)


def synthesize(spec: Spec, out_dir: str | Path, medium: Medium, ml: list[float], *,
               tank_ml: float = 23000.0, seed: int = 0, model: str = "single", spp: int = 256,
               brightness: float | list[float] | None = None, noise: CameraNoise = CameraNoise(),
               medium_name: str = "") -> Path:
    """Write a synthetic capture of ``medium`` diluted ``ml`` in ``tank_ml``; returns the spec path.

    ``spec`` gives the geometry (its images and calibration are ignored).  Each
    image's concentration is ml / tank_ml; the medium is the undiluted liquid.
    """
    if tank_ml <= 0 or not np.isfinite(tank_ml):
        raise InputError(f"--tank-ml: got {tank_ml}: must be a positive volume in ml")
    for v in ml:
        if not (v > 0 and np.isfinite(v)):
            raise InputError(f"--ml: got {v}: must be a positive volume in ml")
    for flag, v in (("--gain", noise.gain), ("--read-var", noise.read_var)):
        if not (v >= 0 and np.isfinite(v)):  # until 2026-12-07 -1 wrote NaN or an unfittable spec
            raise InputError(f"{flag}: got {v}: must be a finite variance >= 0 (0: no such noise)")
    from .memory import check_memory

    check_memory(spec, "synth", tracer=model == "hybrid")
    rng = make_rng(seed)
    with staged_output_dir(out_dir) as out:  # checked before any work; moved into place at the end
        raw, truth = _write_capture(spec, out, medium, ml, tank_ml=tank_ml, seed=seed, model=model,
                                    spp=spp, brightness=brightness, noise=noise, rng=rng,
                                    medium_name=medium_name)
        dump_spec(raw, out / "capture.yaml")
        write_json(out / "truth.json", truth)
    return Path(out_dir) / "capture.yaml"


def _write_capture(spec: Spec, out: Path, medium: Medium, ml: list[float], *, tank_ml: float,
                   seed: int, model: str, spp: int, brightness, noise: CameraNoise,
                   rng: np.random.Generator, medium_name: str) -> tuple[dict, dict]:
    """Render and write the images of :func:`synthesize` into ``out``; returns the capture
    spec's data and truth.json's."""
    light = spec.light
    if brightness is None:
        brightness = DEFAULT_BRIGHTNESS if light.type == "bulb" else DEFAULT_SPOT_INTENSITY
    bright = np.broadcast_to(np.asarray(brightness, float), (3,)).copy()
    raw = copy.deepcopy(spec.raw)
    raw.pop("images", None)
    raw.pop("calibration", None)
    # ``channels`` (the channels to fit) is kept: the images hold R, G and B and truth.json
    # all three, and a fit of the capture fits the ones its spec names (until 2026-12-06 it
    # was dropped, and a one-channel study's capture fitted all three)
    raw["name"] = f"synthetic-{medium_name or 'medium'}".replace(" ", "-").lower()
    if light.type == "spot":
        raw["light"]["intensity"] = bright.tolist()  # a spot cannot be calibrated by a photo
    entries, truth_imgs = [], []
    notes = []
    water = np.asarray(spec.water_kappa_a, float)  # the clear water's own absorption, 1/mm
    for k, v in enumerate(ml):
        c = v / tank_ml
        tank_medium = _with_water(medium.scaled(c), water)
        clean, err = _render(spec, None, tank_medium, bright, model, spp, seed + 1000 + k)
        img = noise.apply(clean, rng)
        extra = _image_notes(k, img, clean, err, noise, spp, notes)
        name = f"images/medium_{k:02d}_{v:g}ml.tiff"
        write_float_tiff(out / name, np.minimum(img, SATURATION).astype(np.float32))
        entries.append({"path": name, "exposure_s": 1.0, "concentration": float(c),
                        "saturation": SATURATION})
        truth_imgs.append({"path": name, "ml": v, "tank_ml": tank_ml, "concentration": c,
                           "tank": tank_medium.as_dict(), **extra})
    notes += [NOISE_FREE_NOTE] if noise.is_zero() else []
    clear = _render(spec, None, _with_water(medium.scaled(0.0), water), bright, "single", spp,
                    seed)[0]
    write_float_tiff(out / "images/clear_water.tiff",
                     np.minimum(noise.apply(clear, rng), SATURATION).astype(np.float32))
    raw["images"] = entries
    raw["calibration"] = {"clear_water": {"path": "images/clear_water.tiff", "exposure_s": 1.0,
                                          "saturation": SATURATION}}
    raw["noise"] = {"gain": noise.gain, "read_var": noise.read_var}
    # what rendered the images (docs/spec.md, "synthetic"): a single-scattering render holds
    # no multiple scattering, which the single-scattering check then need not suspect
    raw["synthetic"] = {"model": model}
    return raw, {
        "medium": medium_name, "model": model, "seed": seed,
        "undiluted": medium.as_dict(), "images": truth_imgs,
        "brightness": dict(zip(CHANNELS, bright.tolist())),
        "brightness_meaning": "bulb radiance in the water" if light.type == "bulb"
        else "spot radiant intensity in the water (image units x mm^2)",
        "water_kappa_a": dict(zip(CHANNELS, water.tolist())),
        "noise": {"gain": noise.gain, "read_var": noise.read_var}, "notes": notes,
        "units": {"length": "mm", "kappa": "1/mm"},
    }
