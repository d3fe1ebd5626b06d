"""A large test sky made of held-out 512 x 512 skies: sources of the sizes a 512 series knows,
spread over a field of SIZE x SIZE pixels (issue 61's large fields).

    python3 benches/mosaic_sky.py --size 1024 --seed 940000 --out mosaic-1024.fits [--r2d2 target/release/r2d2]

`r2d2 trainset --procedural K --size 512 --seed SEED` draws (SIZE/512)^2 skies (seeds 940000..
are test seeds: never used for training or selection); each fills one 512 x 512 cell of the
field, scaled by 10^u (u uniform in [-1, 0], so the cells' peaks differ as sources in a real
field do) and flipped at random; the result is normalised to a peak of 1 (Jy/pixel).
Image it with `benches/vs_wsclean.py --size SIZE --sky-fits OUT`.
"""

import argparse
import glob
import os
import subprocess
import tempfile

import numpy as np
from astropy.io import fits

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, required=True, help="a multiple of 512")
    ap.add_argument("--seed", type=int, default=940000)
    ap.add_argument("--telescope", default="vla")
    ap.add_argument("--r2d2", default=os.path.join(REPO, "target", "release", "r2d2"))
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    if args.size % 512:
        raise SystemExit("--size must be a multiple of 512")
    cells = args.size // 512
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        # Only the skies are used: the observations are drawn an hour apart (few samples, fast),
        # which leaves the skies as they are (each sky's seed is its own).
        subprocess.run([args.r2d2, "-q", "trainset", "--telescope", args.telescope, "--procedural", str(cells * cells), "--seed", str(args.seed),
                        "--size", "512", "--integration-s", "3600", "--parquet", "--out", tmp], check=True)
        skies = sorted(glob.glob(os.path.join(tmp, "vis", "*.sky.fits")))
        assert len(skies) == cells * cells, skies
        field = np.zeros((args.size, args.size))
        for k, path in enumerate(skies):
            sky = np.squeeze(fits.getdata(path)).astype(float)
            sky = sky / sky.max() * 10 ** rng.uniform(-1, 0)
            if rng.random() < 0.5:
                sky = sky[::-1]
            if rng.random() < 0.5:
                sky = sky[:, ::-1]
            y, x = divmod(k, cells)
            field[y * 512:(y + 1) * 512, x * 512:(x + 1) * 512] = sky
    field /= field.max()
    header = fits.Header()
    header["BUNIT"] = "JY/PIXEL"
    header["HISTORY"] = f"benches/mosaic_sky.py --size {args.size} --seed {args.seed} --telescope {args.telescope}"
    fits.PrimaryHDU(field.astype(np.float32), header).writeto(args.out, overwrite=True)
    print(f"{args.out}: {args.size} x {args.size}, {cells * cells} held-out skies (seeds {args.seed}..), {np.count_nonzero(field > 1e-4)} pixels above 1e-4")


if __name__ == "__main__":
    main()
