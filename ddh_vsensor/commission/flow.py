"""The pumps' flow model measured on calibration runs: each chamber's oil balance, window by
window, against the rod's measured travel.

With the valves closed, chamber s's oil is conserved (the unit model's chamber equation,
integrated over a window of the run)::

    integral q_geo,s(n) dt - sign_s A_s dx - integral V_s(x)/beta dp_s
        = integral q_leak,s dt + V_dead e_hose dp_s / 100 bar - (d_s - 1) integral q_geo,s dt
          + X dV_air,s

with q_geo the displacement flow of the measured motor speed, dx the draw-wire's travel,
dp_s the chamber's gauge pressure (logged where a transducer was fitted, otherwise the
Kalman filter's estimate from the motor torque with the datasheet model), and the leakage of
the unit model with the structure terms as unknowns::

    q_leak,s = f_s k_s [(1 - o) dp/mu + o sqrt(dp_r) / mu_r dp / sqrt(max(|dp|, 1 bar))]
               x (1 + g r) / (1 + g),                r = |n_pump| / n_rated

X the free air in the oil at atmospheric pressure (dV_air the volume a unit share of air in
the chamber loses, compressed polytropically over the window), f_s the leakage against the
datasheet's (per side: it sets the volumetric efficiency), d_s
the delivered displacement against the datasheet's per the cylinder's area (a belt ratio or
a bore off by a percent moves the rod a percent of every stroke), o the orifice share and g
the speed gain (shared by the unit's two sides: one family of pumps), e_hose the hoses'
expansion. The left side is known from the run; the right is linear in the window's sums of
k dp/mu, its speed-weighted sum, the same of the orifice law and of the displacement flow, so
one bounded least-squares fit over every window of every run finds them (from logged
pressures the displacement even on a side the load never presses: it does not need
pressure; read from the torque, a pressure is a loaded side's only, and air and hoses, which
are the pressure's rate, are left out). Their standard
deviations come from the fit's Jacobian and residual; a value whose evidence does not pin it
(too few loaded windows on a side, one temperature, one speed) keeps the datasheet's, with
the run that would measure it.

Windows are left out where a valve may be open (a chamber below the anti-cavitation valve's
cracking pressure or near its relief setting) or the rod within a few millimetres of a stroke
end (the stop takes force and flow the balance does not have).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.air import ATMOSPHERE_PA, MIN_ABSOLUTE_PA, POLYTROPIC_EXPONENT
from ddh_vsensor.physics.conversions import BAR_PA
from ddh_vsensor.physics.pump import rating_viscosity_pa_s
from ddh_vsensor.physics.tank_sensor import pump_oil_temperature_c
from ddh_vsensor.physics.unit import DDHUnit

WINDOW_S = 1.0                  # balance window: long against the position's noise
STOP_CLEARANCE_M = 3.0e-3       # windows with the rod this close to a stroke end are left out
RELIEF_MARGIN_PA = 10.0 * BAR_PA
ORIFICE_LAMINAR_PA = 1.0e5      # the unit model's: an orifice path flows laminar below 1 bar
LOADED_PA = 20.0 * BAR_PA       # a window loads a side when its mean pressure is above this
MIN_LOADED_WINDOWS = 20         # a side's leakage factor needs this many loaded windows
# identified when its standard deviation is below: the leakage factor (relative), the
# displacement factor, the orifice share, the speed gain, the hoses' expansion per 100 bar,
# the entrained air's share
MAX_SD = {"leakage": 0.05, "displacement": 0.002, "orifice_share": 0.1, "speed_gain": 0.2,
          "hose_expansion": 0.01, "air_fraction": 0.001}
BOUNDS = {"leakage": (0.05, 20.0), "displacement": (0.8, 1.2), "orifice_share": (0.0, 0.9),
          "speed_gain": (0.0, 2.0), "hose_expansion": (0.0, 0.2), "air_fraction": (0.0, 0.1)}
ESTIMATE_PASSES = 3             # fits with pressures estimated under the model fitted before
COLUMNS = 7     # per window: sums of L, L r, O, O r, V_dead dp / 100 bar, q_geo and the air's


@dataclass
class Balance:
    """One side's windows: the known left side (m^3) and the sums the leakage is linear in."""

    y_m3: np.ndarray                    # (windows,)
    sums: np.ndarray                    # (windows, COLUMNS)
    mean_dp_pa: np.ndarray              # (windows,) the side's mean gauge pressure
    temp_c: np.ndarray                  # (windows,) the oil's mean temperature
    speed_ratio: np.ndarray             # (windows,) mean |n_pump| / n_rated

    @classmethod
    def empty(cls) -> Balance:
        return cls(np.zeros(0), np.zeros((0, COLUMNS)), np.zeros(0), np.zeros(0), np.zeros(0))

    def loaded(self) -> Balance:
        """Only the windows whose mean pressure is above :data:`LOADED_PA`: where a pressure
        read from the torque is the side's own (the torque carries the loaded chamber's;
        the other's is the model's guess)."""
        keep = self.mean_dp_pa > LOADED_PA
        return Balance(*(getattr(self, f)[keep]
                         for f in ("y_m3", "sums", "mean_dp_pa", "temp_c", "speed_ratio")))

    def extend(self, other: Balance) -> Balance:
        return Balance(*(np.concatenate([getattr(self, f), getattr(other, f)])
                         for f in ("y_m3", "sums", "mean_dp_pa", "temp_c", "speed_ratio")))


@dataclass(frozen=True)
class Estimate:
    """A fitted value with its standard deviation; ``identified`` False keeps the datasheet's
    value and says what run would measure it."""

    value: float
    sd: float
    identified: bool
    datasheet: float
    problem: str | None = None


@dataclass
class FlowFit:
    """One unit's flow model as the runs measured it."""

    unit: str
    pressures: str                                  # "logged" or "estimated"
    leakage: dict[str, Estimate]                    # per side "a", "b"
    displacement: dict[str, Estimate]               # per side: against the datasheet's
    orifice_share: Estimate
    speed_gain: Estimate
    hose_expansion_per_100bar: Estimate
    air_fraction: Estimate
    windows: dict[str, int]                         # per side
    loaded_windows: dict[str, int]
    residual_rms_ml: dict[str, float] = field(default_factory=dict)  # per side and window
    datasheet_rms_ml: dict[str, float] = field(default_factory=dict)

    def named(self) -> list[tuple[str, Estimate]]:
        """Every value with the name the command and the report give it."""
        return [*((f"pump {s.upper()} displacement factor", self.displacement[s])
                  for s in "ab"),
                *((f"pump {s.upper()} leakage factor", self.leakage[s]) for s in "ab"),
                ("orifice share", self.orifice_share), ("speed gain", self.speed_gain),
                ("hose expansion per 100 bar", self.hose_expansion_per_100bar),
                ("entrained air (share at 1 atm)", self.air_fraction)]

    @property
    def measured(self) -> bool:
        """Whether the runs measured any of the flow model's values."""
        return any(e.identified for _, e in self.named())


def gauge_pressures(unit: DDHUnit, run: Run) -> tuple[np.ndarray, np.ndarray] | None:
    """The run's logged chamber pressures over the reservoir (Pa), or None where it has none."""
    if run.p_a_bar is None or run.p_b_bar is None:
        return None
    p_a, p_b = run.p_a_bar * BAR_PA, run.p_b_bar * BAR_PA
    if not (np.isfinite(p_a).all() and np.isfinite(p_b).all()):
        return None
    return p_a - unit.reservoir_pa, p_b - unit.reservoir_pa


def estimated_pressures(cfg: Config, jobs: Sequence[tuple[str, Run]]
                        ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The chambers' gauge pressures (Pa) the Kalman filter reads from the motor torque under
    the configured (datasheet) model, started where the draw-wire says, no references."""
    from ddh_vsensor.estimator import kalman
    starts = []
    for _, run in jobs:
        finite = np.flatnonzero(np.isfinite(run.position_mm))
        starts.append(float(run.position_mm[finite[0]]))
    try:
        results = kalman.run_many(cfg, list(jobs), references=False,
                                  initial_positions_mm=starts,
                                  settings=kalman.settings_from_config(cfg))
    except ValueError as exc:
        raise UserError(f"the chamber pressures are not logged and cannot be estimated: {exc} "
                        "(log them, or resample the runs to one even rate)") from None
    return [(r.pressures_bar[:, 0] * BAR_PA, r.pressures_bar[:, 1] * BAR_PA) for r in results]


def _position_m(run: Run) -> np.ndarray:
    """The draw-wire's position at every sample (linear between the samples it has)."""
    x = run.position_mm
    ok = np.isfinite(x)
    if ok.all():
        return x * 1e-3
    return np.interp(run.time_s, run.time_s[ok], x[ok]) * 1e-3


def balances(cfg: Config, unit: DDHUnit, run: Run, dp_a: np.ndarray, dp_b: np.ndarray,
             window_s: float = WINDOW_S) -> dict[str, Balance]:
    """Both sides' windows of one run (only those where the balance holds)."""
    hyd = cfg.hydraulics
    t, n, x = run.time_s, run.speed_rpm, _position_m(run)
    temp_c = pump_oil_temperature_c(t, run.oil_temp_c, cfg.hydraulics.oil_temp_lag_s)
    mu = unit.oil.dynamic_viscosity_pa_s(temp_c)
    dp_r, mu_r = hyd.nominal_pressure_bar * BAR_PA, rating_viscosity_pa_s(unit.oil, hyd)
    stroke = unit.cylinder.stroke_m
    h = np.diff(t)
    off_stops = (x > STOP_CLEARANCE_M) & (x < stroke - STOP_CLEARANCE_M)
    starts = np.searchsorted(t, np.arange(t[0], t[-1], window_s))
    out = {}
    for side, dp, sign in ((unit.a, dp_a, 1.0), (unit.b, dp_b, -1.0)):
        pump = side.pump
        k = pump.leak_coeff_m3
        r = np.abs(pump.speed_ratio * n) / hyd.nominal_pump_speed_rpm
        laminar = k * dp / mu
        orifice = k * math.sqrt(dp_r) / mu_r * dp / np.sqrt(np.maximum(np.abs(dp),
                                                                        ORIFICE_LAMINAR_PA))
        volume = unit.dead_volume_m3 + side.area_m2 * (x if sign > 0 else stroke - x)

        def trapezoid(f: np.ndarray) -> np.ndarray:
            return 0.5 * (f[1:] + f[:-1]) * h

        geometric = trapezoid(pump.geometric_flow_m3_s(n))
        y = (geometric - sign * side.area_m2 * np.diff(x)
             - volume[:-1] / unit.bulk_modulus_pa * np.diff(dp))
        # the air a unit share of entrained air holds, compressed polytropically
        absolute = np.maximum(dp + unit.reservoir_pa + ATMOSPHERE_PA, MIN_ABSOLUTE_PA)
        air = -volume[:-1] * np.diff((ATMOSPHERE_PA / absolute) ** (1.0 / POLYTROPIC_EXPONENT))
        cols = np.stack([trapezoid(laminar), trapezoid(laminar * r), trapezoid(orifice),
                         trapezoid(orifice * r),
                         unit.dead_volume_m3 * np.diff(dp) / (100.0 * BAR_PA), geometric, air],
                        axis=1)
        closed = ((dp > -0.5 * side.anticav.cracking_pa)
                  & (dp < side.relief.setting_pa - RELIEF_MARGIN_PA) & off_stops)
        good = closed[1:] & closed[:-1]
        rows = [(i0, i1) for i0, i1 in zip(starts[:-1], starts[1:])
                if i1 - i0 >= 2 and good[i0:i1].all()]
        if not rows:
            out[side.name] = Balance.empty()
            continue
        out[side.name] = Balance(
            np.array([y[i0:i1].sum() for i0, i1 in rows]),
            np.array([cols[i0:i1].sum(axis=0) for i0, i1 in rows]),
            np.array([dp[i0:i1].mean() for i0, i1 in rows]),
            np.array([temp_c[i0:i1].mean() for i0, i1 in rows]),
            np.array([r[i0:i1].mean() for i0, i1 in rows]))
    return out


def _model(v: dict[str, float], side: str, sums: np.ndarray) -> np.ndarray:
    """The windows' balance under parameters ``v``: the leakage, the hoses' share of the
    compression, less the displacement's excess over the datasheet's."""
    f, o, g = v[f"leakage_{side}"], v["orifice_share"], v["speed_gain"]
    lam, lam_r, orf, orf_r, hose, geo, air = sums.T
    return (f / (1.0 + g) * ((1.0 - o) * (lam + g * lam_r) + o * (orf + g * orf_r))
            + v["hose_expansion"] * hose - (v[f"displacement_{side}"] - 1.0) * geo
            + v["air_fraction"] * air)


def fit_unit(cfg: Config, unit_name: str, side_balances: dict[str, Balance],
             pressures: str) -> FlowFit:
    """The unit's leakage and displacement factors (per side), orifice share, speed gain and
    hoses' expansion from its windows: one bounded least-squares fit; each value's standard
    deviation from the Jacobian, the residual's variance per side."""
    from scipy.optimize import least_squares
    u = cfg.unit(unit_name)
    datasheet = {"orifice_share": (u.pump_a.leakage_orifice_share
                                   + u.pump_b.leakage_orifice_share) / 2,
                 "speed_gain": (u.pump_a.leakage_speed_gain + u.pump_b.leakage_speed_gain) / 2,
                 "hose_expansion": cfg.hydraulics.hose_expansion_per_100bar,
                 "air_fraction": cfg.hydraulics.air_fraction,
                 "leakage_a": 1.0, "leakage_b": 1.0, "displacement_a": 1.0,
                 "displacement_b": 1.0}
    sides = [s for s in ("a", "b") if len(side_balances[s].y_m3)]
    if not sides:
        raise UserError(f"{unit_name}: no window where the chambers' balance holds (valves "
                        "closed, the rod clear of its stops): run the calibration programme")
    loaded = {s: int(np.sum(side_balances[s].mean_dp_pa > LOADED_PA)) if s in sides else 0
              for s in ("a", "b")}
    leaky = [s for s in sides if loaded[s] >= MIN_LOADED_WINDOWS] or sides
    # free: every side's displacement, the loaded sides' leakage, the shared shape and (from
    # logged pressures only: it is dp/dt, which a pressure read from the torque has with the
    # drive's lag and ripple) the hoses
    # a pressure read from the torque is a loaded side's: there a side needs its loaded
    # windows for its displacement too
    moved = sides if pressures == "logged" else [s for s in sides
                                                 if loaded[s] >= MIN_LOADED_WINDOWS]
    names = ([f"displacement_{s}" for s in moved] + [f"leakage_{s}" for s in leaky]
             + ["orifice_share", "speed_gain", "air_fraction"]
             + (["hose_expansion"] if pressures == "logged" else []))
    bounds = [BOUNDS[n.rsplit("_", 1)[0] if n[-2:] in ("_a", "_b") else n] for n in names]
    # start inside the bounds, off the shares' and gain's lower bound (a zero gradient there)
    start = dict(datasheet, orifice_share=min(datasheet["orifice_share"] + 0.05, 0.85),
                 speed_gain=min(datasheet["speed_gain"] + 0.05, 1.95))
    # each side's spread to start; a side of one window has none, and takes the unit's
    pooled = max(float(np.std(np.concatenate([side_balances[s].y_m3 for s in sides]))), 1e-12)
    scale = {s: float(np.std(side_balances[s].y_m3)) if len(side_balances[s].y_m3) > 1
             else pooled for s in sides}

    def values(p: np.ndarray) -> dict[str, float]:
        """The parameters; a side whose leakage the runs cannot show leaks like the other
        side's pumps (one family), not like the datasheet, in the other's balance terms."""
        v = dict(datasheet, **dict(zip(names, p)))
        for s in ("a", "b"):
            other = "b" if s == "a" else "a"
            if s not in leaky and other in leaky:
                v[f"leakage_{s}"] = v[f"leakage_{other}"]
        return v

    def residuals(p: np.ndarray) -> np.ndarray:
        v = values(p)
        return np.concatenate([(_model(v, s, side_balances[s].sums) - side_balances[s].y_m3)
                               / scale[s] for s in sides])

    lo, hi = zip(*bounds)
    fit = least_squares(residuals, np.array([start[n] for n in names]), bounds=(lo, hi),
                        x_scale="jac")
    # refit with each side's rows scaled by its own residual level, the sides weighing by
    # their noise; a side's level is shrunk toward the unit's over MIN_LOADED_WINDOWS
    # windows (a side of a few windows, fitted exactly, would otherwise weigh without bound)
    rows = np.cumsum([0] + [len(side_balances[s].y_m3) for s in sides])
    unit_ms = float(np.mean(fit.fun ** 2))
    for i, s in enumerate(sides):
        part = fit.fun[rows[i]:rows[i + 1]]
        scale[s] *= max(math.sqrt((float(part @ part) + MIN_LOADED_WINDOWS * unit_ms)
                                  / (len(part) + MIN_LOADED_WINDOWS)), 1e-9)
    fit = least_squares(residuals, fit.x, bounds=(lo, hi), x_scale="jac")
    dof = max(len(fit.fun) - len(fit.x), 1)
    info = fit.jac.T @ fit.jac
    cov = np.linalg.pinv(info) * float(fit.fun @ fit.fun) / dof
    variance = np.maximum(np.diag(cov), 0.0)
    # a parameter the windows do not move at all has no information, not zero variance
    blind = np.diag(info) <= 1e-12 * max(float(np.max(np.diag(info))), 1e-300)
    sd = dict(zip(names, np.where(blind, np.inf, np.sqrt(variance))))
    value = values(fit.x)
    temps = np.concatenate([side_balances[s].temp_c for s in sides])
    speeds = np.concatenate([side_balances[s].speed_ratio for s in sides])

    def estimate(key: str, what: str) -> Estimate:
        ds = datasheet[key]
        if key not in sd:
            return Estimate(ds, math.nan, False, ds, what)
        ok = sd[key] < MAX_SD[key.rsplit("_", 1)[0] if key[-2:] in ("_a", "_b") else key]
        return Estimate(float(value[key]) if ok else ds, float(sd[key]), bool(ok), ds,
                        None if ok else f"+-{sd[key]:.3g}: {what}")

    leak_why = {s: (f"the {s.upper()} chamber was loaded (> {LOADED_PA / BAR_PA:g} bar) in "
                    f"{loaded[s]} windows of {WINDOW_S:g} s" + (
                        f", {MIN_LOADED_WINDOWS} needed" if loaded[s] < MIN_LOADED_WINDOWS
                        else ", at too few pressures and speeds to tell its leakage") +
                    f": move the rod at several speeds against a load that pressurises "
                    f"chamber {s.upper()}, and hold it loaded") for s in ("a", "b")}
    span = f"oil {temps.min():.0f}..{temps.max():.0f} degC" if len(temps) else "no oil"
    fitted = FlowFit(
        unit=unit_name, pressures=pressures,
        leakage={s: estimate(f"leakage_{s}", leak_why[s]) for s in ("a", "b")},
        displacement={s: estimate(f"displacement_{s}",
                                  f"the {s.upper()} chamber's balance held in "
                                  f"{len(side_balances[s].y_m3)} windows"
                                  + ("" if pressures == "logged" else
                                     f" ({loaded[s]} loaded, {MIN_LOADED_WINDOWS} needed "
                                     "where the pressures are read from the torque)")
                                  + ": move the rod end to end clear of its stops, loaded")
                      for s in ("a", "b")},
        orifice_share=estimate("orifice_share",
                               f"{span}: loaded moves at two oil temperatures at least 30 K "
                               "apart separate the orifice share from the laminar leakage"),
        speed_gain=estimate("speed_gain",
                            f"pump speeds up to {speeds.max() if len(speeds) else 0:.2f} of "
                            "the rated: loaded moves at low and high speed measure it"),
        hose_expansion_per_100bar=estimate(
            "hose_expansion",
            "the chambers' compliance is their pressure's rate, which a pressure read from "
            "the torque has with the drive's lag and ripple: log the chamber pressures on a "
            "calibration day" if pressures != "logged" else
            "pressure changes of 100 bar and more in loaded moves measure it"),
        air_fraction=estimate("air_fraction",
                              "the air shows where a chamber's pressure rises from low: "
                              "loaded moves from rest and reversals under load"),
        windows={s: len(side_balances[s].y_m3) for s in ("a", "b")}, loaded_windows=loaded)
    for s in sides:
        b = side_balances[s]
        fitted.residual_rms_ml[s] = float(np.sqrt(np.mean((_model(value, s, b.sums)
                                                           - b.y_m3) ** 2))) * 1e6
        fitted.datasheet_rms_ml[s] = float(np.sqrt(np.mean((_model(datasheet, s, b.sums)
                                                            - b.y_m3) ** 2))) * 1e6
    return fitted


MACHINE_WIDE = ("hose_expansion_per_100bar", "air_fraction")   # the hydraulics' keys


def machine_wide(fits: dict[str, FlowFit], key: str) -> Estimate | None:
    """A value every unit's oil or hoses share: the units that measured it, weighted by
    their variances (None where none did)."""
    found = [getattr(f, key) for f in fits.values() if getattr(f, key).identified]
    if not found:
        return None
    w = np.array([1.0 / max(e.sd, 1e-9) ** 2 for e in found])
    return Estimate(float(np.dot(w, [e.value for e in found]) / w.sum()),
                    float(1.0 / math.sqrt(w.sum())), True, found[0].datasheet)


def applied(cfg: Config, fits: dict[str, FlowFit]) -> Config:
    """``cfg`` with the measured values of ``fits`` (the identified ones) in place."""
    units = dict(cfg.units)
    for a, fit in fits.items():
        u = cfg.unit(a)
        pumps = {}
        for side in ("a", "b"):
            pump = getattr(u, f"pump_{side}")
            change = {}
            if fit.displacement[side].identified:
                change["displacement_cm3_rev"] = (pump.displacement_cm3_rev
                                                  * fit.displacement[side].value)
            if fit.leakage[side].identified:
                change["volumetric_efficiency"] = 1.0 - fit.leakage[side].value * (
                    1.0 - pump.volumetric_efficiency)
            if fit.orifice_share.identified:
                change["leakage_orifice_share"] = fit.orifice_share.value
            if fit.speed_gain.identified:
                change["leakage_speed_gain"] = fit.speed_gain.value
            pumps[f"pump_{side}"] = dataclasses.replace(pump, **change)
        units[a] = dataclasses.replace(u, **pumps)
    shared = {key: e.value for key in MACHINE_WIDE if (e := machine_wide(fits, key))}
    return dataclasses.replace(cfg, units=units,
                               hydraulics=dataclasses.replace(cfg.hydraulics, **shared))


def fit_flows(cfg: Config, runs: dict[str, list[Run]],
              passes: int = ESTIMATE_PASSES) -> dict[str, FlowFit]:
    """Every unit's flow model from its runs; pressures logged where every run of the unit
    has them, else estimated by the filter (one batch for all runs), again under the model
    the previous pass measured (a pressure read from the torque depends a little on the
    leakage the filter assumes) for ``passes`` passes in all."""
    units = {a: DDHUnit.from_config(cfg, a) for a in runs}
    logged = {a: [gauge_pressures(units[a], r) for r in rs] for a, rs in runs.items()}
    need = [(a, r) for a, rs in runs.items() for r, p in zip(rs, logged[a]) if p is None]
    model = cfg
    for _ in range(passes if need else 1):
        estimated = iter(estimated_pressures(model, need) if need else [])
        out = {}
        for a, rs in runs.items():
            total = {"a": Balance.empty(), "b": Balance.empty()}
            kinds = set()
            for r, p in zip(rs, logged[a]):
                kinds.add("logged" if p is not None else "estimated")
                dp_a, dp_b = p if p is not None else next(estimated)
                for s, b in balances(cfg, units[a], r, dp_a, dp_b).items():
                    total[s] = total[s].extend(b if p is not None else b.loaded())
            out[a] = fit_unit(cfg, a, total, " and ".join(sorted(kinds)))
        model = applied(cfg, out)
    return out
