"""The pumps' flow model measured on a calibration day (the programme's two runs): on a plant
whose leakage is 1.3x the datasheet's, 30 % through orifices and rising with speed (gain
0.5), whose pumps deliver 1 % more than their datasheet's displacement and whose oil holds
0.5 % of air, the fit finds each value from logged pressures and, less closely, from pressures
the filter reads from the torque (not the air: that needs the pressures); what the runs
cannot show stays the datasheet's, with the run that would."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ddh_vsensor.commission.drive import fit_drive
from ddh_vsensor.commission.flow import (
    COLUMNS,
    Balance,
    FlowFit,
    applied,
    fit_flows,
    fit_unit,
)
from ddh_vsensor.commission.programme import calibration_cycle
from ddh_vsensor.config import Config
from ddh_vsensor.sim.effects import UnitEffects
from ddh_vsensor.sim.run import RunSpec, simulate_campaign

TRUE = {"leakage": 1.3, "orifice_share": 0.3, "speed_gain": 0.5, "displacement": 1.01,
        "air_fraction": 0.005}
PLANT = UnitEffects(pump_leakage=TRUE["leakage"], leak_orifice=100 * TRUE["orifice_share"],
                    leak_speed=TRUE["speed_gain"], displacement=TRUE["displacement"],
                    compressibility=TRUE["air_fraction"])
# tolerances on the leakage factor (relative), the share, the gain and the displacement
# factor. Measured: logged within 0.2 %, 0.001, 0.002, 0.0004; estimated (three passes)
# within 1.5 %, 0.026, 0.072, 0.0006
TOLERANCE = {"logged": (0.01, 0.01, 0.01, 0.0005), "estimated": (0.05, 0.07, 0.2, 0.002)}


@pytest.fixture(scope="module")
def runs(cfg: Config) -> dict[str, list]:
    """The calibration programme: full payload at 25 degC, empty at 65 degC."""
    effects = {a: PLANT for a in cfg.unit_names}
    simulated = simulate_campaign(cfg, [
        RunSpec(cycle=calibration_cycle(cfg), payload_kg=p, oil_temp_c=t, effects=effects,
                seed=i) for i, (p, t) in enumerate(((1040.0, 25.0), (0.0, 65.0)))])
    return {a: [r[a] for r in simulated] for a in cfg.unit_names}


@pytest.fixture(scope="module")
def fits(cfg: Config, runs: dict[str, list]) -> dict[str, dict[str, FlowFit]]:
    blind = {a: [dataclasses.replace(r, p_a_bar=None, p_b_bar=None) for r in rs]
             for a, rs in runs.items()}
    return {"logged": fit_flows(cfg, runs), "estimated": fit_flows(cfg, blind)}


@pytest.mark.parametrize("pressures", ["logged", "estimated"])
def test_the_loaded_sides_leakage_displacement_and_structure_are_found(
        fits: dict[str, dict[str, FlowFit]], pressures: str) -> None:
    tol = TOLERANCE[pressures]
    for unit, side in (("boom", "a"), ("bucket", "b")):
        fit = fits[pressures][unit]
        assert fit.pressures == pressures
        leak = fit.leakage[side]
        assert leak.identified
        assert leak.value == pytest.approx(TRUE["leakage"], rel=tol[0])
        assert fit.orifice_share.identified
        assert fit.orifice_share.value == pytest.approx(TRUE["orifice_share"], abs=tol[1])
        assert fit.speed_gain.value == pytest.approx(TRUE["speed_gain"], abs=tol[2])
        disp = fit.displacement[side]
        assert disp.identified
        assert disp.value == pytest.approx(TRUE["displacement"], abs=tol[3])
        # the fitted model explains the balance several times better than the datasheet's
        assert fit.residual_rms_ml[side] < fit.datasheet_rms_ml[side] / 2
        if pressures == "logged":       # measured: 0.0044, 0.0045
            assert fit.air_fraction.value == pytest.approx(TRUE["air_fraction"], abs=0.001)


def test_what_the_runs_cannot_show_keeps_the_datasheet(
        fits: dict[str, dict[str, FlowFit]]) -> None:
    boom = fits["estimated"]["boom"]
    leak_b = boom.leakage["b"]              # the boom's rod side is never loaded
    assert not leak_b.identified and leak_b.value == 1.0 and "hold it loaded" in leak_b.problem
    # from logged pressures its displacement shows; from the torque's it does not
    assert fits["logged"]["boom"].displacement["b"].identified
    disp_b = boom.displacement["b"]
    assert not disp_b.identified and "read from the torque" in disp_b.problem
    hose = boom.hose_expansion_per_100bar
    assert not hose.identified and math.isnan(hose.sd)
    assert "log the chamber pressures" in hose.problem
    assert not boom.air_fraction.identified and boom.air_fraction.value == 0.0


def test_one_temperature_knows_the_orifice_share_less(
        cfg: Config, runs: dict[str, list], fits: dict[str, dict[str, FlowFit]]) -> None:
    """The share shows in how the leakage follows viscosity and, less, pressure: one oil
    temperature leaves only the pressure, and the fit says so in its sigma, not by a
    confident wrong value."""
    both = fits["logged"]["boom"].orifice_share
    warm = fit_flows(cfg, {a: rs[1:] for a, rs in runs.items()})["boom"].orifice_share
    assert warm.sd > 3 * both.sd
    assert abs(warm.value - TRUE["orifice_share"]) < 3 * warm.sd


def test_the_tank_sensors_lag_is_configured_not_measured(cfg: Config) -> None:
    """The tank sensor trails the warming oil by 3 minutes: configured, the leakage comes out
    as it is; left at 0, the leakage factor takes the steady offset (measured 1.355 for 1.3),
    and the balance's residual cannot tell the two apart (within 0.2 %)."""
    effects = {a: dataclasses.replace(PLANT, oil_temp_lag=180.0) for a in cfg.unit_names}
    simulated = simulate_campaign(cfg, [
        RunSpec(cycle=calibration_cycle(cfg), payload_kg=p, oil_temp_c=t, effects=effects,
                seed=i) for i, (p, t) in enumerate(((1040.0, 25.0), (0.0, 65.0)))])
    runs = {a: [r[a] for r in simulated] for a in cfg.unit_names}
    told = dataclasses.replace(cfg, hydraulics=dataclasses.replace(cfg.hydraulics,
                                                                   oil_temp_lag_s=180.0))
    right, blind = fit_flows(told, runs)["boom"], fit_flows(cfg, runs)["boom"]
    assert right.leakage["a"].value == pytest.approx(TRUE["leakage"], rel=0.01)
    assert blind.leakage["a"].value > TRUE["leakage"] * 1.03
    assert blind.residual_rms_ml["a"] == pytest.approx(right.residual_rms_ml["a"], rel=0.002)


def test_the_drive_is_read_through_the_pumps_as_commissioned(cfg: Config,
                                                             runs: dict[str, list]) -> None:
    """A true drive on pumps 1 % larger than their datasheet's: through the datasheet's pumps
    the pressures' torque is 1 % short and the reading looks 1 % high; through the pumps as
    commissioned (the displacement the calibrated configuration carries) it reads true, so
    the estimator's pressures from the commissioned reading are the plant's."""
    measured = applied(cfg, fit_flows(cfg, runs))
    for unit in ("boom", "bucket"):
        datasheet = fit_drive(cfg, unit, runs[unit])
        commissioned = fit_drive(measured, unit, runs[unit])
        # measured: 1.0001 and 1.0003 commissioned, 1.0044 and 1.0017 on the datasheet (the
        # unloaded side's displacement is not identified, so less than 1 %)
        assert commissioned.gain == pytest.approx(1.0, abs=0.001)
        assert datasheet.gain > commissioned.gain + 0.001


def test_a_side_of_one_window_does_not_steer_the_fit(cfg: Config) -> None:
    """The loaded side's 400 windows say leakage 0.8, share 0.3, gain 0.4; the other side
    held its balance in one window only, 20 noise levels off (a window the model does not
    describe). Weighed by its own spread (none) or its own residual (fitted exactly: none),
    that window took the fit (a drawn bucket's leakage 1.68 for 0.77); weighed by the unit's
    level it is one window among 401."""
    rng = np.random.default_rng(7)
    true = {"leakage_b": 0.8, "orifice_share": 0.3, "speed_gain": 0.4, "displacement_b": 1.0,
            "hose_expansion": 0.0, "air_fraction": 0.0}
    noise_m3 = 1e-6

    def side(n: int, offset_m3: float) -> Balance:
        sums = np.zeros((n, COLUMNS))
        sums[:, :4] = rng.uniform(20e-6, 80e-6, (n, 4))     # laminar, orifice and speed terms
        sums[:, 5] = rng.uniform(0.0, 5e-3, n)              # displacement flow
        f, o, g = true["leakage_b"], true["orifice_share"], true["speed_gain"]
        y = (f / (1.0 + g) * ((1.0 - o) * (sums[:, 0] + g * sums[:, 1])
                              + o * (sums[:, 2] + g * sums[:, 3]))
             + rng.normal(0.0, noise_m3, n) + offset_m3)
        return Balance(y, sums, np.full(n, 60e5), rng.uniform(20.0, 70.0, n),
                       rng.uniform(0.1, 1.0, n))

    fit = fit_unit(cfg, "bucket", {"a": side(1, 20 * noise_m3), "b": side(400, 0.0)},
                   "estimated")
    assert fit.leakage["b"].identified
    assert fit.leakage["b"].value == pytest.approx(true["leakage_b"], rel=0.02)
    assert fit.orifice_share.value == pytest.approx(true["orifice_share"], abs=0.03)
