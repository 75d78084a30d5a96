#!/usr/bin/env python3
"""Noise limits of a similarity fit between two noisy copies of one image (numpy/scipy only).

Independent of the Rust code: it reads the image with astropy and computes, for Gaussian white
noise of K times the image's background noise added to both copies (the `simulate --noise K`
Monte Carlo):

1. the Cramér–Rao bound, `Cov ≥ 2σ²(Σ c cᵀ)⁻¹`, with `c` the derivatives of the image with
   respect to (scale, rotation, dx, dy, gain, offset) about the array centre: the bound for
   two noisy copies of an unknown scene (Robinson & Milanfar 2004). The image derivatives
   are 8th-order central differences, close to the band-limited derivative (2nd-order ones
   underestimate the gradient energy by ~25 % on TRACE and overstate the bound);
2. the exact covariance of the engine's refinement equations, linearised: both images
   smoothed by `--smoothing` px, the reference's (noisy) gradient as instrument, the slope
   from the noise-free gradient; one noise realisation for the instrument;
3. the covariance of the best estimator of that kind found (`--best`, with 4.): a symmetric one, whose
   instrument is the gradient of the two images' mean (its noise is then uncorrelated with
   the difference's, and half as large), filtered by a Gaussian of 0.5–1 px or by a power of
   the Wiener filter built from the noise-free image's own spectrum (an oracle no real
   estimator has). The residual stays unfiltered. With the scene unknown, an instrument's
   noise costs information wherever the scene's power is comparable to the noise's, so this
   sits above the bound; it shows how close an estimator of this kind can come;
4. with `--best`, the bound for a shift alone when the scene is random with the image's own
   spectrum, which the Wiener-weighted symmetric instrument attains (see
   `random_scene_translation_bound`).

The image is cleaned of hot pixels first, as `simulate` cleans the scene it warps
(`preprocess::remove_spikes_from_scene`, default fraction 1.0), and
a hot pixel left in would count as a 1000-DN point feature, which no solar scene has
(on TRACE 1024² its 29 spikes alone would lower the bound by 30 %).

    python3 tools/noise_limits.py data/real/trace_171_19980519T222143_1024.fits --noise 3 [--best]
"""
import argparse

import numpy as np
from astropy.io import fits
from scipy import ndimage

ARCSEC_PER_RAD = 206264.80624709636


def background_noise(img, block=16, quantile=0.10):
    """`simulate`'s background σ, computed independently: the RMS residual of a least-squares
    quadratic surface in each 16×16 block (blocks with a non-finite pixel, or constant ones,
    skipped), the 10th percentile of those, divided by the exact 10th percentile of
    √(χ²_ν/ν) for ν = 250 (scipy), where pure noise would put it."""
    from scipy import stats
    h, w = img.shape
    yy, xx = np.mgrid[0:block, 0:block]
    design = np.c_[np.ones(block * block), xx.ravel(), yy.ravel(),
                   xx.ravel() ** 2, yy.ravel() ** 2, (xx * yy).ravel()]
    sigmas = []
    for y in range(0, h - block + 1, block):
        for x in range(0, w - block + 1, block):
            b = img[y:y + block, x:x + block].astype(float).ravel()
            if not np.all(np.isfinite(b)) or b.max() == b.min():
                continue
            coef, *_ = np.linalg.lstsq(design, b, rcond=None)
            r = b - design @ coef
            sigmas.append(np.sqrt(r @ r / (b.size - 6)))
    dof = block * block - 6
    at_quantile = np.sqrt(stats.chi2.ppf(quantile, dof) / dof)
    return np.quantile(sigmas, quantile, method="nearest") / at_quantile


def remove_hot_pixels(img, fraction=1.0, noise_sigmas=5.0, lone=0.0):
    """The engine's rules (`preprocess::remove_hot_pixels_with`): |v − m| > fraction·|m|,
    > k·σ (image-wide MAD of v − m) and > k × the robust spread of the 8 neighbours about
    m; and the pixel stands alone: it rises above the floor of its 8 neighbours by more than
    `lone` × what the brightest of them does (mirrored for a dark pixel), or does so together
    with that neighbour (a two-pixel hit) when the neighbour is a suspect too. Replaced by m
    (3×3 median). `lone = 0` (every suspect) is how `simulate` cleans the scene it warps
    (`remove_spikes_from_scene`); the engine cleans each image with `lone = 10`."""
    m = ndimage.median_filter(img, 3, mode="nearest")
    dev = np.abs(img - m)
    sigma = 1.482602218505602 * np.median(dev)
    pad = np.pad(img, 1, mode="edge")
    h, w = img.shape
    neigh = np.stack([pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                      for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)])
    spread = 1.482602218505602 * np.median(np.abs(neigh - m), axis=0)
    suspect = (dev > fraction * np.abs(m)) & (dev > noise_sigmas * sigma)
    candidates = suspect & (dev > noise_sigmas * spread)

    def rise(y, x, sign, skip=None):
        """(the pixel's rise over the neighbours' floor / the brightest one's, where it is)"""
        vals = [(sign * img[yy, xx], (yy, xx))
                for yy in range(max(y - 1, 0), min(y + 2, h))
                for xx in range(max(x - 1, 0), min(x + 2, w))
                if (yy, xx) not in ((y, x), skip) and np.isfinite(img[yy, xx])]
        if not vals:
            return np.inf, None
        floor = min(v for v, _ in vals)
        top, where = max(vals)
        up = sign * img[y, x] - floor
        return (up / (top - floor) if top > floor else np.inf), where

    hot = np.zeros_like(candidates)
    for y, x in zip(*np.nonzero(candidates)):
        sign = 1.0 if img[y, x] > m[y, x] else -1.0
        ratio, partner = rise(y, x, sign)
        if ratio > lone:
            hot[y, x] = True
        elif suspect[partner]:
            hot[y, x] = rise(y, x, sign, partner)[0] > lone and rise(*partner, sign, (y, x))[0] > lone
    out = np.where(hot, m, img)
    return out, int(hot.sum())


def derivative(img, axis, order):
    f = lambda k: np.roll(img, -k, axis=axis)  # noqa: E731 (edges are masked out)
    if order == 2:
        return (f(1) - f(-1)) / 2
    return (-f(4) / 280 + 4 * f(3) / 105 - f(2) / 5 + 4 * f(1) / 5
            - 4 * f(-1) / 5 + f(-2) / 5 - 4 * f(-3) / 105 + f(-4) / 280)


def columns(img, gx, gy, qx, qy):
    return [gx * qx + gy * qy, -gx * qy + gy * qx, gx, gy, img, np.ones_like(img)]


def sigmas(cov):
    sd = np.sqrt(np.diag(cov))
    return sd[0], sd[1] * ARCSEC_PER_RAD, sd[2], sd[3]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("image")
    ap.add_argument("--noise", type=float, default=3.0, help="K: noise σ = K × background σ")
    ap.add_argument("--smoothing", type=float, default=0.7, help="the refinement's smoothing, px")
    ap.add_argument("--margin", type=int, default=8, help="border left out, px")
    ap.add_argument("--keep-hot-pixels", action="store_true")
    ap.add_argument("--best", action="store_true", help="also scan symmetric instruments (3.)")
    a = ap.parse_args()

    img = fits.getdata(a.image).astype(np.float64)
    img, hot = (img, 0) if a.keep_hot_pixels else remove_hot_pixels(img)
    sigma = a.noise * background_noise(img)
    h, w = img.shape
    yy, xx = np.mgrid[:h, :w]
    qx, qy = xx - (w - 1) / 2, yy - (h - 1) / 2
    mask = np.zeros((h, w), bool)
    mask[a.margin:-a.margin, a.margin:-a.margin] = True
    print(f"{a.image}: {w}×{h}, {hot} hot pixels cleaned, noise σ = {sigma:.3f} "
          f"({a.noise}× background)")
    print(f"{'':44s}{'scale':>10s}{'rot ″':>9s}{'dx px':>10s}{'dy px':>10s}")

    for order in (2, 8):
        c = [v[mask] for v in columns(img, derivative(img, 1, order), derivative(img, 0, order), qx, qy)]
        fisher = np.array([[np.dot(u, v) for v in c] for u in c]) / (2 * sigma**2)
        label = f"Cramér–Rao bound ({ {2: '2nd', 8: '8th'}[order]}-order derivatives)"
        print(f"{label:44s}%10.3g%9.3g%10.3g%10.3g" % sigmas(np.linalg.inv(fisher)))

    s = a.smoothing
    smooth = ndimage.gaussian_filter(img, s) if s > 0 else img
    rng = np.random.default_rng(5)
    noise = rng.normal(0.0, sigma, img.shape)
    noisy = smooth + (ndimage.gaussian_filter(noise, s) if s > 0 else noise)
    slope_cols = columns(smooth, derivative(smooth, 1, 2), derivative(smooth, 0, 2), qx, qy)
    inst = columns(noisy, derivative(noisy, 1, 2), derivative(noisy, 0, 2), qx, qy)
    reach = max(1, int(np.ceil(4 * s)))
    inst[4] = (np.roll(noisy, reach, 0) + np.roll(noisy, -reach, 0)
               + np.roll(noisy, reach, 1) + np.roll(noisy, -reach, 1)) / 4
    z = [v * mask for v in inst]
    f = [v * mask for v in slope_cols]
    A = np.array([[np.sum(zi * fj) for fj in f] for zi in z])
    # Residual noise: both images' white noise through the smoothing (autocorrelation √2·s).
    kz = [2 * sigma**2 * (ndimage.gaussian_filter(zi, np.sqrt(2) * s) if s > 0 else zi) for zi in z]
    B = np.array([[np.sum(zi * kj) for kj in kz] for zi in z])
    Ai = np.linalg.inv(A)
    label = f"refinement's equations, {s} px smoothing"
    print(f"{label:44s}%10.3g%9.3g%10.3g%10.3g" % sigmas(Ai @ B @ Ai.T))
    if a.best:
        best_symmetric(img, sigma, mask, qx, qy)
        random_scene_translation_bound(img, sigma)


def best_symmetric(img, sigma, mask, qx, qy):
    def cols(im):
        return [v[mask] for v in columns(im, derivative(im, 1, 8), derivative(im, 0, 8), qx, qy)]

    f = cols(img)
    rng = np.random.default_rng(6)
    mean_of_both = img + (rng.normal(0.0, sigma, img.shape) + rng.normal(0.0, sigma, img.shape)) / 2
    h, w = img.shape
    power = np.abs(np.fft.fft2(img - img.mean())) ** 2 / img.size
    ring = np.minimum((np.hypot(np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]) * 512).astype(int), 511)
    radial = np.bincount(ring.ravel(), power.ravel(), 512) / np.maximum(np.bincount(ring.ravel(), None, 512), 1)
    wiener = radial[ring] / (radial[ring] + sigma**2 / 2)
    candidates = [(f"Gaussian {s} px", ndimage.gaussian_filter(mean_of_both, s)) for s in (0.5, 0.7, 0.8, 1.0)]
    candidates += [(f"Wiener^{p}", np.real(np.fft.ifft2(np.fft.fft2(mean_of_both) * wiener**p))) for p in (1, 2)]
    for name, instrument in candidates:
        z = cols(instrument)
        A = np.array([[np.dot(zi, fj) for fj in f] for zi in z])
        B = 2 * sigma**2 * np.array([[np.dot(zi, zj) for zj in z] for zi in z])
        Ai = np.linalg.inv(A)
        label = f"symmetric instrument, {name}"
        print(f"{label:44s}%10.3g%9.3g%10.3g%10.3g" % sigmas(Ai @ B @ Ai.T))


def random_scene_translation_bound(img, sigma):
    """The Cramér–Rao bound of a shift alone when the scene is unknown and random (Gaussian,
    with the image's own power spectrum P) rather than a fixed unknown: per Fourier mode of
    the two noisy copies, the Fisher information is k²·P²/(σ_N²·(2P + σ_N²)) instead of the
    fixed scene's k²·P/(2σ_N²) (σ_N² = N·σ² for the unnormalised DFT). The loss is where the
    scene's power is comparable to the noise's, and the symmetric Wiener-weighted instrument
    above attains this bound: it is the limit for an estimator that must learn the scene from
    the two noisy images. Spectra of the image mirrored into a 2×2 tile (no edge jumps)."""
    tile = np.block([[img, img[:, ::-1]], [img[::-1, :], img[::-1, ::-1]]])
    power = np.abs(np.fft.fft2(tile - tile.mean())) ** 2
    noise_power = tile.size * sigma**2
    for axis, name in ((1, "dx"), (0, "dy")):
        k2 = (2 * np.pi * np.fft.fftfreq(tile.shape[axis])) ** 2
        k2 = k2[None, :] if axis == 1 else k2[:, None]
        # The tile holds four copies of the image.
        fixed = (k2 * power / (2 * noise_power)).sum() / 4
        random = (k2 * power**2 / (noise_power * (2 * power + noise_power))).sum() / 4
        print(f"shift alone, {name}: Cramér–Rao bound {fixed ** -0.5:.3g} px for a fixed scene, "
              f"{random ** -0.5:.3g} px for a random one with the image's spectrum")


if __name__ == "__main__":
    main()
