"""Writes an observation as the reference implementation (R2D2-RI) keeps one: a MATLAB .mat
file with `y`, `u`, `v`, `w`, `nW`, `nWimag`, `frequency`, `maxProjBaseline`, for the .mat
reader's tests.

    python3 tests/make_mat.py IN.parquet OUT.mat [--version 5|5z|7.3] [--imaging-weights]
        [--rows] [--unit-m] [--drop FIELD ...] [--single]

As the reference's ms2mat writes them: u, v, w in wavelengths with the MeasurementSet's sign
(`uvw / (c / frequency)`), `y` the raw visibilities, `nW = sqrt(natural weight)` (1/sigma),
`nWimag` the square root of the imaging weights (empty unless --imaging-weights, which writes
a deterministic pattern), `frequency` a scalar (the table must hold one frequency), arrays as
N x 1 columns (--rows: 1 x N, as the pyxis variant writes them).

--version 5: scipy.io.savemat (MAT v5); 5z: the same, compressed; 7.3: HDF5 as MATLAB's
`save -v7.3` writes it (h5py): a 512-byte MAT header as the user block, each variable a
dataset with a MATLAB_class attribute, complex as a compound of `real` and `imag`, arrays
transposed (MATLAB is column-major). --unit-m stores u, v, w in metres with `unit = 'm'`.
--drop removes a field (to make bad input). --single stores y as complex64 and u, v, w as
float32. --folded PATH also writes the same samples as a Parquet table whose natural weights are
the .mat's natural times imaging weights: imaged with natural weighting it is what the .mat is
with the `given` weighting.
"""

import argparse
import sys

import numpy as np
import pyarrow.parquet as pq

C = 299792458.0


def imaging_weights(n):
    """A pattern of square-rooted imaging weights in (0.2, 1]."""
    k = np.arange(n)
    return 0.2 + 0.8 * (0.5 + 0.5 * np.cos(0.37 * k))


def fields(table, args):
    freq = np.unique(table["frequency"])
    if len(freq) != 1:
        sys.exit(f"{args.input}: {len(freq)} frequencies; the reference's .mat holds one channel")
    f = float(freq[0])
    keep = ~table["flag"] if "flag" in table else np.ones(len(table["u"]), bool)
    scale = 1.0 if args.unit_m else f / C
    u = table["u"][keep] * scale
    v = table["v"][keep] * scale
    w = table["w"][keep] * scale
    y = (table["vis_re"][keep] + 1j * table["vis_im"][keep])
    weight = table["weight"][keep] if "weight" in table else np.ones(len(u))
    out = {
        "y": y.astype(np.complex64 if args.single else np.complex128),
        "u": u.astype(np.float32 if args.single else np.float64),
        "v": v.astype(np.float32 if args.single else np.float64),
        "w": w.astype(np.float32 if args.single else np.float64),
        "nW": np.sqrt(weight),
        "nWimag": imaging_weights(len(u)) if args.imaging_weights else np.zeros((0,)),
        "frequency": np.float64(f),
        "maxProjBaseline": np.float64(np.sqrt(np.max(u**2 + v**2))),
    }
    if args.unit_m:
        out["unit"] = "m"
    for name in args.drop:
        out.pop(name, None)
    return out


def shaped(value, rows):
    if isinstance(value, np.ndarray) and value.ndim == 1 and value.size > 0:
        return value.reshape((1, -1) if rows else (-1, 1))
    return value


def write_v73(path, data):
    import h5py

    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in data.items():
            if isinstance(value, str):
                d = f.create_dataset(name, data=np.frombuffer(value.encode("utf-16-le"), np.uint16).reshape(-1, 1))
                d.attrs["MATLAB_class"] = np.bytes_("char")
                d.attrs["MATLAB_int_decode"] = np.int32(2)
                continue
            a = np.atleast_2d(np.asarray(value))
            if a.size == 0:
                # MATLAB writes an empty array as its dimensions with MATLAB_empty set.
                d = f.create_dataset(name, data=np.array([0, 0], np.uint64))
                d.attrs["MATLAB_class"] = np.bytes_("double")
                d.attrs["MATLAB_empty"] = np.uint8(1)
                continue
            a = a.T  # column-major: an N x 1 MATLAB column is a 1 x N dataset
            if np.iscomplexobj(a):
                part = np.float32 if a.dtype == np.complex64 else np.float64
                compound = np.empty(a.shape, dtype=[("real", part), ("imag", part)])
                compound["real"], compound["imag"] = a.real, a.imag
                d = f.create_dataset(name, data=compound, compression="gzip", chunks=True)
                d.attrs["MATLAB_class"] = np.bytes_("single" if part == np.float32 else "double")
            else:
                d = f.create_dataset(name, data=a, compression="gzip" if a.size > 16 else None, chunks=True if a.size > 16 else None)
                d.attrs["MATLAB_class"] = np.bytes_("single" if a.dtype == np.float32 else "double")
    with open(path, "r+b") as f:
        f.write(header.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("input")
    p.add_argument("output")
    p.add_argument("--version", default="5", choices=["5", "5z", "7.3"])
    p.add_argument("--imaging-weights", action="store_true")
    p.add_argument("--rows", action="store_true")
    p.add_argument("--unit-m", action="store_true")
    p.add_argument("--single", action="store_true")
    p.add_argument("--drop", nargs="*", default=[])
    p.add_argument("--folded", help="also write this Parquet table: the .mat's samples with the imaging weights folded into the natural weights")
    args = p.parse_args()
    t = pq.read_table(args.input)
    table = {name: t.column(name).to_numpy(zero_copy_only=False) for name in t.column_names}
    data = {k: shaped(v, args.rows) for k, v in fields(table, args).items()}
    if args.folded:
        import pyarrow as pa

        d = fields(table, args)
        scale = 1.0 if args.unit_m else C / float(d["frequency"])
        iw = d["nWimag"] ** 2 if d["nWimag"].size else 1.0
        out = pa.table({
            "u": np.asarray(d["u"], np.float64) * scale, "v": np.asarray(d["v"], np.float64) * scale, "w": np.asarray(d["w"], np.float64) * scale,
            "frequency": np.full(len(d["u"]), float(d["frequency"])),
            "vis_re": d["y"].real.astype(np.float64), "vis_im": d["y"].imag.astype(np.float64),
            "weight": d["nW"] ** 2 * iw,
        }).replace_schema_metadata(t.schema.metadata)
        pq.write_table(out, args.folded)
    if args.version == "7.3":
        write_v73(args.output, data)
    else:
        import scipy.io

        scipy.io.savemat(args.output, data, do_compression=args.version == "5z", oned_as="column")


if __name__ == "__main__":
    main()
