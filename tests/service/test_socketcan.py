"""The service on a real SocketCAN interface (vcan0): kernel filters and the event loop's
reader. Skipped, with the reason, where the kernel has no CAN or there is no vcan0."""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path

import can
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.service import Service, ServiceOptions

CHANNEL = "vcan0"


def _socketcan_missing() -> str | None:
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN"
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return f"the kernel lacks SocketCAN (AF_CAN socket: {exc})"
    if not Path(f"/sys/class/net/{CHANNEL}").exists():
        return (f"no {CHANNEL} interface (modprobe vcan; ip link add dev {CHANNEL} type vcan; "
                f"ip link set up {CHANNEL})")
    return None


pytestmark = pytest.mark.skipif(_socketcan_missing() is not None,
                                reason=_socketcan_missing() or "")


def test_service_on_vcan_with_kernel_filters(cfg, unit_tables) -> None:
    codec = FrameCodec(cfg)
    pos_id = codec.ids[message_name("position", "boom")]

    async def scenario():
        service = Service(cfg, unit_tables, {"interface": "socketcan", "channel": CHANNEL},
                          ServiceOptions())
        await service.start()
        feeder = can.Bus(interface="socketcan", channel=CHANNEL)
        listener = can.Bus(interface="socketcan", channel=CHANNEL,
                           can_filters=[{"can_id": pos_id, "can_mask": 0x7FF}])
        try:
            feeder.send(codec.encode_oil_temp(30.0))
            for k in range(30):
                feeder.send(codec.encode_sevcon("boom", 4.0, 1500.0))
                feeder.send(can.Message(arbitration_id=0x123, data=b"x", is_extended_id=False))
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.05)
            seen = []
            while (msg := listener.recv(0.0)) is not None:
                seen.append(msg)
        finally:
            feeder.shutdown()
            listener.shutdown()
            await service.shutdown()
        return service, seen

    service, seen = asyncio.run(scenario())
    assert service.link._fd is None                        # closed again
    assert service.units["boom"].integrated >= 25
    assert service.inputs.counts["unknown"] == 0           # filtered in the kernel
    assert seen and codec.decode(seen[-1])[1]["Position"] > 0.0
