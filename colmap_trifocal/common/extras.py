"""The optional dependencies (pip extras) and the one-line error when one is missing.

``pip install colmap-trifocal`` installs what calibration, mapping and the demo need.
Drawing (Open3D for ``show`` and ``run --png``; matplotlib for the plots of ``evaluate``,
``synthetic`` and the notebooks) is the extra ``viz``, a Dask cluster (``--dask``) the
extra ``dask``; ``all`` is both. A command checks its extras before any work.
"""

from __future__ import annotations

import importlib.util

from .errors import CalibrationError

#: module imported -> (the extra that installs it, the package's name for people).
EXTRAS = {
    "open3d": ("viz", "Open3D"),
    "matplotlib": ("viz", "matplotlib"),
    "distributed": ("dask", "Dask"),
}


def is_installed(module: str) -> bool:
    """Whether ``module`` can be imported here (found on the path; not imported)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # ValueError: a module set to None in sys.modules
        return False


def missing_extra(module: str, purpose: str) -> CalibrationError:
    """The error for ``purpose`` (``show``, ``--dask``, ...) without ``module``: one line
    naming the extra to install."""
    extra, name = EXTRAS[module]
    return CalibrationError(
        f"{purpose} needs {name}, which is not installed: "
        f"pip install 'colmap-trifocal[{extra}]' (or [all])"
    )


def require_extra(module: str, purpose: str) -> None:
    """Raise :func:`missing_extra`'s error unless ``module`` is installed."""
    if not is_installed(module):
        raise missing_extra(module, purpose)
