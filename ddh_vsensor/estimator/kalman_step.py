"""The Kalman filter's compiled sample (``_kalman.c``, the unit model's ``_unit.c`` compiled
in): the library, and numpy records of its structs built from the C's own field tables (name,
offset, size, C type), so no Python copy of a layout exists to drift from the C. A record is
filled by field name, every field named once: a field added to the C and not set here, or set
here and gone from the C, is an error, not a zero."""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from ddh_vsensor.compiled import required_library
from ddh_vsensor.model.unit import check_layouts

KINDS = ("settings", "unit", "filter", "arrays")
_FORMATS = {"double": np.float64, "int": np.int32, "long": np.int64, "const double *": np.uintp,
            "double *": np.uintp, "unsigned char *": np.uintp,
            "const unsigned char *": np.uintp}

_LIB: ctypes.CDLL | None = None
_DTYPES: dict[str, np.dtype] = {}
_C_TYPES: dict[str, str] = {}          # the arrays' fields: what each pointer points to
_POINTEE = {"const double *": np.float64, "double *": np.float64, "unsigned char *": np.bool_,
            "const unsigned char *": np.bool_}


def _dtype(lib: ctypes.CDLL, kind: int) -> np.dtype:
    name_p, type_p, size = ctypes.c_char_p(), ctypes.c_char_p(), ctypes.c_long()
    names, formats, offsets = [], [], []
    while (offset := lib.kf_field(kind, len(names), ctypes.byref(name_p), ctypes.byref(type_p),
                                  ctypes.byref(size))) >= 0:
        c_type = type_p.value.decode()
        if c_type not in _FORMATS:
            raise ImportError(f"ddh_vsensor.estimator._kalman: field {name_p.value.decode()} "
                              f"has C type {c_type!r}, which the binding does not map")
        base = np.dtype(_FORMATS[c_type])
        count = size.value // base.itemsize
        if count * base.itemsize != size.value:
            raise ImportError(f"ddh_vsensor.estimator._kalman: field {name_p.value.decode()} "
                              f"of {size.value} bytes is no whole number of {c_type}")
        if KINDS[kind] == "arrays":
            _C_TYPES[name_p.value.decode()] = c_type
        names.append(name_p.value.decode())
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": lib.kf_struct_size(kind)})


def library() -> ctypes.CDLL:
    """The compiled sample (loaded and checked once); ImportError where it was not built."""
    global _LIB
    if _LIB is None:
        lib = required_library("ddh_vsensor.estimator._kalman")
        ptr, long_ = ctypes.c_void_p, ctypes.c_long
        lib.kf_field.argtypes = [ctypes.c_int, ctypes.c_int, ptr, ptr, ptr]
        lib.kf_field.restype = long_
        lib.kf_struct_size.argtypes = [ctypes.c_int]
        lib.kf_struct_size.restype = long_
        lib.kf_max_states.restype = long_
        # the unit model compiled in here is the plant's: its structs checked as the plant's are
        check_layouts(lib)
        lib.kf_predict_update.argtypes = [long_, long_, long_] + [ptr] * 11
        lib.kf_predict_update.restype = None
        lib.kf_finish.argtypes = [long_, long_, long_] + [ptr] * 7
        lib.kf_finish.restype = long_
        lib.kf_sample.argtypes = [long_, long_, long_] + [ptr] * 11
        lib.kf_sample.restype = long_
        lib.kf_run.argtypes = [long_, long_, long_, long_] + [ptr] * 11
        lib.kf_run.restype = long_
        for kind, name in enumerate(KINDS):
            _DTYPES[name] = _dtype(lib, kind)
        _LIB = lib
    return _LIB


def max_states() -> int:
    """The most states a compiled filter holds (11 + 2 per Hall switch)."""
    return int(library().kf_max_states())


def field_names(kind: str) -> tuple[str, ...]:
    """The fields of struct ``kf_<kind>``, as the C lists them."""
    library()
    return _DTYPES[kind].names


def record(kind: str, count: int, **fields: Any) -> np.ndarray:
    """``count`` records of struct ``kind``, each field from ``fields`` (a value or one per
    record); every field of the C struct must be given, and no other."""
    library()
    dtype = _DTYPES[kind]
    missing = [n for n in dtype.names if n not in fields]
    unknown = [n for n in fields if n not in dtype.names]
    if missing or unknown:
        raise TypeError(f"struct kf_{kind}: fields not given {missing}, not in the C {unknown}")
    out = np.zeros(count, dtype=dtype)
    for name, value in fields.items():
        out[name] = value
    return out


def pointers(**arrays: np.ndarray) -> np.ndarray:
    """The ``arrays`` record: each array's address (each must be C-contiguous)."""
    library()
    for name, a in arrays.items():
        want = _POINTEE.get(_C_TYPES.get(name, ""))
        if not a.flags.c_contiguous or a.dtype != want:
            raise ValueError(f"kalman arrays: {name} is {a.dtype}"
                             f"{'' if a.flags.c_contiguous else ', not C-contiguous'}: the C "
                             f"reads {want}")
    return record("arrays", 1, **{name: a.ctypes.data for name, a in arrays.items()})
