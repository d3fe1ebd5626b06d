"""r2d2_imaging: radio-interferometric imaging with R2D2 deep-network series, from Python.

A thin layer over the Rust engine (the same one the ``r2d2`` command runs): the engine works
with the GIL released on its own threads, Ctrl-C stops it at the next job boundary, and its
errors are raised as :class:`R2D2Error` carrying the engine's message.

- :func:`run` / :func:`validate`: a YAML pipeline, as ``r2d2 run`` / ``r2d2 validate``.
- :func:`image`: one observation through the default imaging pipeline, as ``r2d2 image``.
- :mod:`r2d2_imaging.dask`: many jobs over the workers of a ``dask.distributed`` cluster.
- ``r2d2.yml`` beside this file: Stimela2 cabs for ``r2d2 image``, ``r2d2 run`` and
  ``r2d2 simulate`` (``_include: (r2d2_imaging)r2d2.yml``).
"""

from __future__ import annotations

import json
import os
from typing import Any, Mapping, Optional, Union

from . import _native
from ._native import R2D2Error

__version__ = _native.__version__
__all__ = ["R2D2Error", "run", "validate", "__version__"]

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

    Returns the run's report: ``jobs`` (ids in completion order), ``seconds`` and
    ``stage_seconds``. Raises :class:`R2D2Error` with the engine's message (stage and job),
    or ``KeyboardInterrupt`` after stopping the engine cleanly on Ctrl-C."""
    text, name = _pipeline_text(pipeline)
    return _native.run(text, name, _overrides(set))
