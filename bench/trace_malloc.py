"""What keeping freed memory (fitmedia.util.keep_freed_memory) does to the tracer's cost.

One multiple-scattering trace (fitmedia.forward.multiple.MultipleScattering.orders, 256
paths per sample pixel, the full model's grid for capture_specs/bulb_64x48.yaml: 48 x 64
sample pixels), Espresso 8 ml in 23 l, channel G, traced ``REPEATS`` times after one warm-up
in two fresh processes: glibc's default malloc (the reference) and with the freed memory
kept.  Printed: wall, user and system seconds per trace and peak RSS of each process, and
the ratios kept / default, all measured in this run.  Run it on an idle machine: the
system time is page faults, which another process's load changes.

Usage:  python bench/trace_malloc.py [repeats]     (default 4)
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, resource, sys, time
from fitmedia.forward.multiple import MultipleScattering
from fitmedia.inference.full import trace_bin
from fitmedia.medium import medium_by_name
from fitmedia.spec import load_spec
import fitmedia.util as util

if sys.argv[2] == "default":  # the tracer tunes malloc when it is built: not here
    util._MALLOC_TUNED = True
spec = load_spec(sys.argv[1], require_images=False)
ms = MultipleScattering(spec, None, channels=("G",), bin=trace_bin(spec.camera))
m = medium_by_name("Espresso").scaled(8 / 23000)
kt = float(m.kappa_a[1] + m.kappa_s[1])
ms.orders(kt, float(m.g[1]), seed=0)
repeats = int(sys.argv[3])
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
for s in range(repeats):
    ms.orders(kt, float(m.g[1]), seed=s + 1)
r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
print(json.dumps({"wall": (t1 - t0) / repeats, "user": (r1.ru_utime - r0.ru_utime) / repeats,
                  "sys": (r1.ru_stime - r0.ru_stime) / repeats,
                  "rss_mb": r1.ru_maxrss / 1024, "grid": list(ms.low_shape)}))
"""


def run(mode: str, repeats: int) -> dict:
    spec = ROOT / "capture_specs" / "bulb_64x48.yaml"
    out = subprocess.run([sys.executable, "-c", CHILD, str(spec), mode, str(repeats)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(repeats: int) -> None:
    ref, kept = run("default", repeats), run("kept", repeats)
    print(f"one trace, grid {ref['grid'][0]} x {ref['grid'][1]} sample pixels, 256 paths, "
          f"{repeats} repeats")
    print(f"{'':>8} {'wall s':>8} {'user s':>8} {'sys s':>8} {'peak RSS MB':>12}")
    for name, r in (("default", ref), ("kept", kept)):
        print(f"{name:>8} {r['wall']:8.3f} {r['user']:8.3f} {r['sys']:8.3f} {r['rss_mb']:12.0f}")
    print(f"ratio kept / default: wall {kept['wall'] / ref['wall']:.2f}, "
          f"CPU {(kept['user'] + kept['sys']) / (ref['user'] + ref['sys']):.2f}, "
          f"peak RSS {kept['rss_mb'] / ref['rss_mb']:.2f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 4)
