#!/usr/bin/env python3
"""Write the MeerKAT and SKA-Mid antenna tables of this directory from their published
geodetic positions.

Source: `simms/telescope/layouts/skamid.geodetic.yaml` of the PyPI package simms 3.0.2
(RATT-RU; the positions are the SKA Observatory's published MeerKAT and SKA-Mid antenna
locations, WGS84 longitude, latitude in degrees and height in metres). Only the coordinates
are taken, as data; no code of simms is used. Run:

    pip download simms==3.0.2 --no-deps -d /tmp/simms && unzip -o -q /tmp/simms/*.whl -d /tmp/simms
    python3 data/telescopes/make_layouts.py /tmp/simms/simms/telescope/layouts/skamid.geodetic.yaml

Geodetic to ITRF (Earth-centred, Earth-fixed) with the WGS84 ellipsoid; tests/telescopes.rs
checks the tables against astropy's EarthLocation.from_geodetic.
"""
import math
import sys

import yaml

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563

# (file, subarray in the source, telescope, what it is)
TABLES = [
    ("meerkat.itrf.txt", "meerkat", "MeerKAT", "MeerKAT's 64 dishes of 13.5 m (M000..M063)"),
    ("skamid-aastar.itrf.txt", "skamid-aastar", "SKA-Mid",
     "SKA-Mid AA*: the 64 MeerKAT dishes (13.5 m) and the SKA dishes (15 m) the source lists for it"),
]


def itrf(lon_deg, lat_deg, height_m):
    lon, lat = math.radians(lon_deg), math.radians(lat_deg)
    e2 = WGS84_F * (2.0 - WGS84_F)
    n = WGS84_A / math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
    x = (n + height_m) * math.cos(lat) * math.cos(lon)
    y = (n + height_m) * math.cos(lat) * math.sin(lon)
    z = (n * (1.0 - e2) + height_m) * math.sin(lat)
    return x, y, z


def main(source):
    with open(source) as f:
        layout = yaml.safe_load(f)
    names = layout["antnames"]
    sizes = layout["size"]
    where = dict(zip(names, zip(layout["antlocations"], sizes)))
    for file, subarray, telescope, what in TABLES:
        lines = [
            f"# {telescope}: {what}.",
            "# Source: simms 3.0.2 (PyPI), simms/telescope/layouts/skamid.geodetic.yaml,",
            f"# subarray '{subarray}' (WGS84 geodetic), converted to ITRF by make_layouts.py.",
            "#X Y Z dish_diam station mount",
        ]
        for name in layout["subarray"][subarray]:
            (lon, lat, h), size = where[name]
            x, y, z = itrf(lon, lat, h)
            lines.append(f"{x:.4f} {y:.4f} {z:.4f} {size:g} {name} ALT-AZ")
        with open(f"{sys.path[0]}/{file}", "w") as out:
            out.write("\n".join(lines) + "\n")
        print(f"{file}: {len(lines) - 4} antennas")


if __name__ == "__main__":
    main(sys.argv[1])
