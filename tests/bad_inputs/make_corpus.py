"""The bad-input corpus of issue 17: one case per class of bad input, generated into a folder
(nothing committed but this script).  Each case has its command line, the exit code it must
give and the words its message must contain; tests/test_bad_inputs.py runs every case through
the real entry point (``python -m fitmedia.cli``) in a subprocess.

    python tests/bad_inputs/make_corpus.py OUT          # write every case into OUT, list them
    python tests/bad_inputs/make_corpus.py OUT --run    # and run them: the table of docs/testing.md

Cases share one tiny synthetic capture (16 x 12 pixels, two dilutions of Espresso and the
clear water, noise in the spec) made once with :func:`make_base`.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

W, H = 16, 12


def geometry(width: int = W, height: int = H) -> dict:
    """The canonical tank and bulb seen by a width x height camera (fx scaled with width)."""
    fx = 375.0 * width / 200.0
    return {"fitmedia_spec": 1, "name": "corpus",
            "tank": {"inner_size": [300, 250, 300],
                     "front_wall": {"thickness": 6.0, "ior": 1.5}, "walls": "black"},
            "medium": {"ior": 1.33},
            "camera": {"size": [width, height], "fx": fx, "fy": fx, "cx": width / 2,
                       "cy": height / 2, "position": [0, 0, 900], "look_at": [0, 0, 0],
                       "up": [0, 1, 0]},
            "light": {"type": "bulb", "position": [40, 10, 30], "radius": 6}}


def make_base(root: Path) -> Path:
    """The shared capture ``root/base/capture.yaml`` (synthesised in-process, ~1 s)."""
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import parse_spec
    from fitmedia.synth import synthesize

    base = root / "base"
    if not (base / "capture.yaml").is_file():
        spec = parse_spec(geometry(), require_images=False)
        synthesize(spec, base, medium_by_name("Espresso"), [8.0, 32.0], seed=1,
                   medium_name="Espresso")
    return base / "capture.yaml"


@dataclass
class Case:
    """One bad input: ``build(case_dir, base_spec)`` writes its files; ``argv`` (after
    ``python -m fitmedia.cli``) may use {d} (the case's folder) and {base} (the base capture's
    folder); the run must exit with ``code`` and its stderr contain every one of ``words``.
    ``out_left`` is True where a failed run may still leave files in {d}/out (a known gap)."""

    name: str
    klass: str
    argv: list[str]
    code: int
    words: list[str]
    build: Callable[[Path, Path], None] | None = None
    timeout: float = 10.0
    out_left: bool = False
    env: dict = field(default_factory=dict)


def _text(name: str, text: str) -> Callable[[Path, Path], None]:
    def build(d: Path, base: Path) -> None:
        (d / name).write_text(text)
    return build


def _spec(mutate: Callable[[dict, Path, Path], None]) -> Callable[[Path, Path], None]:
    """Write d/spec.yaml: the base capture's spec, image paths absolute, then ``mutate``d."""
    def build(d: Path, base: Path) -> None:
        data = yaml.safe_load(base.read_text())
        for e in data["images"] + [data["calibration"]["clear_water"]]:
            e["path"] = str(base.parent / e["path"])
        mutate(data, d, base)
        (d / "spec.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return build


def _geometry_spec(mutate: Callable[[dict], None]) -> Callable[[Path, Path], None]:
    def build(d: Path, base: Path) -> None:
        g = geometry()
        mutate(g)
        (d / "geo.yaml").write_text(yaml.safe_dump(g, sort_keys=False))
    return build


def _image(index: int | str, transform: Callable[[np.ndarray], np.ndarray]):
    """Mutation: image ``index`` ('clear' for the clear water) replaced by a transformed copy."""
    def mutate(data: dict, d: Path, base: Path) -> None:
        import tifffile

        e = data["calibration"]["clear_water"] if index == "clear" else data["images"][index]
        with np.errstate(all="ignore"):
            img = transform(tifffile.imread(e["path"]).astype(np.float32))
        e["path"] = str(d / "image.tiff")
        tifffile.imwrite(e["path"], img.astype(np.float32), photometric="rgb")
    return mutate


def _copy_image(data: dict, d: Path, base: Path) -> None:
    shutil.copy(data["images"][0]["path"], d / "copy.tiff")
    data["images"][1]["path"] = str(d / "copy.tiff")


def _truncated(data: dict, d: Path, base: Path) -> None:
    (d / "broken.tiff").write_bytes(Path(data["images"][0]["path"]).read_bytes()[:300])
    data["images"][0]["path"] = str(d / "broken.tiff")


def _empty_checkpoint(d: Path, base: Path) -> None:
    (d / "out").mkdir()
    (d / "out" / "checkpoint_R.npz").write_bytes(b"")


def _write_dng(path: Path) -> bytes:
    """A valid 32 x 24 Bayer DNG (tests/test_raw.py's writer); returns its bytes."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from test_raw import write_bayer_dng

    write_bayer_dng(path, np.full((24, 32), 600, np.uint16))
    return path.read_bytes()


def _raw(kind: str):
    """Mutation: images[0] replaced by an unreadable ('garbage') or truncated RAW file."""
    def mutate(data: dict, d: Path, base: Path) -> None:
        body = b"not a raw file " * 40 if kind == "garbage" else _write_dng(d / "full.dng")[:1200]
        (d / "x.dng").write_bytes(body)
        data["images"][0]["path"] = str(d / "x.dng")
    return mutate


def _tiff(name: str, arr: np.ndarray) -> str:
    import tifffile

    tifffile.imwrite(name, arr, photometric="rgb" if arr.ndim == 3 else None)
    return name


def _other_size(data: dict, d: Path, base: Path) -> None:
    import tifffile

    img = tifffile.imread(data["images"][1]["path"])
    data["images"][1]["path"] = _tiff(str(d / "big.tiff"), np.pad(img, ((0, 2), (0, 2), (0, 0))))


def _black(data: dict, d: Path, base: Path) -> None:
    """images[0]: read noise only (the spec's read_var), no glow."""
    sd = np.sqrt(data["noise"]["read_var"])
    noise = np.random.default_rng(3).normal(0.0, sd, (H, W, 3)).astype(np.float32)
    data["images"][0]["path"] = _tiff(str(d / "black.tiff"), noise)


def _all_saturated(data: dict, d: Path, base: Path) -> None:
    data["images"][0].update(path=_tiff(str(d / "sat.tiff"), np.full((H, W, 3), 65535, np.uint16)),
                             response="linear")
    data["images"][0].pop("saturation", None)


def _glow_saturated_bracket(data: dict, d: Path, base: Path) -> None:
    """images[0]: a 2-frame float bracket whose brightest 30 % (the glow) is above the entry's
    saturation in both frames and whose rest is read noise."""
    import tifffile

    img = tifffile.imread(data["images"][0]["path"])
    glow = img.max(axis=2, keepdims=True) > np.percentile(img.max(axis=2), 70)
    sd, rng, paths = np.sqrt(data["noise"]["read_var"]), np.random.default_rng(4), []
    for k, t in enumerate((1.0, 0.5)):
        frame = np.where(glow, 10.0, rng.normal(0.0, sd * t, img.shape)).astype(np.float32)
        paths.append(_tiff(str(d / f"b{k}.tiff"), frame))
    data["images"][0].update(path=paths, exposure_s=[1.0, 0.5], saturation=5.0)
    data["noise"]["exposure_s"] = 1.0


def _wrong_size(key: str):
    def mutate(data: dict, d: Path, base: Path) -> None:
        arr = np.ones((5, 7), np.uint8) if key == "mask" else np.ones((5, 7, 3), np.float32)
        data["images"][0][key] = _tiff(str(d / f"{key}.tiff"), arr)
    return mutate


def _curve_rows(data: dict, d: Path, base: Path) -> None:
    """images[0]: a 16-bit file with a 256-row (8-bit) response curve."""
    np.savetxt(d / "curve.csv", np.linspace(0.0, 1.0, 256)[:, None] ** 2.2 * np.ones(3),
               delimiter=",")
    data["images"][0].update(path=_tiff(str(d / "a16.tiff"), np.full((H, W, 3), 900, np.uint16)),
                             response={"curve": "curve.csv"})
    data["images"][0].pop("saturation", None)


BOMB = "\n".join([f"l0: &l0 [{', '.join(['lol'] * 9)}]"]
                 + [f"l{k}: &l{k} [{', '.join([f'*l{k - 1}'] * 9)}]" for k in range(1, 10)])
FIT = ["fit", "{d}/spec.yaml", "--out", "{d}/out", "--no-mcmc", "--quiet"]
SYNTH = ["--medium", "Espresso", "--ml", "8", "--out", "{d}/out"]


def cases() -> list[Case]:
    """Every case of the corpus (their classes: docs/testing.md, "Bad-input corpus")."""
    yaml_synth = ["synth", "{d}/geo.yaml"] + SYNTH
    return [
        # -- the spec's YAML
        Case("malformed_yaml", "malformed YAML", yaml_synth, 2, ["not valid YAML", "line"],
             _text("geo.yaml", "tank: [1, 2\n  camera: {")),
        Case("duplicate_key", "duplicate YAML keys", yaml_synth, 2,
             ["duplicate key 'fx'", "lines"],
             _text("geo.yaml", yaml.safe_dump(geometry(), sort_keys=False).replace(
                 "  fx: 30.0\n", "  fx: 30.0\n  fx: 60.0\n"))),
        Case("alias_bomb", "YAML alias bomb", yaml_synth, 2, ["expands to more than", "aliases"],
             _text("geo.yaml", BOMB)),
        Case("deep_nesting", "deep YAML nesting", yaml_synth, 2, ["nested more than 32"],
             _text("geo.yaml", "x: " + "[" * 5000 + "]" * 5000 + "\n")),
        Case("int_key", "non-string YAML key", yaml_synth, 2, ["2024", "not text"],
             _text("geo.yaml", "2024: x\n")),
        Case("unsafe_tag", "unsafe YAML tag", yaml_synth, 2, ["not valid YAML", "python/object"],
             _text("geo.yaml", "fitmedia_spec: !!python/object/apply:os.system [echo hi]\n")),
        Case("not_a_mapping", "malformed YAML", yaml_synth, 2, ["must be a YAML mapping"],
             _text("geo.yaml", "- 1\n- 2\n")),
        # -- the spec's fields
        Case("unknown_key_typo", "unknown key (typo)", yaml_synth, 2,
             ["tank", "did you mean 'front_wall'"],
             _geometry_spec(lambda g: g["tank"].update(front_wal=g["tank"].pop("front_wall")))),
        Case("nan_in_spec", "NaN in the spec", yaml_synth, 2, ["light.radius", "finite"],
             _geometry_spec(lambda g: g["light"].update(radius=float("nan")))),
        Case("negative_size", "negative size", yaml_synth, 2, ["tank.inner_size[1]", "-250"],
             _geometry_spec(lambda g: g["tank"].update(inner_size=[300, -250, 300]))),
        Case("negative_camera_size", "negative size", yaml_synth, 2, ["camera.size"],
             _geometry_spec(lambda g: g["camera"].update(size=[-16, 12]))),
        Case("missing_spec", "missing file", ["synth", "{d}/nope.yaml"] + SYNTH, 2,
             ["nope.yaml", "file not found"]),
        Case("missing_image", "missing file", FIT, 2, ["images[0].path", "file not found"],
             _spec(lambda d, *_: d["images"][0].update(path="/nonexistent/x.tiff"))),
        Case("path_traversal", "path traversal in image paths", FIT, 2,
             ["etc/passwd", "unknown image type"],
             _spec(lambda d, *_: d["images"][0].update(path="../../../../../../../etc/passwd"))),
        # -- images
        Case("truncated_image", "broken image file", FIT, 2, ["broken.tiff"],
             _spec(_truncated)),
        Case("nan_in_image", "NaN in an image", FIT, 2, ["image.tiff", "NaN"],
             _spec(_image(0, lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7,
                                                np.nan, a)))),
        Case("saturated_image", "saturated image", FIT, 2, ["saturated"],
             _spec(lambda d, *_: d["images"][0].update(saturation=1e-12))),
        Case("all_zero_image", "all-zero image", FIT, 2, ["image.tiff", "0 at every usable"],
             _spec(_image(0, np.zeros_like))),
        Case("negative_image", "negative pixels", FIT, 2, ["image.tiff", "below", "read-noise"],
             _spec(_image(0, lambda a: -np.abs(a) - 1e-3))),
        Case("same_file_twice", "same image twice", FIT, 2, ["images[1]", "images[0]"],
             _spec(lambda d, *_: d["images"][1].update(path=d["images"][0]["path"]))),
        Case("identical_copy", "same image twice", FIT, 2, ["copy.tiff", "same file content"],
             _spec(_copy_image)),
        Case("medium_is_clear_water", "medium image = clear water", FIT, 2,
             ["calibration.clear_water", "images[0]"],
             _spec(lambda d, *_: d["images"][0].update(path=d["calibration"]["clear_water"]
                                                       ["path"]))),
        Case("tiny_exposure", "exposure over/underflow", FIT, 2, ["exposure_s", "1e+100"],
             _spec(lambda d, *_: d["images"][0].update(exposure_s=1e-300))),
        Case("huge_exposure", "exposure over/underflow", FIT, 2, ["exposure_s", "1e-100"],
             _spec(lambda d, *_: d["images"][0].update(exposure_s=1e300))),
        Case("raw_unreadable", "broken RAW file", FIT, 2,
             ["x.dng", "not a readable camera RAW file"], _spec(_raw("garbage"))),
        Case("raw_truncated", "broken RAW file", FIT, 2,
             ["x.dng", "not a readable camera RAW file"], _spec(_raw("truncated"))),
        Case("images_of_other_sizes", "image of the wrong size", FIT, 2,
             ["big.tiff", "18x14", "expected 16x12"], _spec(_other_size)),
        Case("mask_wrong_size", "image of the wrong size", FIT, 2,
             ["mask.tiff", "7x5", "expected 16x12"], _spec(_wrong_size("mask"))),
        Case("flat_wrong_size", "image of the wrong size", FIT, 2,
             ["flat.tiff", "7x5", "expected 16x12"], _spec(_wrong_size("flat"))),
        Case("binning_wrong_size", "image of the wrong size", FIT, 2,
             ["expected 48x36", "times binning 3"],
             _spec(lambda d, *_: d["images"][0].update(binning=3))),
        Case("curve_rows_for_16_bit", "response curve", FIT, 2,
             ["curve.csv", "256 rows", "16-bit image needs 65536 rows"], _spec(_curve_rows)),
        Case("black_image", "black or saturated image", FIT, 2,
             ["black.tiff", "a black image"], _spec(_black)),
        Case("wholly_saturated", "black or saturated image", FIT, 2,
             ["sat.tiff", "saturated in 100%"], _spec(_all_saturated)),
        Case("bracket_glow_saturated", "black or saturated image", FIT, 2,
             ["b0.tiff + ", "no unsaturated sample of the glow"], _spec(_glow_saturated_bracket)),
        Case("bulb_not_seen", "camera cannot see the bulb", FIT, 2,
             ["cannot see the bulb", "outside the wall's opening"],
             _spec(lambda d, *_: d["camera"].update(position=[600, 0, 300],
                                                    look_at=[600, 0, 0]))),
        # -- memory
        Case("huge_synth", "huge spec (memory)", ["synth", "{d}/geo.yaml"] + SYNTH, 2,
             ["GiB of memory", "FITMEDIA_MAX_MEMORY_GB"],
             _geometry_spec(lambda g: g["camera"].update(size=[40000, 25000]))),
        Case("huge_fit", "huge spec (memory)", FIT, 2, ["GiB of memory", "limit"],
             _spec(lambda d, *_: d["camera"].update(size=[40000, 25000]))),
        # -- command line and output folders
        Case("unknown_medium", "bad CLI argument",
             ["synth", "{d}/geo.yaml", "--medium", "Lowfat Mlik", "--ml", "8", "--out",
              "{d}/out"], 2, ["--medium", "Lowfat Milk"], _geometry_spec(lambda g: None)),
        Case("negative_ml", "bad CLI argument",
             ["synth", "{d}/geo.yaml", "--medium", "Espresso", "--ml", "-3", "--out", "{d}/out"],
             2, ["--ml"], _geometry_spec(lambda g: None)),
        Case("workers_zero", "bad CLI argument", FIT + ["--workers", "0"], 2,
             ["--workers", "positive integer"], _spec(lambda *_: None)),
        Case("n_tau_negative", "bad CLI argument", FIT + ["--n-tau", "-1"], 2,
             ["--n-tau", "positive number"], _spec(lambda *_: None)),
        Case("n_tau_zero", "bad CLI argument", FIT + ["--n-tau", "0"], 2,
             ["--n-tau", "positive number"], _spec(lambda *_: None)),
        Case("seed_negative", "bad CLI argument", ["synth", "{d}/geo.yaml"] + SYNTH
             + ["--seed", "-1"], 2, ["--seed", "integer >= 0"], _geometry_spec(lambda g: None)),
        Case("out_empty", "output folder", ["synth", "{d}/geo.yaml", "--medium", "Espresso",
                                            "--ml", "8", "--out", ""], 2,
             ["--out", "expected a folder"], _geometry_spec(lambda g: None)),
        Case("out_is_a_file", "output folder", FIT[:3] + ["{d}/afile", "--no-mcmc"], 2,
             ["afile", "not a folder"], _spec(lambda d, c, b: (c / "afile").write_text("x"))),
        Case("synth_out_is_a_file", "output folder",
             ["synth", "{d}/geo.yaml", "--medium", "Espresso", "--ml", "8", "--out",
              "{d}/afile"], 2, ["afile", "not a folder"],
             lambda d, b: (_geometry_spec(lambda g: None)(d, b), (d / "afile").write_text("x"))),
        Case("empty_checkpoint", "unusable checkpoint with --resume",  # refused before the MAP
             FIT[:4] + ["--quiet", "--resume"], 2,
             ["checkpoint_R.npz"],
             lambda d, b: (_spec(lambda *_: None)(d, b), _empty_checkpoint(d, b)),
             out_left=True),  # the bad checkpoint itself stays (nothing removed, by design)
        Case("report_missing_folder", "report input", ["report", "{d}/nothing"], 2,
             ["results.json", "file not found"]),
        Case("report_missing_row", "report input", ["report", "{d}"], 2,
             ["parameters.g.G is missing"], _text("results.json", (
                 '{"channels": ["R", "G", "B"], "parameters": {'
                 + ", ".join(f'"{q}": {{' + ", ".join(f'"{c}": {{"map": 0.5}}' for c in
                                                      ("RB" if q == "g" else "RGB")) + "}"
                             for q in ("kappa_a", "kappa_s", "kappa_t", "albedo", "g"))
                 + "}}"))),
        Case("bad_memory_env", "bad CLI argument", ["synth", "{d}/geo.yaml"] + SYNTH, 2,
             ["FITMEDIA_MAX_MEMORY_GB", "'lots'"], _geometry_spec(lambda g: None),
             env={"FITMEDIA_MAX_MEMORY_GB": "lots"}),
    ]


def build_case(case: Case, root: Path, base: Path) -> Path:
    """Write ``case``'s files into a fresh ``root/<name>``; returns that folder."""
    d = root / case.name
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    if case.build is not None:
        case.build(d, base)
    return d


def run_case(case: Case, d: Path, base: Path) -> tuple[subprocess.CompletedProcess, float]:
    """Run ``case`` (its files in ``d``) through ``python -m fitmedia.cli``; (result, wall s)."""
    import os

    argv = [a.replace("{d}", str(d)).replace("{base}", str(base.parent)) for a in case.argv]
    env = {**os.environ, **case.env}
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "fitmedia.cli", *argv], capture_output=True,
                         text=True, timeout=case.timeout, env=env, cwd=d)
    return res, time.perf_counter() - t0


def problems(case: Case, res: subprocess.CompletedProcess, d: Path) -> list[str]:
    """What is wrong with a run of ``case``: exit code, missing words in the message (the last
    line of stderr; the only one, unless argparse printed its usage above it), a traceback or
    a warning (numpy's overflow warnings), files left in {d}/out (unless ``case.out_left``)."""
    out = []
    if res.returncode != case.code:
        out.append(f"exit {res.returncode}, expected {case.code}")
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    message = lines[-1] if lines else ""
    out += [f"no {w!r} in the message" for w in case.words if w not in message]
    if len(lines) > 1 and not res.stderr.startswith("usage:"):
        out.append(f"{len(lines)} lines on stderr, expected one")
    if "Traceback" in res.stderr or "Warning" in res.stderr:
        out.append("a traceback or a warning")
    left = d / "out"
    if not case.out_left and left.exists() and any(left.iterdir()):
        out.append(f"files left in {left}: {sorted(p.name for p in left.iterdir())}")
    return out


def main(argv: list[str]) -> int:
    root = Path(argv[0]).resolve()
    root.mkdir(parents=True, exist_ok=True)
    base = make_base(root)
    rows, n_bad = [], 0
    for case in cases():
        d = build_case(case, root, base)
        if "--run" not in argv:
            print(f"{case.name:24s} {case.klass:34s} exit {case.code}  {' '.join(case.argv)}")
            continue
        try:
            res, wall = run_case(case, d, base)
            bad = problems(case, res, d)
        except subprocess.TimeoutExpired:
            bad, wall = [f"no answer in {case.timeout:g} s (a hang)"], case.timeout
        n_bad += bool(bad)
        rows.append((case.klass, not bad))
        print(f"{'PASS' if not bad else 'FAIL'} {case.name:24s} {wall:5.1f} s  {'; '.join(bad)}")
    if rows:
        classes = sorted({k for k, _ in rows})
        print(f"\n{len(rows)} cases in {len(classes)} classes, {len(rows) - n_bad} pass")
        for k in classes:
            sel = [ok for kk, ok in rows if kk == k]
            print(f"| {k} | {len(sel)} | {sum(sel)} |")
    return 1 if n_bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
