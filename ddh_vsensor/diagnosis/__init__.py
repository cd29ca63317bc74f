"""Model diagnosis: where the estimate fails on measured runs, why (a catalogue of physical
extensions fitted and cross-validated), and the extended model (see README.md here).

``diagnose(cfg, actuator, runs, mode)`` -> :class:`Diagnosis`; ``write_report`` writes it;
``Extension.load(path, cfg, actuator).estimator(cfg, tables, ...)`` applies a saved one.
"""

from ddh_vsensor.diagnosis.analyze import Diagnosis, diagnose
from ddh_vsensor.diagnosis.causes import CAUSE_NAMES
from ddh_vsensor.estimator.extension import ExtendedEstimator, Extension, ExtensionError
from ddh_vsensor.diagnosis.runs import AnalysisRun, load_analysis_run, prepare_run

__all__ = ["AnalysisRun", "CAUSE_NAMES", "Diagnosis", "ExtendedEstimator", "Extension",
           "ExtensionError", "diagnose", "load_analysis_run", "prepare_run"]
