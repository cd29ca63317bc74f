"""NMT heartbeat consumer for the Sevcon controllers, on canopen's ``RemoteNode`` NMT master.

Which controllers are consumed is configuration (``faults.heartbeat_node_ids``), never decided
by what appears on the bus: a consumed controller is "not operational" from the start until
its first OPERATIONAL heartbeat, again whenever its last heartbeat is older than the consumer
time or reports another state. The verdict only raises a flag (Flags.CONTROLLER_NOT_OPERATIONAL): the
controller's frames are integrated whatever its heartbeat says.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import canopen
from canopen.nmt import NMT_STATES
from canopen.objectdictionary import ObjectDictionary

from ddh_vsensor.service.limits import RateLimitedLog

log = logging.getLogger(__name__)

OPERATIONAL = 5
DEFAULT_CONSUMER_TIME_S = 1.5   # heartbeat producers ship 100..1000 ms; 1.5x the slowest


class HeartbeatConsumer:
    """One controller's heartbeat, consumed through ``network`` (a canopen.Network)."""

    def __init__(self, network: canopen.Network, node_id: int, name: str,
                 consumer_time_s: float = DEFAULT_CONSUMER_TIME_S,
                 clock: Callable[[], float] = time.monotonic,
                 log_interval_s: float = 5.0) -> None:
        self.name, self.node_id = name, node_id
        self.consumer_time_s = consumer_time_s
        self.clock = clock
        self.node = canopen.RemoteNode(node_id, ObjectDictionary())
        network.add_node(self.node)
        # Only the heartbeat is consumed: SDO responses and EMCY messages of this node would
        # pile up in canopen's unbounded queues and logs, as nobody reads them here.
        network.unsubscribe(self.node.sdo.tx_cobid, self.node.sdo.on_response)
        network.unsubscribe(0x80 + node_id, self.node.emcy.on_emcy)
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.last_rx_s: float | None = None
        self.state: int | None = None
        self.count = 0
        self._reported = ""
        self._log = RateLimitedLog(log, log_interval_s)

    def _on_heartbeat(self, state: int) -> None:
        self.last_rx_s = self.clock()
        self.state = state & 0x7F
        self.count += 1

    def status(self, now_s: float | None = None) -> tuple[bool, str]:
        """(operational, why)."""
        if self.last_rx_s is None:
            ok, why = False, "no heartbeat yet"
        else:
            now_s = self.clock() if now_s is None else now_s
            if now_s - self.last_rx_s > self.consumer_time_s:
                ok, why = False, f"heartbeat lost ({now_s - self.last_rx_s:.1f} s)"
            elif self.state != OPERATIONAL:
                ok, why = False, NMT_STATES.get(self.state or 0, f"state {self.state}").lower()
            else:
                ok, why = True, "operational"
        key = why.split(" (")[0]
        if key != self._reported:
            self._reported = key
            self._log.log(logging.INFO if ok else logging.WARNING, "state",
                          "%s controller (node %d): %s", self.name, self.node_id, why)
        return ok, why
