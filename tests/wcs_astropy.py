#!/usr/bin/env python3
"""Check with astropy that a FITS image from r2d2-imaging puts pixels where the imager does.

The imager places pixel (ix, iy) (0-based, ix along FITS axis 1) at direction cosines
    l = -pixel * (ix - nx // 2)   (radians, towards increasing RA: east is left)
    m =  pixel * (iy - ny // 2)
about the phase centre (ra0, dec0), i.e. at
    RA  = ra0 + atan2(l, cos(dec0) n - m sin(dec0)),  n = sqrt(1 - l^2 - m^2)
    Dec = asin(m cos(dec0) + sin(dec0) n).
This script takes phase centre, pixel size and image size from the header, computes the
world coordinates of a set of pixels both that way and with astropy.wcs.WCS, and fails
if they differ by more than 1e-9 degrees, or if the centre pixel is not the phase centre.

Usage:  python3 tests/wcs_astropy.py IMAGE.fits
A suitable file comes from the Rust test `fits::tests::wcs_pixels_map_to_sky_like_the_imager`
when R2D2_WCS_FITS_OUT names where to copy it:
    R2D2_WCS_FITS_OUT=/tmp/wcs.fits cargo test --release --lib wcs_pixels_map
    python3 tests/wcs_astropy.py /tmp/wcs.fits
Exit status 0 when everything agrees, 1 on a mismatch, 2 on bad usage.
"""

import math
import sys

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS

TOLERANCE_DEG = 1e-9


def angle_diff(a, b):
    """Difference of two angles in degrees, wrapped into [-180, 180)."""
    return (a - b + 180.0) % 360.0 - 180.0


def imager_world(ix, iy, nx, ny, ra0, dec0, pixel_deg):
    """World coordinates (degrees) of pixel (ix, iy) by the imager's convention."""
    pixel = math.radians(pixel_deg)
    l = -pixel * (ix - nx // 2)
    m = pixel * (iy - ny // 2)
    n = math.sqrt(1.0 - l * l - m * m)
    ra0, dec0 = math.radians(ra0), math.radians(dec0)
    ra = ra0 + math.atan2(l, math.cos(dec0) * n - m * math.sin(dec0))
    dec = math.asin(m * math.cos(dec0) + math.sin(dec0) * n)
    return math.degrees(ra) % 360.0, math.degrees(dec)


def main(argv):
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    path = argv[1]
    header = fits.getheader(path)
    nx, ny = header["NAXIS1"], header["NAXIS2"]
    ra0, dec0 = header["CRVAL1"], header["CRVAL2"]
    pixel_deg = header["CDELT2"]
    failures = []

    expected_crpix = (nx // 2 + 1, ny // 2 + 1)
    if (header["CRPIX1"], header["CRPIX2"]) != expected_crpix:
        failures.append(f"CRPIX = ({header['CRPIX1']}, {header['CRPIX2']}), expected {expected_crpix}")
    if header["CDELT1"] != -pixel_deg:
        failures.append(f"CDELT1 = {header['CDELT1']}, expected -CDELT2 = {-pixel_deg}")

    wcs = WCS(header).celestial
    pixels = [(nx // 2, ny // 2), (nx // 2 - 10, ny // 2 + 5), (0, 0), (nx - 1, ny - 1), (3, ny - 2), (nx - 7, 1)]
    xs = np.array([p[0] for p in pixels], dtype=float)
    ys = np.array([p[1] for p in pixels], dtype=float)
    ras, decs = wcs.wcs_pix2world(xs, ys, 0)  # origin 0: same pixel numbering as the imager

    for (ix, iy), ra_a, dec_a in zip(pixels, ras, decs):
        ra_i, dec_i = imager_world(ix, iy, nx, ny, ra0, dec0, pixel_deg)
        d_ra, d_dec = angle_diff(ra_a, ra_i), dec_a - dec_i
        ok = abs(d_ra) < TOLERANCE_DEG and abs(d_dec) < TOLERANCE_DEG
        print(f"pixel ({ix:4d}, {iy:4d}): astropy ({ra_a:.10f}, {dec_a:.10f})  "
              f"imager ({ra_i:.10f}, {dec_i:.10f})  {'ok' if ok else 'MISMATCH'}")
        if not ok:
            failures.append(f"pixel ({ix}, {iy}) differs by ({d_ra:.3g}, {d_dec:.3g}) deg")

    ra_c, dec_c = ras[0], decs[0]
    if abs(angle_diff(ra_c, ra0)) > TOLERANCE_DEG or abs(dec_c - dec0) > TOLERANCE_DEG:
        failures.append(f"centre pixel is at ({ra_c}, {dec_c}), not the phase centre ({ra0}, {dec0})")
    ra_off, dec_off = ras[1], decs[1]
    if not (angle_diff(ra_off, ra0) > 0 and dec_off > dec0):
        failures.append("pixel (nx/2 - 10, ny/2 + 5) should be east (higher RA) and north of the centre")

    for failure in failures:
        print(f"FAIL: {failure}", file=sys.stderr)
    print(f"{path}: {'FAILED' if failures else 'all pixels agree with astropy'}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
