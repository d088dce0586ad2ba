"""The same synthetic capture written as a float TIFF, a 3-frame 16-bit bracket with a dark
frame, and Bayer DNGs, each fitted (MAP only): issue 16, docs/spec.md "Camera formats compared".

Run: python docs/studies/camera_formats.py [SEED] [OUT_DIR]  (about 2 CPU-minutes per format)
"""
from __future__ import annotations

import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
import tifffile
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / 'tests'))
from conftest import geometry_dict
from test_raw import write_bayer_dng
from fitmedia.spec import parse_spec
from fitmedia.medium import medium_by_name
from fitmedia.forward.single import SingleScattering
from fitmedia.inference.fit import FitOptions
from fitmedia.pipeline import fit
from fitmedia.images import write_float_tiff

OUT = Path(sys.argv[2] if len(sys.argv) > 2 else 'camera_formats_out'); W, H = 64, 48; ML = 16.0; TANK = 23000.0
A, B = 2.0, 25.0   # DN per electron, read variance DN^2 (per stored sample)
rng = np.random.default_rng(int(sys.argv[1]) if len(sys.argv) > 1 else 7)
geo = geometry_dict(width=W, height=H)
spec = parse_spec(geo, require_images=False)
med = medium_by_name('Lowfat Milk')
c = ML / TANK
model = SingleScattering(spec, None, channels=("R", "G", "B"), supersample=2)
L = model.render(c * med.kappa_a, c * med.kappa_s, med.g, np.ones(3))      # image units
L0 = model.render(0 * med.kappa_a, 0 * med.kappa_s, med.g, np.ones(3))     # clear water

def shot(mean_dn):
    return A * rng.poisson(np.clip(mean_dn, 0, None) / A) + rng.normal(0, np.sqrt(B), mean_dn.shape)

def spec_with(name, img, clear, noise, extra=None):
    d = copy.deepcopy(geo); d['name'] = name
    d['images'] = [dict(img, concentration=c)]; d['calibration'] = {'clear_water': clear}
    d['noise'] = noise
    p = OUT / name / 'capture.yaml'; p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(yaml.safe_dump(d)); return p

specs = {}
# (a) float TIFF, one frame, K = 20000 DN/s per image unit, t = 1 s
K = 2.0e4
d = OUT / 'float'; d.mkdir(parents=True, exist_ok=True)
write_float_tiff(d / 'm.tiff', shot(K * L)); write_float_tiff(d / 'w.tiff', shot(K * L0))
specs['float'] = spec_with('float', {'path': 'm.tiff', 'exposure_s': 1.0},
                           {'path': 'w.tiff', 'exposure_s': 1.0}, {'gain': A, 'read_var': B})
# (b) 16-bit bracket 1, 0.25, 0.0625 s, K = 2e5 DN/s, pedestal 500, one shared dark
Kb, ped, ts = 2.0e5, 500.0, [1.0, 0.25, 0.0625]
d = OUT / 'bracket'; d.mkdir(parents=True, exist_ok=True)
def u16(x): return np.clip(np.round(x), 0, 65535).astype(np.uint16)
for tag, img in (('m', L), ('w', L0)):
    for k, t in enumerate(ts):
        tifffile.imwrite(d / f'{tag}{k}.tif', u16(ped + shot(Kb * t * img)), photometric='rgb')
tifffile.imwrite(d / 'dark.tif', u16(ped + rng.normal(0, np.sqrt(B), L.shape)), photometric='rgb')
br = lambda tag: {'path': [f'{tag}{k}.tif' for k in range(3)], 'exposure_s': ts,
                  'dark': 'dark.tif', 'response': 'linear'}
specs['bracket'] = spec_with('bracket', br('m'), br('w'), {'gain': A, 'read_var': B, 'exposure_s': 1.0})
# (c) Bayer DNG, each binned pixel's four sites see its radiance, K = 1.2e4, black 512
Kd, black = 1.2e4, 512
d = OUT / 'dng'; d.mkdir(parents=True, exist_ok=True)
for tag, img in (('m', L), ('w', L0)):
    site = np.empty((2 * H, 2 * W))
    for (i, j), ch in zip(((0, 0), (0, 1), (1, 0), (1, 1)), (0, 1, 1, 2)):
        site[i::2, j::2] = black + shot(Kd * img[..., ch])
    write_bayer_dng(d / f'{tag}.dng', np.clip(np.round(site), 0, 16383), black=(black,) * 4)
specs['dng'] = spec_with('dng', {'path': 'm.dng', 'exposure_s': 1.0},
                         {'path': 'w.dng', 'exposure_s': 1.0}, {'gain': A, 'read_var': B})
truth = {ch: dict(kappa_t=float(med.kappa_a[i] + med.kappa_s[i]), kappa_s=float(med.kappa_s[i]),
                  g=float(med.g[i])) for i, ch in enumerate('RGB')}
print('truth', json.dumps(truth))
for name, p in specs.items():
    t0 = time.time()
    res = fit(p, OUT / name / 'fit', FitOptions(mcmc=False, workers=1, progress=False), report=False)
    pars = res['parameters']; dg = res['diagnostics']['channels']
    row = {ch: {k: round(pars[k][ch]['map'], 4) for k in ('kappa_t', 'kappa_s', 'g')} for ch in 'RGB'}
    chi = {ch: round(dg[ch].get('chi2_per_pixel_map', dg[ch].get('chi2_per_pixel', float('nan'))), 3) for ch in 'RGB'}
    print(name, f'{time.time() - t0:.0f}s', json.dumps(row), 'chi2/px', chi, flush=True)
