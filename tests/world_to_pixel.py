"""Print the 0-based pixel (x y) of a sky position in a FITS image, by astropy's WCS.

Usage: python3 tests/world_to_pixel.py IMAGE.fits RA_DEG DEC_DEG
An independent check of the WCS the imager writes (used by tests/cli.rs).
"""
import sys

from astropy.io import fits
from astropy.wcs import WCS

path, ra, dec = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
with fits.open(path) as hdul:
    wcs = WCS(hdul[0].header).celestial
x, y = wcs.world_to_pixel_values(ra, dec)
print(f"{float(x):.6f} {float(y):.6f}")
