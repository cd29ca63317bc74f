"""Any measured run file as a :class:`~ddh_vsensor.measured.Run`: the interchange CSV, or a
CAN log in any format python-can reads (BLF, ASC, candump, CSV of frames ...), decoded with
the frame layout of the machine's configuration."""

from __future__ import annotations

from pathlib import Path

from ddh_vsensor.config import Config, load_config
from ddh_vsensor.errors import UserError
from ddh_vsensor.measured import Run
from ddh_vsensor.io.csv import read_csv


def read_run(path: str | Path, cfg: Config | None = None, unit: str | None = None) -> Run:
    """One unit's run. A ``.csv`` file is the measured-data format (one unit per file); any
    other file is a CAN log, for which ``unit`` picks the unit (the configuration's only unit
    when it has one). A CSV whose ``# actuator:`` line names another unit than ``unit`` is
    refused."""
    if str(path).lower().endswith(".csv"):
        return read_csv(path, actuator=unit)
    from ddh_vsensor.io.log import read_can_log
    cfg = cfg if cfg is not None else load_config()
    if unit is None:
        if len(cfg.unit_names) != 1:
            raise UserError(f"{path}: a CAN log holds every unit; say which one (units: "
                            f"{', '.join(cfg.unit_names)})")
        unit = cfg.unit_names[0]
    return read_can_log(path, cfg.require_unit(unit), cfg)

