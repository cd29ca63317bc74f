"""An extended Kalman filter on the unit's own dynamics (``--mode kalman``).

The `dynamic` mode integrates a chamber model and bounds its error by hand (1 % of the travel
since the last reference plus a hold rate). Where the plant has structure the model lacks,
that bound does not follow the error. This filter asks instead how well the samples pin the
rod down under the model *and* what the model is known not to know, and checks its own
innovations to see when the model does not fit.

State z = [x (m), v (m/s), q_a (Pa), q_b (Pa), F_load (N), dT (K), eps, tau_off (N*m),
comp, disp, tau_stuck (N*m), o_1..o_m (m), c_1..c_m (m)]:

- ``q_a``, ``q_b`` the oil each chamber holds, as the gauge pressure at which air-free oil
  would hold as much (``ddh_stored_pa`` of the unit model; without air, the pressure itself):
  with entrained air a pascal near vacuum is a share of the chamber, and a state, a
  perturbation or a spread in pressure there is no amount of oil at all. The rows run on the
  pressure holding it (``ddh_pressure_pa``), kept with the filter;

- ``F_load`` the external load (random walk; the moving mass follows from the payload it
  implies), ``tau_off`` an offset of the drive's torque estimate (random walk);
- ``dT`` the pumps' oil above the tank sensor's reading (Gauss-Markov, sigma
  :attr:`KalmanSettings.temp_sd_c`: the sensor's thermal lag times the oil's warm-up rate;
  time :attr:`KalmanSettings.temp_tau_s`, bounded at :attr:`KalmanSettings.temp_bound_sd`
  sigma: beyond, it would be another error taken for temperature); it enters the viscosity,
  so the laminar leakage, per row;
- ``eps`` the unmodelled flow, normalised: a first-order Gauss-Markov process of unit
  variance, the flow error being dq = sigma_q eps with sigma_q the RMS of what the model's
  flows are known to lack (:meth:`_Bank._flow_sigma`): the datasheet's leakage band, the share
  of the leakage that may pass orifice-like gaps (the orifice law against the laminar one at
  the same rating-point leakage), the pumps' trapped volumes compressed and lost every
  revolution, each a bound whose RMS is bound / sqrt(3). The error is a function of the
  operating point, so it decorrelates as that moves, over
  :attr:`KalmanSettings.flow_travel_strokes` of travel (a stroke sweeps a cycle's speeds,
  pressures and chamber volumes), and at a hold, where nothing moves, only over
  :attr:`KalmanSettings.flow_tau_s`: a leakage the model lacks at the hold's pressure creeps
  the estimate at one rate for the hold's length, so its travel grows with the hold's time,
  not its square root. It is not a parameter: what a hold teaches about it is forgotten
  within a stroke, because a leakage of another shape learnt at the hold pressure does not
  hold at other pressures and speeds. Where the tolerance bands are wrong for the machine,
  the edges say by how much: sigma_q^2 is scaled by the posterior mean of the edges'
  normalised innovations squared (the bands as its prior, :attr:`KalmanSettings.
  edge_prior_edges` edges' weight; never below them, the bands bound what a healthy unit
  has). It moves the rod only
  (x += T dq / A_a), not the chambers' balance: the load sets the pressures, the flows the
  speed, so a flow error's lasting trace is a rod-velocity error; entered as a chamber flow
  it would shift the pressures and give the torque a hold on it that it does not have on the
  real plant. At a stroke end it moves the rod as far as the rod floats on the oil (the
  torque's odds below): a rod held a millimetre short of the stop by a leakage the model
  lacks is there by the flow error, one pressed on the stop not at all;
- ``comp`` the chambers' compliance off the model's (entrained air, hose walls; relative,
  constant, uniform prior over +-:attr:`KalmanSettings.compliance_tolerance`): a full chamber
  holds millimetres of travel in compression, so the signed oil volume the model's pressures
  take moves the rod by comp times that volume over the area (the mean of the two chambers'
  accounts); against a stroke end it moves nothing;
- ``disp`` the pumps' delivered displacement per the cylinder's area off the model's
  (relative, constant, uniform prior over +-:attr:`KalmanSettings.displacement_tolerance`):
  the rod travels disp times more than the model moves it, on every stroke, so the error
  grows with the travel, not its square root (the flow error's decorrelation would have
  it); the Hall edges measure it;
- ``tau_stuck`` where in the pumps' friction band a motor standing still stuck: the band's
  pumping and motoring torques both hold the pressures, so the drive's torque is anywhere
  between them, but it is *one* value for the stop, not a new draw each sample. Drawn anew
  (uniform over the band) as the motor stops, moved across the band by the drive's
  controller over :attr:`KalmanSettings.stuck_torque_s`, never wider than the band; it
  enters the torque only while the motor stands;
- ``o_i`` one offset per Hall switch (constant, prior uniform over
  +-``reference_tolerance_mm``): a switch mounted 2 mm off is off by 2 mm on every pass;
  ``c_i`` the rod's position at switch i's last edge, kept from the edge's sample until the
  debounce accepts it (a stochastic clone: the travel since is the filter's own, with its
  covariance, so a stop met within the debounce time is not mistaken for the switch's
  offset).

Prediction is the simulator's own plant (:class:`ddh_vsensor.model.plant.Plant`, its rows built
from the configuration with the structure terms it states; its C step, ``model/_unit.c``, is
compiled into the filter's sample, ``_kalman.c``, which steps the rows itself) in speed mode:
the motor follows the measured speed (the parabola through the last three samples, over
``substeps`` backward-Euler steps per sample) and the plant reports the torque the drive needs,
inertia included; the drive at its torque limit, the rod on a stop and the relief valves open
are the plant's own states, so a rod pressed on a stop by the drive at its limit needs no mode
of its own. One plant batch holds, per filter, the nominal row and one row per perturbed plant
state (x, v, dp_a, dp_b, F_load, dT): the Jacobian comes from one batched step by finite
differences. x is perturbed away from the nearer stroke end by
:attr:`KalmanSettings.stop_reach` sigma: the slope of a stop's clip over the position's spread
is the share of rods not yet there, so the spread closes as the pumps push the rods behind the
mean onto the stop, not when the mean arrives; and only as far as the torque says the rod is
on the stop: the nominal row's torque (on the stop: closed chambers, the stop carrying the
load) and the perturbed row's (short of it, floating on the oil) are the two modes'
likelihoods of the sample's torque, at even odds, and the slope is weighed by the first's
share (a model whose leakage is off pushes its rods onto the stop while the machine holds
the rod a millimetre short: the torque says which).

Measurement: the logged motor torque is the plant's torque over the *last* substep plus
``tau_off`` plus noise whose variance is physics (the drive's estimate error, the reading's
timing within its sample, the speed's resolution read as inertia torque, the limiter at the
speed limit); a motor standing still is held in its pumps' friction band (taken at the band's
middle plus ``tau_stuck``). An innovation beyond :attr:`KalmanSettings.huber`
sigma is down-weighted (Huber): it is a linearisation the sample does not fit. One beyond the
chi-square gate at :attr:`KalmanSettings.false_alarm` is a torque the model cannot explain (a
chamber the model pressurises at a reversal while the plant's still cavitates, a force it
lacks): it leaves the slow states (load, oil offset, torque offset: a payload or a digging
force does not move by the kilonewtons such a torque would ask within a sample) and the
position's variance takes the travel the model predicted over that sample, which the sample
does not confirm. The torque
does not update what is position (x, the flow error, the displacement, the switches' offsets
and the clones: a Schmidt "consider" update, Joseph's covariance):
mid-stroke its dependence on x (the chambers' volumes) is too weak to trust, and near a
stroke end any force the model lacks reads as the stop.

Hall switch edges (debounced as the estimator does, taken when accepted) measure c_i - o_i:
the rod at the edge's instant (its time from the I/O module where logged, else anywhere
within the sample) where the switch really switches, the direction of travel from the rod's
velocity then or, where the filter has it standing, from the pumps'. A Hall edge whose
innovation fails the chi-square gate means the estimate or the switch is wrong, and the edge
cannot say which: the update is taken, the position variance widened by the disagreement,
and the samples flagged until another switch agrees. The normalised edge innovations are
returned (:attr:`KalmanResult.edge_innovations`): their mean square checks the flow-error
bounds against the data (at most about 1 where the plant has the structure the bounds stand
for). Each scales the flow error's spread (above) and feeds a CUSUM of the normalised
innovations squared against :attr:`KalmanSettings.edge_cusum_ratio` times their predicted
variance, its threshold (:func:`cusum_threshold`) set for a mean of 1 /
:attr:`KalmanSettings.edge_false_alarm` edges between false alarms; while it is beyond, the
bands are wrong for this machine and the samples carry :data:`MODEL_INCONSISTENT`.

End stops: the plant stops its rows at them and the mean is clipped to [0, stroke]; the
variance is not truncated: truncating the re-Gaussianised estimate every sample re-counts one
constraint as new information. Every
variance is kept non-negative and a non-finite state raises.

Published: position = x, uncertainty = :attr:`KalmanSettings.coverage` x sqrt(P_xx). Self-check:
the normalised innovations squared of the torque over a sliding window against the chi-square
bound at :attr:`KalmanSettings.false_alarm`; beyond it the sample carries
:data:`MODEL_INCONSISTENT` (bit 7, reserved in :class:`.Flags`: the proposed new bit) and the
covariance grows by the excess (fading memory), so that a value published once the check
passes again is not a confident wrong one.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2

from ddh_vsensor.config import DATASHEET_TOLERANCES, Config, HydraulicsConfig, MotorConfig
from ddh_vsensor.estimator.estimator import ReferenceEvent, RunEstimate
from ddh_vsensor.estimator import kalman_step
from ddh_vsensor.estimator.flags import Flags
from ddh_vsensor.estimator.timing import (shaft_torque_nm, torque_at_speed_instants)
from ddh_vsensor.estimator.references import (DIRECTION_SPEED_MM_S, Switch,
                                              accepted_edges, switches_from_config)
from ddh_vsensor.measured import Run
from ddh_vsensor.physics.conversions import BAR_PA
from ddh_vsensor.physics.pump import rating_viscosity_pa_s
from ddh_vsensor.physics.steady import steady_state_at_torque
from ddh_vsensor.physics.tank_sensor import pump_oil_temperature_c
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.model.plant import Plant, RowSpec

MODEL_INCONSISTENT = int(Flags.MODEL_INCONSISTENT)
_NOT_REFERENCED, _AT_SOFT_LIMIT = int(Flags.NOT_REFERENCED), int(Flags.AT_SOFT_LIMIT)
X, V, PA, PB, LOAD, DT, EPS, TOFF, COMP, DISP, STICK = range(11)
SLOW = [LOAD, DT, TOFF]          # the slow states: a torque the model cannot explain leaves them
N_BASE = 11                     # states before the per-switch offsets
N_PLANT = 6                     # states the plant sees (the rest enter linearly: no row)
N_ROWS = N_PLANT + 1            # nominal + one per perturbed plant state
# finite-difference steps of the perturbed states (SI, K): well inside each state's
# uncertainty, well above the step's rounding
DELTAS = np.array([1e-4, 1e-4, 2e4, 2e4, 50.0, 0.1])
SQRT_3 = math.sqrt(3.0)


@dataclass(frozen=True)
class KalmanSettings:
    """The filter's noises and choices, each with what it stands for (the comments above or
    beside a field are its meaning; the docs' table of settings is made from them)."""

    # plant steps per sample (2 ms at 100 Hz): backward Euler over them damps what the samples
    # cannot resolve (a nearly empty chamber's stiffness against the rod's mass rings near
    # the samples' Nyquist frequency; finer steps resolve it and the torque's update chases it)
    substeps: int = 5
    # the published uncertainty, in the position's sigmas
    coverage: float = 3.0
    # the position's sigma never below it: a stroke end's mechanical tolerance
    floor_mm: float = 0.1
    # x's finite-difference step, in its sigmas, away from the nearer stroke end: the slope of
    # the stop's clip over the spread (the position's spread closes as the rods behind arrive)
    stop_reach: float = 2.0
    # the drive's torque error per sample (its estimate from the motor's currents)
    drive_torque_nm: float = DATASHEET_TOLERANCES.torque_noise_nm
    # when the torque was read within its sample against the speed
    torque_timing_s: float = 1.0e-3
    # the logged speed's resolution (its inertia torque over a sample is a noise)
    speed_step_rpm: float = 1.0
    # the torque's noise at the speed limit, where the drive's limiter sets it
    limiter_torque_nm: float = 5.0
    # prior: the position's sigma at a known start (the bench's: the truth's first sample)
    position_mm: float = 0.5
    # prior: the rod's velocity's sigma at the start
    velocity_mm_s: float = 1.0
    # prior: each chamber pressure's sigma at the start (from the steady state there)
    pressure_bar: float = 5.0
    # prior: the load's sigma at the start, as a share of |F_load| (the payload unknown),
    # at least the cylinder's static friction
    load_share: float = 0.3
    # prior: the drive's torque offset's sigma (its calibration)
    torque_offset_nm: float = DATASHEET_TOLERANCES.torque_offset_nm
    # the unmodelled flow, a Gauss-Markov error of the rod's flow balance, has a stationary
    # sigma that is the RMS of physical bounds (``_kalman.c``'s flow_sigma), each a share
    # anywhere within its band (RMS bound / sqrt(3)): the pumps' leakage's band, +-
    leak_tolerance: float = DATASHEET_TOLERANCES.pump_leakage
    # the unmodelled flow's bound: the share of the rating point's leakage that may pass
    # orifice-like gaps (turbulent: no thinner with cold oil, not linear in pressure)
    orifice_share: float = DATASHEET_TOLERANCES.leakage_orifice_share
    # the unmodelled flow's bound: the pumps' trapped volumes (up to this share of the
    # displacement) compressed to the port's pressure every revolution and lost:
    # dq = b |p| / beta |q_displacement|
    trapped_share: float = DATASHEET_TOLERANCES.trapped_volume_share
    # the unmodelled flow's floor: the seals' bypass a new cylinder may have (~1 ml/min)
    flow_floor_m3_s: float = 2e-8
    # the unmodelled flow changes as the operating point does: over this much travel, in
    # strokes (a stroke sweeps the speeds, pressures and chamber volumes a cycle has)
    flow_travel_strokes: float = 1.0
    # at a hold, where nothing moves, the unmodelled flow keeps over about a work cycle's
    # longest hold
    flow_tau_s: float = 30.0
    # the chambers' effective compliance (entrained air, hose walls) off the oil's by up to
    # this share: a state (comp), uniform prior
    compliance_tolerance: float = DATASHEET_TOLERANCES.compliance
    # the pumps' delivered displacement per the cylinder's area off the model's by up to this
    # share: a state (disp), uniform prior
    displacement_tolerance: float = DATASHEET_TOLERANCES.pump_displacement
    # the pumps' oil against the tank sensor: a Gauss-Markov offset (K) on the viscosity. The
    # sensor lags the pumps' oil by its thermal lag (~3 min) while the oil warms at up to
    # ~1 K/min in work: sigma ~3 K
    temp_sd_c: float = DATASHEET_TOLERANCES.oil_temp_c
    # the oil offset wanders as fast as the tank's temperature does: its thermal time constant
    temp_tau_s: float = 600.0
    # the oil offset's bound, in its sigmas (beyond, it would be another error taken for
    # temperature)
    temp_bound_sd: float = 4.0
    # process noise: the load's random walk, a share of the start's |F_load| per sqrt(s)
    # (geometry, friction)
    load_walk_share: float = 0.02
    # process noise: a white force (friction not modelled), N per sqrt(s)
    force_noise_n: float = 200.0
    # process noise: a white flow, a share of a pump's rated leakage per sqrt(s)
    flow_noise_share: float = 0.02
    # process noise: the drive's torque offset's walk, and with it what of the drive's
    # reading the model lacks (a speed-proportional loss, its filter, unless configured),
    # N*m per sqrt(s)
    torque_offset_walk_nm: float = 0.05
    # a motor stuck in its pumps' friction band: its torque is one value within the band (the
    # stuck torque state), moved across it by the drive's controller within about this time
    # (a position loop's integral action winding while the rod stands)
    stuck_torque_s: float = 1.0
    # a Hall switch's switching point from pass to pass
    switch_repeat_mm: float = 0.05
    # torque innovations beyond this many sigma are down-weighted (Huber)
    huber: float = 3.0
    # a torque innovation beyond the chi-square gate at false_alarm leaves the slow states
    # and gives the position's variance the sample's predicted travel
    unexplained_gate: bool = True
    # the self-check's window: the torque's normalised innovations squared summed over it
    nis_window_s: float = 1.0
    # the self-check's and the gates' false-alarm rate (their chi-square quantile)
    false_alarm: float = 1e-3
    # the fading memory's cap per window, beyond the self-check's bound
    max_inflation: float = 10.0
    # the edges' check of the flow-error bounds: the tolerance bands' weight in the flow
    # error's variance scale, in edges (an inverse-gamma prior at 1)
    edge_prior_edges: float = 2.0
    # the edges' CUSUM: the edges' normalised innovations squared against a variance this
    # many times the predicted one
    edge_cusum_ratio: float = 4.0
    # the edges' CUSUM's threshold: set for this false-alarm rate per edge (mean run length
    # 1 / rate)
    edge_false_alarm: float = 1e-2


def settings_from_config(cfg: Config, base: KalmanSettings | None = None) -> KalmanSettings:
    """``base`` (default: the defaults) with the parameters' bands the configuration states
    (its ``tolerances``: the reference loader's measured, a new machine's a datasheet's)."""
    t = cfg.tolerances
    return dataclasses.replace(base or KalmanSettings(), leak_tolerance=t.pump_leakage,
                               orifice_share=t.leakage_orifice_share,
                               trapped_share=t.trapped_volume_share,
                               compliance_tolerance=t.compliance,
                               displacement_tolerance=t.pump_displacement,
                               temp_sd_c=t.oil_temp_c,
                               torque_offset_nm=t.torque_offset_nm,
                               drive_torque_nm=t.torque_noise_nm)


@dataclass
class KalmanResult:
    """One filter's output over its run, with its internals for study."""

    estimate: RunEstimate
    load_n: np.ndarray
    temp_offset_c: np.ndarray           # the pumps' oil above the tank sensor's reading
    flow_error_m3_s: np.ndarray         # the unmodelled flow's estimate (into chamber A)
    flow_sigma_m3_s: np.ndarray         # its stationary standard deviation there
    torque_offset_nm: np.ndarray
    nis: np.ndarray                     # per-sample normalised torque innovation squared
    nis_window: np.ndarray              # its sum over the window / the chi-square bound
    pressures_bar: np.ndarray           # (samples, 2): the chambers' gauge pressures
    switch_offsets_mm: dict[str, float] = field(default_factory=dict)   # at the run's end
    # per accepted edge (not the cold start's first): innovation / its predicted sigma
    edge_innovations: list[float] = field(default_factory=list)
    seconds: float = 0.0                # wall time of the batch this filter ran in
    samples: int = 0
    # the flow error's variance over the tolerance bands' the edges implied by the run's end
    flow_variance_scale: float = 1.0


@dataclass
class _Job:
    actuator: str
    run: Run
    unit: DDHUnit
    switches: tuple[Switch, ...]
    x0_mm: float | None
    # the bands of what is known of this unit: each side's leakage, the delivered displacement
    leak_tolerance_a: float
    leak_tolerance_b: float
    displacement_tolerance: float
    motor: MotorConfig                  # the drive's reading of the shaft's torque
    torque_offset_sd_nm: float          # what is known of its offset, in the shaft's N*m


@functools.lru_cache
def cusum_threshold(ratio: float, false_alarm: float, cells: int = 200) -> float:
    """The threshold h of the CUSUM g = max(0, g + (1 - 1/ratio) nu^2 / 2 - ln(ratio) / 2)
    (the log-likelihood ratio of a variance ratio times the predicted one) over nu ~ N(0, 1)
    whose mean run length to a false alarm is 1 / false_alarm: Brook and Evans' Markov chain
    on [0, h) in cells, the threshold bisected."""
    a, c = 0.5 * (1.0 - 1.0 / ratio), 0.5 * math.log(ratio)

    def run_length(h: float) -> float:
        bounds = np.linspace(0.0, h, cells + 1)[1:]                  # cells' upper bounds
        def law(g: np.ndarray) -> np.ndarray:
            """P(next statistic in each cell | g), the reset to 0 in the first."""
            cdf = chi2.cdf(np.maximum(bounds[None, :] - g[:, None] + c, 0.0) / a, 1)
            return np.diff(cdf, axis=1, prepend=0.0)
        m = law((np.arange(cells) + 0.5) * h / cells)
        lengths = np.linalg.solve(np.eye(cells) - m, np.ones(cells))
        return 1.0 + float(law(np.zeros(1))[0] @ lengths)

    lo, hi = 0.0, 50.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if run_length(mid) < 1.0 / false_alarm else (lo, mid)
    return hi


def _job(cfg: Config, actuator: str, unit: DDHUnit, run: Run, references: bool,
         x0_mm: float | None, settings: KalmanSettings) -> _Job:
    """One filter's unit, run and bands of what is known, from the configuration."""
    u = cfg.unit(actuator)
    bands = [settings.leak_tolerance if p.leakage_tolerance is None else p.leakage_tolerance
             for p in (u.pump_a, u.pump_b)]
    return _Job(actuator, run, unit, switches_from_config(u) if references else (), x0_mm,
                *bands, settings.displacement_tolerance if u.displacement_tolerance is None
                else u.displacement_tolerance, u.motor,
                (settings.torque_offset_nm if u.motor.torque_offset_tolerance_nm is None
                 else u.motor.torque_offset_tolerance_nm) / u.motor.torque_gain)


def run_many(cfg: Config, jobs: Sequence[tuple[str, Run]], *, references: bool = True,
             initial_positions_mm: Sequence[float | None] | None = None,
             settings: KalmanSettings = KalmanSettings()) -> list[KalmanResult]:
    """Filter many runs (of any units) in lockstep: one plant batch, N_ROWS rows each.

    Every run must be sampled at the same, even rate (frames lost or late: feed the run
    frame by frame, :class:`.kalman_online.OnlineKalman` bridges them)."""
    if not jobs:
        return []
    positions = list(initial_positions_mm) if initial_positions_mm is not None \
        else [None] * len(jobs)
    units: dict[str, DDHUnit] = {}
    prepared = []
    for (actuator, r), x0 in zip(jobs, positions):
        if actuator not in units:
            units[actuator] = DDHUnit.from_config(cfg, actuator)
        prepared.append(_job(cfg, actuator, units[actuator], r, references, x0, settings))
    periods = [float(np.median(np.diff(j.run.time_s))) for j in prepared]
    period = periods[0]
    for j, p in zip(prepared, periods):
        dt = np.diff(j.run.time_s)
        if abs(p - period) > 1e-6 * period or np.max(np.abs(dt - period)) > 0.05 * period:
            raise ValueError(f"{j.run.source}: the Kalman filter's batch needs evenly sampled "
                             "runs at one rate")
    return _Bank(prepared, period, settings, cfg.estimator.debounce_s, cfg.hydraulics,
                 {a: RowSpec.from_config(cfg, a) for a in units}).run()


def run(cfg: Config, actuator: str, measured: Run, *, references: bool = True,
        initial_position_mm: float | None = None,
        settings: KalmanSettings = KalmanSettings()) -> RunEstimate:
    """One run, as :meth:`.Estimator.run` returns it (``initial_position_mm`` None: a cold
    start, mid-stroke, not referenced until the first edge)."""
    return run_many(cfg, [(actuator, measured)], references=references,
                    initial_positions_mm=[initial_position_mm], settings=settings)[0].estimate


def sample_flags(inconsistent: Any, not_referenced: Any, x_mm: Any, stroke_mm: float) -> Any:
    """The flags of a filter's samples (arrays) or of one sample (its values): model
    inconsistent, not referenced, at a stroke end."""
    return (MODEL_INCONSISTENT * inconsistent | _NOT_REFERENCED * not_referenced
            | _AT_SOFT_LIMIT * ((x_mm <= 0.0) | (x_mm >= stroke_mm)))


class _Bank:
    """B filters stepped together; arrays are (B, ...) and plant rows b * N_ROWS + j. A sample
    is the compiled step's (``_kalman.c``: the prediction through the plant's own rows, the
    torque's update); the Hall edges' updates between its two halves are here."""

    def __init__(self, jobs: list[_Job], period_s: float, s: KalmanSettings,
                 debounce_s: float, hydraulics: HydraulicsConfig,
                 rows: dict[str, RowSpec]) -> None:
        self.jobs, self.s, self.debounce_s = jobs, s, debounce_s
        self.B = B = len(jobs)
        self.lengths = np.array([len(j.run.time_s) for j in jobs])
        self.N = int(self.lengths.max())
        h = period_s / s.substeps
        self.plant = Plant([rows[j.actuator] for j in jobs for _ in range(N_ROWS)], h)
        self.nom = np.arange(B) * N_ROWS
        # padded inputs: past its end a run holds its last sample
        def pad(get) -> np.ndarray:
            out = np.empty((self.N, B))
            for b, j in enumerate(jobs):
                col = np.asarray(get(j), dtype=float)
                out[:len(col), b] = col
                out[len(col):, b] = col[-1]
            return out
        self.speed = pad(lambda j: j.run.speed_rpm)
        # the shaft's torque from the drive's reading: less its offsets, over its gain, its
        # filter undone (:mod:`.timing`); its reporting lag (motor.torque_lag_s) stays within
        # the torque's timing noise, the model's torque being its last substep's
        self.torque = pad(lambda j: torque_at_speed_instants(
            j.run.time_s, shaft_torque_nm(j.run.torque_nm, j.run.speed_rpm, j.motor),
            j.motor.torque_filter_s, 2.0 * period_s))
        # the pumps' oil: the tank sensor's reading ahead by its configured lag
        self.temp = pad(lambda j: pump_oil_temperature_c(j.run.time_s, j.run.oil_temp_c,
                                                         hydraulics.oil_temp_lag_s))
        self.time = pad(lambda j: j.run.time_s)
        self.measured = np.ones((self.N, B), dtype=bool)   # False: a lost frame, interpolated
        col = lambda f: np.array([float(f(j)) for j in jobs])  # noqa: E731
        self.stroke = col(lambda j: j.unit.cylinder.stroke_m)
        self.area_a = col(lambda j: j.unit.a.area_m2)
        self.q_signed_a = col(lambda j: j.unit.a.pump.geometric_flow_m3_s(1.0))
        # per switch an offset state and a clone of the rod's position at its last edge
        m = max((len(j.switches) for j in jobs), default=0)
        self.slot = [{sw.name: N_BASE + i for i, sw in enumerate(j.switches)} for j in jobs]
        self.clone = [{sw.name: N_BASE + m + i for i, sw in enumerate(j.switches)}
                      for j in jobs]
        self.n_states = N_BASE + 2 * m
        if self.n_states > kalman_step.max_states():
            raise ValueError(f"kalman: {m} Hall switches on one unit; the compiled filter holds "
                             f"{(kalman_step.max_states() - N_BASE) // 2} at most")
        leak_a = col(lambda j: j.unit.a.pump.leak_coeff_m3)
        leak_b = col(lambda j: j.unit.b.pump.leak_coeff_m3)
        # what the valves let a chamber's pressure reach: the anti-cavitation valve's opening
        # less, and the relief's setting plus, the pressure over which each passes the side's
        # largest pump flow (at the speed limit); an update never takes a pressure beyond
        # (with entrained air, a chamber taken below vacuum would hold the air of a vacuum)
        def reach(side, valve) -> np.ndarray:
            return col(lambda j: abs(getattr(j.unit, side).pump.geometric_flow_m3_s(
                j.unit.motor.speed_limit_rpm)) / getattr(getattr(j.unit, side),
                                                         valve).gradient_m3_s_pa)
        # the chambers' states are the oil they hold (the pressure itself without air)
        stored_floor = np.stack([self._stored(col(
            lambda j, side=side: getattr(j.unit, side).anticav.cracking_pa)
            - reach(side, "anticav")) for side in "ab"], axis=1)
        stored_ceiling = np.stack([self._stored(col(
            lambda j, side=side: getattr(j.unit, side).relief.setting_pa)
            + reach(side, "relief")) for side in "ab"], axis=1)
        # a side's leakage at the rating point, through an orifice: k_lam dp_r / mu_r sqrt(dp/dp_r)
        dp_r = hydraulics.nominal_pressure_bar * BAR_PA
        mu_r = rating_viscosity_pa_s(jobs[0].unit.oil, hydraulics)
        oil = jobs[0].unit.oil
        self.units = kalman_step.record(
            "unit", B, stroke_m=self.stroke, area_a_m2=self.area_a,
            area_b_m2=col(lambda j: j.unit.b.area_m2),
            inertia_kg_m2=col(lambda j: j.unit.motor.inertia_kg_m2),
            speed_limit_rpm=col(lambda j: j.unit.motor.speed_limit_rpm),
            mass_kg=col(lambda j: j.unit.load.mass_kg),
            mass_per_n_kg=col(lambda j: j.unit.load.mass_per_payload_kg
                              / j.unit.load.force_per_payload_kg_n
                              if j.unit.load.force_per_payload_kg_n else 0.0),
            holding_n=col(lambda j: j.unit.load.holding_force_n),
            # rated leakage flow of the larger pump: the scale of the flow noise
            rated_leak_m3_s=col(lambda j: max(s_.pump.leak_coeff_m3 for s_ in j.unit.sides)
                                * 250e5 / float(oil.dynamic_viscosity_pa_s(40.0))),
            dead_m3=col(lambda j: j.unit.dead_volume_m3),
            beta_pa=col(lambda j: j.unit.bulk_modulus_pa),
            leak_a_m3=leak_a, leak_b_m3=leak_b,
            leak_band_a=col(lambda j: j.leak_tolerance_a),
            leak_band_b=col(lambda j: j.leak_tolerance_b),
            orifice_a=leak_a * math.sqrt(dp_r) / mu_r, orifice_b=leak_b * math.sqrt(dp_r) / mu_r,
            q_per_rpm_a_m3_s=col(lambda j: abs(j.unit.a.pump.geometric_flow_m3_s(1.0))),
            q_per_rpm_b_m3_s=col(lambda j: abs(j.unit.b.pump.geometric_flow_m3_s(1.0))),
            # half the pumps' friction band at standstill per Pa: ideal (1/eta - eta) / 2
            band_half_nm_per_pa=np.array([[sd.pump.sign * sd.pump.speed_ratio
                                           * sd.pump.displacement_m3_rev / (2.0 * math.pi)
                                           * (1.0 / sd.pump.eta_hm - sd.pump.eta_hm) / 2.0
                                           for sd in j.unit.sides] for j in jobs]),
            stored_floor_pa=stored_floor, stored_ceiling_pa=stored_ceiling)
        walther_a, walther_b = oil.walther_coefficients
        win = max(1, int(round(s.nis_window_s / period_s)))
        self.edge_gate = float(chi2.ppf(1.0 - s.false_alarm, 1))
        self.settings = kalman_step.record(
            "settings", 1, period_s=period_s, substep_s=self.plant.h, substeps=s.substeps,
            nis_window=win, unexplained_gate=int(s.unexplained_gate),
            nis_bound=float(chi2.ppf(1.0 - s.false_alarm, win)),
            torque_gate=float(chi2.ppf(1.0 - s.false_alarm, 1)), deltas=DELTAS,
            stop_reach=s.stop_reach, drive_torque_nm=s.drive_torque_nm,
            torque_timing_s=s.torque_timing_s, speed_step_rpm=s.speed_step_rpm,
            limiter_torque_nm=s.limiter_torque_nm, leak_orifice_share=s.orifice_share,
            trapped_share=s.trapped_share, flow_floor_m3_s=s.flow_floor_m3_s,
            flow_travel_strokes=s.flow_travel_strokes, flow_tau_s=s.flow_tau_s,
            temp_sd_c=s.temp_sd_c, temp_bound_c=s.temp_bound_sd * s.temp_sd_c,
            phi_t=math.exp(-period_s / s.temp_tau_s), load_walk_share=s.load_walk_share,
            force_noise_n=s.force_noise_n, flow_noise_share=s.flow_noise_share,
            torque_offset_walk_nm=s.torque_offset_walk_nm, stuck_torque_s=s.stuck_torque_s,
            huber=s.huber, max_inflation=s.max_inflation,
            inflate_per_sample=period_s / s.nis_window_s, floor_m=s.floor_mm * 1e-3,
            walther_intercept=walther_a, walther_slope=walther_b,
            density_15c_kg_m3=oil.cfg.density_kg_m3_at_15c,
            expansion_per_k=oil.cfg.thermal_expansion_per_k)
        # the edges' check of the flow error's bounds: an inverse-gamma posterior's mean from
        # the edges' innovations squared, each normalised to the bands' spread, and the CUSUM
        # that flags the bands wrong
        self.edge_sum = np.zeros(B)
        self.edge_n = np.zeros(B)
        self.cusum = np.zeros(B)
        self.cusum_h = cusum_threshold(s.edge_cusum_ratio, s.edge_false_alarm)

    # --- pieces ---------------------------------------------------------------------------

    def _stored(self, dp_pa: np.ndarray) -> np.ndarray:
        """Per filter, the oil its chamber holds at gauge pressure ``dp_pa``, as a pressure."""
        return self.plant.stored_pa(dp_pa, self.nom)

    def _pressure(self, stored_pa: np.ndarray) -> np.ndarray:
        """Per filter, the gauge pressure at which its chamber holds ``stored_pa``."""
        return self.plant.pressure_pa(stored_pa, self.nom)

    def _initial(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s, B = self.s, self.B
        n = self.n_states
        z = np.zeros((B, n))
        p0 = np.zeros((B, n))
        referenced = np.ones(B, dtype=bool)
        for b, j in enumerate(self.jobs):
            st = steady_state_at_torque(j.unit, self.speed[0, b], self.torque[0, b],
                                        self.temp[0, b])
            x0 = j.x0_mm
            if x0 is None:
                x0, sx = 0.5 * self.stroke[b] * 1e3, self.stroke[b] * 1e3 / math.sqrt(12.0)
                referenced[b] = False
            else:
                sx = s.position_mm
            force = float(st.load_force_n)
            z[b, :N_BASE] = [x0 * 1e-3, float(st.velocity_m_s),
                             float(st.p_a_pa - j.unit.reservoir_pa),
                             float(st.p_b_pa - j.unit.reservoir_pa), force, 0.0, 0.0, 0.0, 0.0,
                             0.0, 0.0]
            sf = max(s.load_share * abs(force), j.unit.cylinder.static_friction_n)
            p0[b, :N_BASE] = [(sx * 1e-3) ** 2, (s.velocity_mm_s * 1e-3) ** 2,
                              (s.pressure_bar * 1e5) ** 2, (s.pressure_bar * 1e5) ** 2, sf ** 2,
                              s.temp_sd_c ** 2, 1.0,
                              j.torque_offset_sd_nm ** 2, s.compliance_tolerance ** 2 / 3.0,
                              j.displacement_tolerance ** 2 / 3.0, 0.0]
            # a switch mounted off is off by the same on every pass: uniform over its tolerance
            for sw in j.switches:
                p0[b, self.slot[b][sw.name]] = (sw.tolerance_mm * 1e-3) ** 2 / 3.0
        z[:, PA], z[:, PB] = self._stored(z[:, PA]), self._stored(z[:, PB])
        P = np.zeros((B, n, n))
        P[:, np.arange(n), np.arange(n)] = p0
        # the constant parameters' prior variances (their bands') cap their variance
        self.prior_var = np.full((B, n), np.inf)
        constant = [COMP, DISP, STICK, *range(N_BASE, N_BASE + max((len(j.switches)
                                                            for j in self.jobs), default=0))]
        self.prior_var[:, constant] = p0[:, constant]
        return z, P, referenced

    # --- the loop -------------------------------------------------------------------------

    def run(self) -> list[KalmanResult]:
        """Every filter from its run's first sample to the longest run's last (a run past
        its end holds its last sample); the samples between two with edges in one compiled
        loop."""
        t_start = time.perf_counter()
        self.start()
        k = 0
        for event in sorted({e for e in (*self.seen, *self.edges) if e < self.N}) + [self.N]:
            if event > k:
                done = self._lib.kf_run(self.B, self.n_states, k, event, *self._predict_args)
                if done < event:
                    self._non_finite(done)
            if event < self.N:
                self.step(event)
            k = event + 1
        return self.results(time.perf_counter() - t_start)

    def start(self) -> None:
        """The filters before their first sample: states, covariances, the edges each run's
        switches give, and the outputs' arrays."""
        B, N = self.B, self.N
        z, P, referenced = self._initial()
        self.suspect: list[str | None] = [None] * B
        self.nis, self.nis_win = np.zeros((N, B)), np.zeros((N, B))
        self.flagged = np.zeros((N, B), dtype=bool)
        self.not_ref = np.zeros((N, B), dtype=bool)
        self.out = (np.empty((N, B)), np.empty((N, B)), np.empty((N, B)), np.empty((N, B)),
                    np.empty((N, B)), np.empty((N, B)), np.zeros((N, B)), np.zeros((N, B)),
                    np.empty((N, B, 2)))
        # reference edges: edge index -> [(filter, switch, edge time)] (the rod's position
        # then is cloned) and accept index -> [(filter, edge index, rising, switch)]
        self.seen: dict[int, list[tuple[int, Switch, float]]] = {}
        self.edges: dict[int, list[tuple[int, int, bool, Switch]]] = {}
        for b, j in enumerate(self.jobs):
            for sw in j.switches:
                if sw.name not in j.run.refs:
                    continue
                timed = j.run.ref_edge_s.get(sw.name)
                for acc, c, rising in accepted_edges(j.run.time_s, j.run.refs[sw.name],
                                                     self.debounce_s):
                    te = float(timed[c]) if timed is not None and np.isfinite(timed[c]) \
                        else math.nan
                    self.seen.setdefault(c, []).append((b, sw, te))
                    self.edges.setdefault(acc, []).append((b, c, rising, sw))
        self.events: list[list[ReferenceEvent]] = [[] for _ in range(B)]
        self.edge_innovations: list[list[float]] = [[] for _ in range(B)]
        self.pending: dict[tuple[int, str], tuple[float, float, float]] = {}
        # derive the start's discrete states from its state
        p_a, p_b = self._pressure(z[:, PA]), self._pressure(z[:, PB])
        self.plant.set_state(np.repeat(z[:, X], N_ROWS), np.repeat(self.speed[0], N_ROWS),
                             np.repeat(p_a, N_ROWS), np.repeat(p_b, N_ROWS))
        self.filters = kalman_step.record(
            "filter", B, since=0, load_scale_n=np.maximum(np.abs(z[:, LOAD]), 1.0), flow_scale=1.0,
            flow_sigma_m3_s=0.0, phi_q=1.0,
            friction_state=self.plant.friction_state[self.nom],
            regime_a=self.plant.regime_a[self.nom], regime_b=self.plant.regime_b[self.nom],
            was_stopped=0, referenced=referenced, held=0, p_pa=np.stack([p_a, p_b], axis=1))
        # views of the records' fields the edges' updates read and set
        self.referenced, self.flow_scale = self.filters["referenced"], self.filters["flow_scale"]
        self.z, self.P = z, P
        out_x, out_v, out_sd, out_load, out_dt, out_toff, out_dq, out_sq, out_p = self.out
        self.arrays = kalman_step.pointers(
            measured=self.measured, speed_rpm=self.speed, torque_nm=self.torque,
            temp_c=self.temp, nis=self.nis,
            nis_window=self.nis_win, x_m=out_x, v_m_s=out_v, sd_m=out_sd, load_n=out_load,
            temp_offset_c=out_dt, torque_offset_nm=out_toff, flow_error_m3_s=out_dq,
            flow_sigma_m3_s=out_sq, pressures_bar=out_p, flagged=self.flagged,
            not_referenced=self.not_ref)
        records = [a.ctypes.data for a in (self.settings, self.units, self.filters, z, P)]
        params, state, inputs, counters = self.plant.c_pointers()
        self._predict_args = (*records, self.prior_var.ctypes.data, params, state, inputs,
                              self.arrays.ctypes.data, counters)
        self._finish_args = (*records, params, self.arrays.ctypes.data)
        self._lib = kalman_step.library()

    def step(self, k: int) -> None:
        """Sample k of every filter: the prediction from k - 1 and the torque's update
        (k > 0), the edges seen and accepted at k, the outputs at k."""
        lib = self._lib
        seen, edges = self.seen.get(k), self.edges.get(k)
        if not seen and not edges:
            bad = lib.kf_sample(self.B, self.n_states, k, *self._predict_args)
        else:
            lib.kf_predict_update(self.B, self.n_states, k, *self._predict_args)
            # a switch changed: the rod's position at that instant, as known now, is kept
            # (cloned) until the debounce accepts the edge; the stop or anything else met
            # before then cannot be mistaken for the switch's offset
            for b, sw, te in seen or ():
                self._clone(self.z, self.P, b, k, sw, te)
            for b, c, rising, sw in edges or ():
                self._reference(self.z, self.P, b, k, c, rising, sw, self.referenced,
                                self.events)
            bad = lib.kf_finish(self.B, self.n_states, k, *self._finish_args)
        if bad:
            self._non_finite(k)

    def _non_finite(self, k: int) -> None:
        """Stop: a filter's state left the finite numbers at sample k."""
        bad = [self.jobs[b].run.source for b in range(self.B)
               if not (np.isfinite(self.z[b]).all() and np.isfinite(self.P[b]).all())]
        raise FloatingPointError(f"kalman: non-finite state at sample {k}: {bad}")

    # --- the online bank's one filter: what the service does to it -------------------------

    def restart(self, k: int) -> None:
        """Start again at sample k, after inputs not integrated (the samples before are not
        its past): the rod's velocity and the chambers' pressures from the steady state at
        the sample's speed and torque, with the start's spreads; what is slow or constant
        (position, load, oil, offsets, parameters, switches) is kept."""
        assert self.B == 1, "the online bank holds one filter"
        s, j, z, P = self.s, self.jobs[0], self.z[0], self.P[0]
        st = steady_state_at_torque(j.unit, self.speed[k, 0], self.torque[k, 0],
                                    self.temp[k, 0])
        fast = [V, PA, PB, STICK]
        P[fast, :] = 0.0
        P[:, fast] = 0.0
        p_a, p_b = float(st.p_a_pa - j.unit.reservoir_pa), float(st.p_b_pa - j.unit.reservoir_pa)
        stored_a, stored_b = self.plant.stored_pa([p_a, p_b], self.nom[[0, 0]])
        z[fast] = [float(st.velocity_m_s), float(stored_a), float(stored_b), 0.0]
        P[V, V] = (s.velocity_mm_s * 1e-3) ** 2
        P[PA, PA] = P[PB, PB] = (s.pressure_bar * 1e5) ** 2
        self.plant.set_state(np.full(N_ROWS, z[X]), np.full(N_ROWS, self.speed[k, 0]),
                             np.full(N_ROWS, p_a), np.full(N_ROWS, p_b))
        f = self.filters
        f["p_pa"] = [p_a, p_b]
        f["since"], f["was_stopped"] = k, 0
        f["friction_state"], f["regime_a"], f["regime_b"] = (
            self.plant.friction_state[0], self.plant.regime_a[0], self.plant.regime_b[0])

    def preset(self, position_m: float, sd_m: float) -> None:
        """The rod is at ``position_m`` within ``sd_m`` (a preset, a restored state): known
        now, correlated with nothing the filter holds."""
        z, P = self.z[0], self.P[0]
        z[X] = min(max(position_m, 0.0), self.stroke[0])
        P[X, :] = 0.0
        P[:, X] = 0.0
        P[X, X] = sd_m ** 2

    def widen(self, sd_m: float) -> None:
        """The position's sigma grows by ``sd_m`` (travel not integrated): an error of its
        own, independent of what the filter holds (scaling x's row instead would claim the
        untracked travel a multiple of, say, a switch's offset, which the next edge would
        then "learn")."""
        P = self.P[0]
        sd = math.sqrt(max(P[X, X], 0.0))
        P[X, X] += (sd + sd_m) ** 2 - sd ** 2

    def learned(self) -> dict[str, float]:
        """What outlives a restart: the constant and slow states (the torque offset in N*m,
        the compliance and displacement relative, each switch's offset in mm), each with its
        variance (``<name>_var``), and the edges' check of the flow-error bounds."""
        z, P = self.z[0], self.P[0]
        out: dict[str, float] = {}
        for name, (i, scale) in self._learnable().items():
            out[name] = float(z[i]) * scale
            out[f"{name}_var"] = float(P[i, i]) * scale ** 2
        out.update(flow_scale=float(self.flow_scale[0]), edge_sum=float(self.edge_sum[0]),
                   edge_n=float(self.edge_n[0]), cusum=float(self.cusum[0]))
        return out

    def teach(self, learned: dict[str, float]) -> None:
        """Carry on from what :meth:`learned` gave (an earlier run's): each state's value and
        variance, uncorrelated with the rest; a name this filter does not hold (a switch no
        longer configured) is passed over, one it holds and the record lacks keeps its
        prior."""
        z, P = self.z[0], self.P[0]
        for name, (i, scale) in self._learnable().items():
            if name in learned and f"{name}_var" in learned:
                P[i, :] = 0.0
                P[:, i] = 0.0
                z[i] = learned[name] / scale
                P[i, i] = min(max(learned[f"{name}_var"], 0.0) / scale ** 2,
                              self.prior_var[0, i])
        if {"flow_scale", "edge_sum", "edge_n", "cusum"} <= learned.keys():
            self.flow_scale[0] = max(1.0, learned["flow_scale"])
            self.edge_sum[0], self.edge_n[0] = learned["edge_sum"], learned["edge_n"]
            self.cusum[0] = max(0.0, learned["cusum"])
            self.filters["held"][0] = self.cusum[0] > self.cusum_h

    def _learnable(self) -> dict[str, tuple[int, float]]:
        """The states :meth:`learned` keeps: name -> (index, scale to its unit)."""
        return {"torque_offset_nm": (TOFF, 1.0), "compliance": (COMP, 1.0),
                "displacement": (DISP, 1.0),
                **{f"switch_offset_mm.{name}": (i, 1e3) for name, i in self.slot[0].items()}}

    def results(self, seconds: float) -> list[KalmanResult]:
        """Each filter's outputs over its own run; ``seconds`` the batch's wall time."""
        s, z = self.s, self.z
        nis, nis_win, flagged, not_ref = self.nis, self.nis_win, self.flagged, self.not_ref
        out_x, out_v, out_sd, out_load, out_dt, out_toff, out_dq, out_sq, out_p = self.out
        events = self.events
        results = []
        for b, j in enumerate(self.jobs):
            n = int(self.lengths[b])
            x_mm = out_x[:n, b] * 1e3
            flags = sample_flags(flagged[:n, b], not_ref[:n, b], x_mm,
                                 self.stroke[b] * 1e3).astype(np.uint8)
            est = RunEstimate(x_mm, out_v[:n, b] * 1e3, s.coverage * out_sd[:n, b] * 1e3, flags,
                              events[b])
            offsets = {name: float(z[b, i]) * 1e3 for name, i in self.slot[b].items()}
            results.append(KalmanResult(est, out_load[:n, b], out_dt[:n, b], out_dq[:n, b],
                                        out_sq[:n, b], out_toff[:n, b], nis[:n, b],
                                        nis_win[:n, b], out_p[:n, b], offsets,
                                        self.edge_innovations[b], seconds,
                                        int(self.lengths.sum()),
                                        float(self.flow_scale[b])))
        return results

    def _check_flow_bounds(self, b: int, nu2: float) -> None:
        """An edge's normalised innovation squared against the flow error's spread: where the
        tolerance bands are wrong for this machine, the edges measure how wrong. The spread
        is scaled to the posterior mean of its variance over the bands' (the prior: the bands,
        weighted as :attr:`KalmanSettings.edge_prior_edges` edges; never below them: the
        bands bound what a healthy unit may have), and the CUSUM flags the excess."""
        s = self.s
        # the edge's spread was mostly the flow error's at the scale then: back to the bands'
        self.edge_sum[b] += nu2 * self.flow_scale[b]
        self.edge_n[b] += 1.0
        self.flow_scale[b] = max(1.0, (s.edge_prior_edges + self.edge_sum[b])
                                 / (s.edge_prior_edges + self.edge_n[b]))
        ratio = s.edge_cusum_ratio
        self.cusum[b] = max(0.0, self.cusum[b] + 0.5 * (1.0 - 1.0 / ratio) * nu2
                            - 0.5 * math.log(ratio))

    def _clone(self, z: np.ndarray, P: np.ndarray, b: int, c: int, sw: Switch,
               edge_s: float) -> None:
        """Keep the rod's position at the edge's instant (sample c back to the edge's time,
        or anywhere within the sample where the log has no time) as a state of its own."""
        t = self.time[:, b]
        v_c = float(z[b, V])
        if math.isfinite(edge_s):
            back, timing_var = t[c] - edge_s, 0.0
        else:
            back = 0.5 * (t[c] - t[c - 1]) if c > 0 else 0.0
            timing_var = (v_c * 2.0 * back) ** 2 / 12.0
        i = self.clone[b][sw.name]
        h = np.zeros(self.n_states)
        h[X], h[V] = 1.0, -back
        row = h @ P[b]
        var = float(row @ h)
        z[b, i] = h @ z[b]
        P[b, i, :] = P[b, :, i] = row
        P[b, i, i] = var
        self.pending[(b, sw.name)] = (float(z[b, X]), v_c, timing_var)

    def _reference(self, z: np.ndarray, P: np.ndarray, b: int, k: int, c: int, rising: bool,
                   sw: Switch, referenced: np.ndarray, events: list[list[ReferenceEvent]]
                   ) -> None:
        """A debounced edge accepted at k, seen at c: the rod's position at the edge's
        instant (the clone) minus the switch's offset is the switching position."""
        x_c, v_c, timing_var = self.pending.pop((b, sw.name))
        # the direction of travel at the edge: the way the pumps drive the rod (the measured
        # speed through their displacement; the filter's velocity is an estimate, and after a
        # restart a guess), unless they turn too slowly to say: then the rod's velocity
        v_pumps = self.speed[c, b] * self.q_signed_a[b] / self.area_a[b]
        if abs(v_pumps) * 1e3 >= DIRECTION_SPEED_MM_S:
            v_c = v_pumps
        p_mm = sw.edge_position_mm(rising, v_c * 1e3, x_c * 1e3)
        o, i = self.slot[b][sw.name], self.clone[b][sw.name]
        y = p_mm * 1e-3 + z[b, o] - z[b, i]
        r = timing_var + (self.s.switch_repeat_mm * 1e-3) ** 2
        h = np.zeros(self.n_states)
        h[i], h[o] = 1.0, -1.0
        # the position as a common mode: the rod now and at the edge (the travel since known)
        e = np.zeros(self.n_states)
        e[X] = e[i] = 1.0
        cold = not referenced[b]
        if cold:
            # a cold start: the position unknown by the stroke
            P[b] += self.stroke[b] ** 2 * np.outer(e, e)
            referenced[b] = True
        else:
            s_ = max(float(h @ P[b] @ h), 0.0) + r
            self.edge_innovations[b].append(y / math.sqrt(s_))
            self._check_flow_bounds(b, y * y / s_)
            if y * y / s_ > self.edge_gate:
                # beyond the gate the estimate or the switch is wrong and this edge cannot
                # say which: both are widened by the disagreement before the update (the
                # position carries it until another switch agrees; its samples are flagged)
                self.suspect[b] = sw.name
                P[b] += y * y * np.outer(e, e)
                P[b, o, o] += y * y
            elif sw.name != self.suspect[b]:
                self.suspect[b] = None
        ph = P[b] @ h
        s_ = max(float(h @ ph), 0.0) + r
        K = ph / s_
        z[b] += K * y
        z[b, [PA, PB]] = np.clip(z[b, [PA, PB]], self.units["stored_floor_pa"][b],
                                 self.units["stored_ceiling_pa"][b])
        P[b] -= np.outer(K, ph)
        events[b].append(ReferenceEvent(k, c, sw.name, rising, p_mm, -y * 1e3, False,
                                        float(K[X])))
        self.filters["held"][b] = self.suspect[b] is not None or self.cusum[b] > self.cusum_h
