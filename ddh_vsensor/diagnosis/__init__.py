"""Model diagnosis: where the estimate fails on measured runs, why (a catalogue of physical
extensions fitted and cross-validated), and the extended model (see README.md here).

``diagnose(cfg, actuator, runs, mode)`` -> :class:`Diagnosis`; ``write_report`` writes it;
``Extension.load(path, cfg, actuator).estimator(cfg, tables, ...)`` applies a saved one.
"""

from .analyze import Diagnosis, diagnose
from .causes import CAUSE_NAMES
from ..estimator.extension import ExtendedEstimator, Extension, ExtensionError
from .runs import AnalysisRun, load_analysis_run, prepare_run

__all__ = ["AnalysisRun", "CAUSE_NAMES", "Diagnosis", "ExtendedEstimator", "Extension",
           "ExtensionError", "diagnose", "load_analysis_run", "prepare_run"]
