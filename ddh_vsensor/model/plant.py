"""Time-domain plant of DDH units: motor, pumps, chambers, valves, cylinder, load.

One row = one unit of one run; rows run in lockstep, each stepped by the unit's dynamics of
:mod:`ddh_vsensor.model.unit` (backward Euler with an active-set iteration over the discrete
states, in C; its docstring has the equations and every effect's law). The plant holds the
rows' constants, states and inputs as numpy arrays of the C structs, and its attributes are
views of their fields: writing ``plant.load`` or ``plant.x`` (whole or per row) between steps
changes what the next step sees.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ddh_vsensor.model.unit import Counters, Input, RowSpec, State, library, rows_array


class _Field:
    """A plant attribute that is one field of every row's C struct: reading gives the view
    (shape ``(rows,)``), assigning writes into it (whole, or broadcast)."""

    def __init__(self, table: str, field: str) -> None:
        self.table, self.field = table, field

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, plant: Any, owner: type | None = None) -> Any:
        return self if plant is None else plant._views[self.name]

    def __set__(self, plant: Any, value: Any) -> None:
        plant._views[self.name][...] = value


class Plant:
    """A batch of independent DDH units integrated in lockstep by backward Euler.

    Public arrays (shape ``(rows,)``, SI units, n in rpm) are views of the rows' C structs:
    the state ``x``, ``v``, ``dp_a``, ``dp_b``, ``n``, ``torque`` (the motor's actual torque
    over the last step), the discrete states ``friction_state``, ``motor_state``,
    ``regime_a``, ``regime_b``, the speed mode ``speed_controlled``, ``speed_command`` and
    the constants below that other code reads or sets per row (``load``, ``mass``, ...);
    ``params`` and ``state`` hold every field. ``steps`` counts steps,
    ``unconverged_steps`` those where a row's discrete states did not settle,
    ``iterations`` the linear solves over all rows.
    """

    # no other attributes: a write to one the step does not read would pass unnoticed
    __slots__ = ("rows", "h", "size", "params", "state", "_input", "_counters", "_views",
                 "_torque_in", "_mu_in", "_lib", "_args", "steps", "unconverged_steps")

    x = _Field("state", "x_m")
    v = _Field("state", "v_m_s")
    dp_a = _Field("state", "dp_a_pa")
    dp_b = _Field("state", "dp_b_pa")
    n = _Field("state", "n_rpm")
    torque = _Field("state", "torque_nm")
    friction_state = _Field("state", "friction_state")
    motor_state = _Field("state", "motor_state")
    regime_a = _Field("state", "regime_a")
    regime_b = _Field("state", "regime_b")
    speed_controlled = _Field("input", "speed_controlled")
    speed_command = _Field("input", "speed_rpm")
    area_a = _Field("params", "area_a_m2")
    area_b = _Field("params", "area_b_m2")
    stroke = _Field("params", "stroke_m")
    dead = _Field("params", "dead_volume_m3")
    mass = _Field("params", "mass_kg")
    load = _Field("params", "load_n")
    c_viscous = _Field("params", "viscous_friction_n_s_m")
    reservoir = _Field("params", "reservoir_pa")
    orifice_a = _Field("params", "orifice_leak_a_m3_s_sqrt_pa")
    orifice_b = _Field("params", "orifice_leak_b_m3_s_sqrt_pa")
    leak_base = _Field("params", "leak_base")
    leak_slope_a = _Field("params", "leak_slope_a_per_rpm")
    leak_slope_b = _Field("params", "leak_slope_b_per_rpm")

    def __init__(self, rows: Sequence[RowSpec], step_s: float) -> None:
        if not rows:
            raise ValueError("a plant needs at least one row")
        if step_s <= 0.0:
            raise ValueError("step must be positive")
        self._lib = library()
        self.rows = tuple(rows)
        self.h = float(step_s)
        self.size = len(rows)
        self.params = rows_array(self.rows)
        self.state = np.zeros(self.size, dtype=np.dtype(State))
        self.state["regime_a"] = self.state["regime_b"] = 2
        self._input = np.zeros(self.size, dtype=np.dtype(Input))
        self._counters = np.zeros(1, dtype=np.dtype(Counters))
        tables = {"params": self.params, "state": self.state, "input": self._input}
        self._views = {name: tables[f.table][f.field] for name, f in vars(Plant).items()
                       if isinstance(f, _Field)}
        self._torque_in, self._mu_in = self._input["torque_nm"], self._input["mu_pa_s"]
        self._args = (self.size, self.params.ctypes.data, self.state.ctypes.data,
                      self._input.ctypes.data, self.h, self._counters.ctypes.data)
        self.steps = 0
        self.unconverged_steps = 0

    @property
    def iterations(self) -> int:
        return int(self._counters["iterations"][0])

    def c_pointers(self) -> tuple[int, int, int, int]:
        """The rows' params, states, inputs and the counters as C addresses: for C code that
        steps the rows itself (the Kalman filter's sample)."""
        return (self.params.ctypes.data, self.state.ctypes.data, self._input.ctypes.data,
                self._counters.ctypes.data)

    def set_speed_control(self, mask: np.ndarray, speed_rpm: np.ndarray | float = 0.0) -> None:
        """Rows in ``mask`` follow ``speed_rpm`` exactly (the drive in speed mode) from the
        next step on; the others are torque-controlled. The torque then reported is the one
        the drive needs."""
        mask = np.asarray(mask, dtype=bool) & np.ones(self.size, dtype=bool)
        self.speed_command = np.where(mask, speed_rpm, 0.0)
        self.speed_controlled = mask

    def set_state(self, x_m: np.ndarray, speed_rpm: np.ndarray, dp_a: np.ndarray,
                  dp_b: np.ndarray, velocity_m_s: np.ndarray | None = None) -> None:
        """Start from given states (x clipped to the stroke); discrete states and the torque
        are derived from them."""
        s = self.state
        s["x_m"], s["n_rpm"], s["dp_a_pa"], s["dp_b_pa"] = x_m, speed_rpm, dp_a, dp_b
        s["v_m_s"] = 0.0 if velocity_m_s is None else velocity_m_s
        self._lib.ddh_settle_rows(self.size, self.params.ctypes.data, s.ctypes.data,
                                  self._input.ctypes.data)

    def stored_pa(self, dp_pa: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Per row (of ``rows``, default all), the oil a chamber at gauge pressure ``dp_pa``
        holds, as the pressure at which air-free oil would hold as much (the pressure itself
        without air)."""
        idx = np.arange(self.size) if rows is None else np.asarray(rows)
        dp = np.broadcast_to(np.asarray(dp_pa, dtype=float), idx.shape)
        row = self.params.ctypes.data
        return np.array([self._lib.ddh_stored_pa(row + int(i) * self.params.itemsize, float(d))
                         for i, d in zip(idx, dp)])

    def pressure_pa(self, stored_pa: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Per row (of ``rows``, default all), the gauge pressure at which a chamber holds
        ``stored_pa`` (:meth:`stored_pa`'s inverse)."""
        idx = np.arange(self.size) if rows is None else np.asarray(rows)
        q = np.broadcast_to(np.asarray(stored_pa, dtype=float), idx.shape)
        row = self.params.ctypes.data
        return np.array([self._lib.ddh_pressure_pa(row + int(i) * self.params.itemsize,
                                                   float(v), float(v)) for i, v in zip(idx, q)])

    def pump_torque(self, dp_a: np.ndarray, dp_b: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Pump torque at the motor for given pressures and speeds (physics' efficiency law)."""
        s = self.state.copy()
        s["dp_a_pa"], s["dp_b_pa"], s["n_rpm"] = dp_a, dp_b, n
        self._lib.ddh_settle_rows(self.size, self.params.ctypes.data, s.ctypes.data,
                                  self._input.ctypes.data)
        return s["torque_nm"].copy()

    def step(self, torque_cmd: np.ndarray, mu_pa_s: np.ndarray) -> None:
        """Advance one step with the commanded motor torque (clipped to the limit) and the
        oil's dynamic viscosity (Pa s)."""
        self._torque_in[...] = torque_cmd
        self._mu_in[...] = mu_pa_s
        if self._lib.ddh_step_rows(*self._args):
            self.unconverged_steps += 1
        self.steps += 1

    def chamber_volumes_m3(self, x: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        x = self.x if x is None else x
        return self.dead + self.area_a * x, self.dead + self.area_b * (self.stroke - x)

