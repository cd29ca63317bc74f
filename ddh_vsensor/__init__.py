"""ddh-vsensor: a virtual position sensor for pump-controlled (DDH) hydraulic cylinders.

The library face::

    import ddh_vsensor as dv
    cfg = dv.load_config("my-machine.yaml")       # None: the embedded reference loader
    est = dv.Estimator.from_config(cfg, "lift")   # tables loaded (tables=DIR) or built now
    res = est.run(dv.read_run("lift.csv", cfg, "lift"))   # CSV or any python-can log
    print(res.position_mm[-1], dv.flag_text(res.flags[-1]))

Names load on first use, so ``import ddh_vsensor`` (and the daemon's start) stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from ddh_vsensor.version import __version__

# public name -> module that defines it
_FACE = {
    "Config": ".config", "ConfigError": ".config", "load_config": ".config",
    "UserError": ".errors",
    "Estimator": ".estimator.estimator", "RunEstimate": ".estimator.estimator",
    "Step": ".estimator.estimator",
    "Flags": ".estimator.flags", "flag_text": ".estimator.flags",
    "Run": ".measured", "read_csv": ".io.csv", "write_csv": ".io.csv",
    "read_run": ".io.reader",
    "UnitTables": ".tables.lookup", "build_unit_tables": ".tables.build",
}

__all__ = sorted(_FACE) + ["__version__"]

if TYPE_CHECKING:
    from ddh_vsensor.config import Config, ConfigError, load_config
    from ddh_vsensor.errors import UserError
    from ddh_vsensor.estimator.estimator import Estimator, RunEstimate, Step
    from ddh_vsensor.estimator.flags import Flags, flag_text
    from ddh_vsensor.measured import Run
    from ddh_vsensor.io.csv import read_csv, write_csv
    from ddh_vsensor.io.reader import read_run
    from ddh_vsensor.tables.build import build_unit_tables
    from ddh_vsensor.tables.lookup import UnitTables


def __getattr__(name: str) -> Any:
    module = _FACE.get(name)
    if module is None:
        raise AttributeError(f"module 'ddh_vsensor' has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
