"""The master's side of an emulated sensor: one SDO/NMT client per node, over canopen.

What a PLC or a configuration tool does with the sensor (read the live values, write the
preset and the event timers, switch its NMT state), written once for ``status``, ``demo``,
the benchmarks and the tests. The client is a canopen ``RemoteNode`` from the sensor's EDS;
SDO aborts (``canopen.SdoAbortedError``) and missing answers
(``canopen.SdoCommunicationError``) reach the caller unchanged.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import can
import canopen

from ddh_vsensor.canbus.eds import unit_object_dictionary
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.flags import flag_text
from ddh_vsensor.device.objects import SPEED_STEP_MM_S, UNCERTAINTY_STEP_MM

SDO_TIMEOUT_S = 2.0


class SensorClient:
    """One sensor node as a master sees it. ``node`` is the canopen ``RemoteNode`` for
    anything beyond the values named here (any object, NMT, EMCY log)."""

    def __init__(self, network: canopen.Network, cfg: Config, unit: str, *,
                 timeout_s: float = SDO_TIMEOUT_S, attempts: int | None = None) -> None:
        self.unit = cfg.require_unit(unit)
        self.node_id = cfg.can.units[unit].sensor_node_id
        self.step_mm = cfg.can.position_step_mm
        node = network.nodes.get(self.node_id) or network.add_node(
            self.node_id, unit_object_dictionary(cfg, unit))
        assert isinstance(node, canopen.RemoteNode)
        node.sdo.RESPONSE_TIMEOUT = timeout_s
        if attempts is not None:
            node.sdo.MAX_RETRIES = attempts   # canopen counts attempts: 0 would retry forever
        self.node = node

    @property
    def sdo(self) -> canopen.sdo.SdoClient:
        return self.node.sdo

    @property
    def nmt(self) -> canopen.nmt.NmtMaster:
        return self.node.nmt

    # --- live values ---------------------------------------------------------------------

    @property
    def position_steps(self) -> int:
        return int(self.sdo[0x6020][1].raw)

    @property
    def position_mm(self) -> float:
        return self.position_steps * self.step_mm

    @property
    def speed_mm_s(self) -> float:
        return self.sdo[0x6030][1].raw * SPEED_STEP_MM_S

    @property
    def uncertainty_mm(self) -> float:
        return self.sdo[0x2001].raw * UNCERTAINTY_STEP_MM

    @property
    def flags(self) -> int:
        return int(self.sdo[0x2002].raw)

    @property
    def input_frames(self) -> int:
        return int(self.sdo[0x2003].raw)

    @property
    def rejected_frames(self) -> int:
        return int(self.sdo[0x2004].raw)

    def read_all(self) -> dict[str, Any]:
        """Every value ``status`` shows, read now (one SDO upload each)."""
        position = self.position_steps
        flags = self.flags
        identity = self.sdo[0x1018]
        return {
            "device_type": f"0x{self.sdo[0x1000].raw:08X}",
            "device_name": self.sdo[0x1008].raw,
            "vendor_id": f"0x{identity[1].raw:08X}",
            "product_code": f"0x{identity[2].raw:08X}",
            "revision_number": f"0x{identity[3].raw:08X}",
            "serial_number": identity[4].raw,
            "position_mm": position * self.step_mm,
            "position_steps": position,
            "measuring_step_nm": self.sdo[0x6005][1].raw,
            "speed_mm_s": self.speed_mm_s,
            "uncertainty_mm": self.uncertainty_mm,
            "flags": flags,
            "flag_names": flag_text(flags),
            "input_frames": self.input_frames,
            "rejected_frames": self.rejected_frames,
            "tpdo1_event_timer_ms": self.sdo[0x1800][5].raw,
            "tpdo2_event_timer_ms": self.sdo[0x1801][5].raw,
            "heartbeat_ms": self.sdo[0x1017].raw,
            "controller_heartbeat_consumer_ms": self.sdo[0x1016][1].raw & 0xFFFF,
            "guard_time_ms": self.sdo[0x100C].raw,
            "life_time_factor": self.sdo[0x100D].raw,
            "error_register": self.sdo[0x1001].raw,
        }

    # --- settings ------------------------------------------------------------------------

    def preset(self, position_mm: float) -> None:
        """CiA 406 preset 0x6010 (a manual reference), in measuring steps."""
        self.sdo[0x6010][1].raw = round(position_mm / self.step_mm)

    @property
    def event_timer_ms(self) -> int:
        return int(self.sdo[0x1800][5].raw)

    @property
    def diag_timer_ms(self) -> int:
        return int(self.sdo[0x1801][5].raw)

    @diag_timer_ms.setter
    def diag_timer_ms(self, ms: int) -> None:
        self.sdo[0x1801][5].raw = ms


def clients(network: canopen.Network, cfg: Config, units: Iterable[str] | None = None,
            **kwargs: Any) -> dict[str, SensorClient]:
    """A client per unit (default: every unit of the machine) on ``network``."""
    return {u: SensorClient(network, cfg, u, **kwargs)
            for u in (cfg.unit_names if units is None else units)}


@contextlib.contextmanager
def sdo_network(bus: can.BusABC) -> Iterator[canopen.Network]:
    """A canopen Network on an open bus, fed by a python-can Notifier thread (the SDO client
    blocks the caller while the notifier delivers the responses); the bus stays the
    caller's."""
    network = canopen.Network(bus)
    notifier = can.Notifier(bus, network.listeners, 0.1)
    try:
        yield network
    finally:
        notifier.stop(1.0)


def commission(bus_kwargs: Mapping[str, Any], cfg: Config,
               presets: Mapping[str, float] | None = None, diag_ms: int | None = None,
               timeout_s: float = SDO_TIMEOUT_S, units: Iterable[str] | None = None) -> None:
    """Open the bus, then per unit (default: every unit) the diagnostic frame's event timer
    and the preset, over SDO (blocking: from a thread in an event loop)."""
    bus = can.Bus(**bus_kwargs)
    try:
        with sdo_network(bus) as network:
            for unit, client in clients(network, cfg, units, timeout_s=timeout_s).items():
                if diag_ms is not None:
                    client.diag_timer_ms = diag_ms
                if presets and unit in presets:
                    client.preset(presets[unit])
    finally:
        bus.shutdown()
