"""The light the analytic single-scattering model leaves out, and the full-transport model.

``MultipleScattering`` estimates every path that ``SingleScattering`` does not render:
scattering orders >= 2, and order 1 lit through one reflection at the front wall
(docs/multiple_scattering.md): orders 1-2 with the camera paths of ``ms_paths``, and a
bulb's orders >= 3 with the photons of ``ms_light`` (a spot's with the camera paths).  It
traces at a reduced resolution (``bin`` x ``bin`` camera pixels per sample
pixel) and interpolates to the camera's pixels; the term is smooth.  Each render
returns the image and its per-pixel Monte Carlo standard error (from
independent batches of paths).  The albedo enters as albedo^order, so one trace
per (kappa_t, g) serves every albedo (``orders``).

``FullTransport`` is a ForwardModel: the analytic single scattering plus the
term from a local model refreshed around a point (``refresh``): per-order
images there and their finite differences in log kappa_t and atanh g, with the
same random numbers.  Between refreshes a render costs a few matrix products.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage, sparse

from ..errors import InputError
from ..geometry import pixel_grid, trace_to_water
from ..spec import Camera, Spec
from .base import check_render_args
from .ms_light import LIGHT_FROM_ORDER, LightTracer
from .ms_paths import PathTracer
from .ms_table import TermTable
from .single import SingleScattering

DEFAULT_BIN = 4
DEFAULT_PATHS = 256  # paths per sample pixel and channel
DEFAULT_BATCHES = 16
DEFAULT_SMOOTH = 0.0  # Gaussian sigma (sample pixels); 1.0 lowers the noise 3x and the glow sum 0.8 %


def _binned_camera(cam: Camera, b: int) -> Camera:
    """The camera with b x b pixels merged (same pinhole: the focal lengths and principal
    point scale by 1/b; a last partial bin extends past the image)."""
    return dataclasses.replace(cam, width=-(-cam.width // b), height=-(-cam.height // b),
                               fx=cam.fx / b, fy=cam.fy / b, cx=cam.cx / b, cy=cam.cy / b)


#: iterations of back-projection in the term's upsampling (``_sharpened``): 0 is plain
#: bilinear interpolation, whose smoothing of the glow's peak at bin 2 made the term 9 % low
#: next to the bulb and moved kappa_t and g (docs/multiple_scattering.md, "Upsampling")
BACKPROJECT = 2


def _block_mean(low: tuple[int, int], cam: Camera, b: int, cover: np.ndarray) -> sparse.csr_matrix:
    """(h*w, H*W): each sample pixel's mean over its b x b camera pixels, per unit water area
    (each camera pixel weighted by the fraction ``cover`` of it that sees the water), which is
    what a sample pixel's traced value estimates; 0 for a sample pixel that sees no water."""
    h, w = low
    yy, xx = np.meshgrid(np.arange(cam.height), np.arange(cam.width), indexing="ij")
    blk = ((yy // b) * w + xx // b).ravel()
    tot = np.bincount(blk, weights=cover, minlength=h * w)
    wts = np.divide(cover, tot[blk], out=np.zeros_like(cover), where=tot[blk] > 0)
    return sparse.csr_matrix((wts, (blk, np.arange(cam.height * cam.width))),
                             shape=(h * w, cam.height * cam.width))


def _only_water(up: sparse.csr_matrix, water: np.ndarray) -> sparse.csr_matrix:
    """The interpolation ``up`` from the sample pixels that see water (``water``) alone, each
    row's weights renormalised to sum 1 (a sample pixel that sees none holds 0, not the
    field's value: interpolating from it would pull the edge of the water towards 0)."""
    kept = up @ sparse.diags(water.astype(float))
    tot = np.asarray(kept.sum(axis=1)).ravel()
    return (sparse.diags(np.divide(1.0, tot, out=np.zeros_like(tot), where=tot > 0)) @ kept).tocsr()


def _sharpening(up: sparse.csr_matrix, block: sparse.csr_matrix, n: int) -> sparse.csr_matrix:
    """The sample-pixel operator T (h*w, h*w) with ``up @ T`` the upsampler ``up`` (camera <-
    sample pixels, per unit water area) after ``n`` steps of back-projection: f_0 = up low,
    f_(k+1) = f_k + up (low - block f_k), so that the camera image's block means (``block``)
    approach the sample pixels' values instead of a smoothed copy of them.  With f_k = up T_k
    low: T_0 = I and T_(k+1) = I + T_k - (block up) T_k.  Kept apart from ``up`` so that a
    product of two upsampled images (``MultipleScattering.upsampled_products``) needs ``up``'s
    few weights per camera pixel (4), not the sharpened matrix's (22 at bin 4)."""
    eye = sparse.identity(up.shape[1], format="csr")
    back = (block @ up).tocsr()
    out = eye
    for _ in range(n):
        out = (eye + out - back @ out).tocsr()
    return out


def _sharpened(up: sparse.csr_matrix, block: sparse.csr_matrix, n: int) -> sparse.csr_matrix:
    """The upsampler ``up`` with ``n`` steps of back-projection (``_sharpening``) as one matrix
    (H*W, h*w): sum_j (I - up block)^j up = up T."""
    return (up @ _sharpening(up, block, n)).tocsr()


def _pair_products(up: sparse.csr_matrix) -> tuple[sparse.csr_matrix, np.ndarray, np.ndarray]:
    """For ``sum_n (up @ y_n) * (up @ z_n)`` without forming either image: the ordered pairs
    (i, j) of sample pixels that share a camera pixel in ``up`` (arrays ``i``, ``j``) and the
    matrix ``w`` (H*W, pairs) of their weights up_pi up_pj, so that the sum is
    ``w @ sum_n y_n[i] z_n[j]``."""
    up = up.tocsr(copy=True)
    up.eliminate_zeros()  # bilinear weights of 0 (all but one at bin 1) pair nothing
    r = np.diff(up.indptr)
    most = int(r.max(initial=0))
    rows, ii, jj, vals = [], [], [], []
    for a in range(most):
        for b in range(most):
            sel = np.flatnonzero((r > a) & (r > b))
            pa, pb = up.indptr[sel] + a, up.indptr[sel] + b
            rows.append(sel)
            ii.append(up.indices[pa])
            jj.append(up.indices[pb])
            vals.append(up.data[pa] * up.data[pb])
    n = up.shape[1]
    key = np.concatenate(ii).astype(np.int64) * n + np.concatenate(jj)
    pairs, col = np.unique(key, return_inverse=True)
    w = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), col)),
                          shape=(up.shape[0], len(pairs)))
    return w, pairs // n, pairs % n


def _upsampler(low: tuple[int, int], cam: Camera, b: int) -> sparse.csr_matrix:
    """Bilinear interpolation (H*W, h*w) from the sample pixels' centres to the camera's."""
    h, w = low
    y = (np.arange(cam.height) + 0.5) / b - 0.5
    x = (np.arange(cam.width) + 0.5) / b - 0.5
    rows, cols, vals = [], [], []
    yy, xx = np.meshgrid(np.clip(y, 0, h - 1), np.clip(x, 0, w - 1), indexing="ij")
    i0, j0 = np.minimum(np.floor(yy).astype(int), h - 2 if h > 1 else 0), \
        np.minimum(np.floor(xx).astype(int), w - 2 if w > 1 else 0)
    fy, fx = yy - i0, xx - j0
    idx = np.arange(cam.height * cam.width).reshape(cam.height, cam.width)
    for di, wy in ((0, 1 - fy), (1, fy)):
        for dj, wx in ((0, 1 - fx), (1, fx)):
            rows.append(idx.ravel())
            cols.append((np.minimum(i0 + di, h - 1) * w + np.minimum(j0 + dj, w - 1)).ravel())
            vals.append((wy * wx).ravel())
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(cam.height * cam.width, h * w))


#: a local model's per-order arrays, each (batches, K, h*w): the images at the refresh point
#: and their finite differences in log kappa_t and atanh g
LOCAL_PARTS = ("batches", "d_kt", "d_g")


def _order_major(loc: dict) -> np.ndarray:
    """A local model's ``LOCAL_PARTS`` as one C-contiguous array (K, 3, batches, h*w), built
    once (filled in place: one copy of the arrays, not two at a time) and kept in ``loc``: the
    sum over the orders is then one matrix-vector product over contiguous memory, where
    ``tensordot`` over the middle axis copied every array on every call (65 % of a sampler's
    time at 100 x 75 px, bin 1; bench/ms_local_render.py)."""
    if "order_major" not in loc:
        b, k, p = loc[LOCAL_PARTS[0]].shape
        out = np.empty((k, len(LOCAL_PARTS), b, p))
        for i, name in enumerate(LOCAL_PARTS):
            out[:, i] = loc[name].transpose(1, 0, 2)
        loc["order_major"] = out
    return loc["order_major"]


def _with_order_major(loc: dict) -> dict:
    """``loc`` with its order-major array built and its ``LOCAL_PARTS`` replaced by views of it
    (one copy of the local model in memory, not two)."""
    stack = _order_major(loc)
    for i, name in enumerate(LOCAL_PARTS):
        loc[name] = stack[:, i].transpose(1, 0, 2)
    return loc


class MultipleScattering:
    """Monte Carlo estimate of what ``SingleScattering`` leaves out (see module docstring).

    Parameters
    ----------
    spec : Spec
    image_index : int or None
        As for SingleScattering.
    channels : tuple of str, optional
    bin : int
        Camera pixels per sample pixel side.
    n_paths : int
        Paths per sample pixel and channel.
    batches : int
        Independent batches for the standard error.
    smooth : float
        Gaussian sigma (sample pixels) of an optional smoothing over the water (0: none; its
        bias is measured in docs/multiple_scattering.md).
    """

    def __init__(self, spec: Spec, image_index: int | None = 0, *,
                 channels: tuple[str, ...] | None = None, bin: int = DEFAULT_BIN,
                 n_paths: int = DEFAULT_PATHS, batches: int = DEFAULT_BATCHES,
                 smooth: float = DEFAULT_SMOOTH):
        use = image_index is not None and spec.images
        self.camera = spec.camera_for(image_index) if use else spec.camera
        self.light = spec.light_for(image_index) if use else spec.light
        if int(bin) < 1 or int(n_paths) < int(batches) or int(batches) < 2:
            raise InputError(f"bin {bin}, n_paths {n_paths}, batches {batches}: need bin >= 1, "
                             f"batches >= 2 and n_paths >= batches")
        if not smooth >= 0:
            raise InputError(f"smooth: got {smooth}, expected a sigma >= 0 (sample pixels)")
        self.spec, self.bin, self.smooth = spec, int(bin), float(smooth)
        self._image_index = image_index
        self.n_paths, self.batches = int(n_paths), int(batches)
        self.channels = tuple(channels or spec.channels)
        self.shape = (self.camera.height, self.camera.width)
        self.low_camera = _binned_camera(self.camera, self.bin)
        self.low_shape = (self.low_camera.height, self.low_camera.width)
        # its line integrals with 6 + 4 nodes: -0.02 % on the term against 8 + 8, 12 % faster
        single = SingleScattering(dataclasses.replace(spec, camera=self.low_camera, images=()), None,
                                  channels=self.channels[:1],
                                  nodes=6, nodes_upper=4)
        self.tracer = PathTracer(self.low_camera, spec.tank, spec.medium_ior, self.light, single)
        x, y = pixel_grid(self.low_camera, sub=4)
        rays = trace_to_water(self.low_camera, spec.tank, spec.medium_ior, np.ravel(x), np.ravel(y))
        self._low_cover = (rays.factor.reshape(x.shape) > 0).mean(axis=-1).ravel()
        # orders >= LIGHT_FROM_ORDER of a bulb from photons (ms_light: not heavy-tailed);
        # a spot's every order from the camera paths
        self.photons = None
        if self.light.type != "spot":
            x, y = pixel_grid(self.low_camera, sub=8)
            rays = trace_to_water(self.low_camera, spec.tank, spec.medium_ior, np.ravel(x),
                                  np.ravel(y))
            self.photons = LightTracer(self.tracer,
                                       (rays.factor.reshape(x.shape) > 0).mean(axis=-1).ravel())
        self._up = _upsampler(self.low_shape, self.camera, self.bin)  # bilinear: the errors'
        x, y = pixel_grid(self.camera, sub=2)  # fraction of each camera pixel that sees the water
        rays = trace_to_water(self.camera, spec.tank, spec.medium_ior, np.ravel(x), np.ravel(y))
        self._cover = (rays.factor.reshape(x.shape) > 0).mean(axis=-1).ravel()
        self.support = self._cover.reshape(self.shape) > 0
        # the values' upsampler: bilinear sharpened by back-projection, the product of the
        # bilinear weights and a sample-pixel operator (``_sharpening``); exactly bilinear at
        # bin 1, where camera and sample pixels coincide (no operator)
        self._up_base, self._sharpen = self._up, None
        if self.bin > 1:
            self._up_base = _only_water(self._up, self._low_cover > 0)
            self._sharpen = _sharpening(
                self._up_base, _block_mean(self.low_shape, self.camera, self.bin, self._cover),
                BACKPROJECT)
        self._up_mean = self._up if self._sharpen is None else \
            (self._up_base @ self._sharpen).tocsr()
        self._pairs: tuple | None = None  # _pair_products(self._up_base), built when first used

    def orders(self, kappa_t: float, g: float, *, seed: int = 0, rr_albedo: float = 1.0,
               max_order: int = 400) -> np.ndarray:
        """Per-batch, per-order mean radiance at the sample pixels for a unit bulb and albedo 1,
        shape (batches, K, h*w) with K - 1 the highest order reached (index 0 unused), each
        divided by the fraction of the sample pixel that sees the water (0 where none).
        A bulb's orders >= ``LIGHT_FROM_ORDER`` are the photons' (``ms_light``), the lower
        ones the camera paths'; a spot's are all the camera paths'."""
        return self.orders_at(kappa_t, g, (), seed=seed, rr_albedo=rr_albedo,
                              max_order=max_order)[0]

    def orders_at(self, kappa_t: float, g: float, variants: tuple[tuple[float, float], ...], *,
                  seed: int = 0, rr_albedo: float = 1.0, max_order: int = 400
                  ) -> list[np.ndarray]:
        """:meth:`orders` at (kappa_t, g) and at each (kappa_t, g) of ``variants``, with the
        same random numbers (one trace, reweighted to each point; a spot's camera paths: one
        trace per point), padded to one number of orders."""
        points = [(float(kappa_t), float(g))] + [(float(a), float(b)) for a, b in variants]
        if self.photons is None:  # a spot: every order from camera paths, one trace per point
            runs = [self._camera_orders(((kt, gg),), seed, rr_albedo, max_order)[0]
                    for kt, gg in points]
        else:  # a bulb's orders 1-2: one trace, reweighted to the other points (stop 38)
            runs = self._camera_orders(points, seed, rr_albedo,
                                       min(max_order, LIGHT_FROM_ORDER - 1))
            lights = self.photons.trace(points[0][0], points[0][1], self.n_paths * self.tracer.n_pix,
                                        int(seed), self.batches, max_order, rr_albedo,
                                        from_order=LIGHT_FROM_ORDER, variants=tuple(points[1:]))
            for r, lt in zip(runs, lights):
                lt[:, : r.shape[1]] += r[:, :LIGHT_FROM_ORDER]
            runs = lights
        last = max(max(np.flatnonzero(r.any(axis=(0, 2))).max(initial=1), 1) for r in runs)
        return [np.pad(r[:, : last + 1], ((0, 0), (0, max(0, last + 1 - r.shape[1])), (0, 0)))
                for r in runs]

    def _camera_orders(self, points, seed: int, rr_albedo: float, max_order: int
                       ) -> list[np.ndarray]:
        """The camera paths' per-batch, per-order means (orders up to ``max_order``) at each
        (kappa_t, g) of ``points``, from the first point's paths (``PathTracer.trace_at``)."""
        accs, entered = self.tracer.trace_at(points, self.n_paths, int(seed), self.batches,
                                             max_order, rr_albedo)
        with np.errstate(divide="ignore", invalid="ignore"):
            per_batch = np.where(entered > 0, entered / self.batches, np.inf)
        return [acc[:, : max_order + 1] / per_batch for acc in accs]

    def smoothed(self, per: np.ndarray) -> np.ndarray:
        """Gaussian smoothing (sigma ``smooth`` sample pixels) of each row of ``per`` (n, h*w),
        normalised over the sample pixels that see the water."""
        if self.smooth <= 0:
            return per
        sh = (self._low_cover > 0).astype(float).reshape(self.low_shape)
        ks = ndimage.gaussian_filter(sh, self.smooth, mode="constant")
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = np.where(ks > 0, sh / ks, 0.0)
        out = [ndimage.gaussian_filter(r.reshape(self.low_shape), self.smooth, mode="constant") * gain
               for r in per]
        return np.reshape(out, per.shape)

    def combine(self, orders: np.ndarray, albedo: float) -> tuple[np.ndarray, np.ndarray]:
        """Camera-resolution image (H*W,) and standard error of sum_k albedo^k orders_k."""
        pw = albedo ** np.arange(orders.shape[1])
        pw[0] = 0.0
        per = self.smoothed(np.tensordot(orders, pw, axes=([1], [0])))  # (batches, h*w)
        mean = per.mean(axis=0)
        err = per.std(axis=0, ddof=1) / math.sqrt(per.shape[0])
        return self.upsample(mean), self.upsample_err(err)

    def upsample(self, low: np.ndarray) -> np.ndarray:
        """Sample-pixel values (per unit water area) -> camera pixels (times the water cover):
        bilinear interpolation sharpened by ``BACKPROJECT`` steps of back-projection."""
        return (self._up_base @ self._sharpened_low(low)) * self._cover

    def _sharpened_low(self, low: np.ndarray) -> np.ndarray:
        """``low`` (sample pixels first) after the back-projection's sample-pixel operator
        (``_sharpening``); unchanged at bin 1, which has none."""
        return low if self._sharpen is None else self._sharpen @ low

    def upsample_rows(self, low: np.ndarray) -> np.ndarray:
        """:meth:`upsample` of each row of ``low`` (n, h*w): (n, H*W)."""
        return (self._up_mean @ low.T).T * self._cover

    def upsampled_products(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``sum(upsample_rows(a) * upsample_rows(b), axis=0)`` for ``a``, ``b`` (n, h*w), the
        same to rounding without forming either (n, H*W) image: the sharpening on the sample
        pixels, then the sums over n of each pair of sample pixels that share a camera pixel,
        weighted (``_pair_products``).  The likelihood's excess variance calls it at every
        posterior evaluation (``FullTransport.ms_part``); at 200 x 150 px, bin 4, one
        ``render_with_variance`` took 10.1 ms with it against 20.1 ms with the images formed
        (bench/ms_local_render.py --size 200 150)."""
        if self._pairs is None:
            self._pairs = _pair_products(self._up_base)
        w, i, j = self._pairs
        y, z = self._sharpened_low(a.T), self._sharpened_low(b.T)  # (h*w, n)
        return (w @ np.einsum("pn,pn->p", y[i], z[j])) * self._cover ** 2

    def upsample_err(self, low: np.ndarray) -> np.ndarray:
        """A standard error per sample pixel -> camera pixels, interpolated bilinearly (times
        the water cover; the likelihood's weights: inference/likelihood.py, refresh_models)."""
        return (self._up @ low) * self._cover

    def share(self, kappa_a, kappa_s, g, *, seed: int = 0,
              single: SingleScattering | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Share of multiple scattering in the glow per channel, MS / (analytic + MS) summed
        over the glow (pixels off the bulb whose analytic order 1 is above 1e-3 of its
        brightest), and its standard error from the batches; NaN where kappa_s = 0.

        ``single``: the analytic model of the same image and channels (built if None).
        """
        share, err, _, _ = self.share_and_render(kappa_a, kappa_s, g, 1.0, seed=seed,
                                                 single=single)
        return share, err

    def share_and_render(self, kappa_a, kappa_s, g, brightness, *, seed: int = 0,
                         single: SingleScattering | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`share` and :meth:`render` from one trace: share, its standard error (per
        channel), the term's image and its standard error ((H, W, C))."""
        c = len(self.channels)
        ka, ks, gg, br = check_render_args(c, kappa_a, kappa_s, g, brightness)
        order1 = self._order1(ka, ks, gg, single)
        share, err = np.full(c, np.nan), np.full(c, np.nan)
        img, img_err = np.zeros((*self.shape, c)), np.zeros((*self.shape, c))
        for k in range(c):
            if ks[k] <= 0:
                continue
            kt, a = ka[k] + ks[k], ks[k] / (ka[k] + ks[k])
            orders = self.orders(kt, gg[k], seed=seed, rr_albedo=a)
            share[k], err[k] = self._share_of(orders, a, *order1[k])
            m, e = self.combine(orders, a)
            img[..., k], img_err[..., k] = (m * br[k]).reshape(self.shape), \
                (e * abs(br[k])).reshape(self.shape)
        return share, err, img, img_err

    def _order1(self, ka, ks, gg, single: SingleScattering | None
                ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per channel: the analytic order 1 (H*W,) for a unit bulb and the glow's pixels (off
        the bulb, order 1 above 1e-3 of its brightest), for :meth:`_share_of`."""
        c = len(self.channels)
        single = single or SingleScattering(self.spec, self._image_index, channels=self.channels)
        one = single.render(ka, ks, gg, np.ones(c))
        direct = single.render(ka + ks, np.zeros(c), gg, np.ones(c))
        out = []
        for k in range(c):
            order1 = (one[..., k] - direct[..., k]).ravel()
            off = direct[..., k].ravel() <= 0
            out.append((order1, off & (order1 > 1e-3 * order1[off].max(initial=0.0))))
        return out

    def _share_of(self, orders: np.ndarray, albedo: float, order1: np.ndarray,
                  glow: np.ndarray) -> tuple[float, float]:
        """The term's share of the glow from one channel's trace ``orders``, and its standard
        error from the batches."""
        pw = albedo ** np.arange(orders.shape[1])
        pw[0] = 0.0
        sums = np.array([self.upsample(r)[glow].sum()
                         for r in self.smoothed(np.tensordot(orders, pw, axes=([1], [0])))])
        one = order1[glow].sum()
        if not sums.mean() + one > 0:  # no glow at all (kappa_s ~ 0): no term in it either
            return 0.0, 0.0
        per = np.divide(sums, sums + one, out=np.zeros_like(sums), where=sums + one > 0)
        return float(sums.mean() / (sums.mean() + one)), float(per.std(ddof=1) / math.sqrt(len(per)))

    def render(self, kappa_a, kappa_s, g, brightness, *, seed: int = 0
               ) -> tuple[np.ndarray, np.ndarray]:
        """The term's image and its standard error, both (H, W, C), units of ForwardModel."""
        c = len(self.channels)
        ka, ks, gg, br = check_render_args(c, kappa_a, kappa_s, g, brightness)
        img, err = np.zeros((*self.shape, c)), np.zeros((*self.shape, c))
        for k in range(c):
            kt = ka[k] + ks[k]
            if ks[k] <= 0:
                continue
            a = ks[k] / kt
            m, e = self.combine(self.orders(kt, gg[k], seed=seed, rr_albedo=a), a)
            img[..., k], err[..., k] = (m * br[k]).reshape(self.shape), (e * abs(br[k])).reshape(self.shape)
        return img, err


class FullTransport:
    """ForwardModel with all orders: ``SingleScattering`` plus the multiple-scattering term
    from a local model around the last ``refresh`` point.

    The local model holds, per channel, the per-order images at (kappa_t0, g0) and their
    finite differences in log kappa_t and atanh g (step ``step``, the same random
    numbers), so the term is sum_k albedo^k (I_k + dlog(kappa_t) D_k + d(atanh g) E_k):
    exact in the albedo, first order in the other two.  ``render`` refreshes by itself
    only when no local model exists; a fitter calls ``refresh`` at its current estimate
    and ``needs_refresh`` to know when it has moved too far.

    Parameters
    ----------
    spec, image_index, channels : as for SingleScattering.
    bin, n_paths, batches : as for MultipleScattering.
    seed : int
        Random numbers of every refresh (common random numbers).
    step : float
        Finite-difference step in log kappa_t and atanh g.
    single : SingleScattering, optional
        An existing analytic model of the same image to reuse.
    """

    def __init__(self, spec: Spec, image_index: int | None = 0, *,
                 channels: tuple[str, ...] | None = None, bin: int = DEFAULT_BIN,
                 n_paths: int = DEFAULT_PATHS, batches: int = DEFAULT_BATCHES, seed: int = 0,
                 step: float = 0.05, single: SingleScattering | None = None):
        self.single = single or SingleScattering(spec, image_index, channels=channels)
        self.channels = self.single.channels
        self.ms = MultipleScattering(spec, image_index, channels=self.channels, bin=bin,
                                     n_paths=n_paths, batches=batches)
        self.shape, self.support = self.single.shape, self.single.support
        self.seed, self.step = int(seed), float(step)
        self._local: list | None = None
        self._var0: np.ndarray | None = None
        #: index of a batch of paths the term leaves out (the jackknife of
        #: inference/full.py: term_jackknife), or None for all of them
        self.leave_out: int | None = None
        #: the sampler's table of the term (``tabulate_term``), or None
        self._term_table: TermTable | None = None

    def tabulate_term(self, albedo: tuple[float, float]) -> None:
        """Serve ``render_with_variance``'s term for albedos in ``albedo`` (low, high) from a
        table of the present local model (``ms_table.TermTable``: the image exact, its excess
        variance interpolated in the albedo); renders it does not serve are computed as
        before.  One channel with scattering only; a refresh, ``rebin`` or
        ``untabulate_term`` drops it.  What it costs in accuracy is for the caller to check
        (``ChannelProblem.tabulated``)."""
        if not self.can_tabulate_term():
            raise ValueError("tabulate_term: one scattering channel with a bulb's local model "
                             "only")
        loc = self._local[0]
        self._term_table = TermTable(loc, _order_major(loc), self.ms, self.shape, albedo)

    def can_tabulate_term(self) -> bool:
        """Whether ``tabulate_term`` can: one channel, its local model built, with scattering,
        of a bulb (a spot's term, camera paths alone, has no excess variance to tabulate)."""
        return (self._local is not None and len(self._local) == 1
                and self._local[0] is not None and self.ms.photons is not None)

    def untabulate_term(self) -> None:
        self._term_table = None

    def rebin(self, bin: int) -> None:
        """Trace the term on sample pixels of ``bin`` x ``bin`` camera pixels from the next
        ``refresh`` on, with the same paths per sample pixel, batches, smoothing and seed; the
        local model is dropped (``render`` refreshes by itself without one)."""
        old = self.ms
        if int(bin) == old.bin:
            return
        self.ms = MultipleScattering(old.spec, old._image_index, channels=self.channels, bin=bin,
                                     n_paths=old.n_paths, batches=old.batches, smooth=old.smooth)
        self._local, self._var0, self._term_table = None, None, None

    def refresh(self, kappa_a, kappa_s, g, brightness=None) -> None:
        """Rebuild the local model at these parameters (arrays of shape (C,)); per scattering
        channel one camera-path and one photon trace, reweighted to the finite-difference
        points (a spot: one camera-path trace per point)."""
        c = len(self.channels)
        ka, ks, gg, _ = check_render_args(c, kappa_a, kappa_s, g,
                                          1.0 if brightness is None else brightness)
        keys = [self._trace_key(ka[k], ks[k], gg[k]) for k in range(c)]
        if self._local is not None and [None if loc is None else loc.get("key")
                                        for loc in self._local] == keys:
            return  # the same point, paths, grid and seed: the same trace (deterministic)
        self._term_table = None
        local = []
        for k in range(c):
            kt, a = ka[k] + ks[k], (ks[k] / (ka[k] + ks[k]) if ks[k] > 0 else 0.0)
            if ks[k] <= 0:
                local.append(None)
                continue
            eta = math.atanh(gg[k])
            runs = self.ms.orders_at(kt, gg[k], ((kt * math.exp(self.step), gg[k]),
                                                 (kt, math.tanh(eta + self.step))),
                                     seed=self.seed, rr_albedo=a)
            base = runs[0]
            # per batch: the finite differences of each batch (the same paths), so that a
            # batch's derivatives leave with it (leave_out) and their noise is in the variance
            local.append(_with_order_major({"kt": kt, "eta": eta, "batches": base,
                                            "d_kt": (runs[1] - base) / self.step,
                                            "d_g": (runs[2] - base) / self.step,
                                            "key": keys[k]}))
        self._local = local
        # the term's Monte Carlo variance at the refresh point, unit brightness
        # (render_with_variance: what it changes by away from there; a spot has none)
        self._var0 = None if self.ms.photons is None else \
            self.ms_part(ka, ks, gg, np.ones(c), excess=True, variance=False)[2]

    def _trace_key(self, kappa_a: float, kappa_s: float, g: float) -> tuple | None:
        """What one channel's trace in ``refresh`` depends on: the point (kappa_a, kappa_s,
        g; the albedo sets the paths' Russian roulette), the finite-difference step, the seed
        and the term's grid and paths.  Two traces with the same key are the same numbers
        (the random numbers are a function of the seed: tests/test_multiple.py), so
        ``refresh`` skips one whose keys all match the local model it has; the key lives in
        the local model, so a local model put back (``models_kept``) brings its own.  None
        for a channel without scattering."""
        if kappa_s <= 0:
            return None
        return (float(kappa_a), float(kappa_s), float(g), self.step, self.seed,
                self.ms.bin, self.ms.n_paths, self.ms.batches)

    def needs_refresh(self, kappa_a, kappa_s, g, tol: float = 0.1) -> bool:
        """True when no local model exists or (log kappa_t, atanh g) of a scattering channel
        moved by more than ``tol`` from the refresh point (or its scattering switched)."""
        if self._local is None:
            return True
        c = len(self.channels)
        ka, ks, gg, _ = check_render_args(c, kappa_a, kappa_s, g, 1.0)
        for k, loc in enumerate(self._local):
            if (loc is None) != (ks[k] <= 0):
                return True
            if loc is not None and (abs(math.log((ka[k] + ks[k]) / loc["kt"])) > tol
                                    or abs(math.atanh(gg[k]) - loc["eta"]) > tol):
                return True
        return False

    @staticmethod
    def _steps(loc: dict, kt: float, g: float) -> tuple[float, ...]:
        """The weights of the local model ``loc``'s ``LOCAL_PARTS`` at (kt, g): the steps
        h = (1, dlog kappa_t, d atanh g) from its refresh point (docs/studies/
        refresh_contraction.py replaces this with a quadratic model's six)."""
        return (1.0, math.log(kt / loc["kt"]), math.atanh(g) - loc["eta"])

    def ms_part(self, kappa_a, kappa_s, g, brightness, *, excess: bool = False,
                variance: bool = True) -> tuple:
        """The multiple-scattering image and its Monte Carlo variance, both (H, W, C), from
        the local model (the variance is that of the refresh point's estimate at this
        albedo, with the noise of the finite differences, which each batch has of its own).
        ``excess``: a third image, the part of that variance that shifts a fit
        (``render_with_variance``): the term's own variance at this albedo plus twice its
        covariance with each finite difference times the step, without the finite
        differences' own variance (which only flattens the local model away from its point)).
        ``variance`` False: the second image is left at 0 (``render_with_variance`` does not
        use it)."""
        c = len(self.channels)
        ka, ks, gg, br = check_render_args(c, kappa_a, kappa_s, g, brightness)
        if self._local is None:
            self.refresh(ka, ks, gg)
        img, var, exc = (np.zeros((*self.shape, c)) for _ in range(3))
        for k, loc in enumerate(self._local):
            if loc is None or ks[k] <= 0:
                continue
            kt = ka[k] + ks[k]
            steps = self._steps(loc, kt, gg[k])
            stack = _order_major(loc)
            pw = (ks[k] / kt) ** np.arange(stack.shape[0])
            pw[0] = 0.0
            parts = list((pw @ stack.reshape(stack.shape[0], -1)).reshape(stack.shape[1:]))
            if self.leave_out is not None:
                parts = [np.delete(x, self.leave_out, axis=0) for x in parts]
            parts = [self.ms.smoothed(x) for x in parts]
            per = sum(h * x for h, x in zip(steps, parts))
            n = per.shape[0]
            mean = np.clip(per.mean(axis=0), 0.0, None)
            img[..., k] = (self.ms.upsample(mean) * br[k]).reshape(self.shape)
            if variance:
                err = per.std(axis=0, ddof=1) / math.sqrt(n)
                var[..., k] = ((self.ms.upsample_err(err) * br[k]) ** 2).reshape(self.shape)
            if excess:
                # at the camera's pixels, each batch's deviation interpolated: a camera pixel
                # between sample pixels mixes their independent errors, and its variance is
                # sum w_i^2 s_i^2, not the interpolated sum w_i s_i^2 (2.6 times that at bin 2,
                # where the likelihood's excess then overshot: docs/inference.md)
                dev = [x - x.mean(axis=0) for x in parts]
                mix = sum(f * h * d for f, h, d in zip((1.0, 2.0, 2.0), steps, dev))
                q = self.ms.upsampled_products(dev[0], mix)
                exc[..., k] = (q * br[k] ** 2 / (n * (n - 1))).reshape(self.shape)
        return (img, var, exc) if excess else (img, var)

    def render_with_variance(self, kappa_a, kappa_s, g, brightness
                             ) -> tuple[np.ndarray, np.ndarray]:
        """The image (``render``) and how much the Monte Carlo variance that moves a fit
        (``ms_part``'s ``excess``) is larger here than at the refresh point, both (H, W, C):
        the likelihood takes out what that change adds to the squared residuals
        (inference/likelihood.py: ``ChannelProblem.log_likelihood``).  A spot's term (camera
        paths alone, heavy-tailed: their batch variance is no estimate to subtract) has None
        here.  Per pixel the change is capped at the variance at the refresh point either way:
        far from there (the albedo has no trust region) the estimate is no longer reliable
        (before the cap, and before a spot's term was left out, a spot's scan found gains of
        10^4 log-posterior units at points where the local model was used far from its
        albedo)."""
        if self.ms.photons is None:
            return self.render(kappa_a, kappa_s, g, brightness), None
        ka, ks, gg, br = check_render_args(len(self.channels), kappa_a, kappa_s, g, brightness)
        got = self._from_term_table(ka, ks, gg, br)
        if got is None:
            img, _, exc = self.ms_part(ka, ks, gg, br, excess=True, variance=False)
        else:
            img, exc = got
        var0 = self._var0 * br ** 2
        return (self.single.render(kappa_a, kappa_s, g, brightness) + img,
                np.clip(exc - var0, -var0, var0))

    def _from_term_table(self, ka, ks, gg, br) -> tuple[np.ndarray, np.ndarray] | None:
        """The term's image and excess variance (H, W, 1) from the table where it serves."""
        table = self._term_table
        if table is None or self.leave_out is not None or self._local is None:
            return None
        got = table.parts(self._local[0], ka[0] + ks[0], ks[0], gg[0], br[0])
        return None if got is None else (got[0][..., None], got[1][..., None])

    def render(self, kappa_a, kappa_s, g, brightness) -> np.ndarray:
        """Image (H, W, C): analytic orders 0 and 1 plus the local multiple-scattering term."""
        return self.single.render(kappa_a, kappa_s, g, brightness) + \
            self.ms_part(kappa_a, kappa_s, g, brightness)[0]
