"""Time-domain plant simulator: the project's own "measured" runs of the DDH units.

``plant`` (dynamics, implicit Euler), ``control`` (the paper's PID), ``cycles`` (setpoint
profiles), ``effects`` (plant changes the tables do not know), ``sensors`` (what the logger
records), ``run`` (specs in, runs and files out).
"""

from ddh_vsensor.sim.effects import EFFECTS, UnitEffects, build_effects
from ddh_vsensor.sim.run import RunSpec, simulate, simulate_campaign, simulate_with_truth, write_run_dir

__all__ = ["EFFECTS", "RunSpec", "UnitEffects", "build_effects", "simulate",
           "simulate_campaign", "simulate_with_truth", "write_run_dir"]
