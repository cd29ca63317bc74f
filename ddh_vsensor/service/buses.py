"""Which buses a machine's frames are on: the default bus (``bus:``, with any command-line
overrides), which carries the oil temperature and the I/O module, and each bus under
``buses:`` that a unit is on; each unit's own frames travel on its unit's bus."""

from __future__ import annotations

from typing import Any

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.config import DEFAULT_BUS, Config
from ddh_vsensor.service.bus import bus_settings

# A unit's own frames: its controller's and its emulated sensor's; they travel on its bus.
UNIT_FRAME_KINDS = ("sevcon", "heartbeat", "position", "diag", "health", "sensor_heartbeat",
                    "emcy", "sdo_tx", "sdo_rx")


def machine_buses(cfg: Config, default: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Settings of every bus the machine's frames are on, by name: the default bus
    (``default``: the config's ``bus:`` with any command-line overrides; it carries the oil
    temperature and the I/O module) and each bus under ``buses:`` that a unit is on."""
    return {DEFAULT_BUS: default, **{name: bus_settings(cfg.bus_kwargs(name))
                                     for name in cfg.buses if cfg.units_on_bus(name)}}


def frame_buses(cfg: Config, codec: FrameCodec) -> dict[int, str]:
    """Frame ID -> name of the bus it travels on, for each unit's own frames (the rest,
    oil temperature, I/O module and NMT, are on the default bus)."""
    return {codec.ids[message_name(kind, unit)]: cfg.can.units[unit].bus
            for unit in cfg.unit_names for kind in UNIT_FRAME_KINDS}
