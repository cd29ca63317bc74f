"""Building the movement tables from the exact steady state of a unit.

At each speed and temperature the load is swept from overrunning to beyond the relief
setting; the torque it produces is the table's axis, so every grid node is the steady state
whose motor torque is exactly that node's torque (see ``steady_state_at_torque``).
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import math
import time
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from ddh_vsensor.compiled import required_library
from ddh_vsensor.version import __version__
from ddh_vsensor.config import Config
from ddh_vsensor.physics.steady import velocity_torque_curve
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.tables.grid import Axis
from ddh_vsensor.tables.lookup import FullTable, PaperTable, UnitTables

FORMAT_VERSION = 1

Progress = Callable[[str, float], None]

# The diagnosis asks for one unit's tables many times over (each cause's grid, each campaign):
# the last few built are kept, their arrays read-only since every caller shares them.
_BUILT: OrderedDict[tuple, UnitTables] = OrderedDict()
BUILT_KEPT = 16


def torque_span_nm(unit: DDHUnit) -> float:
    """Largest |motor torque| the table must cover: both relief valves fully open, or the
    motor's own limit if larger."""
    span = 0.0
    for side in unit.sides:
        p_max = side.relief.setting_pa + 1.0 / side.relief.gradient_m3_s_pa * (
            side.pump.displacement_m3_rev * side.pump.max_speed_rpm / 60.0)
        span += abs(float(side.pump.motor_torque_nm(p_max, 1.0)))
    return max(span, unit.motor.torque_limit_nm)


def _axes(cfg: Config, unit: DDHUnit) -> tuple[Axis, Axis, Axis]:
    tc = cfg.tables
    n_lim = unit.motor.speed_limit_rpm
    n_half = math.ceil(n_lim / tc.speed_step_rpm)
    speed = Axis("speed", "rpm", -n_half * tc.speed_step_rpm, tc.speed_step_rpm, 2 * n_half + 1)
    q_half = math.ceil(torque_span_nm(unit) / tc.torque_step_nm)
    torque = Axis("torque", "N*m", -q_half * tc.torque_step_nm, tc.torque_step_nm,
                  2 * q_half + 1)
    t0, t1, dt = tc.temperatures_c
    temp = Axis.spanning("oil_temp", "degC", t0, t1, dt)
    return speed, torque, temp


@functools.cache
def _interp_library() -> ctypes.CDLL:
    lib = required_library("ddh_vsensor.tables._interp")
    ptr, long_ = ctypes.c_void_p, ctypes.c_long
    lib.interp_rows.argtypes = [long_, long_, long_, ptr, ptr, ptr, ctypes.c_double, ptr]
    lib.interp_rows.restype = None
    return lib


def _interp_rows(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, out: np.ndarray) -> None:
    """Row-wise linear interpolation in mm/s into ``out`` (rows of ``x``'s length): each row
    ``numpy.interp``'s to the bit, in C (a table has hundreds of rows a temperature). ``xp``
    rows are the ascending breakpoints of a piecewise-linear function that reach beyond
    ``x``, so each result is exact."""
    if np.any(xp[:, 0] > x[0]) or np.any(xp[:, -1] < x[-1]):
        raise AssertionError("velocity-torque breakpoints do not span the torque axis")
    x, xp, fp = (np.ascontiguousarray(a, dtype=float) for a in (x, xp, fp))
    if out.shape != (len(xp), len(x)) or not out.flags.c_contiguous or out.dtype != float:
        raise ValueError("interpolation rows: out must be C-contiguous float rows of x")
    _interp_library().interp_rows(len(xp), xp.shape[1], len(x), xp.ctypes.data, fp.ctypes.data,
                     x.ctypes.data, 1e3, out.ctypes.data)


def build_unit_tables(cfg: Config, actuator: str, unit: DDHUnit | None = None,
                      progress: Progress | None = None) -> UnitTables:
    """Both table kinds of one actuator. ``unit`` overrides the physics (e.g. an extended
    model from diagnosis); its config hash is still ``cfg``'s. Tables of a unit built
    lately are given again, not rebuilt (with a fresh ``meta``)."""
    unit = unit or DDHUnit.from_config(cfg, actuator)
    key = (actuator, unit, cfg.tables, cfg.physics_hash(), cfg.source)
    if progress is None and key in _BUILT:
        _BUILT.move_to_end(key)
        kept = _BUILT[key]
        return dataclasses.replace(kept, meta=dict(kept.meta))
    tables = _build(cfg, actuator, unit, progress)
    tables.full.velocity_mm_s.setflags(write=False)
    tables.paper.mm_per_rev.setflags(write=False)
    _BUILT[key] = tables
    while len(_BUILT) > BUILT_KEPT:
        _BUILT.popitem(last=False)
    return dataclasses.replace(tables, meta=dict(tables.meta))


def _build(cfg: Config, actuator: str, unit: DDHUnit, progress: Progress | None
           ) -> UnitTables:
    speed, torque, temp = _axes(cfg, unit)
    started = time.perf_counter()
    full = np.empty((temp.count, speed.count, torque.count))
    edges = np.asarray(cfg.tables.paper_speed_ranges_rpm, dtype=float)
    rep = 0.5 * (edges[:-1] + edges[1:])
    paper_speeds = np.concatenate([rep, -rep])                     # [direction*range]
    paper = np.empty((2, 3, temp.count, torque.count))
    torque_nm, speeds_rpm = torque.values(), speed.values()
    v_mm_s = np.empty((len(paper_speeds), torque.count))
    for k, t_c in enumerate(temp.values()):
        _interp_rows(torque_nm, *velocity_torque_curve(unit, speeds_rpm, t_c), full[k])
        _interp_rows(torque_nm, *velocity_torque_curve(unit, paper_speeds, t_c), v_mm_s)
        paper[:, :, k, :] = (v_mm_s / (paper_speeds[:, None] / 60.0)).reshape(2, 3, -1)
        if progress:
            progress(actuator, (k + 1) / temp.count)
    meta = {
        "format_version": FORMAT_VERSION,
        "config_hash": cfg.physics_hash(),
        "package_version": __version__,
        "actuator": actuator,
        "config_source": cfg.source,
        "units": {"full": "velocity mm/s [oil_temp, speed, torque]",
                  "paper": "mm per motor revolution [direction(+,-), speed range, oil_temp, "
                           "torque]"},
        "grid": {"speed": speed.as_dict(), "torque": torque.as_dict(), "temp": temp.as_dict(),
                 "paper_speed_ranges_rpm": edges.tolist()},
        "build_seconds": time.perf_counter() - started,
    }
    return UnitTables(actuator, FullTable(speed, torque, temp, full),
                      PaperTable(torque, temp, edges, paper), meta)
