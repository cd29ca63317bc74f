"""The package's compiled libraries (C loaded with ctypes, no Python API to keep in step),
found in the package's own directories only: a library loaded from a writable cache or /tmp
could be planted by another user."""

from __future__ import annotations

import ctypes
import importlib.machinery
from pathlib import Path

_ROOT = Path(__file__).parent


def package_library(module: str) -> ctypes.CDLL | None:
    """The compiled library of ``module`` (``ddh_vsensor.room._name``), or None where the
    install could not build it."""
    *rooms, stem = module.split(".")[1:]
    here = _ROOT.joinpath(*rooms)
    found = (here / f"{stem}{suffix}" for suffix in importlib.machinery.EXTENSION_SUFFIXES)
    path = next((f for f in found if f.is_file()), None)
    return None if path is None else ctypes.CDLL(str(path))


def required_library(module: str) -> ctypes.CDLL:
    """:func:`package_library` of a library the package cannot run without: ImportError,
    saying what to do, where the install could not build it."""
    lib = package_library(module)
    if lib is None:
        raise ImportError(f"{module} was not built: install a C compiler (gcc) and reinstall "
                          "ddh-vsensor (in a checkout: python setup.py build_ext --inplace)")
    return lib
