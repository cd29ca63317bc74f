"""The canopen side of one bus: a ``canopen.Network`` the service feeds and sends through."""

from __future__ import annotations

from collections.abc import Callable

import can
import canopen


class ServiceNetwork(canopen.Network):
    """A canopen Network that is never ``connect()``-ed: the service feeds it frames
    (``notify``) from its own reader and it sends through the service's bus link."""

    def __init__(self, send: Callable[[can.Message], bool]) -> None:
        super().__init__(bus=None)
        self._send = send

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._send(can.Message(arbitration_id=can_id, data=bytes(data),
                               is_extended_id=can_id > 0x7FF, is_remote_frame=remote))

    def send_periodic(self, *args: object, **kwargs: object):  # type: ignore[override]
        raise RuntimeError("periodic frames are sent by the service's tick, not by threads")
