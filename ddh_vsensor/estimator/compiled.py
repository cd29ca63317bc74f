"""The chamber models' compiled steps (``_chambers.c``, ``_air_chambers.c``): optional
extensions built with the package, loaded with ctypes (no Python API to keep in step)."""

from __future__ import annotations

import ctypes
import importlib.machinery
from pathlib import Path


def package_library(stem: str) -> ctypes.CDLL | None:
    """The compiled library ``stem`` from the package's own directory, or None where the
    install could not build it. Only there: a library loaded from a writable cache or /tmp
    could be planted by another user."""
    here = Path(__file__).parent
    found = (here / f"{stem}{suffix}" for suffix in importlib.machinery.EXTENSION_SUFFIXES)
    path = next((f for f in found if f.is_file()), None)
    return None if path is None else ctypes.CDLL(str(path))
