"""R2D2 inside WSClean: the series as WSClean's deconvolver (``-python-deconvolution``).

WSClean calls ``deconvolve(residual, model, psf, meta)`` once per major cycle and computes the
next residual from the visibilities with its own gridder. R2D2's iteration is that loop: one
network per major cycle, ``x_i = max(0, x_{i-1} + N_i(r_{i-1}, x_{i-1}))``; after the series,
the final CLEAN's cycles (components of both signs on what the networks leave), each ending in
WSClean's next residual. The series, its stop rule and the final CLEAN are the engine's
(``_native.DrivenSeries``); this module maps WSClean's arrays and settings onto them::

    r2d2-wsclean -size 512 512 -scale 0.2asec -weight briggs 0 obs.ms
    # the same as
    wsclean -python-deconvolution "$(python -m r2d2_imaging.wsclean)" -mgain 0.8 \\
        -niter 1000000 -nmiter 200 -padding 2 -use-wgridder -size 512 512 -scale 0.2asec -weight briggs 0 obs.ms

Units: WSClean's residual is in Jy/beam with the PSF's peak 1, its model in Jy/pixel: the
engine's own conventions (its dirty images equal WSClean's), so images pass unscaled.

What WSClean's ``meta`` tells the deconvolver: the channels' frequencies and weights, the
iteration count and limit (``-niter``), the gains and thresholds. It does not tell the pixel
scale, the weighting, the telescope or the observation: on Linux they are read from WSClean's
own command line (``/proc/self/cmdline``: ``-scale``, ``-weight``, the MS) and the MS, as
``r2d2 image`` reads them, for the series' choice and domain check. ``R2D2_WSCLEAN`` (space
separated ``key=value``) sets or overrides them:

- ``series``: a series name, directory or ``auto`` (default);
- ``telescope``, ``superresolution``, ``weighting`` (``briggs``/``natural``/``uniform``),
  ``robust``: the job, where the command line and the MS do not tell;
- ``channels``: with several channels, ``joined`` (default: one series on the weighted mean
  of the channels, WSClean's channel weights, each channel's model the mean's: a flat
  spectrum) or ``each`` (an independent series per channel, each with its own PSF);
- ``final_clean``: ``on`` (default) or ``off``; ``onnx_runtime``: the ONNX Runtime library.

Each major cycle is logged on WSClean's output (``r2d2: ...``) and to the ``r2d2_imaging``
logger; the domain check's warnings also as :class:`r2d2_imaging.R2D2Warning`.
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import warnings
from typing import Optional

import numpy as np

from . import R2D2Warning, _native, _onnx_runtime

log = logging.getLogger("r2d2_imaging.wsclean")

HOOK = os.path.join(os.path.dirname(os.path.abspath(__file__)), "wsclean_hook.py")

_KEYS = {"series", "telescope", "superresolution", "weighting", "robust", "channels", "final_clean", "onnx_runtime", "threads"}


def _options(text: str) -> dict:
    """``R2D2_WSCLEAN``'s ``key=value`` words."""
    out = {}
    for word in text.split():
        key, sep, value = word.partition("=")
        if not sep or key not in _KEYS:
            raise ValueError(f"R2D2_WSCLEAN: expected key=value words with keys {sorted(_KEYS)}, got {word!r}")
        out[key] = value
    return out


_UNITS = {"asec": 1 / 3600, "arcsec": 1 / 3600, "amin": 1 / 60, "arcmin": 1 / 60, "deg": 1.0, "mas": 1 / 3.6e6, "masec": 1 / 3.6e6}


def _angle_deg(text: str) -> float:
    """A WSClean angle (``0.2asec``, ``1amin``, ``0.01deg``; a bare number is degrees)."""
    m = re.fullmatch(r"([0-9.eE+-]+)\s*([a-z]*)", text.strip())
    if not m or (m.group(2) and m.group(2) not in _UNITS):
        raise ValueError(f"WSClean's -scale {text!r}: expected a number and one of {sorted(_UNITS)}")
    return float(m.group(1)) * (_UNITS[m.group(2)] if m.group(2) else 1.0)


def command_line_job(args: list) -> dict:
    """What WSClean's command line ``args`` (without the program) says of the job: ``scale_deg``,
    ``weighting``, ``robust``, ``ms`` (the first measurement set) where given, ``padding`` and
    ``super_weight`` (WSClean's defaults 1.2 and 1 where not)."""
    job: dict = {"weighting": "uniform", "padding": 1.2, "super_weight": 1.0}  # WSClean's defaults
    i = 0
    positional = []
    while i < len(args):
        a = args[i]
        if a in ("-padding", "-super-weight") and i + 1 < len(args):
            job[a[1:].replace("-", "_")] = float(args[i + 1])
            i += 2
            continue
        if a == "-scale" and i + 1 < len(args):
            job["scale_deg"] = _angle_deg(args[i + 1])
            i += 2
            continue
        if a == "-weight" and i + 1 < len(args):
            job["weighting"] = args[i + 1]
            if args[i + 1] == "briggs" and i + 2 < len(args):
                job["robust"] = float(args[i + 2])
                i += 3
                continue
            i += 2
            continue
        if a.startswith("-"):
            i += 1
            continue
        positional.append(a)
        i += 1
    # The measurement sets are the trailing words that are directories (option values are not).
    for word in reversed(positional):
        if os.path.isdir(word):
            job["ms"] = word
    return job


def _wsclean_args() -> list:
    try:
        with open("/proc/self/cmdline", "rb") as f:
            words = f.read().split(b"\0")
    except OSError:
        return []
    return [w.decode(errors="replace") for w in words[1:] if w]


def weighting_grid_problem(size: int, padding: float, super_weight: float, trained: int, series: str) -> Optional[str]:
    """Where WSClean's uniform or Briggs weights (made on a grid of ``padding x size /
    super_weight`` cells) are not made on the grid the series was trained with (twice its
    trained field, ``trained`` pixels across): the same data then have another PSF than the
    series saw. What to give, else None."""
    cells, trained_cells = padding * size / super_weight, 2 * trained
    if abs(cells - trained_cells) <= 0.01 * trained_cells:
        return None
    return (
        f"WSClean weighs on a grid of {cells:.0f} cells across (-padding {padding:g} x {size} / -super-weight {super_weight:g}); "
        f"series {series} was trained with weights on {trained_cells} (twice its {trained} x {trained} field), so the PSF is not one it saw "
        f"and its image may be wrong: give -padding 2 -super-weight {size / trained:g}"
    )


def _say(message: str, level: int = logging.INFO) -> None:
    """On WSClean's output (stdout, where its own log goes) and to the logger."""
    print(f"r2d2: {message}", flush=True)
    log.log(level, message)


def _convolve(image: np.ndarray, psf: np.ndarray) -> np.ndarray:
    """``psf * image`` (linear, the PSF's peak at (N/2, N/2)), by FFT on twice the field."""
    n = image.shape[0]
    m = 2 * n
    a = np.fft.rfft2(image, s=(m, m))
    b = np.fft.rfft2(psf, s=(m, m))
    full = np.fft.irfft2(a * b, s=(m, m))
    c = n // 2
    return full[c : c + n, c : c + n]


class _Job:
    """One imaging job: the series' state over WSClean's major cycles."""

    def __init__(self, residual: np.ndarray, psf: np.ndarray, meta) -> None:
        nchan, npol, height, width = residual.shape
        if npol != 1:
            raise ValueError(f"R2D2 images one polarization (Stokes I): WSClean gave {npol}; run it with -pol I (or without -join-polarizations)")
        if height != width:
            raise ValueError(f"R2D2 images square fields: WSClean's image is {width} x {height}")
        if meta.mgain >= 1.0:
            raise ValueError("R2D2 needs WSClean's major cycles (one network each): give -mgain below 1 (its value is not used otherwise)")
        env = _options(os.environ.get("R2D2_WSCLEAN", ""))
        words = _wsclean_args()
        cmd = command_line_job(words)
        if words and not any(g in words for g in GRIDDERS):
            _say("WARNING: WSClean's default gridder is less exact than the series needs (held-out skies lost 3.4 dB logSNR): give -use-wgridder (r2d2-wsclean adds it)", logging.WARNING)
        self.size = width
        self.nchan = nchan
        self.mode = env.get("channels", "joined")
        if self.mode not in ("joined", "each"):
            raise ValueError(f"R2D2_WSCLEAN: channels={self.mode!r}: expected joined or each")
        domain: dict = {}
        if "ms" in cmd:
            try:
                domain = dict(_native.observation_domain(cmd["ms"]))
            except Exception as e:  # the domain check is advice; imaging goes on without it
                _say(f"could not read {cmd['ms']} for the series' domain check: {e}", logging.WARNING)
        superresolution = env.get("superresolution")
        if superresolution is None and domain.get("max_uv") and "scale_deg" in cmd:
            superresolution = 1.0 / (2.0 * domain["max_uv"] * math.radians(cmd["scale_deg"]))
        weighting = env.get("weighting", cmd.get("weighting"))
        robust = env.get("robust", cmd.get("robust"))
        self.setup = dict(
            telescope=env.get("telescope", domain.get("telescope")),
            superresolution=None if superresolution is None else float(superresolution),
            weighting=weighting,
            robust=None if robust is None else float(robust),
            track_hours=domain.get("track_hours"),
            integration_s=domain.get("integration_s"),
            final_clean=env.get("final_clean", "on") != "off",
            onnx_runtime=env.get("onnx_runtime") or _onnx_runtime(),
            threads=int(env.get("threads", 0)),
        )
        self.series_name = env.get("series", "auto")
        weights = np.array([c.weight for c in meta.channels], dtype=float) if len(meta.channels) == nchan else np.ones(nchan)
        self.weights = weights / weights.sum() if weights.sum() > 0 else np.full(nchan, 1.0 / nchan)
        self.dirty = residual[:, 0].copy()
        self.outcomes: list = []
        if nchan == 1 or self.mode == "joined":
            self.series = [self._start(self._mean(self.dirty), self._mean_psf(psf))]
        else:
            self.series = [self._start(self.dirty[c], psf[c]) for c in range(nchan)]
        self._check_weighting_grid(cmd)
        self.models: list = [None] * len(self.series)
        self.done: list = [None] * len(self.series)
        self.cycles = 0

    def _check_weighting_grid(self, cmd: dict) -> None:
        """Warn where WSClean's weighting grid (its own weighting's, whatever R2D2_WSCLEAN
        tells the domain check) is not the one the series was trained with."""
        if cmd["weighting"] not in ("uniform", "briggs"):
            return
        trained = self.series[0].trained_size
        if trained is None:
            return
        problem = weighting_grid_problem(self.size, cmd["padding"], cmd["super_weight"], trained, self.series[0].series)
        if problem:
            _say(f"WARNING: {problem}", logging.WARNING)
            warnings.warn(problem, R2D2Warning, stacklevel=3)

    def _mean(self, images: np.ndarray) -> np.ndarray:
        return np.tensordot(self.weights, images, axes=1)

    def _mean_psf(self, psf: np.ndarray) -> np.ndarray:
        p = self._mean(psf)
        return p / p.max()

    def _start(self, dirty: np.ndarray, psf: np.ndarray):
        s = self.setup
        series = _native.DrivenSeries(
            self.series_name, self.size, np.ascontiguousarray(dirty, dtype=float).ravel(), np.ascontiguousarray(psf, dtype=float).ravel(),
            telescope=s["telescope"], superresolution=s["superresolution"], weighting=s["weighting"], robust=s["robust"],
            track_hours=s["track_hours"], integration_s=s["integration_s"], final_clean=s["final_clean"],
            onnx_runtime=s["onnx_runtime"], threads=s["threads"],
        )
        for w in series.warnings:
            _say(f"WARNING: {w}", logging.WARNING)
            warnings.warn(w, R2D2Warning, stacklevel=2)
        return series

    def cycle(self, residual: np.ndarray, model_in: np.ndarray, psf: np.ndarray):
        """One major cycle: the models of every channel, whether to go on."""
        first = self.cycles == 0
        self.cycles += 1
        channel_residuals = residual[:, 0]
        for k, series in enumerate(self.series):
            if self.done[k] is not None:
                continue
            if first:
                r = None
            elif len(self.series) == 1 and self.nchan > 1:
                r = np.ascontiguousarray(self._mean(channel_residuals)).ravel()
            else:
                r = np.ascontiguousarray(channel_residuals[k]).ravel()
            model, outcome = series.next(r)
            self.models[k] = model.reshape(self.size, self.size)
            if outcome is not None:
                self.done[k] = outcome
                _say(
                    f"series {series.series}{'' if len(self.series) == 1 else f' (channel {k})'}: {outcome['networks_run']} networks, "
                    f"kept {outcome['kept_network']}, stop {outcome['stop'] or 'none (the whole series)'}, "
                    f"final CLEAN {outcome['final_clean_cycles']} cycles, residual ratio {outcome['residual_ratio']:.4e}"
                )
        if len(self.series) == 1:
            mfs = self.models[0]
            # A flat spectrum: each channel's model is the mean's. Spectra taken from the
            # channels' dirty values were measured worse: there, a pixel's value changes
            # from channel to channel with the sidelobes of every other source (the PSF
            # scales with frequency), not only with its own spectrum.
            models = np.repeat(mfs[None], self.nchan, axis=0)
        else:
            models = np.stack(self.models)
        models = models[:, None]
        # WSClean computes the exact residual at its next major cycle; this is its estimate
        # meanwhile (what it logs as the level reached).
        new_residual = residual.copy()
        for c in range(self.nchan):
            new_residual[c, 0] -= _convolve(models[c, 0] - model_in[c, 0], psf[c])
        finished = all(d is not None for d in self.done)
        if not finished:
            _say(f"major cycle {self.cycles}: model flux {float(np.tensordot(self.weights, models[:, 0].sum(axis=(1, 2)), axes=1)):.4e} Jy")
        return models, new_residual, finished


_JOB: Optional[_Job] = None


def _setup_logging() -> None:
    """The engine's records on WSClean's output, unless the application configured logging."""
    root = logging.getLogger("r2d2_imaging")
    if not any(not isinstance(h, logging.NullHandler) for h in root.handlers) and not logging.getLogger().handlers:
        handler = logging.StreamHandler(sys.stdout)
        handler.setFormatter(logging.Formatter("r2d2: %(message)s"))
        handler.setLevel(logging.WARNING)
        # This module's own records are on WSClean's output already (_say).
        handler.addFilter(lambda record: not record.name.startswith(log.name))
        root.addHandler(handler)
        root.setLevel(logging.INFO)


def deconvolve(residual, model, psf, meta):
    """WSClean's entry point: one major cycle (see the module's documentation). An error is
    said on WSClean's output before it is raised: WSClean 3.1 stops on it without a word."""
    try:
        return _deconvolve(residual, model, psf, meta)
    except Exception as e:
        message = f"ERROR: {type(e).__name__}: {e}"
        print(f"r2d2: {message}", flush=True)
        print(f"r2d2: {message}", file=sys.stderr, flush=True)
        log.error(message)
        raise


def _deconvolve(residual, model, psf, meta):
    global _JOB
    residual = np.asarray(residual, dtype=float)
    model = np.asarray(model, dtype=float)
    psf = np.asarray(psf, dtype=float)
    if _JOB is None:
        _setup_logging()
        if np.any(model != 0):
            raise ValueError("R2D2 starts from the empty model: WSClean gave a model that is not zero (-continue); image without it")
        _JOB = _Job(residual, psf, meta)
        _say(
            f"series {_JOB.series[0].series} ({_JOB.series[0].networks} networks) on {_JOB.size} x {_JOB.size}"
            + (f", {_JOB.nchan} channels {_JOB.mode}" if _JOB.nchan > 1 else "")
            + f"; telescope {_JOB.setup['telescope'] or 'unknown'}, super-resolution "
            + (f"{_JOB.setup['superresolution']:.3g}" if _JOB.setup["superresolution"] else "unknown")
        )
    models, new_residual, finished = _JOB.cycle(residual, model, psf)
    meta.iteration_number = meta.iteration_number + 1
    if meta.iteration_number >= meta.max_iterations and not finished:
        _say(f"WSClean's -niter ({meta.max_iterations}) ends the series before it finished: give -niter 1000000", logging.WARNING)
    return {"residual": new_residual, "model": models, "level": float(np.abs(new_residual).max()), "continue": not finished}


#: WSClean's settings R2D2 needs, added where the command line does not give them: major
#: cycles (-mgain below 1; its value is not used), limits above any series' length plus
#: its final CLEAN's cycles, and the weighting grid the series were trained with.
#: -padding 2: WSClean weighs on a grid of padding x size cells, and the series were trained
#: with weights on a grid of twice the image size (with WSClean's default 1.2, Briggs 0's PSF
#: was 3 % of its peak from the trained one; with 2, 3e-7).
DEFAULTS = {"-mgain": ["0.8"], "-niter": ["1000000"], "-nmiter": ["200"], "-padding": ["2"]}

#: WSClean's gridder options: without one, `-use-wgridder` is added. The networks see each
#: major cycle's residual; with WSClean's default w-stacking gridder (about 2e-3 of the dirty
#: image from the exact one) the held-out skies' logSNR came out 3.4 dB below `r2d2 image`'s,
#: with the w-gridder equal to it.
GRIDDERS = ("-use-wgridder", "-use-idg", "-gridder")


def served_off_its_trained_size(size: int) -> Optional[int]:
    """The trained size of the series ``auto`` takes for ``size x size`` images where it runs
    off its trained size (the job then weighs on that trained field's uv grid), else None: the
    engine's own choice, with nothing else of the job known. The job's telescope and setting
    are not known here: where ``auto`` then takes another series, the hook warns about the
    weighting grid, naming what to give."""
    return _native.auto_series(size)[1]


def wsclean_command(args: list) -> list:
    """``wsclean`` with this deconvolver, :data:`DEFAULTS` where ``args`` lacks them and the
    w-gridder unless ``args`` chooses a gridder. Where ``auto``'s series runs off its trained
    size (``vla-r2d2-512`` at 64, 96, 128 and 192, ``vla-r2d2-128`` at 32), and neither ``-super-weight`` nor
    a series in ``R2D2_WSCLEAN`` is given, ``-super-weight`` puts WSClean's weighting grid on
    the series' trained field, as ``r2d2 image`` weighs there."""
    command = ["wsclean", "-python-deconvolution", HOOK]
    for option, values in DEFAULTS.items():
        if option not in args:
            command += [option, *values]
    if not any(g in args for g in GRIDDERS):
        command.append("-use-wgridder")
    try:
        named = _options(os.environ.get("R2D2_WSCLEAN", "")).get("series", "auto") != "auto"
    except ValueError:
        named = True  # the hook says what is wrong with R2D2_WSCLEAN
    if "-size" in args and "-super-weight" not in args and not named:
        # Anything wrong on the command line is WSClean's to report, not this helper's.
        try:
            size = int(args[args.index("-size") + 1])
            trained = served_off_its_trained_size(size)
            if trained is not None:
                padding = command_line_job(args)["padding"] if "-padding" in args else float(DEFAULTS["-padding"][0])
                command += ["-super-weight", f"{padding * size / (2 * trained):g}"]
        except (ValueError, IndexError, OverflowError, _native.R2D2Error):
            pass
    return command + list(args)


def main(argv: Optional[list] = None) -> int:
    """``python -m r2d2_imaging.wsclean`` (or ``r2d2-wsclean``): with no arguments (or
    ``--path``), prints the path of the script to give WSClean's ``-python-deconvolution``;
    with WSClean's arguments, runs WSClean with it (and -mgain 0.8 -niter 1000000 -nmiter 200
    -padding 2 where not given, -use-wgridder unless a gridder is chosen, and -super-weight
    where ``auto``'s series runs off its trained size: :func:`wsclean_command`)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args == ["--path"]:
        print(HOOK)
        return 0
    if args[0] in ("-h", "--help"):
        print(main.__doc__)
        return 0
    import subprocess

    command = wsclean_command(args)
    print("r2d2: " + " ".join(command), flush=True)
    # WSClean's embedded Python takes its prefix (the standard library, site-packages) from the
    # first `python3` on PATH: this interpreter's, so that it sees this environment (numpy,
    # this package) and not whichever Python comes first (a conda or pyenv one lacking them).
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([os.path.dirname(sys.executable), env.get("PATH", "")])
    # WSClean's Python may not see this environment's onnxruntime: its library is named.
    runtime = _onnx_runtime()
    if runtime and "onnx_runtime=" not in env.get("R2D2_WSCLEAN", ""):
        env["R2D2_WSCLEAN"] = f"{env.get('R2D2_WSCLEAN', '')} onnx_runtime={runtime}".strip()
    try:
        return subprocess.run(command, env=env).returncode
    except FileNotFoundError:
        print("r2d2: wsclean is not on PATH (Debian/Ubuntu: apt-get install wsclean)", file=sys.stderr)
        return 127


if __name__ == "__main__":
    sys.exit(main())
