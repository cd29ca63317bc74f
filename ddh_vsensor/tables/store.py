"""Table files: one ``<actuator>.npz`` per unit in a directory, versioned and tied to a config.

Loaded with ``allow_pickle=False``; metadata is a JSON string inside the archive. A table built
for another config or format is refused with the command that rebuilds it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ddh_vsensor.atomic import atomic_write
from ddh_vsensor.config import Config
from ddh_vsensor.errors import UserError
from ddh_vsensor.tables.build import FORMAT_VERSION
from ddh_vsensor.tables.grid import Axis
from ddh_vsensor.tables.lookup import FullTable, PaperTable, UnitTables


class TableError(UserError):
    """A table file that is missing, unreadable or built for something else."""


def table_path(directory: str | Path, actuator: str) -> Path:
    return Path(directory) / f"{actuator}.npz"


def save_unit_tables(directory: str | Path, tables: UnitTables) -> Path:
    """Write atomically: a crash mid-write leaves the previous file intact."""
    Path(directory).mkdir(parents=True, exist_ok=True)
    path = table_path(directory, tables.actuator)
    with atomic_write(path, "wb") as fh:
        np.savez(fh, meta=np.array(json.dumps(tables.meta)),
                 full_velocity_mm_s=tables.full.velocity_mm_s,
                 paper_mm_per_rev=tables.paper.mm_per_rev,
                 paper_range_edges_rpm=tables.paper.range_edges_rpm)
    return path


def _axis(meta: dict, name: str) -> Axis:
    return Axis(**meta["grid"][name])


def load_unit_tables(directory: str | Path, actuator: str, cfg: Config | None = None) -> UnitTables:
    """Load one actuator's tables; with ``cfg``, refuse tables built from another config."""
    path = table_path(directory, actuator)
    rebuild = (f"rebuild with: ddh-vsensor tables build --config {cfg.source if cfg else 'FILE'}"
               f" --out {directory}")
    if not path.exists():
        raise TableError(f"{path}: no table file; {rebuild}")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            full_v = data["full_velocity_mm_s"]
            paper_v = data["paper_mm_per_rev"]
            edges = data["paper_range_edges_rpm"]
    except (OSError, ValueError, KeyError) as exc:
        raise TableError(f"{path}: not a ddh-vsensor table file ({exc}); {rebuild}") from None
    if meta.get("format_version") != FORMAT_VERSION:
        raise TableError(f"{path}: table format {meta.get('format_version')}, this version "
                         f"reads {FORMAT_VERSION}; {rebuild}")
    if cfg is not None and meta.get("config_hash") != cfg.physics_hash():
        raise TableError(f"{path}: built for another configuration (hash "
                         f"{meta.get('config_hash')}, {cfg.source} has {cfg.physics_hash()}); "
                         f"{rebuild}")
    speed, torque, temp = _axis(meta, "speed"), _axis(meta, "torque"), _axis(meta, "temp")
    if full_v.shape != (temp.count, speed.count, torque.count):
        raise TableError(f"{path}: grid and data disagree; {rebuild}")
    return UnitTables(actuator, FullTable(speed, torque, temp, full_v),
                      PaperTable(torque, temp, edges, paper_v), meta)


def load_tables(directory: str | Path, cfg: Config) -> dict[str, UnitTables]:
    return {a: load_unit_tables(directory, a, cfg) for a in cfg.unit_names}
