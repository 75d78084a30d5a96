#!/usr/bin/env python3
"""Convert sunpy's Helioviewer JP2 test images to float32 FITS.

Pixel data: Pillow, rows flipped ([::-1]) exactly like sunpy.io._jp2.read
(glymur data[...][::-1]) so FITS row 0 = bottom.
Header: the JP2's embedded XML box (parsed from the file bytes; glymur is not
installed), all keys copied except structural ones. The Helioviewer test files
were downsampled (e.g. AIA 4096 -> 410) without updating the header, so the
main output ("<name>.fits") rescales CDELT/CRPIX (and R_SUN) to the real pixel
grid; "<name>_rawhdr.fits" keeps the header as stored (stale plate scale).
Also copies resampled_hmi.fits, aia_171_level1.fits, hsi_image*.fits as float32.
"""
import os, glob, re
import numpy as np
import xml.etree.ElementTree as ET
from PIL import Image
from astropy.io import fits
import sunpy

D = os.path.join(os.path.dirname(sunpy.__file__), 'data', 'test')
OUT = os.environ.get('OUT', 'other_instruments_fits')
os.makedirs(OUT, exist_ok=True)

SKIP = {'SIMPLE', 'BITPIX', 'NAXIS', 'NAXIS1', 'NAXIS2', 'EXTEND', 'XTENSION', 'PCOUNT',
        'GCOUNT', 'TFIELDS', 'BSCALE', 'BZERO', 'BLANK', 'CHECKSUM', 'DATASUM', 'HISTORY',
        'COMMENT', 'META', 'FITS', 'DATAMIN', 'DATAMAX'}
NAMES = {
    'SOHO_LASCO_C3': 'lasco_c3',
    'SDO_AIA_AIA_193': 'aia_193',
    'EUI_FSI_174': 'eui_fsi_174',
    'HMI_continuum': 'hmi_cont',
}


def conv(v):
    v = v.strip()
    if re.fullmatch(r'[+-]?\d+', v):
        try:
            return int(v)
        except ValueError:
            pass
    try:
        return float(v)
    except ValueError:
        return v


def xml_header(path):
    b = open(path, 'rb').read()
    i = b.find(b'xml <meta>')
    L = int.from_bytes(b[i - 4:i], 'big')
    root = ET.fromstring(b[i + 4:i - 4 + L])
    keys = {}
    for n in root.iter():
        if n.text is None or not n.text.strip():
            continue
        k = n.tag.upper()
        if k in ('NAXIS1', 'NAXIS2') and '_' + k not in keys:
            keys['_' + k] = conv(n.text)
        if k in SKIP or k.startswith(('TTYPE', 'TFORM', 'ZIMAGE', 'ZBITPIX', 'ZNAXIS', 'ZTILE',
                                      'ZCMPTYPE', 'ZNAME', 'ZVAL', 'ZQUANTIZ', 'ZSIMPLE',
                                      'ZEXTEND', 'ZBLANK', 'ZTENSION', 'ZPCOUNT', 'ZGCOUNT',
                                      'ZHECKSUM', 'ZDATASUM', 'TDIM')):
            continue
        if len(k) > 8 or not re.fullmatch(r'[A-Z0-9_-]+', k):
            continue
        keys[k] = conv(n.text)
    return keys


def write(name, data, keys):
    h = fits.Header()
    for k, v in keys.items():
        if isinstance(v, str):
            v = v.replace('\n', ' ')
            v = ''.join(c for c in v if 32 <= ord(c) < 127)[:68]
        try:
            h[k] = v
        except Exception as e:
            print('skip', k, e)
    fits.PrimaryHDU(data.astype(np.float32), h).writeto(os.path.join(OUT, name), overwrite=True,
                                                       output_verify='silentfix')


for f in sorted(glob.glob(os.path.join(D, '*.jp2'))):
    name = next(v for k, v in NAMES.items() if k in f)
    im = Image.open(f)
    a = np.asarray(im).astype(np.float32)[::-1]  # sunpy: Jp2k(filepath)[...][::-1]
    keys = xml_header(f)
    H, W = a.shape
    n1, n2 = keys.pop('_NAXIS1', W), keys.pop('_NAXIS2', H)
    # LASCO: real header has DATE_OBS='2013/05/13' + TIME_OBS; add ISO DATE-OBS
    if 'DATE-OBS' not in keys and 'TIME_OBS' in keys:
        keys['DATE-OBS'] = keys['DATE_OBS'].replace('/', '-') + 'T' + keys['TIME_OBS']
    write(name + '_rawhdr.fits', a, keys)
    k2 = dict(keys)
    if (n1, n2) != (W, H):
        fx, fy = n1 / W, n2 / H
        k2['CDELT1'] = keys['CDELT1'] * fx
        k2['CDELT2'] = keys['CDELT2'] * fy
        k2['CRPIX1'] = (keys['CRPIX1'] - 0.5) / fx + 0.5
        k2['CRPIX2'] = (keys['CRPIX2'] - 0.5) / fy + 0.5
        for k in ('R_SUN', 'SOLAR_R', 'RADIUS'):
            if isinstance(keys.get(k), (int, float)):
                k2[k] = keys[k] / fx
        for k in ('HV_ROCC_INNER', 'HV_ROCC_OUTER'):
            pass  # in solar radii, unchanged
        k2['HISTORY'] = f'rebinned header to {W}x{H} from {n1}x{n2} (helioviewer test file)'
    write(name + '.fits', a, k2)
    print(name, a.shape, a.min(), a.max(), 'hdr naxis', n1, n2)

for src, name in [('resampled_hmi.fits', 'hmi_resampled.fits'),
                  ('aia_171_level1.fits', 'aia_171_l1.fits'),
                  ('hsi_image_20101016_191218.fits', 'rhessi.fits')]:
    with fits.open(os.path.join(D, src)) as hl:
        h = hl[0].header.copy()
        d = hl[0].data.astype(np.float32)
    for k in ('BLANK', 'BSCALE', 'BZERO'):
        h.pop(k, None)
    fits.PrimaryHDU(d, h).writeto(os.path.join(OUT, name), overwrite=True, output_verify='silentfix')
    print(name, d.shape)
