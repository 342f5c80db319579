"""Optional dependencies, imported only where they are needed.

The core (``Retargeter`` and the stages) needs NumPy, numba and SciPy only. File formats and
previews need the ``cli`` extra (``pip install "minretarget[cli]"``): trimesh reads and writes
PLY and OBJ, matplotlib (with its Pillow) draws PNG and GIF previews, tqdm shows progress,
threadpoolctl sets the BLAS threads.
"""
import importlib

# Module name -> the distribution that provides it, where they differ.
_DISTRIBUTIONS = {"PIL": "Pillow"}


class MissingExtra(ImportError):
    """An optional dependency of the ``cli`` extra is not installed."""


def require(module, purpose):
    """Import ``module`` or raise MissingExtra saying what needs it and how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        package = _DISTRIBUTIONS.get(module, module)
        raise MissingExtra(f"{purpose} needs the package {package!r} ({error}); install "
                           "minretarget's command-line extra: pip install \"minretarget[cli]\"") \
            from None
