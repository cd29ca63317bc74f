"""NMT node guarding and life guarding of one emulated sensor (CiA 301), for the masters that
poll their sensors instead of consuming heartbeats (many PLC masters still do, and the
draw-wire sensor the node stands in for answered them).

Node guarding: the master sends a remote frame on 0x700 + node; the node answers with one
byte, the NMT state (4 stopped, 5 operational, 127 pre-operational) and bit 7 a toggle that
starts at 0 after boot-up or a reset and alternates with every answer. Answered whatever the
heartbeat producer time 0x1017 says: a master that polls expects an answer.

Life guarding: with guard time 0x100C (ms) and life time factor 0x100D both non-zero, the
node expects the next request within their product from the first request on; when none
comes it reports a life guarding event (EMCY 8130, error register bit 4) and the end of it
when requests come again. The NMT state is kept (a PLC pausing its polls must not take the
positions off the bus); the master sees the event in the EMCY and the error register.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable

import canopen

log = logging.getLogger(__name__)

GUARD_TIME = 0x100C                 # ms, UNSIGNED16
LIFE_TIME_FACTOR = 0x100D           # UNSIGNED8
TOGGLE = 0x80


class Guarding:
    """The guarding slave of one node: :meth:`on_request` for each remote frame on its
    error-control COB-ID, :meth:`check` every housekeeping tick."""

    def __init__(self, node: canopen.LocalNode, send: Callable[[int, bytes], None],
                 name: str) -> None:
        self.node, self.send, self.name = node, send, name
        self.cob_id = 0x700 + node.id
        self.toggle = 0
        self.requests = 0
        self.last_request_s: float | None = None
        self.lost = False               # a life guarding event is reported and not over

    def reset(self) -> None:
        """Boot-up or a reset: the next answer's toggle is 0, life guarding waits for the
        first request again."""
        self.toggle = 0
        self.last_request_s = None
        self.lost = False

    def life_time_s(self) -> float:
        """Guard time x life time factor (0: life guarding off)."""
        guard_ms = struct.unpack("<H", self.node.get_data(GUARD_TIME, 0))[0]
        factor = self.node.get_data(LIFE_TIME_FACTOR, 0)[0]
        return guard_ms * factor / 1000.0

    def on_request(self, now_s: float) -> None:
        """A guard request: answer with the state and the toggle, and restart the life
        time (ending a life guarding event)."""
        state = self.node.nmt._state                               # noqa: SLF001
        if state == 0:                  # initialising: no answer (CiA 301)
            return
        self.send(self.cob_id, bytes([self.toggle | state]))
        self.toggle ^= TOGGLE
        self.requests += 1
        self.last_request_s = now_s
        if self.lost:
            self.lost = False
            log.info("%s sensor node %d: node guarding requests again", self.name, self.node.id)

    def check(self, now_s: float) -> bool:
        """Whether a life guarding event is on now (logged when it starts; over when a
        request comes or the master sets the life time to 0)."""
        if self.last_request_s is None:
            return self.lost
        life_s = self.life_time_s()
        if self.lost:
            if life_s == 0.0:
                self.lost = False
                log.info("%s sensor node %d: life guarding switched off", self.name,
                         self.node.id)
        elif life_s > 0.0 and now_s - self.last_request_s > life_s:
            self.lost = True
            log.warning("%s sensor node %d: no node guarding request for %.0f ms (guard time "
                        "x life time factor): life guarding event, EMCY 8130", self.name,
                        self.node.id, 1000.0 * (now_s - self.last_request_s))
        return self.lost
