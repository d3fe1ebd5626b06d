"""Writes a MeasurementSet (python-casacore) from a visibility Parquet table, for the MS tests.

    python3 tests/make_ms.py IN.parquet OUT.ms [--corr XX,YY] [--spw K] [--weights spectrum]
        [--flag-hands both] [--stman ssm] [--fields 1] [--autocorrelations]
        [--data-column DATA] [--drop TABLE_OR_COLUMN ...]

Follows benches/vs_wsclean.py's writer: one row per (time, antenna1, antenna2) of the table
(it needs the `time`, `antenna1`, `antenna2` columns that `r2d2 simulate` writes), the
distinct frequencies as channels, UVW in metres. The MS is built so that the engine's Stokes I
of it is exactly the table's samples:

- Both hands of I (XX and YY, or RR and LL) hold the table's visibility, each with half the
  table's weight: I = (A + B) / 2 has weight 4 / (1/wA + 1/wB) = the table's weight. Cross
  hands (4 correlations) hold junk that must not reach I. `--corr XX,XY` has no I.
- `--spw K` cuts the channels into K windows: each row becomes K rows, one per DATA_DESC_ID.
- `--weights spectrum` writes WEIGHT_SPECTRUM; `row` only WEIGHT (the table's weights must
  then be the same over a row's channels); `sigma` only SIGMA (WEIGHT removed);
  `empty-spectrum` WEIGHT and a variable-shape WEIGHT_SPECTRUM column never written.
- `--flag-hands one` flags a flagged sample in one hand only (alternating), the other hand
  keeping valid data: the reader must still exclude it. Channels a row lacks are flagged.
- `--stman mixed` stores DATA, FLAG and WEIGHT_SPECTRUM with TiledColumnStMan and the
  scalar columns with IncrementalStMan (default: StandardStMan, as default_ms); `--stman dp3`
  as DP3 writes an MS: the same, with the array column FLAG_CATEGORY in the scalars'
  IncrementalStMan; `--stman meerkat` as MeerKAT's pipelines write one: the data as `mixed`,
  and `WEIGHT` and `SIGMA` in a TiledShapeStMan.
- `--fields 2` adds a second field (named `OTHER`) with junk rows; the first is `TARGET`.
- `--autocorrelations` adds antenna i-i rows with junk, which must be excluded.
- `--data-column NAME` puts the table's visibilities in NAME (e.g. CORRECTED_DATA) and junk
  in DATA.
- `--drop X` removes a subtable (`POLARIZATION`) or a main-table column (`UVW`) afterwards,
  to make bad input.
"""

import argparse
import math
import os
import shutil
import sys

import numpy as np
from casacore.tables import default_ms, makearrcoldesc, maketabdesc, table

# The benchmark's MS writer reads Parquet tables the same way.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benches"))
from vs_wsclean import read_table, table_samples  # noqa: E402

CORR_CODES = {"I": 1, "Q": 2, "U": 3, "V": 4, "RR": 5, "RL": 6, "LR": 7, "LL": 8,
              "XX": 9, "XY": 10, "YX": 11, "YY": 12}
MJD_OFFSET_S = 4.9e9  # seconds: MS times are MJD seconds; any offset works for the tests


def parse_args():
    p = argparse.ArgumentParser()
    p.add_argument("parquet")
    p.add_argument("ms")
    p.add_argument("--corr", default="XX,YY")
    p.add_argument("--spw", type=int, default=1)
    p.add_argument("--weights", choices=["spectrum", "row", "sigma", "empty-spectrum"], default="spectrum")
    p.add_argument("--flag-hands", choices=["both", "one"], default="both")
    p.add_argument("--stman", choices=["ssm", "mixed", "dp3", "meerkat"], default="ssm")
    p.add_argument("--fields", type=int, choices=[1, 2], default=1)
    p.add_argument("--autocorrelations", action="store_true")
    p.add_argument("--data-column", default="DATA")
    p.add_argument("--interval", type=float, default=30.0, help="INTERVAL and EXPOSURE of every row, seconds")
    p.add_argument("--drop", action="append", default=[])
    return p.parse_args()


def hands(corr):
    """Indices of the two hands forming I (or the one I correlation), or None."""
    if "I" in corr:
        return [corr.index("I")]
    for a, b in (("XX", "YY"), ("RR", "LL")):
        if a in corr and b in corr:
            return [corr.index(a), corr.index(b)]
    return None


def main():
    args = parse_args()
    corr = args.corr.split(",")
    cols, meta = read_table(args.parquet)
    for need in ("time", "antenna1", "antenna2"):
        if need not in cols:
            sys.exit(f"{args.parquet}: no `{need}` column (use a table from `r2d2 simulate`)")
    n, chans, ch, weight, flag, vis = table_samples(cols)

    keys = np.stack([cols["time"], cols["antenna1"], cols["antenna2"]], axis=1).astype(np.float64)
    rows, first, row_of = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    row_of = row_of.ravel()
    nbase, nchan = len(rows), len(chans)
    if np.any(np.bincount(row_of * nchan + ch, minlength=nbase * nchan) > 1):
        sys.exit(f"{args.parquet}: more than one sample per (time, antenna1, antenna2, frequency)")
    uvw = np.zeros((nbase, 3))
    for j, name in enumerate("uvw"):
        uvw[row_of, j] = cols[name]

    ncorr = len(corr)
    h = hands(corr) or [0, min(1, ncorr - 1)]
    data = np.full((nbase, nchan, ncorr), 7.0 - 3.0j, np.complex64)  # junk in the cross hands
    wspec = np.ones((nbase, nchan, ncorr), np.float32)
    fl = np.zeros((nbase, nchan, ncorr), bool)
    fl[:, :, h] = True  # channels a row lacks stay flagged
    for k, p in enumerate(h):
        data[row_of, ch, p] = vis
        wspec[row_of, ch, p] = weight / len(h) if len(h) == 2 else weight
        if args.flag_hands == "both":
            fl[row_of, ch, p] = flag
        else:
            # One hand per flagged sample, alternating; the other hand unflagged.
            fl[row_of, ch, p] = flag & ((row_of + ch) % 2 == k)
    if args.weights != "spectrum":
        spread = np.ptp(np.where(fl, np.nan, wspec), axis=1)
        if np.nanmax(np.nan_to_num(spread, nan=0.0)) > 0:
            sys.exit(f"{args.parquet}: weights differ over a row's channels; use --weights spectrum")
    wrow = np.where(fl, 0, wspec).max(axis=1)  # [nbase, ncorr]: the (common) per-channel weight

    # Windows: contiguous channel ranges, each row repeated once per window.
    bounds = np.linspace(0, nchan, args.spw + 1).round().astype(int)
    if np.any(np.diff(bounds) == 0):
        sys.exit(f"--spw {args.spw}: more windows than the {nchan} channels")
    widths = [b - a for a, b in zip(bounds[:-1], bounds[1:])]
    if len(set(widths)) != 1:
        sys.exit(f"--spw {args.spw}: {nchan} channels do not divide into equal windows")
    wchan = widths[0]
    # `r2d2 simulate` writes MJD seconds; a table of seconds from its start is moved to a date.
    offset = MJD_OFFSET_S if rows[:, 0].max() < MJD_OFFSET_S / 2 else 0.0
    times, a1, a2 = offset + rows[:, 0], rows[:, 1].astype(np.int32), rows[:, 2].astype(np.int32)

    def per_window(x):
        return np.concatenate([x[:, a:b] for a, b in zip(bounds[:-1], bounds[1:])], axis=0)

    def repeat(x):
        return np.concatenate([x] * args.spw, axis=0)

    m_data, m_wspec, m_flag = per_window(data), per_window(wspec), per_window(fl)
    m_time, m_a1, m_a2, m_uvw = repeat(times), repeat(a1), repeat(a2), repeat(uvw)
    m_ddid = np.repeat(np.arange(args.spw, dtype=np.int32), nbase)
    m_field = np.zeros(len(m_time), np.int32)
    m_wrow = np.concatenate([wrow] * args.spw, axis=0)

    def append(extra_time, extra_a1, extra_a2, extra_uvw, ddid, field):
        nonlocal m_data, m_wspec, m_flag, m_time, m_a1, m_a2, m_uvw, m_ddid, m_field, m_wrow
        k = len(extra_time)
        m_data = np.concatenate([m_data, np.full((k, wchan, ncorr), 100.0 + 50j, np.complex64)])
        m_wspec = np.concatenate([m_wspec, np.ones((k, wchan, ncorr), np.float32)])
        m_flag = np.concatenate([m_flag, np.zeros((k, wchan, ncorr), bool)])
        m_time = np.concatenate([m_time, extra_time])
        m_a1 = np.concatenate([m_a1, extra_a1.astype(np.int32)])
        m_a2 = np.concatenate([m_a2, extra_a2.astype(np.int32)])
        m_uvw = np.concatenate([m_uvw, extra_uvw])
        m_ddid = np.concatenate([m_ddid, np.full(k, ddid, np.int32)])
        m_field = np.concatenate([m_field, np.full(k, field, np.int32)])
        m_wrow = np.concatenate([m_wrow, np.ones((k, ncorr))])

    if args.autocorrelations:
        ants = np.unique(np.concatenate([a1, a2]))[:5]
        append(np.full(len(ants), times[0]), ants, ants, np.zeros((len(ants), 3)), 0, 0)
    if args.fields == 2:
        k = min(50, nbase)
        append(times[:k] + 1.0, a1[:k], a2[:k], uvw[:k] * 0.5, 0, 1)

    nrow = len(m_time)
    if os.path.exists(args.ms):
        shutil.rmtree(args.ms)
    columns = [makearrcoldesc("DATA", 0j, valuetype="complex", shape=[wchan, ncorr]),
               makearrcoldesc("FLAG", False, valuetype="boolean", shape=[wchan, ncorr])]
    if args.data_column != "DATA":
        columns.append(makearrcoldesc(args.data_column, 0j, valuetype="complex", shape=[wchan, ncorr]))
    if args.weights == "spectrum":
        columns.append(makearrcoldesc("WEIGHT_SPECTRUM", 0.0, valuetype="float", shape=[wchan, ncorr]))
    elif args.weights == "empty-spectrum":
        columns.append(makearrcoldesc("WEIGHT_SPECTRUM", 0.0, valuetype="float", ndim=2))
    desc = maketabdesc(columns)
    if args.stman == "dp3":
        columns.append(makearrcoldesc("FLAG_CATEGORY", False, valuetype="boolean", ndim=3))
        desc = maketabdesc(columns)
    dminfo = None
    if args.stman in ("mixed", "dp3", "meerkat"):
        tiled = [c for c in ("DATA", args.data_column, "FLAG", "WEIGHT_SPECTRUM")
                 if c == "FLAG" or c in [d["name"] for d in columns]]
        dminfo = {"*1": {"TYPE": "IncrementalStMan", "NAME": "ISM", "SPEC": {"BUCKETSIZE": 32768},
                         "COLUMNS": ["TIME", "ANTENNA1", "ANTENNA2", "FIELD_ID", "DATA_DESC_ID"]
                         + (["FLAG_CATEGORY"] if args.stman == "dp3" else [])}}
        for i, c in enumerate(dict.fromkeys(tiled)):
            dminfo[f"*{i + 2}"] = {"TYPE": "TiledColumnStMan", "NAME": f"Tiled{c}",
                                   "SPEC": {"DEFAULTTILESHAPE": np.array([ncorr, wchan, 64], np.int32)},
                                   "COLUMNS": [c]}
        if args.stman == "meerkat":
            dminfo["*99"] = {"TYPE": "TiledShapeStMan", "NAME": "TiledWeightSigma",
                             "SPEC": {"DEFAULTTILESHAPE": np.array([ncorr, 1024], np.int32)},
                             "COLUMNS": ["WEIGHT", "SIGMA"]}
    ms = default_ms(args.ms, desc, dminfo) if dminfo else default_ms(args.ms, desc)
    ms.addrows(nrow)
    ms.putcol("TIME", m_time)
    ms.putcol("TIME_CENTROID", m_time)
    ms.putcol("INTERVAL", np.full(nrow, args.interval))
    ms.putcol("EXPOSURE", np.full(nrow, args.interval))
    ms.putcol("ANTENNA1", m_a1)
    ms.putcol("ANTENNA2", m_a2)
    ms.putcol("UVW", m_uvw)
    if args.data_column != "DATA":
        ms.putcol(args.data_column, m_data)
        ms.putcol("DATA", np.full_like(m_data, 3.0 + 1j))
    else:
        ms.putcol("DATA", m_data)
    ms.putcol("FLAG", m_flag)
    if args.stman == "dp3":
        # As DP3 writes it: one category, every cell defined, in the scalars' ISM.
        ms.putcol("FLAG_CATEGORY", np.zeros((nrow, 1, wchan, ncorr), bool))
    ms.putcol("FLAG_ROW", m_flag.all(axis=(1, 2)))
    if args.weights == "spectrum":
        ms.putcol("WEIGHT_SPECTRUM", m_wspec)
    ms.putcol("WEIGHT", m_wrow.astype(np.float32))
    sigma = np.where(m_wrow > 0, 1 / np.sqrt(np.maximum(m_wrow, 1e-300)), 0)
    ms.putcol("SIGMA", sigma.astype(np.float32))
    ms.putcol("DATA_DESC_ID", m_ddid)
    ms.putcol("FIELD_ID", m_field)
    for c in ("ARRAY_ID", "OBSERVATION_ID", "FEED1", "FEED2", "PROCESSOR_ID", "SCAN_NUMBER"):
        ms.putcol(c, np.zeros(nrow, np.int32))
    ms.putcol("STATE_ID", np.full(nrow, -1, np.int32))
    if args.weights == "sigma":
        ms.removecols(["WEIGHT"])
    ms.close()

    nant = int(max(m_a1.max(), m_a2.max())) + 1
    ant = table(args.ms + "/ANTENNA", readonly=False, ack=False)
    ant.addrows(nant)
    ant.putcol("NAME", [f"ANT{k:02d}" for k in range(nant)])
    ant.putcol("STATION", [f"ST{k:02d}" for k in range(nant)])
    ant.putcol("POSITION", np.zeros((nant, 3)))
    ant.putcol("DISH_DIAMETER", np.full(nant, 25.0))
    ant.close()

    spw = table(args.ms + "/SPECTRAL_WINDOW", readonly=False, ack=False)
    dd = table(args.ms + "/DATA_DESCRIPTION", readonly=False, ack=False)
    spw.addrows(args.spw)
    dd.addrows(args.spw)
    step = np.diff(chans).min() if nchan > 1 else 1e6
    for s, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        f = chans[a:b]
        w = np.full(len(f), step)
        spw.putcell("NUM_CHAN", s, len(f))
        spw.putcell("CHAN_FREQ", s, f)
        spw.putcell("CHAN_WIDTH", s, w)
        spw.putcell("EFFECTIVE_BW", s, w)
        spw.putcell("RESOLUTION", s, w)
        spw.putcell("REF_FREQUENCY", s, float(f[0]))
        spw.putcell("TOTAL_BANDWIDTH", s, float(w.sum()))
        spw.putcell("MEAS_FREQ_REF", s, 5)
        spw.putcell("NAME", s, f"SPW{s}")
        dd.putcell("SPECTRAL_WINDOW_ID", s, s)
        dd.putcell("POLARIZATION_ID", s, 0)
    spw.close()
    dd.close()

    pol = table(args.ms + "/POLARIZATION", readonly=False, ack=False)
    pol.addrows(1)
    pol.putcell("NUM_CORR", 0, ncorr)
    pol.putcell("CORR_TYPE", 0, np.array([CORR_CODES[c] for c in corr], np.int32))
    pol.putcell("CORR_PRODUCT", 0, np.zeros((ncorr, 2), np.int32))
    pol.close()

    ra = math.radians(float(meta["phase_centre_ra_deg"]))
    dec = math.radians(float(meta["phase_centre_dec_deg"]))
    field = table(args.ms + "/FIELD", readonly=False, ack=False)
    field.addrows(args.fields)
    for f, name in zip(range(args.fields), ("TARGET", "OTHER")):
        direction = np.array([[ra + 0.1 * f, dec]])
        for c in ("PHASE_DIR", "DELAY_DIR", "REFERENCE_DIR"):
            field.putcell(c, f, direction)
        field.putcell("NAME", f, name)
        field.putcell("SOURCE_ID", f, -1)
    field.close()

    obs = table(args.ms + "/OBSERVATION", readonly=False, ack=False)
    obs.addrows(1)
    obs.putcell("TELESCOPE_NAME", 0, meta.get("telescope", "VLA"))
    obs.putcell("TIME_RANGE", 0, np.array([m_time.min(), m_time.max()]))
    obs.putcell("OBSERVER", 0, "tests/make_ms.py")
    obs.close()

    for name in args.drop:
        if os.path.isdir(os.path.join(args.ms, name)):
            shutil.rmtree(os.path.join(args.ms, name))
            # The keyword linking it stays: the reader must say the subtable is missing.
        else:
            ms = table(args.ms, readonly=False, ack=False)
            ms.removecols([name])
            ms.close()
    print(f"{args.ms}: {nrow} rows, {wchan} channels x {args.spw} windows, {ncorr} correlations")


if __name__ == "__main__":
    main()
