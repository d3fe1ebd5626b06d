"""r2d2_imaging: radio-interferometric imaging with R2D2 deep-network series, from Python.

A thin layer over the Rust engine (the same one the ``r2d2`` command runs): the engine works
with the GIL released on its own threads, Ctrl-C stops it at the next job boundary, and its
errors are raised as :class:`R2D2Error` carrying the engine's message and its causes. Errors of
a FITS image, a model series, an ONNX network, a native plugin, a MeasurementSet or a
visibility table (Parquet, Arrow) raise the subclass for that kind (:class:`FitsError`,
:class:`SeriesError`, :class:`OnnxError`, :class:`PluginError`, :class:`MeasurementSetError`,
:class:`TableError`).

- :func:`run` / :func:`validate`: a YAML pipeline, as ``r2d2 run`` / ``r2d2 validate``.
- :func:`image`: one observation through the default imaging pipeline, as ``r2d2 image``.
- :func:`info`: the build, the inference backend and the series found, as ``r2d2 info``.
- Logging: the engine's log records go to :mod:`logging` (logger ``r2d2_imaging``); its
  warnings about a job are also raised as :class:`R2D2Warning` through :mod:`warnings`.
- :mod:`r2d2_imaging.dask`: many jobs over the workers of a ``dask.distributed`` cluster.
- Worker processes: start them with ``multiprocessing.get_context("spawn")`` (or
  ``"forkserver"``). A process forked after the engine ran in its parent (Linux's default
  ``fork``) has none of the engine's compute threads; the engine raises :class:`R2D2Error`
  there, saying so, instead of waiting for ever on them.
- ``r2d2.yml`` beside this file: Stimela2 cabs for ``r2d2 image``, ``r2d2 run`` and
  ``r2d2 simulate`` (``_include: (r2d2_imaging)r2d2.yml``).
"""

from __future__ import annotations

import json
import logging
import os
import warnings
from typing import Any, Mapping, Optional, Union

from . import _native
from ._native import (
    FitsError,
    MeasurementSetError,
    OnnxError,
    PluginError,
    Products,
    R2D2Error,
    SeriesError,
    TableError,
)

__version__ = _native.__version__

# The engine's log records reach Python's `logging` under this logger (and its children, by
# engine module: `r2d2_imaging.stages.residual`, ...), at the level it is set to; a library
# prints nothing on its own, so it has a NullHandler until the application configures
# logging. Job warnings are also raised through `warnings` (R2D2Warning).
logging.getLogger("r2d2_imaging").addHandler(logging.NullHandler())

# Series shipped in the package (the project's own), looked up after the engine's own places
# (none of them when R2D2_MODELS is set), so an installed package images without setup.
_PACKAGE_MODELS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "models")
if os.path.isdir(_PACKAGE_MODELS):
    _native.add_model_dir(_PACKAGE_MODELS)


class R2D2Warning(UserWarning):
    """A warning the engine raised about a job (outside its series' domain, a diverging
    series stopped and the data imaged by the final CLEAN alone), as the command line logs
    it: it is also in the products' ``metrics["warnings"]``."""
__all__ = [
    "R2D2Warning",
    "R2D2Error",
    "FitsError",
    "SeriesError",
    "OnnxError",
    "PluginError",
    "MeasurementSetError",
    "TableError",
    "Products",
    "image",
    "image_options",
    "info",
    "run",
    "validate",
    "__version__",
]

PathLike = Union[str, "os.PathLike[str]"]


def _pipeline_text(pipeline: PathLike) -> tuple[str, str]:
    """The YAML text and the name errors give it: a path is read; a string holding a newline
    is the YAML itself (named ``<string>``)."""
    if isinstance(pipeline, str) and "\n" in pipeline:
        return pipeline, "<string>"
    path = os.fspath(pipeline)
    with open(path, encoding="utf-8") as f:
        return f.read(), path


def _overrides(set: Optional[Mapping[str, Any]]) -> list[str]:
    """``{"image.size": 256, "write.prefix": "out/{job}"}`` as ``r2d2 run --set`` takes them:
    each value written as JSON, which YAML reads back as the same value."""
    if not set:
        return []
    return [f"{key}={json.dumps(os.fspath(v) if isinstance(v, os.PathLike) else v)}" for key, v in set.items()]


def validate(pipeline: PathLike, set: Optional[Mapping[str, Any]] = None) -> list[str]:
    """Check a pipeline (a YAML file, or YAML text) without running it, as ``r2d2 validate``;
    returns its stage names. Raises :class:`R2D2Error` naming the file, line and column."""
    text, name = _pipeline_text(pipeline)
    return _native.validate(text, name, _overrides(set))


def run(pipeline: PathLike, set: Optional[Mapping[str, Any]] = None) -> dict:
    """Run a pipeline (a YAML file, or YAML text) as ``r2d2 run`` does, with ``set``
    overriding values (``{"image.size": 256}``, as ``--set image.size=256``).

    Returns the run's report: ``jobs`` (ids in completion order), ``metrics`` (job id -> its
    metrics as the writer wrote them to ``<prefix>-metrics.json``: residual ratio, SNR, logSNR
    and seconds per iteration), ``seconds`` and ``stage_seconds``. Raises :class:`R2D2Error`
    with the engine's message (stage and job), or ``KeyboardInterrupt`` after stopping the
    engine cleanly on Ctrl-C."""
    text, name = _pipeline_text(pipeline)
    report = _native.run(text, name, _overrides(set), _onnx_runtime())
    files = report.pop("metrics_files")
    report["metrics"] = {}
    for job in report["jobs"]:
        for path in files[job]:
            with open(path, encoding="utf-8") as f:
                report["metrics"][job] = json.load(f)
    return report


def _onnx_runtime() -> Optional[str]:
    """The native ONNX Runtime library for series steps (the engine loads only the one it is
    given, else runs the networks on tract): ORT_DYLIB_PATH, else this interpreter's
    `onnxruntime` package's library, else None."""
    if os.environ.get("ORT_DYLIB_PATH"):
        return os.environ["ORT_DYLIB_PATH"]
    import importlib.util

    spec = importlib.util.find_spec("onnxruntime")
    if spec is None or not spec.submodule_search_locations:
        return None
    capi = os.path.join(list(spec.submodule_search_locations)[0], "capi")
    try:
        names = sorted(n for n in os.listdir(capi) if n.startswith("libonnxruntime.so") or n.startswith("libonnxruntime") and n.endswith(".dylib") or n == "onnxruntime.dll")
    except OSError:
        return None
    return os.path.join(capi, names[-1]) if names else None


def info() -> dict:
    """What this build and machine will use, as ``r2d2 info`` and ``r2d2 models`` tell it:
    ``version``, ``gridder_simd``, ``threads``, ``onnx_backend`` (what ``backend="auto"``
    runs networks on, with this interpreter's ``onnxruntime`` where installed),
    ``model_dirs`` (where series are looked up, in order) and ``series`` (each usable one
    found: ``name``, ``path``, ``networks``, ``image_sizes``, ``telescope``, ``domain``)."""
    return _native.info(_onnx_runtime())


def image(obs, *, id: Optional[str] = None, onnx_runtime: Optional[PathLike] = None, **options):
    """Image one observation as ``r2d2 image`` does, in this process.

    ``obs`` is a path (Parquet, Arrow IPC, MeasurementSet) or a table in the documented
    visibility schema with the observation's metadata on its schema: a ``pyarrow.Table`` or
    ``RecordBatchReader`` (anything with ``__arrow_c_stream__``), read through the Arrow C
    stream without copying its buffers. ``id`` names the job (default: the file name without
    its extension, or ``table``); ``onnx_runtime`` is the ONNX Runtime library (default: the
    ``onnxruntime`` package's, where installed).

    ``options`` are ``r2d2 image``'s options, every one of them, by the name they have on the
    command line with ``_`` for ``-`` (:func:`image_options` lists them; ``r2d2 image --help``
    says what each does): ``size``, ``step`` (``"auto"``, ``"clean"``, a series name or
    directory, or a plugin library), ``iterations``, ``weighting`` and ``robust``,
    ``superresolution`` or ``pixel_arcsec``, ``truth``, ``threads`` (0: every core),
    ``w_term``, WSClean's CLEAN controls (``niter``, ``gain``, ``mgain``, ``auto_threshold``,
    ``threshold``, ``auto_mask``), a mask (``fits_mask``), the MeasurementSet's ``data_column``, ``field``, ``spw``, ``channels`` and
    ``model_column``, ``name`` (also write the products at this prefix), ... A switch is named
    for what it turns on: ``final_clean=False`` is ``--no-final-clean``, ``prefetch=False``
    ``--no-prefetch``. ``None`` leaves an option at its default. The engine checks each as the
    command line does, and its errors name the option.

    Returns :class:`Products`: ``dirty``, ``psf``, ``model``, ``residual`` (and ``image`` for
    CLEAN) as float32 arrays (N, N) in FITS orientation (row 0 at the bottom, as astropy reads
    the files), owned by numpy without a copy; ``metrics``; ``header``; ``write(prefix)``.
    With ``channels_out=N`` (a MeasurementSet), a list: each channel group's :class:`Products`,
    lowest frequency first, then the whole band's with ``join_channels=True``.
    The engine runs with the GIL released; Ctrl-C stops it and raises KeyboardInterrupt;
    its errors raise :class:`R2D2Error`."""
    if not isinstance(obs, (str, os.PathLike, _native.Parts)) and not hasattr(obs, "__arrow_c_stream__"):
        raise TypeError(f"obs: expected a path or an Arrow table (pyarrow.Table, RecordBatchReader), got {type(obs).__name__}")
    every = _native.image(
        os.fspath(obs) if isinstance(obs, os.PathLike) else obs,
        [(name, _option_value(value)) for name, value in options.items() if value is not None],
        id=id, onnx_runtime=os.fspath(onnx_runtime) if onnx_runtime is not None else _onnx_runtime())
    for products in every:
        for message in products.metrics.get("warnings", []):
            warnings.warn(f"job {products.id}: {message}", R2D2Warning, stacklevel=2)
    return every if options.get("channels_out") not in (None, 1) else every[0]


def image_options() -> list:
    """The names of :func:`image`'s options: every option of ``r2d2 image``."""
    return _native.image_options()


def _option_value(value):
    """An option's value as the engine parses it: a switch, or the words of its value."""
    if isinstance(value, bool):
        return value
    if isinstance(value, (list, tuple)):
        return [_option_word(v) for v in value]
    return [_option_word(value)]


def _option_word(value) -> str:
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, float):
        return repr(value)
    return str(value)
