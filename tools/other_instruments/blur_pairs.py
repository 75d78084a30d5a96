"""Known-truth pairs whose frame is also blurred (seeing-like), through `sunjitter align`.

    python3 tools/other_instruments/blur_pairs.py IMAGE BLUR_PX NOISE_K N SEED
    BLUR_KERNEL=pillbox python3 tools/other_instruments/blur_pairs.py ...   (a disk of radius BLUR_PX)

The frame is the image moved by a random similarity (quintic spline, scipy), then blurred by a
Gaussian of BLUR_PX; NOISE_K times the background sigma of noise goes into both. Prints per pair
the status and the error over sigma per parameter, then the RMSE, bias and coverage.
"""
import os, sys, json, subprocess, tempfile, numpy as np
from astropy.io import fits
from scipy import ndimage
path, blur, noise_k, n, seed = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')); import noise_limits
hdu = fits.open(path)[0]; ref, _ = noise_limits.remove_hot_pixels(hdu.data.astype(float))
h, w = ref.shape; c = np.array([(w-1)/2, (h-1)/2]); bg = noise_limits.background_noise(ref)
TMP = tempfile.mkdtemp(); RP, FP = os.path.join(TMP, 'ref.fits'), os.path.join(TMP, 'frame.fits')
rng = np.random.default_rng(seed); yy, xx = np.mgrid[0:h, 0:w].astype(float)
coef = ndimage.spline_filter(ref, order=5, mode='mirror')
zs = []; errs = []
for t in range(n):
    s = rng.uniform(0.995, 1.005); th = rng.uniform(-0.01, 0.01); dx, dy = rng.uniform(-5, 5, 2)
    X = xx - c[0] - dx; Y = yy - c[1] - dy; ct, st = np.cos(th), np.sin(th)
    px = (ct*X + st*Y)/s + c[0]; py = (-st*X + ct*Y)/s + c[1]
    fr = ndimage.map_coordinates(coef, [py, px], order=5, mode='mirror', prefilter=False)
    if blur > 0 and os.environ.get('BLUR_KERNEL') == 'pillbox':
        r_k = int(np.ceil(blur)); yk, xk = np.mgrid[-r_k:r_k+1, -r_k:r_k+1]
        ker = (np.hypot(xk, yk) <= blur).astype(float); fr = ndimage.convolve(fr, ker / ker.sum(), mode='mirror')
    elif blur > 0: fr = ndimage.gaussian_filter(fr, blur)
    r = ref.copy()
    if noise_k > 0: r += noise_k*bg*rng.standard_normal(r.shape); fr += noise_k*bg*rng.standard_normal(fr.shape)
    fits.PrimaryHDU(r.astype(np.float32), hdu.header).writeto(RP, overwrite=True)
    fits.PrimaryHDU(fr.astype(np.float32), hdu.header).writeto(FP, overwrite=True)
    js = json.loads(subprocess.run([os.environ.get('SUNJITTER', 'target/release/sunjitter'),'align',RP,FP,'--json','--config',os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', 'similarity.toml')],capture_output=True,text=True).stdout)
    if js.get('scale') is None: print('failed', js['message'][-100:]); continue
    tr = np.array([s, th*206264.806, dx, dy]); est = np.array([js['scale'], js['rotation_arcsec'], js['dx_px'], js['dy_px']])
    sg = np.array([js['sigma_scale'], js['sigma_rotation_arcsec'], js['sigma_dx_px'], js['sigma_dy_px']])
    zs.append(np.abs(est-tr)/sg); errs.append(est-tr)
    print(t, js['status'], ' '.join('%5.1f' % z for z in zs[-1]), js['message'][-90:])
e = np.array(errs); z = np.array(zs)
print('rmse', np.sqrt((e**2).mean(0)), 'bias', e.mean(0)); print('in1', (z<=1).mean(0), 'in3', (z<=3).mean(0))
