# WSClean's `-python-deconvolution` script: R2D2 as WSClean's deconvolver.
#
#   wsclean -python-deconvolution "$(python -m r2d2_imaging.wsclean)" -mgain 0.8 \
#       -niter 1000000 -nmiter 200 -use-wgridder -size 512 512 -scale 0.2asec -weight briggs 0 obs.ms
#
# WSClean runs this file in its own embedded Python, which is not the environment the package
# was installed into: the package's directory is put at the end of the search path (whatever
# WSClean's Python already has, numpy included, comes first), and everything else is in
# r2d2_imaging.wsclean.
import os
import sys

_site = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _site not in sys.path:
    sys.path.append(_site)

try:
    from r2d2_imaging.wsclean import deconvolve  # noqa: F401 (WSClean calls it)
except Exception as e:
    # WSClean 3.1 stops on this without printing it: it is said here first.
    message = (
        f"r2d2_imaging could not be imported into WSClean's Python {sys.version.split()[0]} "
        f"(prefix {sys.prefix}; the package from {_site}): {type(e).__name__}: {e}. The package "
        f"must be installed for the Python WSClean embeds (the same major.minor version; "
        f"`ldd $(which wsclean) | grep python` names it)"
    )
    print(f"r2d2: ERROR: {message}", flush=True)
    print(f"r2d2: ERROR: {message}", file=sys.stderr, flush=True)
    raise ImportError(message) from e
